"""Path reuse: the first bounces of neighbouring texels shared, weighted by the balance heuristic.

A texel's estimate is I(x) = ∫ f_x(y) L_r(y) dA(y) over the points y its first ray can hit,
``f_x(y) = (cos θ_x / π) cos θ_y / r² V(x, y)`` (tracer docstring, eq. 2.7 in area measure). A
path from x_j finds y_j with density ``p_j(y) = p_j(ω) cos θ_y / r²`` and, from y_j on, an
estimate L̂_j of the light y_j reflects (the path's light after y_j divided by its first
weight w0). Where y_j is Lambertian that light leaves y_j alike in every direction of its side,
so the same L̂_j serves every texel that sees y_j (Bekaert, Sbert & Halton 2002, "Accelerating
path tracing by re-using paths"). The paths of one *tile* (texels within ``tile`` x ``tile``
pixels, the same sample of the same batch) are K sampling techniques of each texel's integral;
the multi-sample balance heuristic (Veach 1997, eq. 9.13) gives texel i

    Î_i = D_i + Σ_j f_i(y_j) L̂_j / Σ_k p_k(y_j),                                       (reuse)

over the tile's Lambertian first hits y_j (the own path among them), ``D_i`` the direct light of
x_i's own path (bake content), the own path unchanged where its first hit is glossy (its light
depends on the direction: only the own technique counts there). Each ``p_k(y_j)`` of another
texel needs a shadow ray from x_k to y_j; the weights of every y sum to 1 over the techniques
that can draw it, so Î_i is unbiased for any tiling (Veach 1997, §9.2.2). With K = 1 it is the
path's own estimate. The tiles move with the sample (``groups``), so their edges do not
print on the lightmap. A path's first vertex is not joined to a light vertex (the tile's
paths draw y_1 together; later vertices are, ``connections``).
"""
import numpy as np

from ..sampling import dot, rows

INV_PI = 1.0 / np.pi
#: Side of a tile in texels (``Settings.path_reuse``; 1: every texel keeps its own paths).
TILE = 4


def unavailable(mode, clamp, transparency):
    """Why a tracer of ``mode`` with the sample ``clamp`` (None: off) and the scene's
    ``transparency`` (None: opaque) does not share first bounces (a sentence), or None."""
    if mode not in ("UNGUIDED", "GUIDED"):
        return f"{mode} keeps each texel's own paths"
    if clamp is not None and clamp.active:
        return "path reuse off: a sample clamp is on (Cycles' own estimator)"
    if transparency is not None:
        return "path reuse off: the scene has transparent (alpha) materials"
    return None


def off_reason(scene, settings):
    """Why a bake of ``scene`` with ``settings`` shares no first bounces although
    ``path_reuse`` > 1 in AUTO, UNGUIDED or GUIDED (a sentence for the report), or None:
    :func:`unavailable`, the tracer's own test."""
    from ..transparency import Transparency
    from .clamp import SampleClamp
    mode = "UNGUIDED" if settings.bake_mode == "AUTO" else settings.bake_mode   # AUTO's parts trace both
    if settings.path_reuse <= 1 or mode not in ("UNGUIDED", "GUIDED"):
        return None
    return unavailable(mode, SampleClamp.from_settings(settings), Transparency.of(scene))


def groups(row, col, sample, tile):
    """(n,) int64 tile of each path: paths with the same ``sample`` number (n,) whose texels
    (``row``, ``col``) (n,) fall in the same block of 2 ``tile`` x 2 ``tile`` pixels, dealt
    into 4 tiles of about ``tile``² texels at random (a hash of texel and sample): a bright
    first hit is shared with texels scattered over the block, not with a square of them. The
    blocks are shifted by sample, so that their edges move from sample to sample."""
    side = 2 * int(tile)
    sample = np.asarray(sample, dtype=np.int64)
    row, col = np.asarray(row, dtype=np.int64), np.asarray(col, dtype=np.int64)
    r = (row + (sample * 3) % side) // side
    c = (col + (sample * 5) % side) // side
    span = int(max(r.max(initial=0), c.max(initial=0))) + 1
    block = (sample * span + r) * span + c
    mixed = (row * 73856093) ^ (col * 19349663) ^ (sample * 83492791)
    mixed = (mixed * 2654435761) % 1000003
    order = np.lexsort((mixed, block))
    b = block[order]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    rank = np.empty(len(b), np.int64)
    rank[order] = np.arange(len(b)) - np.repeat(starts, np.diff(np.r_[starts, len(b)]))
    return np.unique(block * 4 + rank % 4, return_inverse=True)[1].astype(np.int64)


def members(group):
    """``(G, K)`` int64 paths of each of the G groups of ``group (n,)`` (K the largest group,
    -1 pads the smaller ones), in increasing path order within a group."""
    order = np.argsort(group, kind="stable")
    g = group[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    sizes = np.diff(np.r_[starts, len(g)])
    out = np.full((len(starts), int(sizes.max(initial=1))), -1, np.int64)
    out[np.repeat(np.arange(len(starts)), sizes), np.arange(len(g)) - np.repeat(starts, sizes)] = order
    return out


class FirstBounce:
    """What :func:`combine` needs of a wavefront's paths (n): x_0's ray origin, shading and
    geometric normals and state, the first weight w0, and of their first hits y_1 (set by the
    tracer at y_1): position, geometric normal of the side reached, triangle, whether the hit
    is Lambertian; ``direct`` the light of x_0's own (bake content, None: none)."""

    def __init__(self, origin, nrm, gnrm, states, w0):
        n = len(origin)
        self.origin, self.nrm, self.gnrm, self.states, self.w0 = origin, nrm, gnrm, states, w0
        self.y = np.zeros((n, 3), np.float32)
        self.ny = np.zeros((n, 3), np.float32)
        self.tri = np.full(n, -1, np.int64)
        self.lambertian = np.zeros(n, bool)
        self.direct = None

    def arrive(self, idx, pos, gnrm, tri, glossy):
        """The paths ``idx`` reached y_1 at ``pos`` (geometric normals ``gnrm`` of the side
        reached, triangles ``tri``); ``glossy`` (k,) bool or None: hits with a glossy lobe."""
        self.y[idx] = pos
        self.ny[idx] = gnrm
        self.tri[idx] = tri
        self.lambertian[idx] = True if glossy is None else ~glossy


#: Pairs (texel, first hit) per block of :func:`combine` (bounds its temporaries: ``memory.REUSE_BLOCK_BYTES``).
PAIRS_PER_BLOCK = 1 << 19


def combine(tracer, first, L, group, stats):
    """The estimates (reuse) ``(n, 3)`` float32 of the paths with light ``L (n, 3)`` (their own
    estimates) in the tiles ``group (n,)`` (:func:`groups`), :class:`FirstBounce` ``first``."""
    n = len(L)
    direct = first.direct if first.direct is not None else np.zeros((n, 3), np.float32)
    shared = first.lambertian & (first.w0 > 0)
    # Each path's own light after y_1 (w0 L̂), and L̂ = that / w0 where y_1 is shared.
    suffix = L - direct
    light = np.where(shared[:, None], suffix / np.where(shared, first.w0, 1.0)[:, None], 0.0).astype(np.float32)
    out = np.where(shared[:, None], direct, L).astype(np.float64)
    tiles = members(group)
    K = tiles.shape[1]
    step = max(1, PAIRS_PER_BLOCK // (K * K))
    for lo in range(0, len(tiles), step):
        block = tiles[lo:lo + step]
        valid = block >= 0
        m = np.where(valid, block, 0)
        received = _tile_weights(tracer, first, m, valid, shared, stats)        # (G, K_i, K_j)
        value = np.einsum("gij,gjc->gic", received, np.take(light, m, axis=0))
        out[block[valid]] += value[valid]
    return out.astype(np.float32)


def _tile_weights(tracer, first, m, valid, shared, stats):
    """``(G, K, K)`` float32: ``f_i(y_j) / Σ_k p_k(y_j)`` for texel i and first hit j of each
    tile (rows ``m`` (G, K) of the paths, ``valid`` the real ones; 0 where y_j is not shared or
    not seen by x_i)."""
    ox, oy, oz = (np.take(first.origin[:, c], m) for c in range(3))             # (G, K): x_i
    yx, yy, yz = (np.take(first.y[:, c], m) for c in range(3))                  # (G, K): y_j
    tx, ty, tz = yx[:, None, :] - ox[:, :, None], yy[:, None, :] - oy[:, :, None], yz[:, None, :] - oz[:, :, None]
    r2 = tx * tx + ty * ty + tz * tz
    r = np.sqrt(r2)
    inv = np.float32(1.0) / np.where(r > 0, r, np.float32(1.0))
    tx *= inv
    ty *= inv
    tz *= inv
    def facing(normals, rows, side):
        nx, ny, nz = (np.take(normals[:, c], rows) for c in range(3))
        return (nx[side] * tx + ny[side] * ty + nz[side] * tz)
    rows_i, rows_j = (slice(None), slice(None), None), (slice(None), None, slice(None))
    cos_x = facing(first.nrm, m, rows_i)
    cos_y = -facing(first.ny, m, rows_j)
    hit = valid & np.take(shared, m)                                           # y_j exists, Lambertian
    ok = valid[:, :, None] & hit[:, None, :] & (cos_x > 0) & (cos_y > 0) & (r > 0)
    if first.gnrm is not first.nrm:
        ok &= facing(first.gnrm, m, rows_i) > 0
    K = m.shape[1]
    diagonal = np.eye(K, dtype=bool)[None]
    ok = np.where(diagonal, hit[:, :, None] & (r > 0), ok)                     # the own path found y_j
    test = np.flatnonzero(ok & ~diagonal)
    if len(test):
        gi = test // K                        # (G, K) flat index of x_i, and of y_j:
        gj = gi - gi % K + test % K
        tmax = tracer.caster.shadow_distance(r.reshape(-1)[test], np.take(first.tri, m.reshape(-1)[gj]))
        stats.shadow_rays += len(test)
        blocked = tracer.caster.occluded(_columns(ox, oy, oz, gi), _columns(tx, ty, tz, test), tmax)
        ok.reshape(-1)[test[blocked]] = False
        stats.shared_hits += len(test) - int(np.count_nonzero(blocked))
    area = np.where(ok, cos_y / np.where(r2 > 0, r2, np.float32(1.0)), np.float32(0.0))
    f = np.maximum(cos_x, np.float32(0.0)) * np.float32(INV_PI) * area           # f_i(y_j)
    if tracer.guide is None:
        p = f                                                                    # cosine: p_i = f_i
    else:
        p = np.zeros_like(f)
        live = np.flatnonzero(ok)
        rows_i = np.take(m.reshape(-1), live // K)
        p.reshape(-1)[live] = tracer.directions.density(np.take(first.nrm, rows_i, axis=0),
                                                        np.take(first.states, rows_i),
                                                        _columns(tx, ty, tz, live), True) * area.reshape(-1)[live]
    D = p.sum(axis=1)                                                            # Σ_k p_k(y_j)  (G, K_j)
    return f / np.where(D > 0, D, np.float32(1.0))[:, None, :]                    # f = 0 where D = 0


def _columns(x, y, z, index):
    """(k, 3) float32 rows ``(x, y, z)`` at the flat ``index`` of three arrays of one shape."""
    out = np.empty((len(index), 3), np.float32)
    for c, a in enumerate((x, y, z)):
        np.take(a.reshape(-1), index, out=out[:, c])
    return out
