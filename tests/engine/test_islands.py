"""UV islands for the denoiser (``bake/islands``) and the RGBM encoding (``bake/encoding``)."""
import numpy as np

from lmdp_addon.bake import islands
from lmdp_addon.bake.encoding import RGBM_RANGE, rgbm_decode, rgbm_encode


def quad(x0, uv0):
    """Two triangles of a unit quad at x offset ``x0`` with UVs from ``uv0`` (half-wide)."""
    p = np.array([(x0, 0, 0), (x0 + 1, 0, 0), (x0 + 1, 1, 0), (x0, 1, 0)], float)
    u = np.array([(uv0, 0), (uv0 + 0.5, 0), (uv0 + 0.5, 1), (uv0, 1)], float)
    return [p[[0, 1, 2]], p[[0, 2, 3]]], [u[[0, 1, 2]], u[[0, 2, 3]]]


def test_islands_follow_shared_corners_not_touching_uvs():
    (pa, ua), (pb, ub) = quad(0.0, 0.0), quad(2.0, 0.5)     # UV rectangles touch at u = 0.5
    corners, uvs = np.array(pa + pb), np.array(ua + ub)
    island, n = islands.uv_islands(uvs, corners, np.array([0, 1, 2, 3]))
    assert n == 2 and island[0] == island[1] and island[2] == island[3] and island[0] != island[2]
    seam = uvs.copy()
    seam[1] += 0.25                                            # the same quad, its halves cut apart in UV
    island, n = islands.uv_islands(seam[:2], corners[:2], np.array([0, 1]))
    assert n == 2


def test_packed_boxes_do_not_overlap_and_fill_from_their_own_island():
    rng = np.random.default_rng(0)
    R = 32
    row, col = np.nonzero(rng.random((R, R)) < 2)            # every pixel
    island = (col >= 16).astype(int) + 2 * (row >= 20)
    layout = islands.pack_islands(row, col, island, 4, pad=3, gap=2)
    boxes = layout.boxes
    for a in range(4):
        for b in range(a + 1, 4):
            ra, ca, ha, wa = boxes[a]
            rb, cb, hb, wb = boxes[b]
            assert ra + ha + 2 <= rb or rb + hb + 2 <= ra or ca + wa + 2 <= cb or cb + wb + 2 <= ca
    src = layout.fill_source
    for k in range(4):
        r0, c0, h, w = boxes[k]
        assert np.all(island[src[r0:r0 + h, c0:c0 + w]] == k)
    values = rng.random((len(row), 3)).astype(np.float32)
    canvas = islands.canvas_of(layout, values)
    np.testing.assert_array_equal(islands.unpack_islands(layout, canvas), values)
    assert np.all(canvas[src < 0] == 0)


def test_keep_island_light_restores_each_islands_sum():
    rng = np.random.default_rng(1)
    island = rng.integers(0, 3, 500)
    raw = rng.random((500, 3))
    den = raw * (0.9 + 0.05 * island[:, None])
    out = islands.keep_island_light(den, raw, island)
    for k in range(3):
        np.testing.assert_allclose(out[island == k].sum(axis=0), raw[island == k].sum(axis=0), rtol=1e-5)


def test_rgbm_round_trip_is_within_half_a_byte_step():
    rng = np.random.default_rng(2)
    v = (rng.random((4096, 3)) ** 3 * RGBM_RANGE).astype(np.float32)
    back = rgbm_decode(rgbm_encode(v))
    assert np.all(np.abs(back - v) <= (v.max(axis=1, keepdims=True) + RGBM_RANGE / 255) / 510 + 1e-6)
    assert np.all(rgbm_decode(rgbm_encode(np.array([[20.0, 0.0, 0.0]])))[0, 0] == RGBM_RANGE)
