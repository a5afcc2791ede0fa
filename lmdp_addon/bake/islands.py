"""UV islands of a lightmap, each laid out on its own for a denoiser that must not mix them.

A denoiser filters across whatever pixels are next to each other; in a lightmap, pixels next to
each other may belong to different UV islands (different walls, the two sides of a seam) whose
light has nothing in common, and the margin around an island is no surface at all. So the
denoise step (``operators/adapters/denoise.py``) never sees the lightmap as it is:

* :func:`uv_islands` labels the object's triangles by UV connectivity (triangles sharing a UV
  vertex are in one island) and gives every covered texel its island;
* :func:`pack_islands` copies each island's bounding box, grown by ``pad`` pixels, into its own
  place on a canvas, every pixel of the box that is not one of the island's texels filled with the
  value of the island's nearest texel (so the denoiser sees the island continue, never a
  neighbour), with ``gap`` empty pixels between boxes;
* :func:`unpack_islands` reads the island texels back; the margin is then re-filled from them
  (``texels.dilate``), so no denoised light reaches the margin either.

Arrays: ``row, col (n,)`` the texels' pixel indices, ``values (n, C)`` per texel.
"""
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .texels import dilate

#: Pixels each island's box is grown by before it is denoised (the denoiser's support at the
#: island's edge is the island's own continuation).
DEFAULT_PAD = 8
#: Empty pixels between two boxes on the canvas.
DEFAULT_GAP = 8


def uv_islands(triangle_uv, triangle_corners, texel_triangle):
    """``(island of each texel (n,) int64, number of islands)``: the connected components of the
    triangles with UVs ``triangle_uv (T, 3, 2)`` and corners ``triangle_corners (T, 3, 3)``
    (two triangles are connected when they share a corner with the same position and the same
    UV, both to 1e-6: a UV seam or two meshes whose UVs touch are separate islands), read at the
    texels' triangles ``texel_triangle (n,)`` (local indices)."""
    uv = np.asarray(triangle_uv, dtype=np.float64).reshape(-1, 2)
    T = len(uv) // 3
    if T == 0:
        return np.zeros(len(texel_triangle), np.int64), 0
    xyz = np.asarray(triangle_corners, dtype=np.float64).reshape(-1, 3)
    scale = 1e6 / max(float(np.abs(xyz).max()), 1e-30)
    keys = np.concatenate([np.round(uv * 1e6), np.round(xyz * scale)], axis=1).astype(np.int64)
    _, vertex = np.unique(keys, axis=0, return_inverse=True)
    vertex = vertex.reshape(-1)
    tri = np.repeat(np.arange(T), 3)
    n_v = int(vertex.max()) + 1
    graph = coo_matrix((np.ones(len(tri)), (tri, T + vertex)), shape=(T + n_v, T + n_v))
    _, labels = connected_components(graph, directed=False)
    tri_label = labels[:T]
    used, island = np.unique(tri_label[np.asarray(texel_triangle, dtype=np.int64)], return_inverse=True)
    return island.reshape(-1).astype(np.int64), len(used)


@dataclass
class IslandLayout:
    """Where each island's box sits on the canvas.

    shape          (H, W) of the canvas
    island         (n,) island of each texel
    canvas_row, canvas_col  (n,) the texel's pixel on the canvas
    boxes          (k, 4) int: per island (canvas row0, canvas col0, height, width) of its grown box
    fill_source    (H, W) int64: the texel whose value each canvas pixel carries (-1: empty gap)
    """

    shape: tuple
    island: np.ndarray
    canvas_row: np.ndarray
    canvas_col: np.ndarray
    boxes: np.ndarray
    fill_source: np.ndarray


def pack_islands(row, col, island, n_islands, pad=DEFAULT_PAD, gap=DEFAULT_GAP):
    """:class:`IslandLayout` of the texels ``(row, col)`` with their ``island`` labels: boxes on
    shelves, tallest first, the canvas about as wide as the largest of sqrt(total area) and the
    widest box. Every pixel of an island's box maps to the island's nearest texel (Euclidean, in
    pixels), so the canvas can be filled for any per-texel quantity by :func:`canvas_of`."""
    row = np.asarray(row, dtype=np.int64)
    col = np.asarray(col, dtype=np.int64)
    island = np.asarray(island, dtype=np.int64)
    order = np.argsort(island, kind="stable")
    starts = np.searchsorted(island[order], np.arange(n_islands + 1))
    r0 = np.full(n_islands, 0, np.int64)
    c0 = np.full(n_islands, 0, np.int64)
    hh = np.zeros(n_islands, np.int64)
    ww = np.zeros(n_islands, np.int64)
    for k in range(n_islands):      # one box per island (a loop over islands, not texels)
        members = order[starts[k]:starts[k + 1]]
        r0[k], c0[k] = row[members].min() - pad, col[members].min() - pad
        hh[k] = row[members].max() + pad + 1 - r0[k]
        ww[k] = col[members].max() + pad + 1 - c0[k]
    width = int(max(np.sqrt(((hh + gap) * (ww + gap)).sum()), (ww + gap).max())) if n_islands else 1
    place_r = np.zeros(n_islands, np.int64)
    place_c = np.zeros(n_islands, np.int64)
    x = y = shelf = 0
    for k in np.argsort(-hh, kind="stable"):
        if x > 0 and x + ww[k] > width:
            x, y, shelf = 0, y + shelf + gap, 0
        place_r[k], place_c[k] = y, x
        x += ww[k] + gap
        shelf = max(shelf, hh[k])
    H, W = int(y + shelf) if n_islands else 1, int(width)
    canvas_row = row - r0[island] + place_r[island]
    canvas_col = col - c0[island] + place_c[island]
    fill = np.full((H, W), -1, np.int64)
    for k in range(n_islands):
        members = order[starts[k]:starts[k + 1]]
        box = np.ones((hh[k], ww[k]), bool)          # True: not a texel of the island
        lr, lc = row[members] - r0[k], col[members] - c0[k]
        box[lr, lc] = False
        local = np.full((hh[k], ww[k]), -1, np.int64)
        local[lr, lc] = members
        _, (ir, ic) = distance_transform_edt(box, return_indices=True)
        fill[place_r[k]:place_r[k] + hh[k], place_c[k]:place_c[k] + ww[k]] = local[ir, ic]
    boxes = np.stack([place_r, place_c, hh, ww], axis=1) if n_islands else np.zeros((0, 4), np.int64)
    return IslandLayout(shape=(H, W), island=island, canvas_row=canvas_row, canvas_col=canvas_col,
                        boxes=boxes, fill_source=fill)


def canvas_of(layout, values, empty=0.0):
    """(H, W, C) float32 canvas of the per-texel ``values (n, C)``: each box pixel the value of
    its island's nearest texel, the gaps ``empty``."""
    values = np.asarray(values, dtype=np.float32)
    canvas = np.full(layout.shape + values.shape[1:], empty, np.float32)
    filled = layout.fill_source >= 0
    canvas[filled] = values[layout.fill_source[filled]]
    return canvas


def unpack_islands(layout, canvas):
    """(n, C) the canvas values at the texels' own pixels."""
    return np.asarray(canvas)[layout.canvas_row, layout.canvas_col]


# ---- the denoise step's inputs and outputs (no bpy) ----------------------------------------------

@dataclass
class DenoiseInput:
    """One object's lightmap laid out for the denoiser: ``color``, ``albedo``, ``normal`` (H, W, 3)
    float32 canvases of :class:`IslandLayout` ``layout``; ``modulation`` (n, 3) the diffuse
    colour the texels' values were divided by (the denoised values are multiplied back), or
    None."""

    layout: IslandLayout
    color: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    modulation: np.ndarray = None


def denoise_input(scene, ob, multiply_color=False, pad=DEFAULT_PAD, gap=DEFAULT_GAP):
    """:class:`DenoiseInput` of the baked object ``ob`` (``results.ObjectBake``) of ``scene``
    (``SceneArrays``): its texel values with the texels' diffuse colour ρ and normals as guides.
    A lightmap times the colour (``multiply_color``) is denoised *demodulated*: the light
    ``value / ρ`` is filtered and multiplied by ρ again, so the colour's edges stay exact (the
    denoiser only smooths the light). None when the object has no texels."""
    ts = ob.texels
    if len(ts) == 0:
        return None
    tris = np.asarray(ob.triangles)[ts.triangle]
    island, n_islands = uv_islands(scene.triangle_uv[ob.triangles], scene.corners()[ob.triangles], ts.triangle)
    layout = pack_islands(ts.row, ts.col, island, n_islands, pad=pad, gap=gap)
    albedo = np.clip(scene.triangle_albedo[tris], 0.0, 1.0).astype(np.float32)
    value = np.asarray(ob.value, dtype=np.float32)
    modulation = None
    if multiply_color:
        modulation = albedo
        value = np.divide(value, albedo, out=np.zeros_like(value), where=albedo > 0)
    return DenoiseInput(layout=layout, color=canvas_of(layout, value), albedo=canvas_of(layout, albedo),
                        normal=canvas_of(layout, ts.normal), modulation=modulation)


def keep_island_light(denoised, raw, island):
    """``denoised (n, 3)`` with each island's sum per channel scaled to that of ``raw (n, 3)``.

    The raw island sum is an unbiased estimate of the island's light; the denoiser is not
    energy-preserving (it treats the rare bright paths of a small or distant light as outliers
    and removes part of their light), so the scale takes its overall bias out and leaves its
    local smoothing."""
    island = np.asarray(island, dtype=np.int64)
    k = int(island.max()) + 1 if len(island) else 0
    out = np.array(denoised, dtype=np.float32, copy=True)
    for c in range(out.shape[1]):
        den = np.bincount(island, weights=out[:, c].astype(np.float64), minlength=k)
        ref = np.bincount(island, weights=np.asarray(raw)[:, c].astype(np.float64), minlength=k)
        scale = np.divide(ref, den, out=np.ones(k), where=den > 0)
        out[:, c] *= scale[island].astype(np.float32)
    return out


def denoised_image(ob, prepared, canvas, margin):
    """``(values (n, 3), image (R, R, 4))``: the denoised ``canvas`` (H, W, >=3) of ``prepared``
    (:class:`DenoiseInput`) read back at the texels of ``ob`` (times the modulation, if any),
    each island scaled per channel to the raw island's total light (:func:`keep_island_light`),
    and the margin re-filled (``texels.dilate``, Cycles' EXTEND)."""
    ts = ob.texels
    values = unpack_islands(prepared.layout, np.asarray(canvas)[..., :3]).astype(np.float32)
    if prepared.modulation is not None:
        values *= prepared.modulation
    values = keep_island_light(values, ob.value, prepared.layout.island)
    R = ts.resolution
    image = np.zeros((R, R, 4), np.float32)
    rgb, filled = dilate(ts.to_image(values), ts.covered_mask(), int(margin), return_mask=True)
    image[..., :3] = rgb
    image[..., 3] = filled.astype(np.float32)
    return values, image
