"""Texels of a lightmap: which surface point each pixel of a baked image stands for, like Cycles.

Blender's bake (``source/blender/render/intern/bake.cc`` + ``zbuf.cc``, verified against Cycles'
POSITION / NORMAL bakes of Blender 5.0, see ``docs/cycles_conventions.md``) maps an image of
R x R pixels onto a mesh as follows, and this module reproduces it exactly:

* Pixel (column i, row j) (row 0 = bottom row, as in ``Image.pixels``) samples the UV point
  ``((i + 0.5 + 0.001) / R, (j + 0.5 + 0.002) / R)``: the pixel centre nudged by the constant
  offset Blender adds against pixel-aligned UVs (``ZSPAN_X/Y_EPSILON``).
* A pixel is covered by a triangle when that point lies inside the triangle's UV image: rows
  ``ceil(y_min) <= j <= floor(y_max)``, and along a row ``x_left < i <= x_right`` (left edges
  exclusive, right edges inclusive) in the shifted pixel space ``uv * R - (0.501, 0.502)``.
  Triangles are rasterised in order, so where UV triangles overlap the last one wins.
* Cycles' sample 0 shades exactly that point; samples 1, 2, ... are jittered uniformly over a box
  of **half** a pixel around it (``bake_differentials`` stores half the barycentric derivatives).
  A jitter that leaves the triangle is redrawn, up to 10 times, and then falls back to the texel
  point (``bake_jitter_barycentric`` in ``init_from_bake.h``): samples never cross to the
  neighbouring triangle. :func:`sample_footprint` draws the same distribution.
* ``margin`` pixels around the covered ones are filled by :func:`dilate` with ``margin_type =
  'EXTEND'`` semantics (``IMB_filter_extend``). Blender's default ``'ADJACENT_FACES'`` margin
  (which copies pixels across UV seams) is not reproduced: bake with ``margin_type='EXTEND'``
  when comparing images including their margins.

Everything is vectorised over texels: (triangle, pixel) candidates from the triangles' pixel
bounding boxes are tested in chunks of bounded size, so 200k small triangles or one huge one
cost a few numpy passes.

Memory: a :class:`TexelSet` stores per texel only what it cannot derive, its pixel, triangle
and barycentric weights (:data:`TEXEL_BYTES`); positions, normals and differentials are computed
from the triangles when asked for. Rasterising holds a bounded chunk of candidates plus about
:data:`RASTER_BYTES_PER_TEXEL` per covered texel at its peak.
"""
from dataclasses import dataclass

import numpy as np

#: Offset Blender subtracts from ``uv * R`` before rasterising (zbuf.cc: 0.5 + epsilon).
PIXEL_OFFSET = (0.5 + 0.001, 0.5 + 0.002)
#: Half width of Cycles' jitter box around the texel point, in pixels.
FOOTPRINT_HALF_WIDTH = 0.25
#: Bytes a :class:`TexelSet` holds per texel: row, col (int32), triangle (int64), barycentric
#: (3 float64), overlap (bool).
TEXEL_BYTES = 4 + 4 + 8 + 24 + 1
#: Peak bytes of :func:`rasterize_texels` per covered texel (the candidates' output lists, their
#: concatenation, the sort that keeps the last triangle, the TexelSet), beyond its chunk:
#: 93 B measured with ``tracemalloc`` at 4096 x 4096, rounded up.
RASTER_BYTES_PER_TEXEL = 100
#: (triangle, pixel) candidates tested at once by :func:`rasterize_texels` (~100 B each).
MAX_CANDIDATES = 1 << 20
#: Texels whose positions / normals are computed at once (bounded temporaries).
TEXEL_CHUNK = 1 << 18


@dataclass
class TexelSet:
    """The covered texels of one R x R image.

    resolution    R (width = height)
    row, col      (n,) int32 pixel indices; row 0 is the bottom row (Blender's ``Image.pixels``)
    triangle      (n,) int64 index of the triangle each texel lies on
    barycentric   (n, 3) float64 weights of the triangle's corners 0, 1, 2 (sum to 1)
    triangle_corners, triangle_normals: the arrays the texels were computed from (not copied)
    triangle_derivatives  (T, 2, 2) Cycles' bake differentials of each triangle
    overlap       (n,) bool: the texel's centre is covered by more than one triangle (overlapping
        UVs; the last triangle wins, like Blender), or None when not known (a subset)

    Derived on access (not stored, see the module doc): ``position`` (n, 3) float64 world
    position of the texel point (metres), ``normal`` (n, 3) float64 unit normal there
    (interpolated when corner normals were given), ``pixel_barycentric_derivatives`` (n, 2, 2):
    d(b1, b2)/d(x, y) of Cycles' bake differentials (half the true derivative, see the module
    doc); rows: b1, b2; columns: x, y.
    """

    resolution: int
    row: np.ndarray
    col: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    triangle_corners: np.ndarray
    triangle_normals: np.ndarray
    triangle_derivatives: np.ndarray
    overlap: np.ndarray = None

    def __len__(self):
        return len(self.row)

    @property
    def position(self):
        """(n, 3) float64 world positions of the texel points: Σ_k b_k corner_k."""
        return _chunked(len(self), 3, lambda s: np.einsum("nk,nkj->nj", self.barycentric[s],
                                                         self.triangle_corners[self.triangle[s]]))

    @property
    def normal(self):
        """(n, 3) float64 unit normals at the texel points."""
        return _chunked(len(self), 3, lambda s: _interpolate_normals(self.triangle_normals, self.triangle[s],
                                                                    self.barycentric[s]))

    @property
    def pixel_barycentric_derivatives(self):
        """(n, 2, 2) bake differentials of each texel's triangle."""
        return self.triangle_derivatives[self.triangle]

    def subset(self, index):
        """The texels ``index`` (an index array or slice) as a TexelSet (``overlap`` unknown)."""
        return TexelSet(self.resolution, self.row[index], self.col[index], self.triangle[index],
                        self.barycentric[index], self.triangle_corners, self.triangle_normals,
                        self.triangle_derivatives)

    @property
    def flat_index(self):
        """(n,) index into a flattened (R*R) image, row-major from the bottom row."""
        return self.row.astype(np.int64) * self.resolution + self.col

    def covered_mask(self):
        """(R, R) bool image of the covered texels."""
        mask = np.zeros(self.resolution * self.resolution, dtype=bool)
        mask[self.flat_index] = True
        return mask.reshape(self.resolution, self.resolution)

    def to_image(self, values, fill=0.0):
        """Scatter per-texel ``values (n,) or (n, C)`` into an (R, R[, C]) float32 image."""
        values = np.asarray(values)
        shape = (self.resolution * self.resolution,) + values.shape[1:]
        image = np.full(shape, fill, dtype=np.float32)
        image[self.flat_index] = values
        return image.reshape((self.resolution, self.resolution) + values.shape[1:])


@dataclass
class FootprintSamples:
    """Points inside each texel's footprint: barycentric, position, normal (n_texels, k, 3)."""

    barycentric: np.ndarray
    position: np.ndarray
    normal: np.ndarray


def _shifted_pixel_coords(triangle_uv, resolution):
    p = np.asarray(triangle_uv, dtype=np.float64) * float(resolution)
    return p - np.asarray(PIXEL_OFFSET)


def _bake_differentials(p):
    """Cycles' per-triangle barycentric differentials (T, 2, 2), as bake_differentials() does.

    p: (T, 3, 2) corners in pixel space. Returns d(b1, b2)/d(x, y) * 0.5 (Blender's factor).
    """
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(area2) > np.finfo(np.float32).eps
    inv = np.where(ok, 0.5 / np.where(ok, area2, 1.0), 0.0)
    d = np.empty((len(p), 2, 2))
    # Blender: du_dx = (uv2.y - uv3.y) A, dv_dx = (uv3.y - uv1.y) A, du_dy = (uv3.x - uv2.x) A,
    # dv_dy = (uv1.x - uv3.x) A with A = 0.5 / (2 * signed area); u weights corner 0, v corner 1.
    d[:, 0, 0] = (b[:, 1] - c[:, 1]) * inv
    d[:, 1, 0] = (c[:, 1] - a[:, 1]) * inv
    d[:, 0, 1] = (c[:, 0] - b[:, 0]) * inv
    d[:, 1, 1] = (a[:, 0] - c[:, 0]) * inv
    return d


def _chunked(n, width, compute):
    """(n, width) float64 from ``compute(slice)`` over chunks of :data:`TEXEL_CHUNK` rows."""
    out = np.empty((n, width))
    for start in range(0, n, TEXEL_CHUNK):
        s = slice(start, min(start + TEXEL_CHUNK, n))
        out[s] = compute(s)
    return out


def _interpolate_normals(triangle_normals, triangle, bary):
    n = np.asarray(triangle_normals, dtype=np.float64)
    if n.ndim == 3:  # per-corner normals: smooth shading
        out = np.einsum("nk,nkj->nj", bary, n[triangle])
    else:
        out = n[triangle].copy()
    length = np.linalg.norm(out, axis=-1, keepdims=True)
    return out / np.where(length > 0, length, 1.0)


def rasterize_texels(triangle_uv, triangle_corners, triangle_normals, resolution,
                     max_candidates=MAX_CANDIDATES):
    """Covered texels of an R x R image for triangles with UVs, exactly like Blender's bake.

    triangle_uv       (T, 3, 2) UV of each corner
    triangle_corners  (T, 3, 3) world positions of the corners (metres)
    triangle_normals  (T, 3) face normals, or (T, 3, 3) corner normals (smooth shading)
    resolution        R: image width = height in pixels
    Returns a :class:`TexelSet` sorted by pixel (row-major from the bottom row), with
    ``overlap`` marking the texels whose centre several triangles cover.
    """
    R = int(resolution)
    if R <= 0:
        raise ValueError(f"Texel resolution must be positive, got {resolution}")
    corners = np.asarray(triangle_corners, dtype=np.float64).reshape(-1, 3, 3)
    T = len(corners)
    p = _shifted_pixel_coords(np.asarray(triangle_uv).reshape(T, 3, 2), R)
    # Triangles with a non-finite UV cover nothing (``check_bake`` refuses them with a message);
    # zeroed here, they are degenerate and their edge functions stay finite.
    p = np.where(np.all(np.isfinite(p), axis=(1, 2))[:, None, None], p, 0.0)
    x0, y0, count, width = _pixel_boxes(p, R)
    e_from, e_to, e_sign, sign, strict = _edge_functions(p)
    count[sign == 0] = 0  # degenerate in UV: Blender skips it (z0 == 0)
    row, col, triangle, bary = _covered_candidates(x0, y0, count, width, e_from, e_to, e_sign, strict,
                                                   max_candidates)
    row, col, triangle, bary, overlap = _last_triangle_wins(row, col, triangle, bary, R)
    return TexelSet(R, row, col, triangle, bary, corners, np.asarray(triangle_normals),
                    _bake_differentials(p), overlap)


def texel_count_bound(triangle_uv, resolution):
    """An upper bound on the texels that triangles with UVs ``(T, 3, 2)`` cover in an R x R
    image, without rasterising: per triangle the fewer of its clipped pixel box and
    ``A + P/2 + 1`` (a convex region of area A and perimeter P, in pixels, contains at most that
    many points of a lattice of unit spacing), summed, at most R². Tight for large triangles;
    overlapping UVs (an error of their own) count twice. Non-finite UVs cover nothing."""
    R = int(resolution)
    T = len(triangle_uv)
    if T == 0:
        return 0
    p = _shifted_pixel_coords(np.asarray(triangle_uv).reshape(T, 3, 2), R)
    finite = np.all(np.isfinite(p), axis=(1, 2))
    p = np.where(finite[:, None, None], p, 0.0)
    _, _, count, _ = _pixel_boxes(p, R)
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    area = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]))
    perimeter = (np.linalg.norm(b - a, axis=1) + np.linalg.norm(c - b, axis=1)
                 + np.linalg.norm(a - c, axis=1))
    lattice = np.floor(area + 0.5 * perimeter + 1.0)
    per_triangle = np.where(finite, np.minimum(count, lattice), 0)
    return int(min(per_triangle.sum(), R * R))


def _pixel_boxes(p, R):
    """``(x0, y0, count, width)``: the first column and row, the number of pixels and the width
    of each triangle's pixel bounding box (clipped to the image; 0 pixels if not finite)."""
    finite = np.all(np.isfinite(p), axis=(1, 2))
    pmin = np.where(finite[:, None], p.min(axis=1), 0.0)
    pmax = np.where(finite[:, None], p.max(axis=1), -1.0)
    x0 = np.clip(np.floor(pmin[:, 0]), 0, R)  # the left edge is exclusive: start at floor
    x1 = np.clip(np.floor(pmax[:, 0]), -1, R - 1)
    y0 = np.clip(np.ceil(pmin[:, 1]), 0, R)
    y1 = np.clip(np.floor(pmax[:, 1]), -1, R - 1)
    width = np.maximum(x1 - x0 + 1, 0).astype(np.int64)
    height = np.maximum(y1 - y0 + 1, 0).astype(np.int64)
    count = width * height
    count[~finite] = 0
    return x0, y0, count, width


def _edge_functions(p):
    """``(e_from, e_to, e_sign, sign, strict)`` of the triangles' three edges in pixel space:
    edge functions oriented so that the interior is positive; ``strict`` marks left edges.

    Edge k is opposite corner k: from corner k+1 to corner k+2. Each edge is evaluated from its
    endpoints in a canonical (y, x) order, so a shared edge gives exactly opposite values in its
    two triangles and a texel point on it is covered exactly once. ``sign``: the sign of the
    triangle's UV area (0: degenerate).
    """
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    sign = np.sign(area2)
    e_from = p[:, [1, 2, 0]]
    e_to = p[:, [2, 0, 1]]
    swap = (e_from[..., 1] > e_to[..., 1]) | ((e_from[..., 1] == e_to[..., 1]) & (e_from[..., 0] > e_to[..., 0]))
    e_from, e_to = np.where(swap[..., None], e_to, e_from), np.where(swap[..., None], e_from, e_to)
    e_sign = sign[:, None] * np.where(swap, -1.0, 1.0)  # orients each edge's interior positive
    e_dy = e_to[..., 1] - e_from[..., 1]
    strict = (e_sign * -e_dy) > 0  # interior at larger x: a left edge, exclusive
    return e_from, e_to, e_sign, sign, strict


def _covered_candidates(x0, y0, count, width, e_from, e_to, e_sign, strict, max_candidates):
    """``(row, col, triangle, barycentric)`` of every (triangle, pixel) whose texel point the
    triangle covers, in triangle order. The candidates (each triangle's bounding-box pixels) are
    tested in chunks of at most ``max_candidates``, so memory stays bounded whatever the
    triangle sizes; each edge function is evaluated from per-triangle tables gathered per
    candidate (``e = sign · (d_x (y - f_y) - d_y (x - f_x))``)."""
    # Per edge k: its start f, direction d = to - from, orientation sign and strictness (T,).
    d = e_to - e_from
    edges = [tuple(np.ascontiguousarray(a) for a in (e_from[:, k, 0], e_from[:, k, 1], d[:, k, 0],
                                                     d[:, k, 1], e_sign[:, k], strict[:, k]))
             for k in range(3)]
    rows, cols, tris, barys = [], [], [], []
    starts = np.concatenate([[0], np.cumsum(count)])
    total = int(starts[-1])
    for k0 in range(0, total, int(max_candidates)):
        k = np.arange(k0, min(k0 + int(max_candidates), total))
        t_idx = np.searchsorted(starts, k, side="right") - 1
        local = k - np.take(starts, t_idx)
        dy, dx = np.divmod(local, np.take(width, t_idx))
        del k, local
        px = np.take(x0, t_idx) + dx
        py = np.take(y0, t_idx) + dy
        del dx, dy
        e, inside = [], np.ones(len(t_idx), dtype=bool)
        for fx, fy, ex, ey, sign, left in edges:
            ek = (np.take(ex, t_idx) * (py - np.take(fy, t_idx))
                  - np.take(ey, t_idx) * (px - np.take(fx, t_idx))) * np.take(sign, t_idx)
            inside &= np.where(np.take(left, t_idx), ek > 0, ek >= 0)
            e.append(ek)
        hit = np.flatnonzero(inside)
        if len(hit) == 0:
            continue
        e = [np.take(ek, hit) for ek in e]
        total_e = (e[0] + e[1]) + e[2]
        rows.append(np.take(py, hit).astype(np.int32))
        cols.append(np.take(px, hit).astype(np.int32))
        tris.append(np.take(t_idx, hit).astype(np.int64))
        barys.append(np.stack([ek / total_e for ek in e], axis=1))
    if not rows:
        return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(tris), np.concatenate(barys)


def _last_triangle_wins(row, col, triangle, bary, R):
    """One texel per covered pixel, sorted by pixel: where several triangles cover a pixel's
    texel point the last one wins (Blender rasterises in triangle order). Also returns
    ``overlap (n,)`` bool: the pixels covered by more than one triangle (a triangle covers
    each pixel of its box at most once, so a repeated pixel is a second triangle). The
    candidates come in triangle order, so a stable sort by pixel keeps the triangles of a pixel
    in order and the last of them is the winner."""
    flat = row.astype(np.int64) * R + col
    order = np.argsort(flat, kind="stable")
    flat_sorted = np.take(flat, order)
    del flat
    boundary = flat_sorted[1:] != flat_sorted[:-1]
    del flat_sorted
    last = np.append(boundary, True)[:len(order)]       # (empty input: nothing to keep)
    first = np.insert(boundary, 0, True)[:len(order)]
    keep = order[last]
    overlap = ~first[last]
    return row[keep], col[keep], triangle[keep], bary[keep], overlap


#: Jitter attempts before Cycles falls back to the texel point (init_from_bake.h).
JITTER_ATTEMPTS = 10


def sample_footprint(texels, n, rng, include_center=True):
    """``n`` points per texel distributed like Cycles' bake samples.

    Sample 0 is the texel point itself (when ``include_center``); every other sample is uniform
    in the half-pixel box around it, mapped through the triangle's bake differentials; a draw
    that falls outside the triangle is redrawn up to :data:`JITTER_ATTEMPTS` times and then
    replaced by the texel point (``bake_jitter_barycentric``). A bake averaged over many samples
    is therefore the average over this footprint. ``rng``: a numpy Generator. Returns
    :class:`FootprintSamples` with arrays of shape (n_texels, n, 3).
    """
    m = len(texels)
    d = texels.pixel_barycentric_derivatives  # (m, 2, 2): d(b0, b1)/d(x, y)
    c0 = texels.barycentric[:, None, 0]
    c1 = texels.barycentric[:, None, 1]
    # First draw for every sample at once (broadcast over the texel's n samples).
    off = rng.random((m, n, 2)) - 0.5
    b0 = c0 + d[:, None, 0, 0] * off[..., 0] + d[:, None, 0, 1] * off[..., 1]
    b1 = c1 + d[:, None, 1, 0] * off[..., 0] + d[:, None, 1, 1] * off[..., 1]
    pending = ~((b0 > 0.0) & (b1 > 0.0) & (b0 + b1 < 1.0))
    b0 = np.where(pending, c0, b0)     # texel point until a redraw lands in the triangle
    b1 = np.where(pending, c1, b1)
    if include_center and n > 0:       # sample 0 is the texel point itself
        b0[:, 0], b1[:, 0] = c0[:, 0], c1[:, 0]
        pending[:, 0] = False
    for _ in range(JITTER_ATTEMPTS - 1):  # redraws of the few that fell outside
        idx = np.nonzero(pending)
        if len(idx[0]) == 0:
            break
        off = rng.random((len(idx[0]), 2)) - 0.5
        dd = d[idx[0]]
        ju = texels.barycentric[idx[0], 0] + dd[:, 0, 0] * off[:, 0] + dd[:, 0, 1] * off[:, 1]
        jv = texels.barycentric[idx[0], 1] + dd[:, 1, 0] * off[:, 0] + dd[:, 1, 1] * off[:, 1]
        ok = (ju > 0.0) & (jv > 0.0) & (ju + jv < 1.0)
        b0[idx[0][ok], idx[1][ok]] = ju[ok]
        b1[idx[0][ok], idx[1][ok]] = jv[ok]
        pending[idx[0][ok], idx[1][ok]] = False
    bary = np.stack([b0, b1, 1.0 - b0 - b1], axis=-1)
    corners = texels.triangle_corners[texels.triangle]  # (m, 3, 3)
    # b0 c0 + b1 c1 + b2 c2 = c2 + b0 (c0 - c2) + b1 (c1 - c2), broadcast over the samples
    # (the edges once per texel, the sums in place: the same float64 operations).
    position = b0[..., None] * (corners[:, 0] - corners[:, 2])[:, None]
    position += corners[:, None, 2]
    position += b1[..., None] * (corners[:, 1] - corners[:, 2])[:, None]
    normals = np.asarray(texels.triangle_normals, dtype=np.float64)
    if normals.ndim == 3:
        normal = np.einsum("mnk,mkj->mnj", bary, normals[texels.triangle])
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    else:
        normal = np.broadcast_to(texels.normal[:, None, :], position.shape).copy()
    return FootprintSamples(bary, position, normal)


# Weights of IMB_filter_extend's 3 x 3 neighbourhood: 2 for edge neighbours, 1 for corners.
_EXTEND_NEIGHBOURS = [(dy, dx, 1.0 if dx and dy else 2.0)
                      for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dx or dy]


def _four_neighbour_of(mask):
    """(H, W) bool: pixels with a True 4-neighbour in ``mask``."""
    four = np.zeros_like(mask)
    four[:, :-1] |= mask[:, 1:]
    four[:, 1:] |= mask[:, :-1]
    four[:-1, :] |= mask[1:, :]
    four[1:, :] |= mask[:-1, :]
    return four


def dilate(image, covered_mask, margin, return_mask=False):
    """Fill ``margin`` pixels around the covered texels, like Cycles' ``margin_type='EXTEND'``.

    Blender's ``IMB_filter_extend``: ``margin`` passes; in each pass every unassigned pixel with
    an assigned 4-neighbour becomes the weighted mean of its assigned 8-neighbours (weight 2 for
    edge neighbours, 1 for diagonal ones), reading the previous pass's values. Covered pixels are
    never changed. ``image`` (R, R) or (R, R, C); ``covered_mask`` (R, R) bool. Returns the new
    image (and the final assigned mask when ``return_mask``). ``'ADJACENT_FACES'`` is not
    reproduced.
    """
    img = np.array(image, dtype=np.float64, copy=True)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    assigned = np.array(covered_mask, dtype=bool, copy=True)
    if assigned.shape != img.shape[:2]:
        raise ValueError(f"Mask shape {assigned.shape} does not match image shape {img.shape[:2]}")
    H, W = assigned.shape
    for _ in range(int(margin)):
        grow = _four_neighbour_of(assigned) & ~assigned
        gy, gx = np.nonzero(grow)
        if len(gy) == 0:
            break
        # Only the pixels that grow are computed (the ring around the islands): their weighted
        # sums over the 8 neighbours, in the neighbours' order, outside the image adding 0.
        acc = np.zeros((len(gy), img.shape[2]))
        wsum = np.zeros(len(gy))
        for dy, dx, w in _EXTEND_NEIGHBOURS:
            ny, nx = gy + dy, gx + dx
            inside = (ny >= 0) & (ny < H) & (nx >= 0) & (nx < W)
            ny, nx = np.where(inside, ny, 0), np.where(inside, nx, 0)
            m = assigned[ny, nx] & inside
            acc += (w * m)[:, None] * np.where(inside[:, None], img[ny, nx], 0.0)
            wsum += w * m
        img[gy, gx] = acc / wsum[:, None]
        assigned[gy, gx] = True
    out = img[..., 0] if squeeze else img
    out = out.astype(np.asarray(image).dtype if np.asarray(image).dtype.kind == "f" else np.float64)
    return (out, assigned) if return_mask else out
