"""Passive dynamics (thesis 3.1.2, eq. 3.1) estimated by casting rays through every stratum.

For point x and stratum k, ``rays_per_stratum`` (R) rays leave x through stratum k, drawn with
density proportional to BRDF·cos within the stratum, so each carries exactly ``w_k / R``, where
``w_k = ∫_k cos θ dω / π`` is the Lambertian mass of the stratum; each lands in one next state
(:mod:`~lmdp_addon.model.hits`):

* the nearest state point on the hit object whose normal faces the side that was hit
  (the next state is that point with the reversed ray direction as outgoing direction; on a
  Lambertian point only the point matters, on a glossy one the stratum of that direction: its
  unknown, see below and ``design.md``),
* an emitter terminal (uniform emission: one terminal per emitter group),
* the world terminal (escaping ray, world not black); with an environment map (HDRI) one world
  terminal per equal-area direction bin (``world.bin_of_direction``), whose z is the map's mean
  radiance over the bin, so the solution sees a sky that is not uniform,
* the void terminal (z = 0): geometry that carries no states, back faces (of one-sided emitters
  and of every surface), hits with no compatible state, and escapes into a black world.

Blender's lights (``SceneArrays.lamps``) are terminals too, one column each after the void, that
no ray lands in: the build's rays cross lamps as Cycles' rays do (a light is a transparent surface,
``lamp_hits``), so their transitions come from light samples alone, which carry a lamp's whole
light (:meth:`_DynamicsBuild.lamp_entries`, ``lamps.Lamps.transitions``), with a mass that times
their z_T gives their direct light / π.

Glossy points (a material with a microfacet lobe) carry one unknown per outgoing stratum k
(:mod:`~lmdp_addon.model.unknowns`). Their rows leave x with ``rays_per_stratum`` rays sampled
from the BSDF (:class:`~lmdp_addon.bsdf.VertexBSDF`) for the outgoing direction ω_k, the centre
of stratum k: a ray carries ``lum(f cos / p) / (R lum(a_k))``, with ``a_k`` (RGB) the directional
albedo (:func:`directional_albedo`; the state cost's ``q`` in PHYSICAL mode, ``costs.py``), so
``a_k`` times the row is the unbiased estimate of ∫ f(ω_i, ω_k) cos θ_i (...) dω_i (eq. 3.1 with
a non-Lambertian BRDF; the luminance carries the colour of f's shape, exact when f's colour does
not depend on ω_i) and the row sums to one in expectation. Their next-event samples (emitters, lamps) are weighted
by ``f cos`` for ω_k. A ray that lands on a glossy point goes to the unknown of the stratum that
contains the reversed ray direction there; on a Lambertian point to its one unknown. Glossy points
also keep their cosine stratum rows (``stratum_transitions``, read by the guide).

Buried points (:func:`~lmdp_addon.model.locator.buried_points`: inside solids, pressed against
other objects, over the back of a lamp) are states no ray lands on, and their own rays all go to
the void.

The estimate of each p(x'|x) is unbiased, and since the stratum masses sum to one and every ray
lands somewhere, each row of P sums to exactly one (its lamp columns left out).
No Python loop runs over rays or states: rays are generated, traced and binned in large batches
(:class:`_DynamicsBuild`), several at a time on a small thread pool.
"""
import time
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import BudgetError
from ..farm import session as farm_session
from ..bsdf import VertexBSDF
from .hemisphere import stratum_centers, stratum_of_local_direction
from .hits import HitClassifier
from ..lights import EmitterSampler
from .locator import StateLocator, buried_points
from .patterns import DirectionPatterns, LightPatterns
from ..raycast import RayCaster
from ..scene_arrays import LUMINANCE
from ..transparency import ABSORBED
from .unknowns import identity_map
from ..world import world_bin_count

#: Column roles after the point columns.
WORLD = "world"
VOID = "void"

#: Target rays per batch of the build loop. Small enough that even a build of a few thousand
#: points is cut into several batches that overlap on the cores.
RAYS_PER_BATCH = 1 << 16
#: Batches processed concurrently.
BUILD_THREADS = 3
#: BSDF samples and evaluations of the glossy unknowns done at once.
GLOSSY_CHUNK = 1 << 15


@dataclass
class PassiveDynamics:
    """Sparse passive dynamics p(x'|x) of the point-level states plus the terminal states.

    stratum_transitions  CSR (m*S, n) float32: row ``i*S + k`` holds the mass that rays leaving
                         point i through stratum k deliver to each next state (sums to w_k, the
                         stratum's cosine mass ∫_k cos θ dω / π), cosine rays on every point
    P                    CSR (N, n) float32: passive dynamics of the unknowns (one per Lambertian
                         point, S per glossy point: ``unknowns``), rows sum to 1
    n_points, n_strata   m, S
    unknowns             the :class:`~lmdp_addon.model.unknowns.UnknownMap` (N = its n_unknowns)
    glossy_albedo        (G*S, 3) float64 directional albedo a_k of the glossy unknowns, in
                         unknown order (the state cost's q, ``costs.py``), or None
    emitter_radiance     (E, 3) radiance of each emitter terminal (W / sr m^2)
    emitter_names        E names (the emitting objects)
    world_radiance       (3,) radiance of the world terminal (the world's mean with an environment map)
    world_bins           (W, 3) radiance of each directional world terminal (an environment map:
                         the map's mean over the equal-area bin, ``world.bin_of_direction``), or
                         None: one world terminal of ``world_radiance``
    rays_per_stratum     R
    counts               rays per landing category (points, emitters, world, void reasons)
    seconds              wall time of the build's parts (setup, locator, trace, bin, total)
    locator              the :class:`~lmdp_addon.model.locator.StateLocator` the hits were
                         mapped with (buried points excluded: ``locator.targets``)
    warnings             messages for the user (objects mostly buried)
    caster               the :class:`~lmdp_addon.raycast.RayCaster` (BVH) the rays were traced
                         with; the bake of the same scene traces with it too
    lamp_radiance        (L, 3) z_T of each lamp terminal (``Lamps.emission``)
    lamp_names           L names (the light objects)
    Columns: ``0..N-1`` unknowns (N = m without glossy points), ``N..N+E-1`` emitters,
    ``N+E..N+E+W-1`` world (W = 1 for a uniform world), ``N+E+W`` void, ``N+E+W+1..`` lamps
    (Blender's lights: reached only through light samples, ``lamps.py``).
    """

    stratum_transitions: sp.csr_matrix
    P: sp.csr_matrix
    n_points: int
    n_strata: int
    emitter_radiance: np.ndarray
    emitter_names: list
    world_radiance: np.ndarray
    rays_per_stratum: int
    counts: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    locator: object = field(default=None, repr=False)
    warnings: list = field(default_factory=list)
    caster: object = field(default=None, repr=False)
    world_bins: np.ndarray = None
    lamp_radiance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    lamp_names: list = field(default_factory=list)
    unknowns: object = field(default=None, repr=False)
    glossy_albedo: np.ndarray = None
    glossy_rays: int = 0

    @property
    def n_unknowns(self):
        """N: the unknowns of the solve (= n_points without glossy points)."""
        return self.n_points if self.unknowns is None else self.unknowns.n_unknowns

    @property
    def unknown_map(self):
        """The :class:`~lmdp_addon.model.unknowns.UnknownMap` (one unknown per point if unset)."""
        if self.unknowns is None:
            return identity_map(self.n_points, self.n_strata, 1)
        return self.unknowns

    @property
    def n_emitters(self):
        return len(self.emitter_radiance)

    @property
    def n_world(self):
        """W: world terminals (1 uniform, one per direction bin with an environment map)."""
        return 1 if self.world_bins is None else len(self.world_bins)

    def world_terminal_radiance(self):
        """(W, 3) radiance of the world terminals."""
        if self.world_bins is None:
            return np.asarray(self.world_radiance, dtype=np.float64).reshape(1, 3)
        return np.asarray(self.world_bins, dtype=np.float64).reshape(-1, 3)

    @property
    def n_lamps(self):
        return len(self.lamp_radiance)

    @property
    def n_terminals(self):
        return self.n_emitters + self.n_world + 1 + self.n_lamps

    @property
    def n_columns(self):
        return self.n_unknowns + self.n_terminals

    @property
    def world_column(self):
        """The first world column (the only one for a uniform world)."""
        return self.n_unknowns + self.n_emitters

    @property
    def world_columns(self):
        return np.arange(self.world_column, self.world_column + self.n_world)

    @property
    def void_column(self):
        return self.n_unknowns + self.n_emitters + self.n_world

    @property
    def rays(self):
        return self.n_points * self.n_strata * self.rays_per_stratum + self.glossy_rays

    def terminal_labels(self):
        world = [WORLD] if self.world_bins is None else [f"{WORLD}:{k}" for k in range(self.n_world)]
        return ([f"emitter:{n}" for n in self.emitter_names] + world + [VOID]
                + [f"lamp:{n}" for n in self.lamp_names])

    @property
    def row_sum_error(self):
        """Largest deviation of a row sum of P from 1 (float32 rounding without next-event
        estimation; Monte Carlo noise of the emitter terms with it, and of the glossy unknowns'
        BSDF weights, whose rows sum to one in expectation). The lamps' columns are left out:
        their masses are light, not probabilities (``lamps.py``)."""
        P = self.P[:, :self.n_columns - self.n_lamps] if self.n_lamps else self.P
        sums = np.asarray(P.sum(axis=1)).ravel()
        if self.glossy_albedo is not None:   # glossy unknowns that reflect nothing have empty rows
            u = self.unknown_map
            dark = np.zeros(len(sums), dtype=bool)
            dark[u.glossy[u.point] & (u.stratum >= 0)] = ~(self.glossy_albedo @ LUMINANCE > 0)
            sums = sums[~dark]
        return float(np.abs(sums - 1.0).max()) if len(sums) else 0.0

    def memory_bytes(self):
        return sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
                   for m in (self.stratum_transitions, self.P))

    def summary(self):
        c = self.counts
        total = max(sum(c.get(k, 0) for k in ("points", "emitters", "world", "void")), 1)
        nee = (f" + {c['nee_rays']} shadow rays to the emitters" if c.get("nee_rays") else "")
        buried = (f"; {c['buried_points']} buried points (inside or under other geometry: no light, "
                  "no ray lands on them)" if c.get("buried_points") else "")
        glossy = (f" ({self.n_unknowns} unknowns: {self.unknown_map.n_glossy} glossy points x "
                  f"{self.n_strata} directions)" if self.n_unknowns != self.n_points else "")
        return (f"{self.n_unknowns} x {self.n_columns} passive dynamics{glossy}, nnz {self.P.nnz} "
                f"({self.stratum_transitions.nnz} per stratum), {self.rays} rays{nee}: "
                f"{100 * c.get('points', 0) / total:.1f}% to states, "
                f"{100 * c.get('emitters', 0) / total:.1f}% to emitters, "
                f"{100 * c.get('world', 0) / total:.1f}% to the world, "
                f"{100 * c.get('void', 0) / total:.1f}% to the void{buried}")


def estimate_build_bytes(n_points, n_strata, rays_per_stratum, light_samples=0, n_triangles=0,
                         n_glossy=0):
    """Upper estimate of the peak memory of :func:`build_passive_dynamics` (bytes).

    ``n_glossy`` glossy points add S unknowns each: S x R BSDF rays (the same 32 B per ray as
    the stratum rays, and 56 B for the samples kept for the build), their S x K light-sample
    entries (48 B each), and 1 KiB per unknown for its BSDF's set-up (``VertexBSDF``; its
    evaluations run in chunks of :data:`GLOSSY_CHUNK`). Checked against the peak growth of
    builds of 433 to 8192 glossy points (K = 32 to 256): 70 to 809 MiB, estimated 148 to 1065.

    Terms, with coefficients fitted to the build's peak resident memory in its own process
    (``bench/worker.py``; ``make bench`` reports the measured peak next to this estimate) and
    rounded up: 32 B per stratum ray (it can become a non-zero of the stratum-resolved matrix
    and of P, float32 + int32, twice during assembly), 48 B per light sample, 2 KiB per point
    (state arrays, the locator's grid of about 16 to 24 cells per point and its temporaries),
    768 B per triangle (the embree BVH and per-triangle tables, built at the same time as the
    locator's grid, which has at least one cell per triangle), 200 B per ray of the
    ``BUILD_THREADS`` batches in flight, and 8 MiB of fixed overhead. The peak depends on how
    the locator's grid and the first batches overlap, so the coefficients cover the heaviest
    of several runs.
    """
    rays = int(n_points) * int(n_strata) * int(rays_per_stratum)
    glossy_rays = int(n_glossy) * int(n_strata) * int(rays_per_stratum)
    glossy = ((32 + 56) * glossy_rays + 48 * int(n_glossy) * int(n_strata) * int(light_samples)
              + 1024 * int(n_glossy) * int(n_strata))
    return (glossy + 32 * rays + 48 * int(n_points) * int(light_samples) + 2048 * int(n_points)
            + 768 * int(n_triangles) + 200 * min(rays, BUILD_THREADS * RAYS_PER_BATCH) + 8 * 1024 ** 2)


def check_budget(n_points, n_strata, rays_per_stratum, budget_gb, light_samples=0, n_triangles=0,
                 n_glossy=0):
    """Raise :class:`BudgetError` when the estimated build memory exceeds ``budget_gb``."""
    need = estimate_build_bytes(n_points, n_strata, rays_per_stratum, light_samples, n_triangles, n_glossy)
    if budget_gb is not None and need > budget_gb * 1024 ** 3:
        raise BudgetError(
            f"Building the dynamics for {n_points} points x {n_strata} strata x "
            f"{rays_per_stratum} rays would need about {need / 1024 ** 3:.1f} GiB, above the "
            f"memory budget of {budget_gb:g} GiB: lower Point Count, the strata or Rays per "
            "Stratum, or raise the Memory Budget setting")
    return need



#: cos θ nodes of :func:`directional_albedo`'s table, and its samples per node (n x n, stratified).
ALBEDO_NODES = 33
ALBEDO_SAMPLES = 16


def directional_albedo(materials, material, diffuse, mu):
    """(k, 3) directional albedo ``a(μ) = ∫ f(ω_i, ω_o) cos θ_i dω_i`` of the BSDFs of ``material
    (k,)`` with diffuse colour ``diffuse (k, 3)`` for outgoing directions at ``cos θ_o = mu (k,)``
    from the microfacet normal (``VertexBSDF.mu``), clipped to [0, 1]. Linear in the diffuse
    colour, so each material is tabulated once, white and black, at :data:`ALBEDO_NODES` cosines
    (``VertexBSDF.albedo`` with 16 x 16 stratified samples, within about 0.5 % of 32 x 32), and
    read by linear interpolation; 0 where μ <= 0. Directions that a smooth shading normal sends
    below the geometric surface are not taken out (the rays' own weights are)."""
    material = np.asarray(material, dtype=np.int64)
    mu = np.asarray(mu, dtype=np.float64)
    diffuse = np.asarray(diffuse, dtype=np.float64)
    used = np.unique(material)
    nodes = np.linspace(0.0, 1.0, ALBEDO_NODES)
    nodes[0] = 1e-3
    n = len(nodes)
    rows = np.repeat(used, n)
    mus = np.tile(nodes, len(used))
    wi = np.stack([np.sqrt(1.0 - mus * mus), np.zeros(len(mus)), mus], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(mus), 1))
    white = VertexBSDF(materials, rows, np.ones((len(mus), 3)), up, wi).albedo(ALBEDO_SAMPLES).reshape(len(used), n, 3)
    black = VertexBSDF(materials, rows, np.zeros((len(mus), 3)), up, wi).albedo(ALBEDO_SAMPLES).reshape(len(used), n, 3)
    out = np.zeros((len(material), 3))
    where = np.searchsorted(used, material)
    for j in range(len(used)):           # loop over materials (a few), not over unknowns
        sel = np.flatnonzero(where == j)
        for c in range(3):
            b = np.interp(mu[sel], nodes, black[j, :, c])
            w = np.interp(mu[sel], nodes, white[j, :, c])
            out[sel, c] = b + np.clip(diffuse[sel, c], 0.0, None) * (w - b)
    return np.clip(np.where((mu > 0)[:, None], out, 0.0), 0.0, 1.0)


def build_passive_dynamics(scene, states, rays_per_stratum=4, seed=0, progress=None,
                           memory_budget_gb=None, caster=None, exact_nearest=False, light_samples=32,
                           farm=None):
    """Estimate the passive dynamics of every state by ray casting (thesis 3.1.2, eq. 3.1).

    With ``light_samples = K > 0`` the transitions into emitter terminals are also estimated by
    next-event estimation: K stratified points on the emitters per state point, one shadow ray
    each, filed under the stratum that contains its direction. The two estimates are combined
    with multiple importance sampling (balance heuristic): a sample in direction ω towards an
    emitter carries

        (cos θ / π) / (K p_light(ω) + R cos θ / (π w_k)),

    whether it is a shadow ray or a stratum ray (of stratum k) that hit the emitter, where
    ``p_light(ω) = pdf_area · d² / cos θ_y`` is the light sampling density in solid angle and
    ``R cos θ / (π w_k)`` the stratum rays' density. This is unbiased; rows sum to one in
    expectation, small distant lights get the low variance of light sampling and surfaces
    right next to a light the low variance of the stratum rays.
    With K = 0 every row sums to exactly one.

    ``memory_budget_gb``: when given, :func:`check_budget` runs first (callers that checked
    already, like :func:`lmdp_addon.model.pipeline.run_build`, leave it None). ``caster``: a
    :class:`~lmdp_addon.raycast.RayCaster` of ``scene`` to reuse (default: a new one).
    ``farm``: a :class:`lmdp_addon.farm.Farm` whose workers trace the batches (the matrices are
    byte-identical); None: the farm in use in this process (``farm.session.use``), if any, else
    the local thread pool.
    """
    R = int(rays_per_stratum)
    if R < 1:
        raise BudgetError(f"Rays per Stratum must be at least 1 (got {R})")
    if memory_budget_gb is not None:
        check_budget(states.n_points, states.n_strata, R, memory_budget_gb, light_samples,
                     scene.n_triangles, states.unknowns.n_glossy)
    with scene.held():
        build = _DynamicsBuild(scene, states, R, seed, caster, exact_nearest, light_samples)
        farm = farm if farm is not None else farm_session.current()
        if farm is None:
            return build.run(progress)
        with farm.build_batches(scene, states, R, seed, exact_nearest, light_samples,
                                build.points_per_batch) as runner:
            return build.run(progress, runner)


class _DynamicsBuild:
    """One run of :func:`build_passive_dynamics` (with the scene's derived geometry held).

    Set-up (:meth:`__init__`) starts the locator's tables on a thread of their own, builds the
    BVH, finds the buried points and draws the ray patterns; :meth:`run` traces the batches of
    points on the thread pool (:meth:`trace_batch`: stratum rays, then the next-event rays of
    :meth:`emitter_entries`) and assembles the sparse matrices.
    """

    def __init__(self, scene, states, R, seed, caster, exact_nearest, light_samples):
        self.t0 = time.perf_counter()
        self.scene, self.states, self.R = scene, states, R
        self.m, self.S = states.n_points, states.n_strata
        self.unknowns = states.unknowns
        self.N = self.unknowns.n_unknowns
        self.emitter_radiance = scene.emitter_groups()[1]
        self.E = len(self.emitter_radiance)
        self.W = world_bin_count(_environment(scene))
        self.lamps = scene.lamps
        self.n_cols = self.N + self.E + self.W + 1 + len(self.lamps)
        self.seed = int(seed)
        self.light_samples = int(light_samples)
        self.face_normals = scene.triangle_geometry()[0]
        # The locator's tables are built on a thread of their own while the BVH is built and the
        # first batches are traced: only the classification of the hits waits for them.
        self.pool = ThreadPoolExecutor(max_workers=BUILD_THREADS + 1)
        buried_known = Future()
        self.tables = self.pool.submit(self._make_classifier, buried_known, exact_nearest)
        try:
            self._set_up_rays(caster, seed, light_samples, buried_known)
        except BaseException as exc:
            if not buried_known.done():
                buried_known.set_exception(exc)
            self.pool.shutdown(wait=True)
            raise
        self.frames = states.frames.astype(np.float32)
        self.t_setup = time.perf_counter() - self.t0
        self.points_per_batch = max(1, RAYS_PER_BATCH // (self.S * R))
        self.weights_per_row = np.repeat(states.stratum_weight / R, R).astype(np.float32)
        self.ray_rows = np.repeat(np.arange(self.points_per_batch * self.S, dtype=np.int32), R)
        self._set_up_glossy()

    def _make_classifier(self, buried_known, exact_nearest):
        """On the pool: the locator (without the buried points) and its :class:`HitClassifier`."""
        tl = time.perf_counter()
        locator = StateLocator(self.scene, self.states, exact=exact_nearest)
        locator.exclude(buried_known.result(), self.states)
        return locator, HitClassifier(self.scene, locator, self.m), time.perf_counter() - tl

    def _set_up_rays(self, caster, seed, light_samples, buried_known):
        """The BVH, the lifted ray origins, the buried points and the ray patterns."""
        states = self.states
        self.seed = int(seed)
        self.caster = caster = caster or RayCaster(self.scene)
        # Every ray leaves through the upper hemisphere of its point: offset along the normal.
        self.lifted64 = caster.lift(states.points, states.normals, states.point_triangle)
        self.lifted = self.lifted64.astype(np.float32)
        self.buried = buried_points(caster, states, self.lifted)
        buried_known.set_result(self.buried)
        rng = np.random.default_rng([int(seed), 0x1DA7])
        self.patterns = DirectionPatterns(states.strata_u, states.strata_v, self.R, rng)
        self.sampler = EmitterSampler(self.scene)
        self.K = K = int(light_samples) if not self.sampler.empty else 0
        self.light = LightPatterns(self.sampler, K, rng) if K else None
        self.sampler_pdf = 1.0 / self.sampler.total_area if K else 0.0

    def _set_up_glossy(self):
        """The glossy unknowns' BSDFs and their R samples each (deterministic per seed): for
        unknown (x, k) the BSDF of x set up for the outgoing direction ω_k (the centre of stratum
        k in x's frame), R directions ω_i drawn from it (stratified in the first uniform), their
        ``f cos / p`` and densities, and the directional albedo a_k (:func:`directional_albedo`)."""
        u = self.unknowns
        self.glossy_rank = np.cumsum(u.glossy) - 1
        self.glossy_bsdf = None
        self.glossy_albedo = None
        g = u.glossy_points
        if len(g) == 0:
            return
        states, scene, S, R = self.states, self.scene, self.S, self.R
        pts = np.repeat(g, S)
        centres = np.tile(stratum_centers(states.strata_u, states.strata_v), (len(g), 1))
        wo = np.einsum("ki,kij->kj", centres, states.frames[pts])          # rows t, b, n
        tri = states.point_triangle[pts]
        bary = states.point_bary[pts]
        diffuse = scene.albedo_at(tri, bary[:, 0], bary[:, 1])
        self.glossy_bsdf = VertexBSDF(scene.materials, scene.triangle_material[tri], diffuse,
                                      states.bsdf_normals[pts], wo, geometric=states.normals[pts])
        rng = np.random.default_rng([self.seed, 0x6105])
        n = len(pts) * R
        jitter = rng.random((n, 3))
        jitter[:, 0] = (np.tile(np.arange(R), len(pts)) + jitter[:, 0]) / R
        wi, weight, pdf = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
        owner = np.repeat(np.arange(len(pts)), R)
        for a in range(0, n, GLOSSY_CHUNK):   # chunks bound the BSDF's temporaries
            b = slice(a, a + GLOSSY_CHUNK)
            wi[b], weight[b], pdf[b] = self.glossy_bsdf.subset(owner[b]).sample(jitter[b])
        self.glossy_wi = wi.astype(np.float32)                   # (G*S*R, 3) the rays' directions
        self.glossy_weight = weight                              # (G*S*R, 3) f cos / p
        self.glossy_pdf = pdf
        self.glossy_albedo = directional_albedo(scene.materials, scene.triangle_material[tri], diffuse,
                                                self.glossy_bsdf.mu)
        self.glossy_lum = self.glossy_albedo @ LUMINANCE         # normaliser of the rows

    def _unknown_columns(self, col, dirs):
        """Columns of the point-level classification (points, then terminals from m) turned into
        unknowns (points' unknowns, then terminals from N): a landing on a glossy point goes to the
        unknown of the stratum of ``-dirs`` in its frame. The identity without glossy points."""
        if self.N == self.m:
            return col
        col = np.asarray(col, dtype=np.int64)
        out = col + (self.N - self.m)
        on = np.flatnonzero(col < self.m)
        p = col[on]
        local = -np.einsum("kij,kj->ki", self.frames[p], dirs[on])
        out[on] = self.unknowns.columns(p, local)
        return out

    def glossy_entries(self, ids):
        """(row in the batch's unknown block, column, mass) of the glossy unknowns of the points
        ``ids``: their BSDF rays (MIS-weighted where they hit an emitter), their light samples of
        the emitters and the lamps weighted by ``f cos`` for ω_k, each divided by ``lum(a_k)``."""
        u, S, R = self.unknowns, self.S, self.R
        gp = ids[u.glossy[ids]]
        if len(gp) == 0 or self.glossy_bsdf is None:
            return None, {}
        first = u.first[ids[0]]
        gs = (self.glossy_rank[gp][:, None] * S + np.arange(S)).reshape(-1)      # glossy unknowns
        state_row = (u.first[np.repeat(gp, S)] + np.tile(np.arange(S), len(gp)) - first).astype(np.int32)
        ray = (gs[:, None] * R + np.arange(R)).reshape(-1)
        ray_state = np.repeat(np.arange(len(gs)), R)
        owner = np.repeat(gp, S * R)
        weight = self.glossy_weight[ray]
        lum = self.glossy_lum[gs]
        norm = np.where(lum > 0, 1.0 / np.where(lum > 0, lum, 1.0), 0.0)
        mass = (weight @ LUMINANCE) / R * norm[ray_state]
        live = np.flatnonzero((mass > 0) & ~self.buried[owner])
        dirs = self.glossy_wi[ray[live]]
        origins = self.lifted[owner[live]]
        transparency = self.sampler.transparency
        if transparency is None:
            hits = self.caster.intersect(origins, dirs, barycentrics=True)
        else:
            rng = np.random.default_rng([self.seed, 0xA1FB, int(ids[0])])
            hits = transparency.intersect(self.caster, origins, dirs, rng)[:4]
        classifier = self.tables.result()[1]
        col, c = classifier.classify(origins, dirs, *hits, workers=1)
        tri, dist = hits[0], hits[1]
        if transparency is not None:
            col[tri == ABSORBED] = self.m + self.E + self.W
        col = self._unknown_columns(col, dirs)
        m_live = mass[live]
        buried = np.flatnonzero((mass > 0) & self.buried[owner])
        K = self.K
        if K:
            hit_light = np.flatnonzero((col >= self.N) & (col < self.N + self.E))
            cos_y = np.abs(np.einsum("ij,ij->i", self.face_normals[tri[hit_light]], dirs[hit_light]))
            p_light = (dist[hit_light].astype(np.float64) ** 2
                       / (np.maximum(cos_y, 1e-12) * self.sampler.total_area))
            q = R * self.glossy_pdf[ray[live[hit_light]]]
            m_live[hit_light] *= q / (K * p_light + q)
        rows = [state_row[ray_state[live]], state_row[ray_state[buried]]]
        cols = [col, np.full(len(buried), self.N + self.E + self.W, dtype=np.int64)]
        masses = [m_live, mass[buried]]
        for extra in (self._glossy_light_entries(gp, gs, state_row, norm),
                      self._glossy_lamp_entries(gp, gs, state_row, norm)):
            if extra is not None:
                rows.append(extra[0])
                cols.append(extra[1])
                masses.append(extra[2])
        counts = {"glossy_rays": int(len(live))}
        return (np.concatenate(rows).astype(np.int32), np.concatenate(cols).astype(np.int32),
                np.concatenate(masses).astype(np.float32)), counts

    def _light_samples(self, ids):
        """The unoccluded next-event samples of the emitters from the points ``ids``: (owner in
        ``ids``, local and world direction, cos θ at x, light density in solid angle
        ``pdf_A d² / cos θ_y``, transmittance, emitter-triangle index) of each."""
        states, K, caster = self.states, self.K, self.caster
        pos, tri_index = self.light.of_points(ids)                 # (n, K, 3), (n, K)
        d = pos - self.lifted64[ids][:, None, :]
        dist2 = np.einsum("nki,nki->nk", d, d)
        dist = np.sqrt(np.maximum(dist2, 1e-300))
        omega = d / dist[..., None]
        # The shadow ray starts at the lifted point, so its direction and length are measured
        # from there: a connection measured from the surface point and traced from the lifted
        # one misses its target by the lift and grazing rays clip nearby geometry.
        local = np.matmul(omega, states.frames[ids].transpose(0, 2, 1))   # rows t, b, n
        cos_x = local[..., 2]
        cos_y = self.light.cos_emitter(omega, tri_index)
        live = np.flatnonzero((cos_x > 0) & (cos_y > 0) & ~self.buried[ids][:, None])
        owner = live // K
        omega_live = omega.reshape(-1, 3)[live]
        target = np.take(self.sampler.triangles, tri_index.reshape(-1)[live])
        tmax = caster.shadow_distance(dist.reshape(-1)[live], target)
        if self.sampler.transparency is None:
            passed = ~caster.occluded(self.lifted[ids][owner], omega_live, tmax)
        else:   # transparent occluders let 1 - alpha through (Cycles' transparent shadows)
            passed = self.sampler.transparency.transmittance(caster, self.lifted[ids][owner], omega_live, tmax)
            if passed.ndim == 2:     # tinted: the LMDP's transitions carry the luminance
                passed = passed.astype(np.float64) @ LUMINANCE
        transmitted = passed[passed > 0].astype(np.float64)
        live, owner = live[passed > 0], owner[passed > 0]
        p_light = self.sampler_pdf * dist2.reshape(-1)[live] / cos_y.reshape(-1)[live]
        return (owner, local.reshape(-1, 3)[live], omega.reshape(-1, 3)[live], cos_x.reshape(-1)[live],
                p_light, transmitted, tri_index.reshape(-1)[live])

    def _glossy_eval(self, omega, rows):
        """``VertexBSDF.eval`` of the glossy unknowns ``rows`` for directions ``omega``, in chunks
        of :data:`GLOSSY_CHUNK` (the evaluation's temporaries are about 1 KiB per pair)."""
        fcos, pdf = np.empty((len(rows), 3)), np.empty(len(rows))
        for a in range(0, len(rows), GLOSSY_CHUNK):
            b = slice(a, a + GLOSSY_CHUNK)
            fcos[b], pdf[b] = self.glossy_bsdf.eval(omega[b], rows[b])
        return fcos, pdf

    def _glossy_light_entries(self, gp, gs, state_row, norm):
        """Light samples of the emitters for the glossy unknowns: ``f cos / (K p_light + R p_bsdf)``
        (balance heuristic with their BSDF rays), over lum(a_k)."""
        if not self.K:
            return None
        owner, _, omega, _, p_light, passed, tri_index = self._light_samples(gp)
        S = self.S
        if len(owner) == 0:
            return None
        pair_state = (owner[:, None] * S + np.arange(S)).reshape(-1)              # index into gs
        sample = np.repeat(np.arange(len(owner)), S)
        fcos, pdf = self._glossy_eval(omega[sample].astype(np.float64), gs[pair_state])
        mass = (passed[sample] * (fcos @ LUMINANCE) / (self.K * p_light[sample] + self.R * pdf)
                * norm[pair_state])
        cols = self.N + self.sampler.emitter_of_triangle[tri_index[sample]]
        keep = mass > 0
        return state_row[pair_state[keep]], cols[keep], mass[keep]

    def _glossy_lamp_entries(self, gp, gs, state_row, norm):
        """Light samples of the lamps for the glossy unknowns: the Lambertian sample mass
        (``cos θ / π`` times the lamp's share) with ``cos θ / π`` replaced by ``f cos``."""
        if not len(self.lamps):
            return None
        live = gp[~self.buried[gp]]
        if len(live) == 0:
            return None
        rng = np.random.default_rng([self.seed, 0x1A4B6, int(gp[0])])
        owner, lamp, local, mass = self.lamps.transitions(self.lifted64[live], self.states.frames[live],
                                                          max(self.light_samples, 1), rng, self.caster,
                                                          transparency=self.sampler.transparency)
        if len(owner) == 0:
            return None
        S = self.S
        base = np.searchsorted(gp, live)[owner]                  # owner's index in gp
        pair_state = (base[:, None] * S + np.arange(S)).reshape(-1)
        sample = np.repeat(np.arange(len(owner)), S)
        omega = np.einsum("ki,kij->kj", local, self.states.frames[live][owner])
        fcos, _ = self._glossy_eval(omega[sample], gs[pair_state])
        cos = np.maximum(local[sample, 2], 1e-12)
        m = mass[sample] * np.pi * (fcos @ LUMINANCE) / cos * norm[pair_state]
        cols = self.N + self.E + self.W + 1 + lamp[sample]
        keep = m > 0
        return state_row[pair_state[keep]], cols[keep], m[keep]

    # ---- the batches ----------------------------------------------------------------------------

    def run(self, progress, runner=None):
        """Trace every batch on the pool (or by ``runner(starts)``, a farm's: it yields
        ``(batch, trace_batch(starts[batch]))`` in any order), then assemble the
        :class:`PassiveDynamics`."""
        # Batches run on a small thread pool: embree and numpy release the GIL, so tracing one
        # batch overlaps with binning another.
        starts = list(range(0, self.m, self.points_per_batch))
        blocks = [None] * len(starts)
        point_blocks = [None] * len(starts)
        counts = {}
        t_trace = t_bin = 0.0
        done = 0
        with self.pool:
            if runner is not None:
                stream = runner(starts)
            else:
                futures = {self.pool.submit(self.trace_batch, st): b for b, st in enumerate(starts)}
                stream = ((futures[f], f.result()) for f in as_completed(futures))
            try:
                for b, (block, point_block, c, tt, tb) in stream:
                    blocks[b] = block
                    point_blocks[b] = point_block
                    for key, value in c.items():
                        counts[key] = counts.get(key, 0) + value
                    t_trace += tt
                    t_bin += tb
                    done += block.shape[0] // self.S
                    if progress is not None:
                        progress.update(done / self.m, f"{done}/{self.m} points traced")
            except BaseException:
                stream.close()                  # a farm's stream cancels its futures
                for f in futures if runner is None else ():
                    f.cancel()
                raise
            locator, _, t_locator = self.tables.result()
        seconds = {"setup": self.t_setup, "locator": t_locator, "trace": t_trace, "bin": t_bin}
        return self._assemble(blocks, point_blocks, counts, locator, seconds)

    def trace_batch(self, start):
        """Rays of a batch of points -> CSR blocks of the stratum-resolved and the point-level
        dynamics, the landing counts, and the seconds spent tracing and binning."""
        S, R = self.S, self.R
        ids = np.arange(start, min(start + self.points_per_batch, self.m))
        dirs = self.patterns.directions(self.frames[ids], ids)
        origins = np.repeat(self.lifted[ids], S * R, axis=0)
        # Rays of buried points all go to the void: no light reaches them (``buried_points``),
        # so they are not traced.
        inside = np.repeat(self.buried[ids], S * R)
        out = np.flatnonzero(~inside) if inside.any() else slice(None)
        ta = time.perf_counter()
        transparency = self.sampler.transparency
        if transparency is None:
            hits = self.caster.intersect(origins[out], dirs[out], barycentrics=True)
        else:   # rays pass transparent surfaces with probability 1 - alpha, deterministic per batch
            rng = np.random.default_rng([self.seed, 0xA1FA, int(start)])
            hits = transparency.intersect(self.caster, origins[out], dirs[out], rng)[:4]
        tb = time.perf_counter()
        # The next-event rows need no locator: they are done first, while it may still be built.
        nee = self.emitter_entries(ids) if self.K else None
        lamp = self.lamp_entries(ids) if len(self.lamps) else None
        col, tri, dist, c = self._classify(origins, dirs, hits, inside, out)
        if transparency is not None:
            col[tri == ABSORBED] = self.m + self.E + self.W     # the void: past too many transparent surfaces
        col = self._unknown_columns(col, dirs)
        rows, cols, weights = self._stratum_entries(ids, dirs, col, tri, dist)
        for extra in (nee, lamp):
            if extra is not None:
                rows = np.concatenate([rows, extra[0]])
                cols = np.concatenate([cols, extra[1]])
                weights = np.concatenate([weights, extra[2]])
        if self.K:
            c["nee_rays"] = len(ids) * self.K
        n_rows = len(ids) * S
        block = sp.coo_matrix((weights, (rows, cols)), shape=(n_rows, self.n_cols)).tocsr()  # sums duplicates
        # Point-level rows (the Lambertian reduction): point i's row is the sum of its S stratum
        # rows, which are adjacent, so it takes (a copy of) their entries with every S-th row pointer.
        point_block = sp.csr_matrix((block.data.copy(), block.indices.copy(), block.indptr[::S].copy()),
                                    shape=(len(ids), self.n_cols))
        point_block.sum_duplicates()
        if self.N != self.m:
            point_block, glossy_counts = self._unknown_block(ids, point_block)
            for key, value in glossy_counts.items():
                c[key] = c.get(key, 0) + value
        return block, point_block, c, tb - ta, time.perf_counter() - tb

    def _unknown_block(self, ids, point_block):
        """The batch's rows of P over its unknowns: a Lambertian point's row is its point-level
        row, a glossy point's S rows those of :meth:`glossy_entries`."""
        u = self.unknowns
        first = u.first[ids[0]]
        n_rows = int(u.first[ids[-1]] + u.count[ids[-1]] - first)
        coo = point_block.tocoo()
        lamb = ~u.glossy[ids][coo.row]
        rows = [(u.first[ids[coo.row[lamb]]] - first).astype(np.int32)]
        cols, data = [coo.col[lamb].astype(np.int32)], [coo.data[lamb]]
        entries, counts = self.glossy_entries(ids)
        if entries is not None:
            rows.append(entries[0])
            cols.append(entries[1])
            data.append(entries[2])
        block = sp.coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(n_rows, self.n_cols)).tocsr()
        return block, counts

    def _classify(self, origins, dirs, hits, inside, out):
        """Next-state column, hit triangle and distance of every ray of a batch, and the counts
        per landing category (rays of buried points: the void, untraced)."""
        classifier = self.tables.result()[1]
        if not inside.any():
            tri, dist = hits[:2]
            col, c = classifier.classify(origins, dirs, *hits, workers=1)
            return col, tri, dist, c
        tri = np.full(len(dirs), -1, dtype=np.int64)
        dist = np.full(len(dirs), np.inf, dtype=np.float32)
        tri[out], dist[out] = hits[:2]
        col = np.full(len(dirs), self.m + self.E + self.W, dtype=np.int64)
        col[out], c = classifier.classify(origins[out], dirs[out], *hits, workers=1)
        c["void_buried"] = len(dirs) - len(out)
        c["void"] += c["void_buried"]
        return col, tri, dist, c

    def _stratum_entries(self, ids, dirs, col, tri, dist):
        """(row in the batch, column, weight) of every stratum ray: ``w_k / R``, or with
        next-event estimation the MIS weight where it hit an emitter (see
        :func:`build_passive_dynamics`). Rays come ordered by (point, stratum): each row has
        exactly R ray entries."""
        m, E, R, K = self.N, self.E, self.R, self.K
        weights = np.tile(self.weights_per_row, len(ids))
        rows, cols = self.ray_rows[:len(ids) * self.S * R], col.astype(np.int32)
        if K:
            hit_light = np.flatnonzero((col >= m) & (col < m + E))
            cos_x = self.patterns.cos_theta(ids)[hit_light].astype(np.float64)
            cos_y = np.abs(np.einsum("ij,ij->i", self.face_normals[tri[hit_light]], dirs[hit_light]))
            w_k = self.states.stratum_weight[np.tile(self.patterns.ray_stratum, len(ids))[hit_light]]
            p_light = (dist[hit_light].astype(np.float64) ** 2
                       / (np.maximum(cos_y, 1e-12) * self.sampler.total_area))
            weights[hit_light] = (cos_x / np.pi) / (K * p_light + R * cos_x / (np.pi * w_k))
        return rows, cols, weights

    def emitter_entries(self, ids):
        """Next-event estimates of p(emitter | point, stratum) for a batch of points:
        (row in the batch, column, weight) of every unoccluded shadow ray (MIS weight of
        :func:`build_passive_dynamics`)."""
        states, K = self.states, self.K
        owner, local, _, cx, p_light, transmitted, tri_index = self._light_samples(ids)
        k = np.maximum(stratum_of_local_direction(local, states.strata_u, states.strata_v), 0)
        weight = transmitted * (cx / np.pi) / (K * p_light + self.R * cx / (np.pi * states.stratum_weight[k]))
        cols = self.N + self.sampler.emitter_of_triangle[tri_index]
        return (owner * self.S + k).astype(np.int32), cols.astype(np.int32), weight.astype(np.float32)

    def lamp_entries(self, ids):
        """Light samples of the lamps (``Lamps.transitions``) for a batch of points: (row in the
        batch, column, mass) filed under the stratum of each sample's direction; buried points
        get none. Deterministic per batch (its own generator, whatever the thread order)."""
        live = ids[~self.buried[ids]]
        rng = np.random.default_rng([self.seed, 0x1A4B5, int(ids[0]) if len(ids) else 0])
        owner, lamp, local, mass = self.lamps.transitions(self.lifted64[live], self.states.frames[live],
                                                          max(self.light_samples, 1), rng, self.caster,
                                                          transparency=self.sampler.transparency)
        k = np.maximum(stratum_of_local_direction(local, self.states.strata_u, self.states.strata_v), 0)
        rows = (live[owner] - ids[0]) * self.S + k
        cols = self.N + self.E + self.W + 1 + lamp
        return rows.astype(np.int32), cols.astype(np.int32), mass.astype(np.float32)

    # ---- assembly -------------------------------------------------------------------------------

    def _assemble(self, blocks, point_blocks, counts, locator, seconds):
        """The :class:`PassiveDynamics` from the batches' row blocks."""
        scene, states = self.scene, self.states
        counts["rays"] = self.m * self.S * self.R
        counts["buried_points"] = int(np.count_nonzero(self.buried))
        counts["light_samples_per_point"] = self.K
        return PassiveDynamics(
            stratum_transitions=_compact_sparse(_stack(blocks)),
            P=_compact_sparse(_stack(point_blocks)),
            n_points=self.m,
            n_strata=self.S,
            emitter_radiance=np.asarray(self.emitter_radiance, dtype=np.float64),
            emitter_names=scene.emitter_names(),
            world_radiance=np.asarray(scene.world_radiance, dtype=np.float64),
            world_bins=None if _environment(scene) is None else _environment(scene).bin_radiance(),
            rays_per_stratum=self.R,
            counts=counts,
            seconds={**seconds, "total": time.perf_counter() - self.t0},
            locator=locator,
            caster=self.caster,
            warnings=_buried_warnings(scene, states, self.buried),
            lamp_radiance=np.asarray(self.lamps.emission, dtype=np.float64).reshape(-1, 3),
            lamp_names=list(self.lamps.names),
            unknowns=self.unknowns,
            glossy_albedo=self.glossy_albedo,
            glossy_rays=int(counts.get("glossy_rays", 0)),
        )


def _environment(scene):
    """The scene's lit environment map (directional world terminals), or None."""
    env = getattr(scene, "environment", None)
    return env if env is not None and env.lit else None


def _buried_warnings(scene, states, buried):
    """A message for each object most of whose points are buried: a solid inside another, or an
    object in a room whose normals face outwards (it then sees only back faces, which are void)."""
    names = scene.object_names
    total = np.bincount(states.point_object, minlength=len(names))
    hidden = np.bincount(states.point_object[buried], minlength=len(names))
    return [f"{hidden[o]} of the {total[o]} points on {names[o]} see only back faces and get no light: "
            f"if {names[o]} stands in a room whose normals face outwards, flip the room's normals "
            "(Edit Mode > Mesh > Normals > Flip)"
            for o in np.flatnonzero((total > 0) & (hidden > 0.5 * total))]


def _stack(blocks):
    """Row blocks (CSR, same columns) stacked into one CSR matrix."""
    return sp.vstack(blocks, format="csr") if len(blocks) > 1 else blocks[0]


def _compact_sparse(matrix):
    """CSR with float32 data and int32 indices (the storage format of the dynamics)."""
    matrix = sp.csr_matrix(matrix)
    matrix.sum_duplicates()
    matrix.eliminate_zeros()
    out = sp.csr_matrix((matrix.data.astype(np.float32), matrix.indices.astype(np.int32),
                         matrix.indptr.astype(np.int32 if matrix.nnz < 2 ** 31 else np.int64)),
                        shape=matrix.shape)
    return out
