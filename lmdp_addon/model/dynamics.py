"""Passive dynamics (thesis 3.1.2, eq. 3.1) estimated by casting rays through every stratum.

For point x and stratum k, ``rays_per_stratum`` (R) rays leave x through stratum k, drawn with
density proportional to BRDF·cos within the stratum, so each carries exactly ``w_k / R``, where
``w_k = ∫_k cos θ dω / π`` is the Lambertian mass of the stratum; each lands in one next state:

* the nearest state point on the hit object whose normal faces the side that was hit
  (the next state is that point with the reversed ray direction as outgoing direction; for the
  Lambertian reduction only the point matters, see ``design.md``),
* an emitter terminal (uniform emission: one terminal per emitter group),
* the world terminal (escaping ray, world not black),
* the void terminal (z = 0): geometry that carries no states, back faces (of one-sided emitters
  and of every surface), hits with no compatible state, and escapes into a black world.

Buried points (:func:`buried_points`: inside solids, pressed against other objects, over the back
of a lamp) are states no ray lands on, and their own rays all go to the void.

The estimate of each p(x'|x) is unbiased, and since the stratum masses sum to one and every ray
lands somewhere, each row of P sums to exactly one.
No Python loop runs over rays or states: rays are generated, traced and binned in large batches.
"""
import time
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import BudgetError
from .hemisphere import (square_to_hemisphere, stratum_of_local_direction,
                         stratum_square_samples)
from ..lights import EmitterSampler
from .locator import StateLocator, buried_points
from ..raycast import RayCaster

#: Column roles after the point columns.
WORLD = "world"
VOID = "void"

#: Target rays per batch of the build loop. Small enough that even a build of a few thousand
#: points is cut into several batches that overlap on the cores (measured on 2 cores, Cornell
#: box: 2048 points 0.09 -> 0.07 s, 16384 points 0.48 -> 0.42 s going from 2^19 to 2^16 rays).
RAYS_PER_BATCH = 1 << 16
#: Batches processed concurrently.
BUILD_THREADS = 3


@dataclass
class PassiveDynamics:
    """Sparse passive dynamics p(x'|x) of the point-level states plus the terminal states.

    stratum_transitions  CSR (m*S, n) float32: row ``i*S + k`` holds the mass that rays leaving
                         point i through stratum k deliver to each next state (sums to w_k, the
                         stratum's cosine mass ∫_k cos θ dω / π)
    P                    CSR (m, n) float32: point-level passive dynamics, rows sum to 1
    n_points, n_strata   m, S
    emitter_radiance     (E, 3) radiance of each emitter terminal (W / sr m^2)
    emitter_names        E names (the emitting objects)
    world_radiance       (3,) radiance of the world terminal
    Columns: ``0..m-1`` points, ``m..m+E-1`` emitters, ``m+E`` world, ``m+E+1`` void.
    counts               rays per landing category (points, emitters, world, void reasons)
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
    locator: object = field(default=None, repr=False)  #: the StateLocator the hits were mapped with
    warnings: list = field(default_factory=list)       #: messages for the user (objects mostly buried)
    caster: object = field(default=None, repr=False)   #: the RayCaster (BVH) the rays were traced with

    @property
    def n_emitters(self):
        return len(self.emitter_radiance)

    @property
    def n_terminals(self):
        return self.n_emitters + 2

    @property
    def n_columns(self):
        return self.n_points + self.n_terminals

    @property
    def world_column(self):
        return self.n_points + self.n_emitters

    @property
    def void_column(self):
        return self.n_points + self.n_emitters + 1

    @property
    def rays(self):
        return self.n_points * self.n_strata * self.rays_per_stratum

    def terminal_labels(self):
        return [f"emitter:{n}" for n in self.emitter_names] + [WORLD, VOID]

    @property
    def row_sum_error(self):
        """Largest deviation of a row sum of P from 1 (float32 rounding without next-event
        estimation; Monte Carlo noise of the emitter terms with it)."""
        return float(np.abs(np.asarray(self.P.sum(axis=1)).ravel() - 1.0).max()) if self.n_points else 0.0

    def memory_bytes(self):
        return sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
                   for m in (self.stratum_transitions, self.P))

    def summary(self):
        c = self.counts
        total = max(sum(c.get(k, 0) for k in ("points", "emitters", "world", "void")), 1)
        nee = (f" + {c['nee_rays']} shadow rays to the emitters" if c.get("nee_rays") else "")
        buried = (f"; {c['buried_points']} buried points (inside or under other geometry: no light, "
                  "no ray lands on them)" if c.get("buried_points") else "")
        return (f"{self.n_points} x {self.n_columns} passive dynamics, nnz {self.P.nnz} "
                f"({self.stratum_transitions.nnz} per stratum), {self.rays} rays{nee}: "
                f"{100 * c.get('points', 0) / total:.1f}% to states, "
                f"{100 * c.get('emitters', 0) / total:.1f}% to emitters, "
                f"{100 * c.get('world', 0) / total:.1f}% to the world, "
                f"{100 * c.get('void', 0) / total:.1f}% to the void{buried}")


def estimate_build_bytes(n_points, n_strata, rays_per_stratum, light_samples=0, n_triangles=0):
    """Upper estimate of the peak memory of :func:`build_passive_dynamics` (bytes).

    Terms, with coefficients measured (peak resident memory of the build in its own process,
    ``bench/worker.py``) and rounded up: 32 B per stratum ray (it can become a non-zero of the
    stratum-resolved matrix and of P, float32 + int32, twice during assembly; measured 18 B),
    48 B per light sample (measured 47 B), 2 KiB per point (state arrays, the locator's grid of
    about 16 to 24 cells per point and its temporaries), 768 B per triangle (the embree BVH and
    per-triangle tables, built at the same time as the locator's grid, which has at least one
    cell per triangle), 200 B per ray of the ``BUILD_THREADS`` batches in flight, and 8 MiB of
    fixed overhead. Measured against this estimate (``bench/worker.py build``, batches of 2^16
    rays, 4 x 4 strata, 4 rays, 32 light samples): Cornell box 20.5 / 25.6 MiB at 1000 points,
    248 / 381 MiB at 62 500 points; the 249 k-triangle heavy scene 150 / 226 MiB at 2000 points,
    261 / 316 MiB at 16 384 and 354 / 404 MiB at 32 768 points (the heaviest of a few runs: the
    peak depends on how the locator's grid and the first batches overlap).
    """
    rays = int(n_points) * int(n_strata) * int(rays_per_stratum)
    return (32 * rays + 48 * int(n_points) * int(light_samples) + 2048 * int(n_points)
            + 768 * int(n_triangles) + 200 * min(rays, BUILD_THREADS * RAYS_PER_BATCH) + 8 * 1024 ** 2)


def check_budget(n_points, n_strata, rays_per_stratum, budget_gb, light_samples=0, n_triangles=0):
    """Raise :class:`BudgetError` when the estimated build memory exceeds ``budget_gb``."""
    need = estimate_build_bytes(n_points, n_strata, rays_per_stratum, light_samples, n_triangles)
    if budget_gb is not None and need > budget_gb * 1024 ** 3:
        raise BudgetError(
            f"Building the dynamics for {n_points} points x {n_strata} strata x "
            f"{rays_per_stratum} rays would need about {need / 1024 ** 3:.1f} GiB, above the "
            f"memory budget of {budget_gb:g} GiB: lower Point Count, the strata or Rays per "
            "Stratum, or raise the Memory Budget setting")
    return need


class DirectionPatterns:
    """A pool of ray patterns, one per point modulo the pool size: R directions per stratum.

    Within stratum k the R directions are drawn independently with density proportional to
    BRDF·cos (by rejection from the uniform-solid-angle cell), so each ray carries exactly
    ``w_k / R`` of the stratum's cosine mass ``w_k = ∫_k cos θ dω / π``: the estimate of
    ``p(x'|x)`` is unbiased and every row of P sums to one exactly. Sharing patterns between
    points keeps every point's estimate stratified and unbiased while the warp runs once per
    pattern instead of once per ray.
    """

    def __init__(self, strata_u, strata_v, rays_per_stratum, rng, pool=64):
        S, R = strata_u * strata_v, int(rays_per_stratum)
        self.pool = pool
        self.ray_stratum = np.repeat(np.arange(S), R)
        stratum = np.tile(self.ray_stratum, pool)
        # Largest cos θ = 1 - max(a², b²) over each cell, (a, b) = 2(u, v) - 1.
        k = np.arange(S)
        a0, a1 = 2.0 * (k // strata_v) / strata_u - 1.0, 2.0 * (k // strata_v + 1) / strata_u - 1.0
        b0, b1 = 2.0 * (k % strata_v) / strata_v - 1.0, 2.0 * (k % strata_v + 1) / strata_v - 1.0
        a_min = np.where((a0 < 0) & (a1 > 0), 0.0, np.minimum(a0 ** 2, a1 ** 2))
        b_min = np.where((b0 < 0) & (b1 > 0), 0.0, np.minimum(b0 ** 2, b1 ** 2))
        cos_max = 1.0 - np.maximum(a_min, b_min)
        local = np.empty((len(stratum), 3))
        todo = np.arange(len(stratum))
        while len(todo):  # rounds of rejection sampling (a few), vectorised over all rays
            u, v = stratum_square_samples(stratum[todo], rng.random(len(todo)), rng.random(len(todo)),
                                          strata_u, strata_v)
            d = square_to_hemisphere(u, v)
            accept = rng.random(len(todo)) * cos_max[stratum[todo]] < d[:, 2]
            local[todo[accept]] = d[accept]
            todo = todo[~accept]
        self.local = local.reshape(pool, S * R, 3).astype(np.float32)

    def directions(self, frames, point_ids):
        """World directions (len(point_ids) * S * R, 3) for the points with these frames."""
        local = self.local[point_ids % self.pool]          # (n, S*R, 3)
        return np.matmul(local, frames).reshape(-1, 3)      # rows of frames are t, b, n


class LightPatterns:
    """A pool of next-event patterns, one per point modulo the pool size: K points on the
    emitters, stratified by area (``EmitterSampler.stratified``), each pattern with its own
    random shift. As with :class:`DirectionPatterns`, every point's K samples are a stratified
    set of uniform area samples, so its estimate stays unbiased, and the sampling runs once per
    pattern instead of once per shadow ray.
    """

    def __init__(self, sampler, per_point, rng, pool=256):
        self.sampler = sampler
        self.pool = pool
        sample = sampler.stratified(pool, per_point, rng)
        self.position = sample.position.reshape(pool, per_point, 3)
        self.triangle_index = sample.triangle_index.reshape(pool, per_point)
        self.single = len(sampler.triangles) == 1

    def of_points(self, point_ids):
        """Emitter points ``(n, K, 3)`` and their emitter-triangle indices ``(n, K)``."""
        p = point_ids % self.pool
        return self.position[p], self.triangle_index[p]

    def cos_emitter(self, omega, triangle_index):
        """Cosine at the emitter of connections ``omega (n, K, 3)`` leaving the receivers; 0 where
        they reach the back of a one-sided emitter."""
        s = self.sampler
        if self.single:  # the common single-quad light: no gathers
            signed = -(omega @ s.normals[0])
            return np.abs(signed) if s.two_sided[0] else np.maximum(signed, 0.0)
        signed = -np.einsum("nki,nki->nk", omega, s.normals[triangle_index])
        return np.where(s.two_sided[triangle_index], np.abs(signed), np.maximum(signed, 0.0))


class HitClassifier:
    """Per-triangle lookup tables that turn closest hits into next-state columns.

    Columns (see :class:`PassiveDynamics`): points, emitter terminals, world, void.
    """

    def __init__(self, scene, locator, n_points):
        self.scene = scene
        self.locator = locator
        tri_emitter, emitter_radiance = scene.emitter_groups()
        E = len(emitter_radiance)
        self.n_points = n_points
        self.world_col = n_points + E
        self.void_col = n_points + E + 1
        self.world_lit = bool(np.any(scene.world_radiance > 0))
        carries = scene.object_carries_states[scene.triangle_object] & (tri_emitter < 0)
        # Column of a front hit for every triangle (-1: carrier, look the point up), plus a
        # sentinel row T for misses. The back of a face carries no states: a ray that meets it
        # comes from inside a solid or sees a one-sided surface from behind, and goes to the void
        # (a lookup would hand it to the nearest state facing its way, through the solid: the
        # far side of a wall).
        front = np.where(tri_emitter >= 0, n_points + tri_emitter, np.where(carries, -1, self.void_col))
        back = np.where((tri_emitter >= 0) & scene.triangle_emission_two_sided, n_points + tri_emitter,
                        self.void_col)
        miss = self.world_col if self.world_lit else self.void_col
        self.front_col = np.append(front, miss).astype(np.int64)
        self.back_col = np.append(back, miss).astype(np.int64)
        self.normals = np.vstack([locator.face_normals, np.zeros((1, 3))]).astype(np.float32)
        self.is_emitter = np.append(tri_emitter >= 0, False)
        self.carries = np.append(carries, False)

    def classify(self, origins, directions, tri, dist, bary_u, bary_v, workers=-1):
        """Next-state column of every ray and a count per landing category."""
        T = self.scene.n_triangles
        t = np.where(tri >= 0, tri, T)
        front = np.einsum("ij,ij->i", np.take(self.normals, t, axis=0), directions) < 0.0
        col = np.where(front, np.take(self.front_col, t), np.take(self.back_col, t))
        n_miss = int(np.count_nonzero(tri < 0))
        counts = {"world": n_miss if self.world_lit else 0,
                  "void_escape": 0 if self.world_lit else n_miss}
        emitter = self.is_emitter[t]
        counts["emitters"] = int(np.count_nonzero(emitter & (col != self.void_col)))
        counts["void_emitter_back"] = int(np.count_nonzero(emitter & (col == self.void_col)))
        fl = np.flatnonzero(col < 0)                    # front hits on carriers
        pos = None
        if self.locator.exact:
            pos = origins[fl] + directions[fl] * dist[fl, None]
        col[fl] = self.locator.locate_front(t[fl], bary_u[fl], bary_v[fl], pos, workers=workers)
        counts["back_faces"] = int(np.count_nonzero(~front & self.carries[t]))
        unresolved = col < 0
        counts["void_no_state"] = int(np.count_nonzero(unresolved))
        col[unresolved] = self.void_col
        counts["points"] = int(np.count_nonzero(col < self.n_points))
        counts["void_unmodelled"] = int(np.count_nonzero(~emitter & ~self.carries[t] & (tri >= 0)))
        counts["void"] = int(np.count_nonzero(col == self.void_col))
        return col, counts


def build_passive_dynamics(scene, states, rays_per_stratum=4, seed=0, progress=None,
                           memory_budget_gb=None, caster=None, exact_nearest=False, light_samples=32):
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
    """
    R = int(rays_per_stratum)
    if R < 1:
        raise BudgetError(f"Rays per Stratum must be at least 1 (got {R})")
    check_budget(states.n_points, states.n_strata, R, memory_budget_gb, light_samples, scene.n_triangles)
    with scene.held():
        return _build(scene, states, R, seed, progress, caster, exact_nearest, light_samples)


def _build(scene, states, R, seed, progress, caster, exact_nearest, light_samples):
    """:func:`build_passive_dynamics` with the scene's derived geometry held."""
    t0 = time.perf_counter()
    m, S = states.n_points, states.n_strata
    tri_emitter, emitter_radiance = scene.emitter_groups()
    E = len(emitter_radiance)
    n_cols = m + E + 2
    face_normals = scene.triangle_geometry()[0]
    # The locator's tables are built on a thread of their own while the BVH is built and the
    # first batches are traced: only the classification of the hits waits for them.
    pool = ThreadPoolExecutor(max_workers=BUILD_THREADS + 1)

    buried_known = Future()

    def make_classifier():
        tl = time.perf_counter()
        locator = StateLocator(scene, states, exact=exact_nearest)
        locator.exclude(buried_known.result(), states)
        return locator, HitClassifier(scene, locator, m), time.perf_counter() - tl

    tables = pool.submit(make_classifier)
    try:
        caster = caster or RayCaster(scene)
        # Every ray leaves through the upper hemisphere of its point: offset along the normal.
        lifted64 = states.points + caster.offset() * states.normals
        lifted = lifted64.astype(np.float32)
        buried = buried_points(caster, states, lifted)
        buried_known.set_result(buried)
        rng = np.random.default_rng([int(seed), 0x1DA7])
        patterns = DirectionPatterns(states.strata_u, states.strata_v, R, rng)
        sampler = EmitterSampler(scene)
        K = int(light_samples) if not sampler.empty else 0
        light = LightPatterns(sampler, K, rng) if K else None
    except BaseException as exc:
        if not buried_known.done():
            buried_known.set_exception(exc)
        pool.shutdown(wait=True)
        raise
    frames = states.frames.astype(np.float32)
    t_setup = time.perf_counter() - t0

    points_per_batch = max(1, RAYS_PER_BATCH // (S * R))
    weights_per_row = np.repeat(states.stratum_weight / R, R).astype(np.float32)
    ray_rows = np.repeat(np.arange(points_per_batch * S, dtype=np.int32), R)

    def trace_batch(start):
        """Rays of a batch of points -> CSR blocks of the stratum-resolved and the point-level
        dynamics."""
        ids = np.arange(start, min(start + points_per_batch, m))
        dirs = patterns.directions(frames[ids], ids)
        origins = np.repeat(lifted[ids], S * R, axis=0)
        # Rays of buried points all go to the void: no light reaches them (``buried_points``),
        # so they are not traced.
        inside = np.repeat(buried[ids], S * R)
        out = np.flatnonzero(~inside) if inside.any() else slice(None)
        ta = time.perf_counter()
        hits = caster.intersect(origins[out], dirs[out], barycentrics=True)
        tb = time.perf_counter()
        # The next-event rows need no locator: they are done first, while it may still be built.
        nee = _emitter_entries(ids) if K else None
        classifier = tables.result()[1]
        if inside.any():
            tri = np.full(len(dirs), -1, dtype=np.int64)
            dist = np.full(len(dirs), np.inf, dtype=np.float32)
            tri[out], dist[out] = hits[:2]
            col = np.full(len(dirs), m + E + 1, dtype=np.int64)
            col[out], c = classifier.classify(origins[out], dirs[out], *hits, workers=1)
            c["void_buried"] = len(dirs) - len(out)
            c["void"] += c["void_buried"]
        else:
            tri, dist = hits[:2]
            col, c = classifier.classify(origins, dirs, *hits, workers=1)
        # Rays come ordered by (point, stratum): each row has exactly R ray entries.
        n_rows = len(ids) * S
        weights = np.tile(weights_per_row, len(ids))
        rows, cols = ray_rows[:n_rows * R], col.astype(np.int32)
        if K:  # MIS weight of the stratum rays that hit an emitter (docstring)
            hit_light = np.flatnonzero((col >= m) & (col < m + E))
            cos_x = patterns.local[ids % patterns.pool][..., 2].reshape(-1)[hit_light].astype(np.float64)
            cos_y = np.abs(np.einsum("ij,ij->i", face_normals[tri[hit_light]], dirs[hit_light]))
            w_k = states.stratum_weight[np.tile(patterns.ray_stratum, len(ids))[hit_light]]
            p_light = dist[hit_light].astype(np.float64) ** 2 / (np.maximum(cos_y, 1e-12) * sampler.total_area)
            weights[hit_light] = (cos_x / np.pi) / (K * p_light + R * cos_x / (np.pi * w_k))
            rows = np.concatenate([rows, nee[0]])
            cols = np.concatenate([cols, nee[1]])
            weights = np.concatenate([weights, nee[2]])
            c["nee_rays"] = len(ids) * K
        block = sp.coo_matrix((weights, (rows, cols)), shape=(n_rows, n_cols)).tocsr()  # sums duplicates
        # Point-level rows (the Lambertian reduction): point i's row is the sum of its S stratum
        # rows, which are adjacent, so it takes (a copy of) their entries with every S-th row pointer.
        point_block = sp.csr_matrix((block.data.copy(), block.indices.copy(), block.indptr[::S].copy()),
                                    shape=(len(ids), n_cols))
        point_block.sum_duplicates()
        return block, point_block, c, tb - ta, time.perf_counter() - tb

    def _emitter_entries(ids):
        """Next-event estimates of p(emitter | point, stratum) for a batch of points:
        (row in the batch, column, weight) of every unoccluded shadow ray (docstring)."""
        pos, tri_index = light.of_points(ids)                 # (n, K, 3), (n, K)
        d = pos - lifted64[ids][:, None, :]
        dist2 = np.einsum("nki,nki->nk", d, d)
        dist = np.sqrt(np.maximum(dist2, 1e-300))
        omega = d / dist[..., None]
        # The shadow ray starts at the lifted point, so its direction and length are measured
        # from there: a connection measured from the surface point and traced from the lifted
        # one misses its target by the lift and grazing rays clip nearby geometry.
        local = np.matmul(omega, states.frames[ids].transpose(0, 2, 1))   # rows t, b, n
        cos_x = local[..., 2]
        cos_y = light.cos_emitter(omega, tri_index)
        live = np.flatnonzero((cos_x > 0) & (cos_y > 0) & ~buried[ids][:, None])
        owner = live // K
        omega_live = omega.reshape(-1, 3)[live]
        blocked = caster.occluded(lifted[ids][owner], omega_live,
                                  np.maximum(dist.reshape(-1)[live] - caster.offset(), 0.0))
        live, owner = live[~blocked], owner[~blocked]
        k = np.maximum(stratum_of_local_direction(local.reshape(-1, 3)[live], states.strata_u,
                                                  states.strata_v), 0)
        cx = cos_x.reshape(-1)[live]
        p_light = sampler_pdf * dist2.reshape(-1)[live] / cos_y.reshape(-1)[live]  # pdf_A d² / cos θ_y
        weight = (cx / np.pi) / (K * p_light + R * cx / (np.pi * states.stratum_weight[k]))
        cols = m + sampler.emitter_of_triangle[tri_index.reshape(-1)[live]]
        return (owner * S + k).astype(np.int32), cols.astype(np.int32), weight.astype(np.float32)

    sampler_pdf = 1.0 / sampler.total_area if K else 0.0

    # Batches run on a small thread pool: embree and numpy release the GIL, so tracing one
    # batch overlaps with binning another.
    starts = list(range(0, m, points_per_batch))
    blocks = [None] * len(starts)
    point_blocks = [None] * len(starts)
    counts = {}
    t_trace = t_bin = 0.0
    done = 0
    with pool:
        futures = {pool.submit(trace_batch, st): b for b, st in enumerate(starts)}
        try:
            for future in as_completed(futures):
                block, point_block, c, tt, tb = future.result()
                blocks[futures[future]] = block
                point_blocks[futures[future]] = point_block
                for key, value in c.items():
                    counts[key] = counts.get(key, 0) + value
                t_trace += tt
                t_bin += tb
                done += point_block.shape[0]
                if progress is not None:
                    progress.update(done / m, f"{done}/{m} points traced")
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        locator, _, t_locator = tables.result()
    stratum_transitions = _compact_sparse(_stack(blocks))
    P = _compact_sparse(_stack(point_blocks))
    counts["rays"] = m * S * R
    counts["buried_points"] = int(np.count_nonzero(buried))
    warnings = _buried_warnings(scene, states, buried)
    counts["light_samples_per_point"] = K
    return PassiveDynamics(
        stratum_transitions=stratum_transitions,
        P=P,
        n_points=m,
        n_strata=S,
        emitter_radiance=np.asarray(emitter_radiance, dtype=np.float64),
        emitter_names=scene.emitter_names(),
        world_radiance=np.asarray(scene.world_radiance, dtype=np.float64),
        rays_per_stratum=R,
        counts=counts,
        seconds={"setup": t_setup, "locator": t_locator, "trace": t_trace, "bin": t_bin,
                 "total": time.perf_counter() - t0},
        locator=locator,
        caster=caster,
        warnings=warnings,
    )


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
