"""Texel rasterisation, footprint sampling and margin dilation (lmdp_addon.bake.texels), analytic checks.

The agreement with Cycles' own POSITION / NORMAL bakes is tested in
tests/addon/test_texels_vs_cycles.py; here every expected value is computed by hand.
"""
import numpy as np
import pytest

from lmdp_addon.bake import texels
from lmdp_addon.bake.texels import PIXEL_OFFSET, dilate, rasterize_texels, sample_footprint

UNIT_SQUARE_UV = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], dtype=np.float32)


def unit_square(size=1.0, z=0.0):
    """Two triangles covering [0, size]^2 at height z, UV = xy / size, normals +z."""
    corners = np.zeros((2, 3, 3))
    corners[..., :2] = UNIT_SQUARE_UV * size
    corners[..., 2] = z
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    return UNIT_SQUARE_UV, corners, normals


@pytest.mark.parametrize("resolution", [1, 7, 64, 128])
def test_unit_square_covers_every_texel_once_at_the_texel_points(resolution):
    uv, corners, normals = unit_square(size=2.0, z=0.5)
    ts = rasterize_texels(uv, corners, normals, resolution)
    assert len(ts) == resolution * resolution
    assert ts.covered_mask().all()
    # Each pixel exactly once, sorted row-major from the bottom row.
    assert np.array_equal(ts.flat_index, np.arange(resolution * resolution))
    expected_x = 2.0 * (ts.col + PIXEL_OFFSET[0]) / resolution
    expected_y = 2.0 * (ts.row + PIXEL_OFFSET[1]) / resolution
    np.testing.assert_allclose(ts.position[:, 0], expected_x, atol=1e-12)
    np.testing.assert_allclose(ts.position[:, 1], expected_y, atol=1e-12)
    np.testing.assert_allclose(ts.position[:, 2], 0.5)
    np.testing.assert_allclose(ts.barycentric.sum(axis=1), 1.0, atol=1e-12)
    assert ts.barycentric.min() >= 0.0
    np.testing.assert_allclose(ts.normal, np.tile([0, 0, 1.0], (len(ts), 1)))
    # The texel point is above the diagonal by 0.001 px: it lies in the second triangle.
    diagonal = ts.row == ts.col
    assert np.all(ts.triangle[diagonal] == 1)


def test_row_zero_is_the_bottom_of_the_uv_square():
    # A triangle covering only the bottom strip v < 0.25 of the UV square.
    uv = np.array([[[0, 0], [1, 0], [0.5, 0.25]]], dtype=np.float32)
    corners = np.array([[[0, 0, 0], [1, 0, 0], [0.5, 0.25, 0]]], dtype=float)
    ts = rasterize_texels(uv, corners, np.array([[0, 0, 1.0]]), 16)
    assert len(ts) > 0
    assert ts.row.max() < 4
    assert ts.row.min() == 0


def test_barycentrics_reproduce_the_uv_of_each_texel_point():
    rng = np.random.default_rng(3)
    uv = rng.random((20, 3, 2)).astype(np.float32)
    corners = rng.normal(size=(20, 3, 3))
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    ts = rasterize_texels(uv, corners, normals, 50)
    texel_uv = np.einsum("nk,nkj->nj", ts.barycentric, uv[ts.triangle].astype(float))
    np.testing.assert_allclose(texel_uv[:, 0] * 50, ts.col + PIXEL_OFFSET[0], atol=1e-9)
    np.testing.assert_allclose(texel_uv[:, 1] * 50, ts.row + PIXEL_OFFSET[1], atol=1e-9)
    assert ts.barycentric.min() >= 0.0
    np.testing.assert_allclose(ts.position, np.einsum("nk,nkj->nj", ts.barycentric, corners[ts.triangle]))


def test_a_triangle_between_texel_points_covers_nothing():
    # A sliver between the texel points of columns 3 and 4 (pixel x in (3.6, 4.4)).
    R = 10
    uv = np.array([[[3.6, 0.0], [4.4, 0.0], [4.0, 10.0]]], dtype=np.float64) / R + np.array([PIXEL_OFFSET[0] - 0.5, 0]) / R
    ts = rasterize_texels(uv, np.zeros((1, 3, 3)), np.array([[0, 0, 1.0]]), R)
    assert len(ts) == 0


def test_degenerate_and_non_finite_uvs_cover_nothing():
    uv = np.array([[[0, 0], [1, 1], [0.5, 0.5]], [[0, 0], [np.nan, 0], [1, 1]]], dtype=np.float32)
    ts = rasterize_texels(uv, np.zeros((2, 3, 3)), np.tile([0, 0, 1.0], (2, 1)), 32)
    assert len(ts) == 0
    assert ts.covered_mask().shape == (32, 32)


def test_shared_edges_through_texel_points_leave_no_hole_and_no_double():
    # A 1 x 2 chart with pixel-aligned corners: its diagonal has slope 2 and passes exactly
    # through a texel point (x + 0.501, y + 0.502) in every other row.
    R = 64
    x0, y0, w, h = 1.0, 20.5, 15.25, 30.5
    quad = np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]]) / R
    uv = np.array([quad[[0, 1, 2]], quad[[0, 2, 3]]])
    corners = np.concatenate([uv, np.zeros((2, 3, 1))], axis=2)
    ts = rasterize_texels(uv, corners, np.tile([0, 0, 1.0], (2, 1)), R)
    cols = np.arange(R) + PIXEL_OFFSET[0]
    rows = np.arange(R) + PIXEL_OFFSET[1]
    inside_x = (cols > x0) & (cols <= x0 + w)
    inside_y = (rows >= y0) & (rows <= y0 + h)
    expected = inside_y[:, None] & inside_x[None, :]
    assert np.array_equal(ts.covered_mask(), expected)
    assert len(np.unique(ts.flat_index)) == len(ts) == expected.sum()
    assert not ts.overlap.any()   # the shared edge covers its texel points once


def test_the_last_of_overlapping_triangles_wins_like_blender():
    uv = np.array([[[0, 0], [1, 0], [0, 1]]] * 2, dtype=np.float32)
    corners = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 5], [1, 0, 5], [0, 1, 5]]], dtype=float)
    ts = rasterize_texels(uv, corners, np.tile([0, 0, 1.0], (2, 1)), 16)
    assert len(ts) > 0
    assert np.all(ts.triangle == 1)
    np.testing.assert_allclose(ts.position[:, 2], 5.0)


def test_corner_normals_are_interpolated_and_normalised():
    uv, corners, _ = unit_square()
    corner_normals = np.array([[[0, 0, 1], [1, 0, 1], [1, 0, 1]], [[0, 0, 1], [1, 0, 1], [0, 0, 1]]], dtype=float)
    ts = rasterize_texels(uv, corners, corner_normals, 8)
    np.testing.assert_allclose(np.linalg.norm(ts.normal, axis=1), 1.0)
    assert ts.normal[:, 0].min() >= 0.0
    # Texels at larger x lean further towards +x.
    left = ts.normal[ts.col == 0, 0].mean()
    right = ts.normal[ts.col == 7, 0].mean()
    assert right > left + 0.3


def test_many_small_triangles_chunked_like_a_single_pass():
    # A 60 x 60 grid of quads: the chunked expansion must give the same texels for any chunk size.
    n = 60
    s = np.linspace(0, 1, n + 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    i, j = i.ravel(), j.ravel()
    a = np.stack([s[i], s[j]], 1)
    b = np.stack([s[i + 1], s[j]], 1)
    c = np.stack([s[i + 1], s[j + 1]], 1)
    d = np.stack([s[i], s[j + 1]], 1)
    uv = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    corners = np.concatenate([uv, np.zeros((len(uv), 3, 1))], axis=2)
    normals = np.tile([0, 0, 1.0], (len(uv), 1))
    whole = rasterize_texels(uv, corners, normals, 100)
    chunked = rasterize_texels(uv, corners, normals, 100, max_candidates=97)
    assert len(whole) == 100 * 100
    assert np.array_equal(whole.flat_index, chunked.flat_index)
    assert np.array_equal(whole.triangle, chunked.triangle)
    assert not whole.overlap.any() and not chunked.overlap.any()
    np.testing.assert_allclose(whole.position, chunked.position)


def test_bad_resolution_is_refused():
    uv, corners, normals = unit_square()
    with pytest.raises(ValueError):
        rasterize_texels(uv, corners, normals, 0)


# -- footprint ----------------------------------------------------------------------------------

def _pixel_offsets(ts, samples, triangle_uv):
    uv = np.einsum("mnk,mkj->mnj", samples.barycentric, triangle_uv[ts.triangle].astype(float))
    centre = np.stack([ts.col + PIXEL_OFFSET[0], ts.row + PIXEL_OFFSET[1]], 1)
    return uv * ts.resolution - centre[:, None, :]


def test_footprint_is_the_half_pixel_box_with_the_texel_point_first():
    uv, corners, normals = unit_square()
    ts = rasterize_texels(uv, corners, normals, 32)
    samples = sample_footprint(ts, 64, np.random.default_rng(0))
    off = _pixel_offsets(ts, samples, uv)
    np.testing.assert_allclose(off[:, 0], 0.0, atol=1e-9)
    jitter = off[:, 1:].reshape(-1, 2)
    assert np.abs(jitter).max() <= texels.FOOTPRINT_HALF_WIDTH + 1e-9
    # Uniform on [-1/4, 1/4]^2 away from the diagonal: standard deviation (1/2) / sqrt(12).
    interior = np.abs(ts.col - ts.row) > 1
    inner = off[interior, 1:].reshape(-1, 2)
    np.testing.assert_allclose(inner.std(axis=0), 0.5 / np.sqrt(12), rtol=0.02)
    np.testing.assert_allclose(inner.mean(axis=0), 0.0, atol=0.003)
    np.testing.assert_allclose(samples.position, np.einsum("mnk,mkj->mnj", samples.barycentric,
                                                           corners[ts.triangle]))


def test_footprint_never_leaves_the_triangle_and_falls_back_to_the_texel_point():
    uv, corners, normals = unit_square()
    ts = rasterize_texels(uv, corners, normals, 32)
    samples = sample_footprint(ts, 200, np.random.default_rng(1), include_center=False)
    assert samples.barycentric.min() > 0.0
    # Texels on the diagonal keep their samples on their own side (above the diagonal).
    off = _pixel_offsets(ts, samples, uv)
    diagonal = ts.row == ts.col
    above = off[diagonal, :, 1] - off[diagonal, :, 0] > -0.0011
    assert above.all()
    # A triangle much smaller than a pixel: every jitter misses, all samples are the texel point.
    texel_point = (np.array([4.0, 4.0]) + PIXEL_OFFSET) / 8
    tiny_uv = texel_point + np.array([[[-1e-4, -1e-4], [2e-4, -1e-4], [-1e-4, 2e-4]]])
    tiny = rasterize_texels(tiny_uv, np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float),
                            np.array([[0, 0, 1.0]]), 8)
    assert len(tiny) == 1
    s = sample_footprint(tiny, 16, np.random.default_rng(2))
    np.testing.assert_allclose(s.barycentric, np.broadcast_to(tiny.barycentric[:, None, :], s.barycentric.shape))


# -- margin ------------------------------------------------------------------------------------

def test_dilate_fills_the_margin_and_leaves_covered_texels_untouched():
    R = 32
    rng = np.random.default_rng(4)
    image = rng.random((R, R, 3)).astype(np.float32)
    covered = np.zeros((R, R), bool)
    covered[10:20, 12:18] = True
    out, mask = dilate(image, covered, 3, return_mask=True)
    np.testing.assert_array_equal(out[covered], image[covered])
    # EXTEND grows through 4-neighbours: after k passes, pixels within Manhattan distance k of
    # the rectangle... except that a pass also needs an assigned 4-neighbour, so corners lag.
    y, x = np.mgrid[0:R, 0:R]
    dy = np.maximum(np.maximum(10 - y, y - 19), 0)
    dx = np.maximum(np.maximum(12 - x, x - 17), 0)
    assert np.array_equal(mask, dx + dy <= 3)
    # Untouched outside the margin.
    np.testing.assert_array_equal(out[~mask], image[~mask])
    # Margin values are convex combinations of covered values.
    lo = image[covered].min(axis=0)
    hi = image[covered].max(axis=0)
    assert np.all(out[mask] >= lo - 1e-6) and np.all(out[mask] <= hi + 1e-6)


def test_dilate_weights_edge_neighbours_twice_corner_neighbours_once():
    image = np.zeros((5, 5))
    covered = np.zeros((5, 5), bool)
    image[2, 1], covered[2, 1] = 0.0, True   # left edge neighbour of (2, 2)
    image[1, 1], covered[1, 1] = 1.0, True   # lower-left corner neighbour of (2, 2)
    out = dilate(image, covered, 1)
    assert out[2, 2] == pytest.approx(1.0 / 3.0)
    # A pixel whose only assigned neighbours are diagonal is not filled in that pass.
    image2 = np.zeros((5, 5))
    covered2 = np.zeros((5, 5), bool)
    image2[1, 1], covered2[1, 1] = 7.0, True
    out2, mask2 = dilate(image2, covered2, 1, return_mask=True)
    assert not mask2[2, 2] and mask2[1, 2] and mask2[2, 1]
    assert out2[1, 2] == 7.0


def test_dilate_of_a_constant_is_constant_and_zero_margin_is_identity():
    covered = np.zeros((16, 16), bool)
    covered[4:6, 4:9] = True
    image = np.where(covered[..., None], 0.25, -1.0) * np.ones((16, 16, 2))
    out, mask = dilate(image, covered, 16, return_mask=True)
    np.testing.assert_allclose(out[mask], 0.25)
    same = dilate(image, covered, 0)
    np.testing.assert_array_equal(same, image)
    with pytest.raises(ValueError):
        dilate(image, covered[:8], 1)
