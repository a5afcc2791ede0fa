"""The engine's texels (lmdp_addon.bake.texels) are Cycles' texels: same coverage, same surface points,
same normals, same footprint and the same EXTEND margin, on the Cornell box built in Blender.

Reference: Cycles' POSITION and NORMAL bakes (``bake_cycles``) of the demo meshes, one sample
(sample 0 is the texel point itself, no jitter) unless the footprint is under test.

Tolerances, and why:
* coverage: exact (no texel may differ);
* positions: 1e-5 m. Both sides compute the same point; Cycles in float32 (relative precision
  6e-8 on coordinates of ~1 m, a few ulps through the barycentric interpolation) vs float64 here;
* texels whose point lies exactly on a triangle edge (a barycentric < 1e-6; with pixel-aligned
  UVs and 1:2 charts the 0.001/0.002 px offset can put it there) are jittered by Cycles even at
  sample 0: a jitter that is not strictly inside the triangle is redrawn by a hash. For those the
  tolerance is the half-pixel footprint box itself;
* normals: 1e-5 after decoding Cycles' object-space encoding n/2 + 0.5 (float32).
* footprint statistics: 5 standard errors of the statistic, computed from the box's variance.
"""
import bpy
import numpy as np
import pytest


@pytest.fixture
def cornell(fresh_scene, lmdp_ext):
    demo = lmdp_ext.sub("operators.adapters.demo_scenes")
    extract = lmdp_ext.sub("operators.adapters.extract")
    carriers = demo.build_demo_scene("CORNELL_BOX", bpy.context)
    scene_arrays = extract.extract_scene(bpy.context, carriers)
    return demo, scene_arrays, lmdp_ext.sub("lmdp_addon.bake.texels")


SENTINEL = -1.0e9


def engine_texels(texels, sa, name, resolution):
    mask = sa.triangle_object == sa.object_names.index(name)
    normals, _ = sa.triangle_geometry()
    return texels.rasterize_texels(sa.triangle_uv[mask], sa.corners()[mask], normals[mask], resolution)


def footprint_bound(ts):
    """Per texel: how far (m) a point can be from the texel point inside the half-pixel box."""
    tri = ts.triangle_corners[ts.triangle]
    d = 2.0 * ts.pixel_barycentric_derivatives  # true d(b0, b1)/d(x, y)
    dP = (tri[:, 0, None, :] - tri[:, 2, None, :]) * d[:, 0, :, None] + \
         (tri[:, 1, None, :] - tri[:, 2, None, :]) * d[:, 1, :, None]  # (n, 2 axes, 3)
    return 0.25 * np.linalg.norm(dP, axis=2).sum(axis=1)


@pytest.mark.parametrize("name,resolution", [("Floor", 128), ("TallBox", 128), ("TallBox", 64),
                                             ("ShortBox", 97)])
def test_coverage_positions_and_normals_match_cycles(cornell, name, resolution):
    demo, sa, texels = cornell
    obj = bpy.data.objects[name]
    position = demo.bake_cycles(bpy.context, obj, 'POSITION', resolution=resolution, samples=1, fill=SENTINEL)
    normal = demo.bake_cycles(bpy.context, obj, 'NORMAL', resolution=resolution, samples=1, fill=SENTINEL,
                              normal_space='OBJECT')
    ts = engine_texels(texels, sa, name, resolution)
    covered = position[..., 0] > SENTINEL / 2
    np.testing.assert_array_equal(ts.covered_mask(), covered)
    assert np.array_equal(covered, normal[..., 0] > SENTINEL / 2)
    if name == "Floor":
        assert covered.all()  # the floor's UVs cover [0, 1]^2
    cycles_position = position[ts.row, ts.col, :3].astype(np.float64)
    error = np.linalg.norm(cycles_position - ts.position, axis=1)
    on_edge = ts.barycentric.min(axis=1) < 1e-6
    assert error[~on_edge].max() < 1e-5
    assert np.all(error[on_edge] <= footprint_bound(ts)[on_edge] + 1e-5)
    assert on_edge.mean() < 0.02
    # The object's transform is the identity: object space = world space.
    cycles_normal = (normal[ts.row, ts.col, :3].astype(np.float64) - 0.5 - 1e-5) * 2.0
    np.testing.assert_allclose(cycles_normal, ts.normal, atol=1e-5)


def test_jitter_is_a_half_pixel_box_and_stays_inside_the_triangle(cornell):
    """POSITION accumulates (sums) its samples: sum - S p0 is the sum of the S - 1 jitters."""
    demo, sa, texels = cornell
    R = 64
    floor = bpy.data.objects["Floor"]
    ts = engine_texels(texels, sa, "Floor", R)
    # Floor: x, y in [-0.5, 0.5] map linearly to u, v in [0, 1]: one pixel is 1/R metres.
    # Two samples: sample 0 is the texel point, sample 1 one jitter per texel (scrambled per pixel).
    two = demo.bake_cycles(bpy.context, floor, 'POSITION', resolution=R, samples=2, fill=SENTINEL)
    jitter_px = (two[ts.row, ts.col, :2] - 2 * ts.position[:, :2]) * R
    assert np.abs(jitter_px).max() <= 0.25 + 1e-4
    interior = np.abs(ts.row - ts.col) > 1
    m = interior.sum()
    box_std = 0.5 / np.sqrt(12.0)  # uniform on [-1/4, 1/4]; a whole-pixel box would give twice
    # Standard error of a sample std of m uniform values: box_std * sqrt((1.8 - 1) / (4 m)).
    np.testing.assert_allclose(jitter_px[interior].std(axis=0), box_std,
                               atol=5 * box_std * np.sqrt(0.8 / (4 * m)))
    np.testing.assert_allclose(jitter_px[interior].mean(axis=0), 0.0, atol=5 * box_std / np.sqrt(m))
    # Texels just above the diagonal: jitter redrawn until it lands in their triangle, so their
    # mean jitter is the centroid of the upper half box, (-1/12, +1/12) px; same for our sampler.
    S = 33
    total = demo.bake_cycles(bpy.context, floor, 'POSITION', resolution=R, samples=S, fill=SENTINEL)
    mean_jitter_px = (total[ts.row, ts.col, :2] - S * ts.position[:, :2]) / (S - 1) * R
    diagonal = ts.row == ts.col
    ours = texels.sample_footprint(ts, S, np.random.default_rng(0))
    ours_px = (ours.position[:, 1:, :2].mean(axis=1) - ts.position[:, :2]) * R
    triangle_std = np.sqrt(0.5 ** 2 / 18)  # std of a coordinate on that right triangle
    # Independent samples; Cycles' stratified samples are only more accurate than this.
    tol = 5 * triangle_std / np.sqrt((S - 1) * diagonal.sum())
    for mean in (mean_jitter_px[diagonal].mean(axis=0), ours_px[diagonal].mean(axis=0)):
        np.testing.assert_allclose(mean, (-1 / 12, 1 / 12), atol=tol)
    assert np.all(mean_jitter_px[diagonal, 1] - mean_jitter_px[diagonal, 0] > 0)


@pytest.mark.parametrize("margin", [1, 4, 16])
def test_extend_margin_matches_cycles(cornell, margin):
    demo, sa, texels = cornell
    R = 64
    box = bpy.data.objects["TallBox"]
    position = demo.bake_cycles(bpy.context, box, 'POSITION', resolution=R, samples=1, fill=SENTINEL,
                                margin=margin, margin_type='EXTEND')
    ts = engine_texels(texels, sa, "TallBox", R)
    image = ts.to_image(np.concatenate([ts.position, np.ones((len(ts), 1))], axis=1))
    ours, filled = texels.dilate(image, ts.covered_mask(), margin, return_mask=True)
    cycles_filled = position[..., 0] > SENTINEL / 2
    np.testing.assert_array_equal(filled, cycles_filled)
    assert filled.sum() > ts.covered_mask().sum()
    # Margin texels average a few covered texels: the same inputs up to the on-edge texels above.
    margin_only = filled & ~ts.covered_mask()
    error = np.abs(ours[margin_only] - position[margin_only]).max(axis=1)
    assert np.median(error) < 1e-5
    # Fed Cycles' own covered values, the dilation reproduces Cycles' margin to float precision.
    exact = texels.dilate(np.where(ts.covered_mask()[..., None], position, 0.0), ts.covered_mask(), margin)
    np.testing.assert_allclose(exact[filled], position[filled], atol=2e-6)
