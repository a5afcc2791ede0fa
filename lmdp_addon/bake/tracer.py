"""Wavefront path tracer for indirect diffuse light at surface points (UNGUIDED, GUIDED, FINAL_GATHER).

The quantity is the one of Cycles' ``bake(type='DIFFUSE', pass_filter={'INDIRECT'})``: at a
shading point x with normal n,

    I(x) = E_ind(x) / π = (1/π) ∫_{H(n)} L_r(h(x, ω), -ω) cos θ dω,                 (thesis eq. 2.7)

the irradiance carried by light that has bounced at least once, without x's own albedo: the
emission of the surface hit by the first ray and light escaping to the world straight from x are
*direct* light and are left out, exactly as Cycles splits its passes. ``L_r(y)`` is the reflected
radiance at y = h(x, ω): ``ρ(y) [D(y) + I(y)]`` with D the direct light (emitters and world) and
I the indirect light at y, recursively.

Estimator (per path, all paths of a batch advance together: "wavefront"; no Python loop over rays):

* vertex 0 (the texel point) samples ω0 with pdf ``p0``; weight ``w0 = cos θ0 / (π p0)``;
* at every later vertex y_k (k = 1 .. max_bounces) the throughput is ``β_k = β_{k-1} w_{k-1} ρ(y_k)``
  and **next-event estimation** samples one point on the emitters (triangle chosen with
  probability proportional to area x max-channel radiance; uniform on it far away, uniform in
  its solid angle close by, as Cycles chooses) with a shadow ray; one-sided emitters (area
  lights) count only on their front side, mesh emission on both (``SceneArrays``);
* emitters hit by a ray sampled at y_k (k >= 1) are counted too, and the two estimates of the
  emitted light are combined by multiple importance sampling (the balance heuristic against
  the cosine density, :meth:`IndirectTracer._direct`); the emitter hit by the texel's own first
  ray is direct light and is left out; a uniform world is counted only through sampled rays
  that escape from y_k (k >= 1), weight ``β_k w_k L_world``;
* ``max_bounces`` = N keeps vertices y_1 .. y_N (NEE at each and the escape of y_N's ray), which
  is what Cycles' ``max_bounces = N`` (with ``diffuse_bounces >= N``) bakes: Cycles' kernel uses
  ``N + 1`` internally and stops shading at the vertex whose incoming bounce count reaches it;
* Russian roulette from vertex ``rr_start`` on: survival probability ``min(1, max_c β_c)``,
  survivors divided by it (unbiased).

Direction sampling at a vertex with shading normal n:

* ``UNGUIDED``: cosine-weighted, ``p(ω) = cos θ / π``, so ``w = 1``;
* ``GUIDED``: a one-sample mixture of the optimal policy and cosine sampling,

      p(ω) = α g_s(ω) + (1 - α) max(cos θ, 0) / π,
      g_s(ω) = u*(k(ω) | s) · S / (2π)   for ω in stratum k of s's hemisphere, 0 below it,

  where s is the nearest compatible state point (same object, facing the same side), u*(k|s) its
  directional optimal policy (``policy.stratum_policy``) and the S strata of s's Shirley–Chiu
  grid have solid angle 2π/S each (equal-area map), so g_s is a normalised piecewise-constant
  density. A guide sample picks stratum k by u*(·|s), then a uniform point of the stratum's cell
  of the unit square (uniform in solid angle within the stratum). Directions below the shading
  point's own horizon get ``w = 0`` while the pdf stays exact, so the estimator is unbiased for
  every α < 1 (α = 1 leaves strata with u* = 0 unsampled). Vertices without a compatible state
  use cosine sampling (the choice depends only on the vertex, so the pdf stays consistent).
  The guide at the texel uses u* over the surface states only (``columns='points'``: the light
  wanted there arrives after a bounce); later vertices use ``'points+world'`` (emitters are
  covered by NEE, the world by escaping rays);
* ``FINAL_GATHER``: the first direction is drawn as in GUIDED; at its hit y_1 the PHYSICAL-mode
  solution replaces the rest of the path: ``L_r(y_1) ≈ ρ(y_1) (ẑ_ind(y_1) + D_e(y_1))`` with
  ẑ_ind the indirect irradiance/π of the nearby compatible states, interpolated
  (``GatherField``), and D_e the direct light at y_1 itself by light sampling (one shadow ray).
  Hits without a nearby compatible state, back-face hits, and hits closer to x than half a
  state spacing (``GatherField.too_close``) continue as a GUIDED path. Biased by the
  discretisation of ẑ_ind.

Arrays are float32 in the hot loop (positions of scenes of metres keep ~1e-7 relative precision,
ray origins are offset by ``RayCaster.offset()``, 1e-5 of the scene size).
"""
from dataclasses import dataclass, field

import numpy as np

from ..model.hemisphere import QUARTER_PI, stratum_of_local_direction
from ..raycast import RayCaster

INV_PI = 1.0 / np.pi
#: Largest angle (degrees) between the normals of states whose guide rows are averaged
#: (``neighbour_average``). Measured on the bumpy HEAVY floor (64 samples, 4 seeds), GUIDED's
#: variance per sample relative to UNGUIDED's: 1.08 with exactly equal normals only, 0.98 within
#: 5°, 0.91 within 15°, 0.92 within 30°. Flat scenes are unaffected (their normals are equal).
NEIGHBOUR_MAX_ANGLE = 15.0
MODES = ("UNGUIDED", "GUIDED", "FINAL_GATHER")
#: FINAL_GATHER path-traces first hits closer than this many state spacings α of the hit object
#: (``GatherField.too_close``). Measured with ``bench/bias_map.py HEAVY Floor TallBox --modes
#: FINAL_GATHER --resolution 64 --samples 256 --points 2048``, bias of the texels under the
#: boxes (floor / tall box): +81 / +94 % with no limit, +0.1 / +6.6 % at 0.5, -0.3 / +0.9 % at
#: 0.75, -0.7 / +2.6 % at 1; the heavy floor's bake then takes +12 % (0.5) and +24 % (1) longer,
#: the Cornell box's and the narrow opening's within their noise.
GATHER_MIN_SPACINGS = 0.5


@dataclass
class TraceStats:
    """Work done by :meth:`IndirectTracer.trace` (summed over calls)."""

    paths: int = 0
    rays: int = 0             #: closest-hit rays
    shadow_rays: int = 0      #: NEE occlusion rays
    vertices: int = 0         #: path vertices shaded (y_1, y_2, ...)
    guided_vertices: int = 0  #: vertices that had a compatible state (GUIDED / FINAL_GATHER)
    gathered: int = 0         #: FINAL_GATHER paths ended by the solution at y_1
    gather_fallback: int = 0  #: FINAL_GATHER paths continued by path tracing (no state near y_1)

    def add(self, other):
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    @property
    def total_rays(self):
        return self.rays + self.shadow_rays

    def as_dict(self):
        return {name: int(getattr(self, name)) for name in self.__dataclass_fields__}


# -- the guide --------------------------------------------------------------------------------

@dataclass
class StateGuide:
    """The optimal policy of the states as a sampling density (see the module docstring).

    locator          ``locator.StateLocator`` of the states (nearest compatible state point)
    frames           (m, 3, 3) float64 tangent frames of the states (rows t, b, n)
    first, later     (m, S) u*(k|s) for the texel vertex (columns 'points') and later vertices
                     ('points+world'); each row sums to 1
    strata_u, strata_v  the hemisphere grid of the states
    same_scene       True when the traced scene is the one the states were sampled on (then
                     triangle indices agree and front hits use the fast tabulated lookup)
    object_map       (O_traced,) int: the states' object index of each traced object (-1: none),
                     used when ``same_scene`` is False (objects matched by name)
    """

    locator: object
    frames: np.ndarray
    first: np.ndarray
    later: np.ndarray
    strata_u: int
    strata_v: int
    same_scene: bool = True
    object_map: np.ndarray = None
    cdf_first: np.ndarray = field(init=False, repr=False)
    cdf_later: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.frames = np.asarray(self.frames, dtype=np.float64)
        self.frames32 = self.frames.astype(np.float32)
        self.first = _normalised_rows(self.first)
        self.later = _normalised_rows(self.later)
        self.cdf_first = _row_cdf(self.first)
        self.cdf_later = _row_cdf(self.later)
        shift = np.arange(len(self.first), dtype=np.float64)[:, None]
        self.offset_cdf_first = (self.cdf_first + shift).ravel()
        self.offset_cdf_later = (self.cdf_later + shift).ravel()

    @property
    def n_strata(self):
        return self.strata_u * self.strata_v

    def states_at(self, positions, side_normals, objects):
        """Nearest compatible state of arbitrary surface points (exact tree query); -1 if none."""
        objects = np.asarray(objects)
        if len(objects) == 0:
            return np.zeros(0, dtype=np.int64)
        if self.object_map is not None:
            objects = np.where(objects >= 0, self.object_map[np.maximum(objects, 0)], -1)
        return self.locator.locate(np.asarray(positions, dtype=np.float64),
                                   np.asarray(side_normals, dtype=np.float64), objects, workers=1)

    def states_at_hits(self, tri, bu, bv, positions, side_normals, front, objects):
        """Nearest compatible state of ray hits (-1: none).

        On the scene the states were sampled on, only front hits on state-carrying triangles
        have one (the tabulated ``locate_front``): back faces and other geometry carry no states.
        On another scene every hit is looked up exactly (objects matched by name).
        """
        out = np.full(len(tri), -1, dtype=np.int64)
        if len(tri) == 0:
            return out
        if self.same_scene:
            carrier = front & (self.locator.gu[tri] > 0) if not self.locator.exact else front
            carrier = np.flatnonzero(carrier)
            if len(carrier):
                exact_positions = (_rows(positions, carrier).astype(np.float64)
                                   if self.locator.exact else None)
                out[carrier] = self.locator.locate_front(tri[carrier], bu[carrier], bv[carrier],
                                                         exact_positions, workers=1)
            return out
        return self.states_at(positions, side_normals, objects)

    def sample(self, states, u, first, return_density=False):
        """World directions drawn from g_s for ``states (k,)`` with uniforms ``u (k, 2)``
        (and, with ``return_density``, g_s at them: u*(k|s) S / 2π of the chosen stratum)."""
        prob = self.first if first else self.later
        cdf = self.cdf_first if first else self.cdf_later
        S = self.n_strata
        if S <= 32:  # the stratum is the count of row entries <= u: one row gather, S compares
            k = np.minimum(np.count_nonzero(np.take(cdf, states, axis=0) <= u[:, 0:1], axis=1), S - 1)
        else:  # row s of the CDF shifted by s is one increasing array: one binary search
            offset = self.offset_cdf_first if first else self.offset_cdf_later
            k = np.clip(np.searchsorted(offset, states + u[:, 0], side="right") - states * S, 0, S - 1)
        flat = states * S + k
        lo = np.where(k > 0, np.take(cdf, flat - 1), 0.0)
        p = np.take(prob, flat)
        t = np.clip((u[:, 0] - lo) / np.where(p > 0, p, 1.0), 0.0, 1.0 - 1e-7)
        su = (k // self.strata_v + t) / self.strata_u
        sv = (k % self.strata_v + u[:, 1]) / self.strata_v
        x, y = _concentric32(su, sv)
        r2 = x * x + y * y
        lift = np.sqrt(np.maximum(2.0 - r2, 0.0))
        # Equal-area lift of the disk to the hemisphere (hemisphere.py), then into s's frame.
        d = _rotate_out(_rows(self.frames32, states), x * lift, y * lift, 1.0 - r2)
        if return_density:
            return d, p * (S / (2.0 * np.pi))
        return d

    def density(self, states, directions, first):
        """g_s(ω) (k,) for world directions ``(k, 3)``: u*(k|s) S / 2π, 0 below s's horizon."""
        prob = self.first if first else self.later
        local = _rotate_in(_rows(self.frames32, states), np.asarray(directions, dtype=np.float32))
        k = stratum_of_local_direction(local, self.strata_u, self.strata_v)
        g = np.take(prob, states * self.n_strata + np.maximum(k, 0)) * (self.n_strata / (2.0 * np.pi))
        return np.where(k >= 0, g, 0.0)


def neighbour_average(rows, locator, normals, neighbours, max_angle=None):
    """Mean of the per-stratum distributions ``rows (m, S)`` (or several side by side, (m, n S):
    the mean is taken per column) over each point's ``neighbours`` nearest points (``locator``'s
    6-D distance, same object) whose normal is within ``max_angle`` degrees of its own
    (default ``NEIGHBOUR_MAX_ANGLE``) and on the same side of the horizontal (below).

    u*(k|x) comes from ``R`` rays per stratum (thesis eq. 3.1), so a point's row is a Monte Carlo
    estimate whose noise easily exceeds the differences between neighbouring points. Points with
    the same normal have the same tangent frame (``hemisphere.tangent_frame``), hence the same
    strata, and the mean of their rows is again a distribution over those strata: a guide
    estimated from ``neighbours`` x as many rays. Points whose normals differ by a few degrees
    (curved or bumpy surfaces) have strata turned by about as much; their mean is a slightly
    blurred guide. The frame jumps where a normal's z changes sign (Duff et al.'s branch), so
    points on either side are never mixed. Any rows keep the guided estimator unbiased (the pdf
    is evaluated from the same table it is sampled from); only its variance changes (measured:
    ``baking.GUIDE_NEIGHBOURS``, ``NEIGHBOUR_MAX_ANGLE``). Points with no such neighbour keep
    their row.
    """
    rows = np.asarray(rows, dtype=np.float64)
    out = rows.copy()
    if neighbours <= 1:
        return out
    cos_max = np.cos(np.radians(NEIGHBOUR_MAX_ANGLE if max_angle is None else max_angle))
    for o, tree in locator.trees.items():  # loop over objects, not points
        ids = locator.index[o]
        k = min(int(neighbours), len(ids))
        if k <= 1:
            continue
        _, nn = tree.query(tree.data, k=k, workers=1)
        near = ids[nn]                                                   # (n_o, k)
        close = np.einsum("ij,ikj->ik", normals[ids], normals[near]) >= cos_max
        branch = (normals[ids, 2] >= 0.0)[:, None] == (normals[near, 2] >= 0.0)
        same = close & branch
        w = same / same.sum(axis=1, keepdims=True)                       # self is always in
        out[ids] = np.einsum("ik,iks->is", w, rows[near])
    return out


def _normalised_rows(p):
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, None)
    s = p.sum(axis=1, keepdims=True)
    return np.where(s > 0, p / np.where(s > 0, s, 1.0), 1.0 / p.shape[1])


def _row_cdf(p):
    cdf = np.cumsum(p, axis=1)
    cdf[:, -1] = 1.0
    return cdf


# -- final gather ------------------------------------------------------------------------------

@dataclass
class GatherField:
    """Irradiance/π ẑ of the PHYSICAL solution, interpolated between states: the *indirect*
    part ẑ_ind, the light that arrives after at least one reflection (``baking.build_gather``;
    the tracer adds the direct part at the gather point).

    ``value_at(...)`` returns (k, 3) ẑ at surface points (NaN where no compatible state is
    near): inverse-squared-distance weights over the ``neighbours`` nearest compatible states
    of the same object (6-D distance of ``StateLocator``: position and α·normal). For front hits
    on state-carrying triangles of the solved scene, the value is tabulated on the locator's
    per-triangle grid (cell centres, a quarter of the point spacing). Back-face hits are NaN:
    states describe the front of their faces only (the build sends back-face hits to the
    void), and the nearest state facing the hit's side would be on the far side of the solid,
    so a path that starts inside a box standing on the floor (a texel under it) would gather
    the light outside the box. The tracer continues such paths instead, and those whose hit is
    closer than ``min_spacings`` state spacings (:meth:`too_close`).
    """

    locator: object
    irradiance: np.ndarray          #: (m, 3) ẑ of every state point (W / sr m²)
    neighbours: int = 8
    same_scene: bool = True
    object_map: np.ndarray = None
    table: np.ndarray = None        #: (cells, 3) tabulated ẑ (NaN: none)
    min_spacings: float = GATHER_MIN_SPACINGS

    def __post_init__(self):
        self.irradiance = np.asarray(self.irradiance, dtype=np.float64)
        if self.table is None and self.same_scene and not self.locator.exact and len(self.locator.grid_point):
            self.table = self._tabulate()

    def _tabulate(self):
        """ẑ at the centre of every grid cell that has a nearest compatible state."""
        loc = self.locator
        scene = loc.scene
        sizes = loc.gu * loc.gv
        tri = np.repeat(np.arange(scene.n_triangles), sizes)
        cell = np.arange(len(tri)) - np.repeat(loc.grid_offset, sizes)
        table = np.full((len(tri), 3), np.nan)
        sel = np.flatnonzero(loc.grid_point >= 0)
        t, gv = tri[sel], loc.gv[tri[sel]]
        pos = loc.cell_centres(t, cell[sel] // gv, cell[sel] % gv)
        # Once per bake, before any path: the tree queries use every core.
        table[sel] = self._interpolate(pos, loc.face_normals[t], scene.triangle_object[t], workers=-1)
        return table

    def _interpolate(self, positions, side_normals, objects, workers=1):
        loc = self.locator
        out = np.full((len(positions), 3), np.nan)
        for o, tree in loc.trees.items():  # loop over objects, not points
            sel = np.flatnonzero(objects == o)
            if len(sel) == 0:
                continue
            k = min(self.neighbours, tree.n)
            q = np.hstack([positions[sel], loc.spacing[o] * side_normals[sel]])
            d, nn = tree.query(q, k=k, workers=workers)
            if k == 1:
                d, nn = d[:, None], nn[:, None]
            ids = loc.index[o][nn]
            facing = np.einsum("kij,kj->ki", loc.normals[ids], side_normals[sel]) > 0.0
            w = np.where(facing, 1.0 / np.maximum(d, 1e-9 * loc.spacing[o]) ** 2, 0.0)
            wsum = w.sum(axis=1)
            val = np.einsum("ki,kic->kc", w, self.irradiance[ids]) / np.where(wsum > 0, wsum, 1.0)[:, None]
            out[sel] = np.where((wsum > 0)[:, None], val, np.nan)
        return out

    def too_close(self, distances, objects):
        """True for hits at ``distances`` from the vertex that cast them that are below
        ``min_spacings`` times the state spacing α of their object (``objects``: the traced
        scene's object indices; objects without states never are).

        ẑ is interpolated over states about α apart, so it stands for the light of a
        neighbourhood of that size; a hit much closer than α to the vertex sees a
        neighbourhood the vertex itself is part of, such as the floor under a box between the
        bumps it stands on, where the nearest states lie outside the box and ẑ is far too bright
        (``GATHER_MIN_SPACINGS``). Those paths continue by path tracing.
        """
        obj = np.asarray(objects)
        if self.object_map is not None:
            obj = np.where(obj >= 0, self.object_map[np.maximum(obj, 0)], -1)
        spacing = np.where(obj >= 0, np.take(self.locator.spacing, np.maximum(obj, 0)), 0.0)
        return distances < self.min_spacings * spacing

    def value_at(self, tri, bu, bv, positions, side_normals, front, objects):
        out = np.full((len(tri), 3), np.nan)
        fast = np.zeros(len(tri), dtype=bool)
        if self.table is not None:
            loc = self.locator
            fast = front & (loc.gu[tri] > 0)
            if np.any(fast):
                out[fast] = self.table[loc.cell_of(tri[fast], bu[fast], bv[fast])]
        slow = ~fast & front
        if np.any(slow):
            obj = objects[slow]
            if self.object_map is not None:
                obj = np.where(obj >= 0, self.object_map[np.maximum(obj, 0)], -1)
            out[slow] = self._interpolate(positions[slow].astype(np.float64),
                                          side_normals[slow].astype(np.float64), obj)
        return out


# -- the tracer --------------------------------------------------------------------------------

class IndirectTracer:
    """Traces batches of paths from surface points and returns their indirect-light estimates.

    scene           the :class:`~lmdp_addon.scene_arrays.SceneArrays` that is traced
    mode            'UNGUIDED', 'GUIDED' or 'FINAL_GATHER'
    max_bounces     N: path vertices y_1..y_N after the shading point (Cycles' max_bounces)
    guide           :class:`StateGuide` (GUIDED, FINAL_GATHER)
    gather          :class:`GatherField` (FINAL_GATHER)
    guide_fraction  α of the mixture
    rr_start        first vertex index at which Russian roulette may end a path
    """

    def __init__(self, scene, mode="UNGUIDED", max_bounces=8, guide=None, gather=None,
                 guide_fraction=0.5, rr_start=3, caster=None):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, not {mode!r}")
        if mode in ("GUIDED", "FINAL_GATHER") and guide is None:
            raise ValueError(f"{mode} needs a StateGuide")
        if mode == "FINAL_GATHER" and gather is None:
            raise ValueError("FINAL_GATHER needs a GatherField")
        self.scene = scene
        self.mode = mode
        self.max_bounces = int(max_bounces)
        self.guide = guide if mode != "UNGUIDED" else None
        self.gather = gather if mode == "FINAL_GATHER" else None
        self.guide_fraction = float(np.clip(guide_fraction, 0.0, 1.0)) if self.guide is not None else 0.0
        self.rr_start = int(rr_start)
        self.caster = caster or RayCaster(scene)
        self.eps = np.float32(self.caster.offset())
        normals, areas = scene.triangle_geometry()
        T = scene.n_triangles
        self.face_normals = normals.astype(np.float32)
        self.albedo = np.clip(scene.triangle_albedo, 0.0, 1.0).astype(np.float32)
        self.objects = scene.triangle_object
        self.world = np.asarray(scene.world_radiance, dtype=np.float32)
        self.world_lit = bool(np.any(self.world > 0))
        # Emitter sampling table: triangles with probability ∝ area x max-channel radiance.
        em = np.flatnonzero(scene.is_emissive() & (areas > 0))
        weight = areas[em] * scene.triangle_emission[em].max(axis=1)
        self.n_emitter_triangles = len(em)
        if len(em):
            cdf = np.cumsum(weight)
            prob = weight / cdf[-1]
            c = scene.corners()[em]
            self.emitter_cdf32 = (cdf / cdf[-1]).astype(np.float32)
            self.emitter_two_sided = scene.triangle_emission_two_sided[em]
            self.any_two_sided = bool(np.any(self.emitter_two_sided))
            self.emitter_radiance = scene.triangle_emission[em].astype(np.float32)
            self.emitter_pdf_area = (prob / areas[em]).astype(np.float32)  #: p_A of a point on it
            self.emitter_prob = prob
            # float64 corners and normals for solid-angle sampling (close emitters)
            self.emitter_corners64 = c
            self.emitter_corner64 = np.ascontiguousarray(c[:, 0])
            self.emitter_normal64 = np.ascontiguousarray(normals[em], dtype=np.float64)
            # float32 tables per component (x, y, z) for area sampling and the strategy choice
            normal32, corner32 = self.emitter_normal64.astype(np.float32), c[:, 0].astype(np.float32)
            edge1, edge2 = (c[:, 1] - c[:, 0]).astype(np.float32), (c[:, 2] - c[:, 0]).astype(np.float32)
            self.emitter_normal32_xyz = tuple(np.ascontiguousarray(normal32[:, i]) for i in range(3))
            self.emitter_corner32_xyz = tuple(np.ascontiguousarray(corner32[:, i]) for i in range(3))
            self.emitter_edge1_32_xyz = tuple(np.ascontiguousarray(edge1[:, i]) for i in range(3))
            self.emitter_edge2_32_xyz = tuple(np.ascontiguousarray(edge2[:, i]) for i in range(3))
            self.emitter_plane32 = np.einsum("ij,ij->i", normal32, corner32)
            self.emitter_longest2 = np.max(np.stack([np.sum((c[:, 1] - c[:, 0]) ** 2, axis=1),
                                                     np.sum((c[:, 2] - c[:, 1]) ** 2, axis=1),
                                                     np.sum((c[:, 0] - c[:, 2]) ** 2, axis=1)]),
                                           axis=0).astype(np.float32)
        self.triangle_emitter_index = np.full(T, -1, dtype=np.int64)
        self.triangle_emitter_index[em] = np.arange(len(em))
        # Per scene triangle, for rays that hit emitters: light-sampling p_A (0: not an emitter).
        self.triangle_emitter_pdf_area = np.zeros(T, np.float32)
        if len(em):
            self.triangle_emitter_pdf_area[em] = self.emitter_pdf_area
        self.triangle_two_sided = scene.triangle_emission_two_sided
        self.scene_emission = scene.triangle_emission.astype(np.float32)
        self.tri_count = T

    # -- direction sampling ----------------------------------------------------------------------
    @staticmethod
    def _cosine_directions(normals, u, stratified=True):
        """Cosine-weighted directions about ``normals (k, 3)`` from uniforms ``u (k, 2)``.

        ``stratified``: Shirley–Chiu's concentric map (keeps the strata of stratified ``u``
        compact: the texel's first bounce); otherwise the cheaper polar map
        ``r = sqrt(u0), φ = 2π u1`` (independent uniforms of later bounces). Both are exact
        cosine-weighted warps of the unit square. float32 throughout.
        """
        u = np.asarray(u, dtype=np.float32)
        if stratified:
            x, y = _concentric32(u[:, 0], u[:, 1])
            z = np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))
        else:
            r = np.sqrt(u[:, 0])
            phi = np.float32(2.0 * np.pi) * u[:, 1]
            x = r * np.cos(phi)
            y = r * np.sin(phi)
            z = np.sqrt(np.maximum(1.0 - u[:, 0], 0.0))
        return _local_to_world(normals, x, y, z)

    def _sample(self, normals, states, u, u_mix, first):
        """Directions ``d``, weights ``w = cos θ / (π p(d))`` and ``cos θ`` at vertices."""
        if self.guide is None:
            d = self._cosine_directions(normals, u, stratified=first)
            cos = _dot(normals, d)
            return d, np.ones(len(normals), np.float32), cos
        has = states >= 0
        guided = has & (u_mix < self.guide_fraction)
        use_guide = np.flatnonzero(guided)
        cos_sel = np.flatnonzero(~guided)
        d = np.empty((len(normals), 3), np.float32)
        g = np.zeros(len(normals))
        if len(cos_sel):
            d[cos_sel] = self._cosine_directions(_rows(normals, cos_sel), _rows(u, cos_sel), stratified=first)
        if len(use_guide):
            d[use_guide], g[use_guide] = self.guide.sample(states[use_guide], _rows(u, use_guide), first,
                                                           return_density=True)
        # g_s of the cosine-drawn directions needs their stratum in s's frame; the guide-drawn
        # ones know theirs. The mixture pdf of every direction: α g + (1 - α) cos/π.
        other = np.flatnonzero(has & ~guided)
        if len(other):
            g[other] = self.guide.density(states[other], _rows(d, other), first)
        cos = _dot(normals, d).astype(np.float64)
        pdf = np.where(has, self.guide_fraction * g, 0.0) + np.where(has, 1.0 - self.guide_fraction, 1.0) * np.maximum(cos, 0.0) * INV_PI
        w = np.where((cos > 0) & (pdf > 0), cos * INV_PI / np.where(pdf > 0, pdf, 1.0), 0.0)
        return d, w.astype(np.float32), cos

    # -- next-event estimation -------------------------------------------------------------------
    def _direct(self, points, normals, rng, stats, mis=True):
        """(k, 3) light-sampling half of the MIS estimate of D_e(y) = (1/π) ∫ L_e cos θ dω
        (``mis=False``: the whole of D_e(y) by light sampling alone, weight ``q / p_L``; for
        paths that end at y).

        One point on the emitters (triangle ∝ area x max radiance) with the weight
        ``q / (p_L + q)``: ``p_L`` is the light-sampling density per steradian and
        ``q = cos θ_y / π`` the cosine density. Far from the triangle the point is uniform on it
        (``p_L = p_A r² / cos θ_l``); close to it, uniform in the solid angle Ω it subtends
        (Arvo 1995, ``p_L = P(triangle) / Ω``), as Cycles chooses (:meth:`_near`). The
        sampled-ray half (:meth:`_emission_hits`) uses ``q / (q + p_L)`` with the same q and
        strategy, so the two weights sum to one for every direction and the combination is
        unbiased whatever density drew the ray (in GUIDED mode q is the cosine part of the mixture
        only: a cheaper, still exact, partition of unity; Veach's balance heuristic when sampling
        is purely cosine).
        """
        k = len(points)
        out = np.zeros((k, 3), np.float32)
        if self.n_emitter_triangles == 0 or k == 0:
            return out
        r = rng.random((k, 3), dtype=np.float32)
        r1, r2 = np.ascontiguousarray(r[:, 1]), np.ascontiguousarray(r[:, 2])
        if self.n_emitter_triangles == 1:
            e = np.zeros(k, dtype=np.int64)
        else:
            e = np.minimum(np.searchsorted(self.emitter_cdf32, r[:, 0], side="right"),
                           self.n_emitter_triangles - 1)
        # Direction and distance from the offset origin itself: from the surface point, a shadow
        # ray at a grazing angle would meet the emitter's plane before ``dist`` (close emitters).
        # Per component below: contiguous (k,) arrays are much faster in numpy than (k, 3) rows.
        origin = points + self.eps * normals
        o = tuple(np.ascontiguousarray(origin[:, i]) for i in range(3))
        n_l = tuple(np.take(c, e) for c in self.emitter_normal32_xyz)
        near = self._near(o, e, n_l)
        close = np.flatnonzero(near)
        # Every vertex first gets a point uniform on its triangle (area measure, float32) ...
        sq = np.sqrt(r1)
        b = sq * r2
        a = sq - b
        to = [np.take(c0, e) - oc + a * np.take(c1, e) + b * np.take(c2, e)
              for c0, c1, c2, oc in zip(self.emitter_corner32_xyz, self.emitter_edge1_32_xyz,
                                        self.emitter_edge2_32_xyz, o)]
        dist = np.sqrt(to[0] * to[0] + to[1] * to[1] + to[2] * to[2])
        inv = 1.0 / np.where(dist > 0, dist, 1.0)
        dl = np.empty((k, 3), np.float32)
        for i in range(3):
            dl[:, i] = to[i] * inv
        # ... then the close ones a direction uniform in the solid angle (float64: the spherical
        # construction loses precision), and the distance to the triangle's plane along it.
        if len(close):
            ec = np.take(e, close)
            oc = _rows(origin, close).astype(np.float64)
            dl_close, omega = spherical_triangle_sample(_rows(self.emitter_corners64, ec) - oc[:, None, :],
                                                        np.take(r1, close), np.take(r2, close))
            nc = _rows(self.emitter_normal64, ec)
            denom = _dot(dl_close, nc)
            t = _dot(_rows(self.emitter_corner64, ec) - oc, nc) / np.where(denom != 0, denom, 1e-300)
            dl[close] = dl_close
            dist[close] = np.where((denom != 0) & (t > 0) & (omega > 0), t, 0.0)
            solid_angle = np.zeros(k)
            solid_angle[close] = omega
        d = (dl[:, 0], dl[:, 1], dl[:, 2])
        cos_y = _dot3((normals[:, 0], normals[:, 1], normals[:, 2]), d)
        cos_l = -_dot3(n_l, d)
        if self.any_two_sided:
            cos_l = np.where(np.take(self.emitter_two_sided, e), np.abs(cos_l), cos_l)
        ok = np.flatnonzero((cos_y > 0) & (cos_l > 0) & (dist > 0))
        if len(ok) == 0:
            return out
        tmax = np.maximum(np.take(dist, ok) - self.eps, 0.0)
        blocked = self.caster.occluded(_rows(origin, ok), _rows(dl, ok), tmax)
        stats.shadow_rays += len(ok)
        vis = ok[~blocked]
        if len(vis) == 0:
            return out
        ev = np.take(e, vis)
        dv = np.take(dist, vis)
        p_light = np.take(self.emitter_pdf_area, ev) * dv * dv / np.take(cos_l, vis)
        solid = np.flatnonzero(np.take(near, vis))
        if len(solid):
            p_light[solid] = (np.take(self.emitter_prob, np.take(ev, solid))
                              / np.maximum(np.take(solid_angle, np.take(vis, solid)), 1e-300))
        q = np.take(cos_y, vis) * np.float32(INV_PI)
        weight = q / (p_light + q) if mis else q / p_light
        out[vis] = _rows(self.emitter_radiance, ev) * weight[:, None]
        return out

    def direct_light(self, points, normals, rng, stats=None):
        """D_e(y) (k, 3) = (1/π) ∫ L_e cos θ dω at surface points y with normals ``normals``
        (the side that is lit), by light sampling alone: one shadow ray each (:meth:`_direct`
        with ``mis=False``)."""
        stats = stats if stats is not None else TraceStats()
        return self._direct(np.ascontiguousarray(points, dtype=np.float32),
                            np.ascontiguousarray(normals, dtype=np.float32), rng, stats, mis=False)

    def _near(self, origins, e, n_l=None):
        """Light-sampling strategy per (ray origin ``origins`` float32, (k, 3) or its three (k,)
        components, emitter triangle ``e``), as Cycles chooses it: solid-angle sampling when the
        triangle's longest edge exceeds the origin's distance to its plane (``n_l``: the
        triangles' normals per component, if already gathered). NEE and the MIS weight of emitter hits both call this
        with the same float32 origins, so they always agree on the strategy."""
        o = origins if isinstance(origins, tuple) else (origins[:, 0], origins[:, 1], origins[:, 2])
        if n_l is None:
            n_l = tuple(np.take(c, e) for c in self.emitter_normal32_xyz)
        d_plane = _dot3(o, n_l) - np.take(self.emitter_plane32, e)
        return np.take(self.emitter_longest2, e) > d_plane * d_plane

    def _emission_hits(self, origins, d, tri, dist, cos_from, rays):
        """BSDF-sampling half of the MIS estimate for the rays ``rays (k,)`` of a wavefront (from
        a vertex y_k, k >= 1) that hit geometry: ``(lit, values)``, the rays among them that hit
        an emitter's emitting side and their ``L_e · q / (q + p_L)`` (k_lit, 3), to be multiplied
        by ``β w`` (``cos_from``: cos θ of the ray at the vertex it left; q = cos θ / π, see
        ``_direct``)."""
        none = np.zeros(0, dtype=np.int64), np.zeros((0, 3), np.float32)
        if self.n_emitter_triangles == 0:
            return none
        ray = rays[self.triangle_emitter_pdf_area[tri[rays]] > 0]
        if len(ray) == 0:
            return none
        t = tri[ray]
        cos_l = -_dot(_rows(self.face_normals, t), _rows(d, ray))
        cos_l = np.where(self.triangle_two_sided[t], np.abs(cos_l), cos_l)
        lit = np.flatnonzero(cos_l > 0)
        ray, t, cos_l = ray[lit], t[lit], cos_l[lit]
        p_light = self.triangle_emitter_pdf_area[t] * dist[ray] ** 2 / cos_l
        e = self.triangle_emitter_index[t]
        o32 = _rows(origins, ray)
        near = np.flatnonzero(self._near(o32, e))
        if len(near):
            omega = spherical_triangle_solid_angle(_rows(self.emitter_corners64, e[near])
                                                   - _rows(o32, near).astype(np.float64)[:, None, :])
            p_light[near] = self.emitter_prob[e[near]] / np.maximum(omega, 1e-300)
        q = cos_from[ray] * INV_PI
        return ray, _rows(self.scene_emission, t) * (q / (q + p_light))[:, None]

    # -- the wavefront loop ----------------------------------------------------------------------
    def trace(self, points, normals, states, u_first, u_mix, rng, objects=None):
        """Estimates I(x) = E_ind/π for paths starting at ``points (n, 3)`` on surfaces with
        normals ``normals (n, 3)`` (the side that is baked).

        states   (n,) nearest compatible state of each start point (-1: none; ignored UNGUIDED)
        u_first  (n, 2) uniforms of the first direction (stratified by the caller)
        u_mix    (n,) uniforms choosing guide vs cosine at the first vertex
        rng      numpy Generator for everything else
        Returns ``(values (n, 3) float32, TraceStats)``; the mean of the values is unbiased for
        I (biased by the solution's discretisation in FINAL_GATHER).
        """
        n = len(points)
        stats = TraceStats(paths=n)
        L = np.zeros((n, 3), np.float32)
        if n == 0:
            return L, stats
        idx = np.arange(n)
        pos = np.ascontiguousarray(points, dtype=np.float32)
        nrm = np.ascontiguousarray(normals, dtype=np.float32)
        states = np.asarray(states, dtype=np.int64) if self.guide is not None else np.full(n, -1)
        d, w, cos_prev = self._sample(nrm, states, np.asarray(u_first, np.float64), np.asarray(u_mix), first=True)
        beta = np.ones((n, 3), np.float32)
        keep = np.flatnonzero(w > 0)
        idx, pos, nrm, d, w, cos_prev, beta = _select_rows(keep, idx, pos, nrm, d, w, cos_prev, beta)
        bounce = 1
        while len(idx):
            origin = pos + self.eps * nrm
            tri, dist, bu, bv = self.caster.intersect(origin, d, barycentrics=True)
            stats.rays += len(idx)
            hit = tri >= 0
            h = np.flatnonzero(hit)
            if bounce >= 2:
                # Light found by the direction sampled at y_{bounce-1}: world and emitters (MIS).
                bw = beta * w[:, None]
                if self.world_lit and len(h) < len(idx):
                    miss = np.flatnonzero(~hit)
                    L[idx[miss]] += _rows(bw, miss) * self.world
                if len(h):
                    lit, value = self._emission_hits(origin, d, tri, dist, cos_prev, h)
                    L[idx[lit]] += _rows(bw, lit) * value
            if bounce > self.max_bounces:
                break
            idx, origin, d, w, beta, tri, dist, bu, bv = _select_rows(h, idx, origin, d, w, beta, tri, dist, bu, bv)
            pos = origin + d * dist[:, None]
            ng = _rows(self.face_normals, tri)
            front = _dot(ng, d) < 0
            nrm = np.where(front[:, None], ng, -ng)
            beta = beta * (w[:, None] * _rows(self.albedo, tri))
            stats.vertices += len(idx)
            objs = self.objects[tri]
            if bounce == 1 and self.gather is not None:
                value = self.gather.value_at(tri, bu, bv, pos, nrm, front, objs)
                done = ~np.isnan(value[:, 0]) & ~self.gather.too_close(dist, objs)
                # Radiance leaving y_1: ρ (ẑ_ind + D_e), the direct part by light sampling at
                # y_1 itself (see baking.build_gather); the path ends here.
                g = np.flatnonzero(done)
                direct = self.direct_light(_rows(pos, g), _rows(nrm, g), rng, stats)
                L[idx[g]] += _rows(beta, g) * (value[g].astype(np.float32) + direct)
                stats.gathered += int(done.sum())
                stats.gather_fallback += int((~done).sum())
                live = np.flatnonzero(~done)
                idx, pos, nrm, beta, tri, bu, bv, front, objs = _select_rows(
                    live, idx, pos, nrm, beta, tri, bu, bv, front, objs)
            alive = _channel_max(beta) > 0
            if not np.all(alive):
                idx, pos, nrm, beta, tri, bu, bv, front, objs = _select_rows(
                    np.flatnonzero(alive), idx, pos, nrm, beta, tri, bu, bv, front, objs)
            if len(idx) == 0:
                break
            vstates = np.full(len(idx), -1, dtype=np.int64)
            if self.guide is not None:
                vstates = self.guide.states_at_hits(tri, bu, bv, pos, nrm, front, objs)
                stats.guided_vertices += int(np.count_nonzero(vstates >= 0))
            L[idx] += beta * self._direct(pos, nrm, rng, stats)
            if bounce >= self.rr_start:
                q = np.minimum(_channel_max(beta), 1.0)
                survive = np.flatnonzero(rng.random(len(idx), dtype=np.float32) < q)
                beta = _rows(beta, survive) / q[survive, None]
                idx, pos, nrm, vstates = _select_rows(survive, idx, pos, nrm, vstates)
                if len(idx) == 0:
                    break
            u = rng.random((len(idx), 3))
            d, w, cos_prev = self._sample(nrm, vstates, u[:, :2], u[:, 2], first=False)
            keep = w > 0
            if not np.all(keep):
                idx, pos, nrm, d, w, cos_prev, beta = _select_rows(np.flatnonzero(keep), idx, pos, nrm, d, w,
                                                               cos_prev, beta)
            bounce += 1
        return L, stats


def _concentric32(u, v):
    """Shirley–Chiu's concentric map of the unit square to the disk in float32 (as
    ``hemisphere.concentric_square_to_disk``, without its four-way select)."""
    a = 2.0 * np.asarray(u, dtype=np.float32) - 1.0
    b = 2.0 * np.asarray(v, dtype=np.float32) - 1.0
    use_a = np.abs(a) > np.abs(b)
    r = np.where(use_a, a, b)
    ratio = np.where(use_a, b, a) / np.where(r != 0, r, 1.0)
    phi = np.where(use_a, np.float32(QUARTER_PI) * ratio,
                   np.float32(2 * QUARTER_PI) - np.float32(QUARTER_PI) * ratio)
    return r * np.cos(phi), r * np.sin(phi)


def _dot(x, y):
    """Row-wise dot products of (k, 3) arrays, per component (about 2.5 x faster than
    ``einsum('ij,ij->i')`` on float32 rows in numpy 1.26)."""
    return x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1] + x[:, 2] * y[:, 2]


def _select_rows(index, *arrays):
    """The rows ``index`` of every array (the live paths of a wavefront)."""
    return tuple(np.take(a, index, axis=0) for a in arrays)


def _rows(a, index):
    """``a[index]`` along the first axis (``np.take``: several times faster than fancy indexing
    for the small row tables and long index arrays of the hot loop)."""
    return np.take(a, index, axis=0)


def _channel_max(rgb):
    """Largest of the three channels of (k, 3) values (faster than ``max(axis=1)``)."""
    return np.maximum(np.maximum(rgb[:, 0], rgb[:, 1]), rgb[:, 2])


def _unit3(x, y, z):
    """Unit vectors given as three (k,) component arrays (zero vectors stay zero). The
    spherical-triangle routines work on components: contiguous (k,) arrays are several times
    faster in numpy than the strided columns of (k, 3) arrays."""
    n = np.sqrt(x * x + y * y + z * z)
    inv = 1.0 / np.where(n > 0, n, 1.0)
    return x * inv, y * inv, z * inv


def _cross3(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _corner_units(corners):
    return tuple(_unit3(corners[:, i, 0], corners[:, i, 1], corners[:, i, 2]) for i in range(3))


def _solid_angle_of_units(A, B, C):
    """Van Oosterom & Strackee (1983): tan(Ω/2) = |A·(B x C)| / (1 + A·B + B·C + C·A)."""
    return 2.0 * np.arctan2(np.abs(_dot3(A, _cross3(B, C))), 1.0 + _dot3(A, B) + _dot3(B, C) + _dot3(C, A))


def spherical_triangle_solid_angle(corners):
    """Solid angle (k,) of triangles ``corners (k, 3, 3)`` given relative to the viewpoint
    (Van Oosterom & Strackee 1983)."""
    return _solid_angle_of_units(*_corner_units(corners))


def spherical_triangle_sample(corners, u1, u2):
    """Directions (k, 3) uniform in the solid angle of triangles ``corners (k, 3, 3)`` (relative
    to the viewpoint) from uniforms ``u1, u2``, and the solid angles (k,) (Arvo 1995).

    The pdf of a returned direction is 1 / solid angle. Degenerate triangles get solid angle 0.
    """
    A, B, C = _corner_units(corners)
    n_ab, n_ac = _unit3(*_cross3(A, B)), _unit3(*_cross3(A, C))
    cos_a = np.clip(_dot3(n_ab, n_ac), -1.0, 1.0)   # the triangle's angle α at A
    sin_a = np.sqrt(1.0 - cos_a * cos_a)
    alpha = np.arccos(cos_a)
    # Its area (solid angle) is the spherical excess α + β + γ - π; Van Oosterom's formula gives
    # the same number without the other two angles, and is the one the MIS weights use.
    omega = _solid_angle_of_units(A, B, C)
    a_hat = u1 * omega                                # the sub-triangle's area
    s, t = np.sin(a_hat - alpha), np.cos(a_hat - alpha)
    u = t - cos_a
    ab, ca = _dot3(A, B), _dot3(C, A)
    v = s + sin_a * ab
    den = (v * s + u * t) * sin_a
    q = np.clip(((v * t - u * s) * cos_a - v) / np.where(den != 0, den, 1e-300), -1.0, 1.0)
    perp = _unit3(*(C[i] - ca * A[i] for i in range(3)))
    sq = np.sqrt(np.maximum(1.0 - q * q, 0.0))
    c_hat = tuple(q * A[i] + sq * perp[i] for i in range(3))   # the new third corner
    cb = _dot3(c_hat, B)
    z = 1.0 - u2 * (1.0 - cb)                                   # uniform along the arc B..c_hat
    perp = _unit3(*(c_hat[i] - cb * B[i] for i in range(3)))
    sz = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    d = np.stack([z * B[i] + sz * perp[i] for i in range(3)], axis=1)
    ok = (omega > 1e-12) & np.isfinite(d).all(axis=1)
    return np.where(ok[:, None], d, np.stack(B, axis=1)), np.where(ok, omega, 0.0)


def _rotate_out(frames, x, y, z):
    """World directions (k, 3) of local coordinates ``x, y, z (k,)`` in ``frames (k, 3, 3)``
    (rows t, b, n): ``x t + y b + z n``, per component."""
    out = np.empty((len(frames), 3), np.float32)
    for j in range(3):
        out[:, j] = x * frames[:, 0, j] + y * frames[:, 1, j] + z * frames[:, 2, j]
    return out


def _rotate_in(frames, d):
    """Local coordinates (k, 3) of world directions ``d (k, 3)`` in ``frames (k, 3, 3)``."""
    out = np.empty((len(frames), 3), np.float32)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    for i in range(3):
        out[:, i] = frames[:, i, 0] * dx + frames[:, i, 1] * dy + frames[:, i, 2] * dz
    return out


def _local_to_world(n, x, y, z):
    """World directions (k, 3) float32 of local coordinates ``x, y, z (k,)`` in the frames
    (t, b, n) of unit normals ``n (k, 3)``: Duff et al.'s branchless tangent frame, formed per
    component (contiguous (k,) arrays; faster than (k, 3) products in numpy)."""
    n = np.asarray(n)
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    out = np.empty((len(n), 3), np.float32)
    out[:, 0] = (1.0 + sign * nx * nx * a) * x + b * y + nx * z
    out[:, 1] = sign * b * x + (sign + ny * ny * a) * y + ny * z
    out[:, 2] = -sign * nx * x - ny * y + nz * z
    return out
