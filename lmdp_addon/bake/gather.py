"""Final gather: the PHYSICAL solution's indirect irradiance/π ẑ_ind read at a path's first hit.

FINAL_GATHER draws a texel's first direction as GUIDED does; at its hit y_1 the solution
replaces the rest of the path: ``L_r(y_1) ≈ ρ(y_1) (ẑ_ind(y_1) + D_e(y_1))``, ẑ_ind interpolated
between the nearby compatible states (:class:`GatherField`) and D_e the direct light at y_1
itself by light sampling. Hits without a nearby compatible state, back-face hits and hits closer
to the vertex than half a state spacing (:meth:`GatherField.too_close`) continue as a GUIDED
path. Biased by the discretisation of ẑ_ind.

* :func:`build_gather`: ẑ_ind of every state point from the solved LMDP (thesis eq. 2.22 for
  the light arriving at the states), its source :func:`direct_after_one_bounce`;
* :class:`GatherField`: ẑ_ind between the states (tabulated on the locator's grid).

The gather reuses the build's ray caster (BVH) and locator: it reads the states of the same
scene.
"""
from dataclasses import dataclass

import numpy as np

from .. import world as world_light
from ..bsdf import GlossyRows, VertexBSDF, lambertian_albedo, lambertian_albedo_at
from ..lights import EmitterSampler
from ..raycast import RayCaster
from ..sampling import cosine_directions

#: FINAL_GATHER path-traces first hits closer than this many state spacings of the hit object
#: (:meth:`GatherField.too_close`): ẑ there stands for a neighbourhood the vertex itself is part
#: of; the limit trades that bias near contacts against the time of the paths traced instead.
GATHER_MIN_SPACINGS = 0.5
#: Rays per state point of :func:`direct_after_one_bounce`: ``GATHER_RAY_BUDGET`` rays in all,
#: between ``GATHER_RAYS_MIN`` and ``GATHER_RAYS_MAX`` per point (squares: a stratified grid).
GATHER_RAY_BUDGET = 1 << 18
GATHER_RAYS_MIN = 9
GATHER_RAYS_MAX = 64


@dataclass
class GatherField:
    """Irradiance/π ẑ of the PHYSICAL solution, interpolated between states: the *indirect*
    part ẑ_ind, the light that arrives after at least one reflection (:func:`build_gather`;
    the tracer adds the direct part at the gather point).

    ``value_at(...)`` returns (k, 3) ẑ at surface points (NaN where no compatible state is
    near): inverse-squared-distance weights over the ``neighbours`` nearest compatible states
    of the same object (6-D distance of ``StateLocator``: position and spacing·normal). For front
    hits on state-carrying triangles of the solved scene, the value is tabulated on the locator's
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
        ``min_spacings`` times the state spacing of their object (``objects``: the traced
        scene's object indices; objects without states never are).

        ẑ is interpolated over states about a spacing apart, so it stands for the light of a
        neighbourhood of that size; a hit much closer than that to the vertex sees a
        neighbourhood the vertex itself is part of, such as the floor under a box between the
        bumps it stands on, where the nearest states lie outside the box and ẑ is far too bright
        (:data:`GATHER_MIN_SPACINGS`). Those paths continue by path tracing.
        """
        obj = np.asarray(objects)
        if self.object_map is not None:
            obj = np.where(obj >= 0, self.object_map[np.maximum(obj, 0)], -1)
        spacing = np.where(obj >= 0, np.take(self.locator.spacing, np.maximum(obj, 0)), 0.0)
        return distances < self.min_spacings * spacing

    def value_at(self, tri, bu, bv, positions, side_normals, front, objects):
        """ẑ (k, 3) at ray hits (triangle, barycentrics, positions, the side's normals, front
        flags, traced-scene objects); NaN where no compatible state is near and at back faces."""
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


def gather_rays_per_point(n_points):
    """Rays per point of :func:`direct_after_one_bounce`: a square, about the budget / points."""
    side = int(np.sqrt(max(GATHER_RAY_BUDGET // max(int(n_points), 1), 1)))
    return int(np.clip(side, np.sqrt(GATHER_RAYS_MIN), np.sqrt(GATHER_RAYS_MAX))) ** 2


def direct_after_one_bounce(lmdp, rays_per_point, seed=0, points=None):
    """b (m, 3): the direct light that reaches each state point after one reflection,

        b(x) = ∫ ρ(h) D_e(h) cos θ / π dω,     h the surface that x sees in direction ω,

    estimated with ``rays_per_point`` cosine-distributed rays per point (a jittered square
    grid through the concentric map) and one light sample at each hit (on a glossy hit its
    BSDF's ``f cos`` towards x replaces ``ρ(h) cos θ / π``) (``D_e`` by
    :meth:`~lmdp_addon.lights.EmitterSampler.direct_light` and the lamps'
    :meth:`~lmdp_addon.lamps.Lamps.direct_light`, as the tracer samples it; plus the world's by
    :func:`~lmdp_addon.world.next_event` when the scene has an environment map). Rays that
    escape or meet an emitter or the back of a face give 0 (the direct light of x itself and the
    void of the passive dynamics). Hidden (buried) points get 0, and so do the points not in
    ``points`` (indices; default all). The build's ray caster and its locator's ``targets``
    (the points hits may land on) are reused when the dynamics has them."""
    states, dynamics = lmdp.states, lmdp.dynamics
    scene = lmdp.scene
    caster = dynamics.caster if dynamics.caster is not None else RayCaster(scene)
    m = states.n_points
    b = np.zeros((m, 3))
    if m == 0:
        return b
    lights = EmitterSampler(scene)
    environment = _environment(scene)
    targets = dynamics.locator.targets if dynamics.locator is not None else None
    live = np.arange(m) if points is None else np.unique(np.asarray(points, dtype=np.int64))
    if targets is not None:
        live = live[targets[live]]
    n = int(round(np.sqrt(rays_per_point)))
    R = n * n
    rng = np.random.default_rng([int(seed), 0xD1EC7])
    cell = np.arange(R)
    face_normals = scene.triangle_geometry()[0].astype(np.float32)
    albedo = np.clip(lambertian_albedo(scene), 0.0, 1.0)   # glossy: their hemispherical albedo
    reflects = (albedo.max(axis=1) > 0) & ~scene.is_emissive()
    corners = scene.corners()
    lifted = caster.lift(states.points, states.normals, states.point_triangle)
    smooth = scene.has_smooth_normals() and states.shading_normals is not None
    shading = states.bsdf_normals
    glossy = scene.glossy_triangles() if scene.has_glossy() else None
    per_chunk = max(1, GATHER_RAY_BUDGET // R)
    for start in range(0, len(live), per_chunk):
        ids = live[start:start + per_chunk]
        k = len(ids)
        u = np.empty((k * R, 2))
        u[:, 0] = (np.tile(cell // n, k) + rng.random(k * R)) / n
        u[:, 1] = (np.tile(cell % n, k) + rng.random(k * R)) / n
        owner = np.repeat(ids, R)
        d = cosine_directions(shading[owner].astype(np.float32), u, stratified=True)
        origin = lifted[owner].astype(np.float32)
        tint = None
        if lights.transparency is None:
            tri, _, bu, bv = caster.intersect(origin, d, barycentrics=True)
        else:   # transparent surfaces pass rays with probability 1 - alpha (``transparency``)
            tri, _, bu, bv, _, tint = lights.transparency.intersect(caster, origin, d, rng)
        hit = np.flatnonzero(tri >= 0)
        if smooth:   # shading-normal cosine rays below the geometric surface are absorbed (tracer)
            hit = hit[np.einsum("ij,ij->i", states.normals[owner[hit]], d[hit]) > 0]
        t = tri[hit]
        ng = face_normals[t]
        keep = (np.einsum("ij,ij->i", ng, d[hit]) < 0) & reflects[t]
        hit, t, ng = hit[keep], t[keep], ng[keep]
        # The hit point from its barycentrics: on the triangle whatever the ray's length.
        tc = corners[t]
        pos = tc[:, 0] + bu[hit, None] * (tc[:, 1] - tc[:, 0]) + bv[hit, None] * (tc[:, 2] - tc[:, 0])
        if smooth:
            ns = scene.shading_normals(t, bu[hit], bv[hit])        # the front was hit (keep)
        else:
            ns = ng
        # glossy hits reflect the direct light towards x through their BSDF (f cos for -ω)
        bsdf = _glossy_hits(scene, glossy, t, bu[hit], bv[hit], ns, ng, -d[hit]) if glossy is not None else None
        direct = direct_light_at(scene, lights, environment, caster, pos, ns, ng, t, smooth, rng, bsdf)[0]
        value = lambertian_albedo_at(scene, t, bu[hit], bv[hit]) * direct
        if bsdf is not None:   # their light is f cos-weighted already
            value[bsdf.mask] = direct[bsdf.mask]
        if tint is not None:
            value = value * tint[hit]
        for c in range(3):
            b[:, c] += np.bincount(owner[hit], weights=value[:, c], minlength=m)
    return b / R


def direct_light_at(scene, lights, environment, caster, pos, ns, ng, t, smooth, rng, bsdf=None):
    """``(D̂ (k, 3), shadow rays)``: the direct light at front hits ``pos`` on triangles ``t``
    (shading normals ``ns``, geometric ``ng``; ``smooth``: the scene's shading normals differ)
    by one light sample each of the emitters (``lights``), Blender's lights and the environment
    map (``environment``, or None), in that order of random numbers, without MIS, as the tracer
    samples them; ``bsdf`` (:class:`~lmdp_addon.bsdf.GlossyRows`): rows shaded with their f cos."""
    geometric = ng if smooth else None
    lift = caster.offset(t)
    direct, rays = lights.next_event(pos.astype(np.float32), ns.astype(np.float32), rng, caster, mis=False,
                                     lift=lift, geometric=geometric, bsdf=bsdf)
    if not scene.lamps.empty:
        lamp, shadow = scene.lamps.direct_light(pos, ns, rng, caster, lift=lift, geometric=geometric,
                                                transparency=lights.transparency, bsdf=bsdf)
        direct, rays = direct + lamp, rays + shadow
    if environment is not None:    # the world's direct light at the hit, by world sampling
        env, shadow = world_light.next_event(
            environment, pos.astype(np.float32), ns.astype(np.float32), rng, caster, lift.astype(np.float32),
            geometric=None if geometric is None else geometric.astype(np.float32), mis=False,
            transparency=lights.transparency, bsdf=bsdf)
        direct, rays = direct + env, rays + shadow
    return direct, rays


def _glossy_hits(scene, glossy, tri, bu, bv, shading, geometric, towards):
    """:class:`~lmdp_addon.bsdf.GlossyRows` of the hits on glossy triangles (their BSDF set up for
    the direction ``towards`` the point that cast the ray, with the diffuse colour at the hit), or
    None when no hit is glossy."""
    g = np.flatnonzero(glossy[tri])
    if len(g) == 0:
        return None
    vertex = VertexBSDF(scene.materials, scene.triangle_material[tri[g]], scene.albedo_at(tri[g], bu[g], bv[g]),
                        shading[g], towards[g], geometric=geometric[g])
    return GlossyRows(len(tri), g, vertex)


def _environment(scene):
    """The scene's lit :class:`~lmdp_addon.world.EnvironmentMap`, or None (a uniform world)."""
    env = getattr(scene, "environment", None)
    return env if env is not None and env.lit else None


def build_gather(guide, lmdp, max_bounces=None, seed=0):
    """:class:`GatherField` of the PHYSICAL solution: the *indirect* irradiance/π ẑ of every state
    point, the light that reaches it after at least one reflection,

        ẑ = b + w + P_NN (q ⊙ ẑ),       b = :func:`direct_after_one_bounce`,  w = P_NW z_W,

    eq. 2.22 for the light *arriving* at the states, with the direct part of every reflection
    evaluated where the ray lands rather than at the nearest state (the tracer adds the direct
    light of the gather point itself, also by light sampling). Direct light changes within
    millimetres near an emitter: the states at the edge of the gap between a two-sided light and
    the ceiling see the light's back at point-blank range, and the rays that land on the ceiling
    beside the light (which hardly sees it) would read their z; b evaluates it where the rays
    land.

    The recursion runs over the LMDP's unknowns. A glossy unknown (x, k) takes as its source
    ``w + P_kN (q ⊙ D)``, D the direct light of the unknowns it lands on as the LMDP holds it
    (their emitter and lamp columns, ``P_NT z_T``): its BSDF rays are the build's, not those of
    :func:`direct_after_one_bounce`, which samples a cosine lobe. The field holds one ẑ per
    point, a glossy point's the cosine-weighted mean of its directions' (the tracer path-traces
    on from glossy hits).

    With ``max_bounces`` = N the recursion runs from ẑ = w for N - 1 steps: the gather point is
    the path's first vertex, so the light it reads has at most N - 1 more vertices, as the
    tracer's and Cycles' paths of N bounces (the converged ẑ would add the light of every
    longer path). ``max_bounces=None``: the converged solution. With an environment map (HDRI)
    w = 0: its direct light is sampled at the hits (b) and at the gather point (the tracer)
    instead of read from the LMDP's coarse world terminals.
    """
    problem = lmdp.lmdp
    E = len(lmdp.dynamics.emitter_radiance)
    P_NN = problem.P_NN
    q = np.asarray(problem.q, dtype=np.float64)
    # world (W columns) and void (z = 0); the lamps' columns after them are direct light, sampled
    # at the hits
    W1 = lmdp.dynamics.n_world + 1
    w = np.asarray(problem.P_NT[:, E:E + W1] @ problem.z_terminal[E:E + W1], dtype=np.float64)
    if _environment(lmdp.scene) is not None:
        # An environment map: its direct light is sampled where it arrives (b at the hits, the
        # tracer at the gather point), so ẑ is the indirect light alone, from ẑ = 0.
        w = np.zeros_like(w)
    z_hat = w.copy()
    steps = 100_000 if max_bounces is None else int(max_bounces) - 1
    unknowns = lmdp.dynamics.unknown_map
    if steps > 0:
        b = direct_after_one_bounce(lmdp, gather_rays_per_point(lmdp.states.n_points), seed)
        source = b[unknowns.point] + w
        glossy = np.flatnonzero(unknowns.stratum >= 0)
        if len(glossy):
            direct = _direct_columns(lmdp.dynamics, _environment(lmdp.scene) is not None)
            D = np.asarray(problem.P[:, direct] @ problem.z_terminal[direct - problem.n_points], dtype=np.float64)
            source[glossy] = w[glossy] + np.asarray(P_NN[glossy] @ (q * D))
        for _ in range(steps):
            new = source + np.asarray(P_NN @ (q * z_hat))
            converged = np.max(np.abs(new - z_hat)) <= 1e-12 * max(np.max(np.abs(new)), 1e-300)
            z_hat = new
            if converged:
                break
    irradiance = unknowns.point_values(np.maximum(z_hat, 0.0), lmdp.states.stratum_weight)
    return GatherField(locator=guide.locator, irradiance=irradiance, same_scene=guide.same_scene,
                       object_map=guide.object_map)


def _direct_columns(dynamics, world):
    """Columns of P whose terminals the tracer samples as direct light at a gather point: the
    emitters and the lamps, and the world's with an environment map (``world``)."""
    N, E = dynamics.n_unknowns, dynamics.n_emitters
    cols = [np.arange(N, N + E), N + E + dynamics.n_world + 1 + np.arange(dynamics.n_lamps)]
    if world:
        cols.append(dynamics.world_columns)
    return np.concatenate(cols).astype(np.int64)
