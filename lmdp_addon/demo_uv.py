"""UV layouts of the built-in scenes' parts (:mod:`lmdp_addon.demo_geometry`): one rectangular
chart per quad, shelf-packed into [0, 1]^2 without overlap, or a regular grid of charts.
"""
import numpy as np

#: UV padding between charts of one part, in UV units (2 texels at 128 x 128).
UV_PADDING = 2.0 / 128.0


def quad_dims(vertices, faces):
    """(F, 2) lengths of the first and second edge of each quad (chart width, height)."""
    v = vertices[faces]
    return np.stack([np.linalg.norm(v[:, 1] - v[:, 0], axis=1),
                     np.linalg.norm(v[:, 3] - v[:, 0], axis=1)], axis=1)


def shelf_pack(dims, padding):
    """Non-overlapping layout of rectangles ``dims (F, 2)`` in [0, 1]^2, at a uniform scale.

    Shelf packing (tallest first) with ``padding`` UV units around every chart. Returns the lower
    left corner (F, 2) and the size (F, 2) of each chart in UV units.
    """
    dims = np.asarray(dims, dtype=np.float64)
    n = len(dims)
    order = np.argsort(-dims[:, 1], kind="stable")
    best = None
    total = float(np.sum(dims[:, 0] * dims[:, 1]))
    for width_factor in np.linspace(1.0, 3.0, 41):
        row_limit = max(np.sqrt(total) * width_factor, dims[:, 0].max())
        scale = 1.0
        for _ in range(6):  # the padding is in UV units: iterate scale <-> layout
            pad = padding / scale
            pos = np.zeros((n, 2))
            x = y = pad
            row_height = 0.0
            width = 0.0
            for f in order:
                w, h = dims[f]
                if x + w + pad > row_limit + 2 * pad and x > pad:
                    y += row_height + pad
                    x = pad
                    row_height = 0.0
                pos[f] = (x, y)
                x += w + pad
                row_height = max(row_height, h)
                width = max(width, x)
            height = y + row_height + pad
            scale = 1.0 / max(width, height)
        if best is None or scale > best[0]:
            best = (scale, pos.copy())
    scale, pos = best
    return pos * scale, dims * scale


def quad_charts(vertices, faces, padding=UV_PADDING):
    """Per-corner UVs (F, 4, 2): one rectangle chart per quad, packed without overlap.

    A part with a single quad gets the whole square [0, 1]^2.
    """
    faces = np.asarray(faces)
    if len(faces) == 1:
        return np.array([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]])
    corner, size = shelf_pack(quad_dims(vertices, faces), padding)
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return corner[:, None, :] + unit[None, :, :] * size[:, None, :]


def grid_uv(nu, nv, lo=(0.0, 0.0), hi=(1.0, 1.0)):
    """Per-corner UVs (nu*nv, 4, 2) of an nu x nv grid of quads covering [lo, hi]."""
    u = np.linspace(lo[0], hi[0], nu + 1)
    v = np.linspace(lo[1], hi[1], nv + 1)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="xy")
    i, j = i.ravel(), j.ravel()
    return np.stack([np.stack([u[i], v[j]], 1), np.stack([u[i + 1], v[j]], 1),
                     np.stack([u[i + 1], v[j + 1]], 1), np.stack([u[i], v[j + 1]], 1)], axis=1)
