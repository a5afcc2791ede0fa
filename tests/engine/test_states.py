"""State sampling (thesis 3.1.1): area-proportional, stratified, deterministic, robust."""
import numpy as np
import pytest

from lmdp_addon.errors import SceneError
from lmdp_addon.scene_arrays import SceneArrays
from lmdp_addon.demo_geometry import build_scene_arrays, parts_to_scene_arrays, scene_parts
from lmdp_addon.model.states import sample_states


@pytest.fixture(scope="module")
def cornell():
    return build_scene_arrays("CORNELL_BOX")


def test_exact_count_and_points_lie_on_their_triangles(cornell):
    st = sample_states(cornell, 3000, 4, 4, seed=2)
    assert st.n_points == 3000 and st.n_states == 3000 * 16
    c = cornell.corners()[st.point_triangle]
    normals, _ = cornell.triangle_geometry()
    n = normals[st.point_triangle]
    assert np.allclose(np.einsum("ij,ij->i", st.points - c[:, 0], n), 0, atol=1e-12)
    assert np.allclose(st.normals, n)
    # Barycentric coordinates inside [0, 1].
    e1, e2, d = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0], st.points - c[:, 0]
    g = np.stack([np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2)], 1)
    b1 = np.einsum("ij,ij->i", d, e1)
    b2 = np.einsum("ij,ij->i", d, e2)
    det = g[:, 0] * g[:, 2] - g[:, 1] ** 2
    u = (g[:, 2] * b1 - g[:, 1] * b2) / det
    v = (g[:, 0] * b2 - g[:, 1] * b1) / det
    assert u.min() > -1e-9 and v.min() > -1e-9 and (u + v).max() < 1 + 1e-9
    assert not np.any(np.isin(st.point_object, [cornell.object_names.index("Light")]))


def test_points_are_proportional_to_area_within_one_per_triangle(cornell):
    n = 5000
    st = sample_states(cornell, n, seed=4)
    _, area = cornell.triangle_geometry()
    carriers = cornell.state_triangles()
    expected = n * area / area[carriers].sum()
    got = np.bincount(st.point_triangle, minlength=cornell.n_triangles)
    assert np.all(np.abs(got[carriers] - expected[carriers]) <= 1.0)
    assert np.all(got[~carriers] == 0)
    assert np.allclose(st.point_area.sum(), area[carriers].sum())


def test_sampling_is_stratified_not_plain_random():
    """On the unit floor, counts in an 8 x 8 grid vary far less than independent sampling's."""
    scene = build_scene_arrays("CORNELL_BOX", selected=["Floor"])
    n = 6400
    st = sample_states(scene, n, seed=0)
    floor = st.points
    lo, hi = floor.min(0), floor.max(0)
    cells = np.floor((floor[:, :2] - lo[:2]) / (hi[:2] - lo[:2] + 1e-12) * 8).astype(int)
    counts = np.bincount(cells[:, 0] * 8 + cells[:, 1], minlength=64)
    poisson_sd = np.sqrt(n / 64)
    assert counts.std() < 0.35 * poisson_sd


def test_deterministic_for_a_seed(cornell):
    a = sample_states(cornell, 500, seed=7)
    b = sample_states(cornell, 500, seed=7)
    c = sample_states(cornell, 500, seed=8)
    assert np.array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)


def test_single_point(cornell):
    st = sample_states(cornell, 1, 2, 2, seed=0)
    assert st.n_points == 1 and st.n_states == 4


def test_degenerate_and_non_finite_triangles_are_skipped_and_counted(cornell):
    v = np.vstack([cornell.vertices, [[0, 0, 0], [1, 0, 0], [2, 0, 0], [np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]])
    base = len(cornell.vertices)
    tris = np.vstack([cornell.triangles, [[base, base + 1, base + 2], [base + 3, base + 4, base + 5]]])
    floor = cornell.object_names.index("Floor")
    scene = SceneArrays(v, tris, np.append(cornell.triangle_object, [floor, floor]),
                        np.vstack([cornell.triangle_albedo, [[0.5] * 3] * 2]),
                        np.vstack([cornell.triangle_emission, [[0.0] * 3] * 2]),
                        cornell.object_names, cornell.object_carries_states)
    st = sample_states(scene, 2000, seed=1)
    assert st.skipped_triangles == 2
    assert np.all(np.isfinite(st.points))
    assert not np.any(np.isin(st.point_triangle, [len(tris) - 2, len(tris) - 1]))
    assert "skipped 2 degenerate triangles" in st.summary()


def test_bad_input_messages(cornell):
    with pytest.raises(SceneError, match="at least 1"):
        sample_states(cornell, 0)
    nothing = build_scene_arrays("CORNELL_BOX", selected=[])
    with pytest.raises(SceneError, match="Select at least one mesh"):
        sample_states(nothing, 100)
    parts = [p for p in scene_parts("CORNELL_BOX") if p.name != "Light"]
    dark = parts_to_scene_arrays(parts)
    with pytest.raises(SceneError, match="no light"):
        sample_states(dark, 100)
    only_light = build_scene_arrays("CORNELL_BOX", selected=["Light"])
    with pytest.raises(SceneError, match="entirely emissive"):
        sample_states(only_light, 100)
