"""A fine directional guide from the solution: the light arriving at each state through G x G cells.

The LMDP's 16 strata of 2π/16 sr cannot aim through a hatch. This guide keeps the solve as it is
and, once per bake, tabulates at every state point s the light arriving through each cell c of
a G x G grid on s's Shirley–Chiu square (equal-area cells of 2π/G² sr, the strata of
:mod:`~lmdp_addon.model.hemisphere` at a finer grid):

    L̂_s(c) = (1/R) Σ_r L_r(h(s, ω_r), -ω_r),    ω_r jittered in c (R rays per cell),

the radiance reflected towards s by the surface y = h(s, ω) that the ray meets, read from the
PHYSICAL solution (thesis eq. 2.22 with z the outgoing radiance of the states):

    L_r(y) = ρ(y) (D̂(y) + ẑ_in(s_y)),      ẑ_in = P_NN z_N + P_NW z_W,

with D̂(y) the direct light at y by one light sample at y itself (emitters, lamps and an
environment map, as the tracer samples them: direct light changes within millimetres beside an emitter, so it is not
read from a state a spacing away) and ẑ_in the light arriving at y's nearest compatible state
s_y from other surfaces and the world (one transition of the solved z). Rays that escape see the
world (later vertices only), emitters and back faces give 0: the texel's own vertex wants light
that has bounced, and next-event estimation covers the emitters at later vertices (the same
split as ``policy.stratum_policy``'s 'points' and 'points+world').

The row of s is ``q_s(c) ∝ L̂_s(c) · cos θ_c`` (the product with the cosine of the integrand of
eq. 2.7; ``product=False``: L̂ alone), the sums and ray counts of each cell averaged over s's
neighbours with the same normal (:func:`neighbour_matrix`: the :data:`FINE_NEIGHBOURS` nearest, as
``guide.neighbour_average`` picks them: R x 8 rays per cell), with a share ``floor`` spread
uniformly (0 by default). G follows a ray budget (:func:`fine_resolution`). The
tracer samples it through :class:`~lmdp_addon.bake.guide.StateGuide` with ``strata_u = strata_v
= G`` (the mixture ``α q_s(c) G² / 2π + (1 - α) cos θ / π``, exact pdf, unbiased for α < 1).

* :func:`incoming_table`: the (m, G²) tables of the texel vertex and of later vertices;
* :func:`build_fine_guide`: the :class:`~lmdp_addon.bake.guide.StateGuide` of those tables.
"""
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from ..bsdf import lambertian_albedo_at
from ..lights import EmitterSampler
from ..raycast import RayCaster
from ..sampling import concentric32, rotate_out, rows
from .gather import direct_light_at
from .guide import StateGuide, guide_frame, neighbour_weights

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: Most cells per side of the guide's square (G): 256 cells of 0.025 sr.
FINE_RESOLUTION = 16
#: Rays of the table (states x G² x R) that choose G: the largest power of two up to
#: :data:`FINE_RESOLUTION` within the budget (:func:`fine_resolution`), so the table costs at
#: most a fixed fraction of a second whatever the point count ...
FINE_RAY_BUDGET = 1 << 19
#: ... and at most this many table rays per path of the bake (each path traces about 10 rays and
#: shadow rays): the table stays a small part of the bake it guides, and a 64-sample bake of 2048
#: states already gets G = 16 (through the narrow opening: the bake's variance 0.16 against 0.21
#: of plain path tracing's with G = 8 at 0.125 rays per path).
FINE_RAYS_PER_PATH = 0.5
#: Rays per cell and state (R).
FINE_RAYS_PER_CELL = 1
#: Share of each row spread uniformly over its cells. 0: the cosine share of the mixture already
#: covers every direction (weights <= 1 / (1 - α)), and a floor only dilutes the table.
FINE_FLOOR = 0.0
#: States whose table sums are averaged into each row (:func:`neighbour_matrix`): half of the
#: strata guide's ``GUIDE_NEIGHBOURS``, as the cells are finer than the parallax between states
#: farther apart (measured: variance ratio 0.61-0.69 vs 0.71-0.81 with 16 on the narrow opening,
#: 0.81-0.82 vs 0.85 on the Cornell box, G = 16).
FINE_NEIGHBOURS = 8
#: Rays traced per chunk of states (bounded temporaries) ...
CHUNK_RAYS = 1 << 17
#: ... and chunks traced at once (embree and numpy release the GIL).
TABLE_THREADS = 2


def incoming_radiance_source(lmdp, with_terminals=False):
    """ẑ_in (m,) luminance: the light arriving at each state point from the other surfaces and
    the world in one transition of the solved z, ``P_NN z_N + P_NW z_W`` (PHYSICAL);
    ``with_terminals``: from every column (emitters and lamps too), ``P z``. A glossy point's
    S unknowns (``model.unknowns``) each have a row: the point's value is their mean."""
    problem, dyn = lmdp.lmdp, lmdp.dynamics
    n = dyn.n_unknowns
    z = lmdp.solution.z @ LUMINANCE if lmdp.solution.z.shape[1] == 3 else lmdp.solution.z[:, 0]
    zt = problem.z_terminal @ LUMINANCE if problem.z_terminal.shape[1] == 3 else problem.z_terminal[:, 0]
    col = np.zeros(problem.P.shape[1])
    col[:n] = z
    if with_terminals:
        col[n:] = zt
    else:
        world = np.asarray(dyn.world_columns, dtype=np.int64)
        col[world] = zt[world - n]
    per_unknown = np.asarray(problem.P @ col).reshape(-1)
    unknowns = dyn.unknowns
    if unknowns is None or unknowns.identity:
        return per_unknown
    return np.bincount(unknowns.point, weights=per_unknown, minlength=unknowns.n_points) / unknowns.count


def cells_of_states(n, resolution, rays_per_cell, rng):
    """``(owner, cell)`` of the rays of ``n`` states through a G x G grid: ``R`` =
    ``rays_per_cell`` rays through every cell when R >= 1; when R < 1 each state traces one ray
    through each cell of a 1/K share of its cells (K = round(1/R), the cells with
    ``(iu + iv + r) mod K = 0`` for a random r per state), which the neighbour averaging joins."""
    G = int(resolution)
    C = G * G
    if rays_per_cell >= 1:
        R = int(round(rays_per_cell))
        return np.repeat(np.arange(n), C * R), np.tile(np.repeat(np.arange(C), R), n)
    K = max(int(round(1.0 / rays_per_cell)), 1)
    iu, iv = np.divmod(np.arange(C), G)
    sets = [np.flatnonzero((iu + iv + r) % K == 0) for r in range(K)]
    per = min(len(x) for x in sets)
    sets = np.stack([x[:per] for x in sets])                   # (K, per)
    r = rng.integers(K, size=n)
    return np.repeat(np.arange(n), per), sets[r].reshape(-1)


def incoming_table(lmdp, resolution=FINE_RESOLUTION, rays_per_cell=FINE_RAYS_PER_CELL, seed=0,
                   product=True, direct=True, locator=None):
    """``(first, later, count, rays)``: per state point and cell c of its G x G grid, the sums
    over its rays of L̂_s(c) (times each ray's cosine with ``product``) without the world
    (``first``, the texel vertex) and with it (``later``), (m, G²) float64, the rays through
    each cell ``count`` (m, G²) and the rays traced (closest hits + shadow rays). ``direct``
    False: the direct light at the hit is read from its nearest state too (``ẑ_in`` + the
    state's terminal drive) instead of sampled there. ``locator``: of the states on
    ``lmdp.scene`` (default the build's)."""
    scene, states, dyn = lmdp.scene, lmdp.states, lmdp.dynamics
    G = int(resolution)
    C = G * G
    m = states.n_points
    first = np.zeros(m * C)
    escape = np.zeros(m * C)
    count = np.zeros(m * C)
    if m == 0:
        return first.reshape(m, C), escape.reshape(m, C), count.reshape(m, C), 0
    caster = dyn.caster if dyn.caster is not None else RayCaster(scene)
    locator = dyn.locator if locator is None else locator
    lights = EmitterSampler(scene)
    environment = scene.environment if getattr(scene, "environment", None) is not None \
        and scene.environment.lit else None
    world = np.asarray(scene.world_radiance, dtype=np.float64) @ LUMINANCE
    z_in = incoming_radiance_source(lmdp, with_terminals=not direct)
    face_normals = scene.triangle_geometry()[0].astype(np.float32)
    corners = scene.corners()
    reflects = ~scene.is_emissive()
    smooth = scene.has_smooth_normals()
    lifted = caster.lift(states.points, states.normals, states.point_triangle).astype(np.float32)
    frames = np.asarray(states.frames, dtype=np.float32)
    live = np.arange(m) if locator is None or locator.targets is None else np.flatnonzero(locator.targets)
    rng = np.random.default_rng([int(seed), 0xF1E6])
    owner_all, cell_all = cells_of_states(len(live), G, rays_per_cell, rng)
    owner_all = live[owner_all]

    def chunk(k):
        """The sums of chunk k of the table's rays (its own random stream: the chunks run on
        threads, and their sums are added in chunk order, so the table does not depend on them)."""
        rng = np.random.default_rng([int(seed), 0xF1E6, k])
        start = k * CHUNK_RAYS
        owner = owner_all[start:start + CHUNK_RAYS]
        c = cell_all[start:start + CHUNK_RAYS]
        # The chunk's rays belong to consecutive states: its sums cover the slots lo .. lo + span.
        lo = int(owner[0]) * C
        span = (int(owner[-1]) + 1) * C - lo
        first = np.zeros(span)
        escape = np.zeros(span)
        x, y = concentric32((c // G + rng.random(len(c), dtype=np.float32)) / G,
                            (c % G + rng.random(len(c), dtype=np.float32)) / G)
        r2 = x * x + y * y
        lift = np.sqrt(np.maximum(2.0 - r2, 0.0))      # the equal-area lift (hemisphere.py)
        cos = 1.0 - r2
        d = rotate_out(rows(frames, owner), x * lift, y * lift, cos)
        weight = cos.astype(np.float64) if product else np.ones(len(c))
        origin = lifted[owner]
        if lights.transparency is None:
            tri, _, bu, bv = caster.intersect(origin, d, barycentrics=True)
            tint = None
        else:
            tri, _, bu, bv, _, tint = lights.transparency.intersect(caster, origin, d, rng)
        rays = len(d)
        slot = owner * C + c - lo
        count = np.bincount(slot, minlength=span).astype(np.float64)
        miss = np.flatnonzero(tri == -1)
        if len(miss):
            seen = (environment.radiance_at(d[miss]).astype(np.float64) @ LUMINANCE
                    if environment is not None else np.full(len(miss), world))
            escape += np.bincount(slot[miss], weights=weight[miss] * seen, minlength=span)
        hit = np.flatnonzero(tri >= 0)
        t = tri[hit]
        ng = face_normals[t]
        keep = (np.einsum("ij,ij->i", ng, d[hit]) < 0) & reflects[t]
        hit, t, ng = hit[keep], t[keep], ng[keep]
        if len(hit) == 0:
            return lo, first, escape, count, rays
        tc = corners[t]
        bu_h, bv_h = bu[hit], bv[hit]
        pos = tc[:, 0] + bu_h[:, None] * (tc[:, 1] - tc[:, 0]) + bv_h[:, None] * (tc[:, 2] - tc[:, 0])
        albedo = np.asarray(lambertian_albedo_at(scene, t, bu_h, bv_h), dtype=np.float64)
        if tint is not None:
            albedo = albedo * tint[hit]
        radiance = np.zeros(len(hit))
        if direct:
            ns = scene.shading_normals(t, bu_h, bv_h) if smooth else ng
            radiance, shadow = direct_light_at(scene, lights, environment, caster, pos, ns, ng, t, smooth, rng)
            radiance = np.asarray(radiance, dtype=np.float64)
            radiance = (albedo * radiance) @ LUMINANCE
            rays += shadow
        if locator is not None:
            near = locator.locate_front(t, bu_h, bv_h, pos if locator.exact else None, workers=1)
            radiance = radiance + np.where(near >= 0, (albedo @ LUMINANCE) * z_in[np.maximum(near, 0)], 0.0)
        first += np.bincount(slot[hit], weights=weight[hit] * radiance, minlength=span)
        return lo, first, escape, count, rays

    chunks = range(-(-len(owner_all) // CHUNK_RAYS))
    with ThreadPoolExecutor(max_workers=max(1, min(len(chunks), TABLE_THREADS))) as pool:
        parts = list(pool.map(chunk, chunks))     # in chunk order
    first = np.zeros(m * C)
    escape = np.zeros(m * C)
    count = np.zeros(m * C)
    rays = 0
    for lo, f, e, n, r in parts:
        first[lo:lo + len(f)] += f
        escape[lo:lo + len(e)] += e
        count[lo:lo + len(n)] += n
        rays += r
    first = first.reshape(m, C)
    return first, first + escape.reshape(m, C), count.reshape(m, C), rays


def neighbour_matrix(locator, normals, neighbours):
    """(m, m) CSR: row i averages point i's neighbours as ``guide.neighbour_average`` does
    (identity where a point keeps its own row)."""
    m = len(normals)
    diag = np.ones(m, dtype=bool)
    r, c, w = [], [], []
    for ids, near, wt in neighbour_weights(locator, normals, neighbours):
        diag[ids] = False
        r.append(np.repeat(ids, near.shape[1]))
        c.append(near.ravel())
        w.append(wt.ravel())
    keep = np.flatnonzero(diag)
    r.append(keep)
    c.append(keep)
    w.append(np.ones(len(keep)))
    return sp.csr_matrix((np.concatenate(w), (np.concatenate(r), np.concatenate(c))), shape=(m, m))


def guide_rows(table, floor=FINE_FLOOR):
    """Rows of ``table (m, C)`` normalised to distributions, ``(1 - floor) q + floor / C``; rows
    without light are uniform."""
    C = table.shape[1]
    s = table.sum(axis=1, keepdims=True)
    q = np.where(s > 0, table / np.where(s > 0, s, 1.0), 1.0 / C)
    return (1.0 - floor) * q + floor / C


def fine_resolution(n_points, paths=None, rays_per_cell=FINE_RAYS_PER_CELL, minimum=4, rays_per_path=None):
    """G for ``n_points`` states and a bake of about ``paths`` paths (None: unknown): the largest
    power of two up to :data:`FINE_RESOLUTION` whose table fits the ray budget
    (:data:`FINE_RAY_BUDGET`, ``rays_per_path`` table rays per path, default
    :data:`FINE_RAYS_PER_PATH`), and never below ``minimum`` (the side of the solve's own strata
    grid: the guide is never coarser than the u* it replaces)."""
    per_path = FINE_RAYS_PER_PATH if not rays_per_path else float(rays_per_path)
    budget = FINE_RAY_BUDGET if paths is None else min(FINE_RAY_BUDGET, per_path * paths)
    G = FINE_RESOLUTION
    while G > 4 and n_points * G * G * rays_per_cell > budget:
        G //= 2
    return max(G, int(minimum))


def build_fine_guide(scene, lmdp, resolution=None, rays_per_cell=FINE_RAYS_PER_CELL, seed=0,
                     product=True, floor=FINE_FLOOR, neighbours=None, direct=True, paths=None,
                     rays_per_path=None):
    """:class:`~lmdp_addon.bake.guide.StateGuide` over G x G cells (``resolution`` = G, default
    :func:`fine_resolution` for a bake of ``paths`` paths and ``rays_per_path``) of the
    light arriving at the states (:func:`incoming_table`): per cell the mean of L̂ over the rays
    of the state and its ``neighbours`` (default :data:`FINE_NEIGHBOURS`) nearest states with
    the same normal (:func:`neighbour_matrix`), rows normalised and floored (:func:`guide_rows`).
    Needs the PHYSICAL solution (z is radiance). ``guide.info`` records G, the rays and the
    seconds of the table."""
    t0 = time.perf_counter()
    if resolution is None:
        resolution = fine_resolution(lmdp.states.n_points, paths, rays_per_cell,
                                     minimum=max(4, lmdp.states.strata_u, lmdp.states.strata_v),
                                     rays_per_path=rays_per_path)
    locator, object_map, same = guide_frame(scene, lmdp)
    first, later, count, rays = incoming_table(lmdp, resolution, rays_per_cell, seed, product, direct, locator)
    W = neighbour_matrix(locator, lmdp.states.normals, FINE_NEIGHBOURS if neighbours is None else int(neighbours))
    n = np.asarray(W @ count)
    inv = np.where(n > 0, 1.0 / np.where(n > 0, n, 1.0), 0.0)
    guide = StateGuide(locator=locator, frames=lmdp.states.frames,
                       first=guide_rows(np.asarray(W @ first) * inv, floor),
                       later=guide_rows(np.asarray(W @ later) * inv, floor),
                       strata_u=int(resolution), strata_v=int(resolution), same_scene=same, object_map=object_map)
    guide.info = {"fine_resolution": int(resolution), "fine_rays": int(rays),
                  "fine_seconds": time.perf_counter() - t0}
    return guide
