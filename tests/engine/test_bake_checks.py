"""The checks of a bake (lmdp_addon.bake.checks): every error before any work, one
rasterisation per object, and the plan the bake runs from."""
import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import checks, driver
from lmdp_addon.bake.checks import check_bake
from lmdp_addon.bake.texels import rasterize_texels
from lmdp_addon.errors import Cancelled, SceneError, StageOrderError
from lmdp_addon.model import pipeline
from lmdp_addon.progress import Progress
from lmdp_addon.settings import Settings

from bake_scenes import small


def test_texels_are_the_texels_module_on_the_object_triangles(cornell):
    index = cornell.object_names.index("TallBox")
    ts, tris = checks.object_texels(cornell, index, 32)
    normals, _ = cornell.triangle_geometry()
    mask = cornell.triangle_object == index
    ref = rasterize_texels(cornell.triangle_uv[mask], cornell.corners()[mask], normals[mask], 32)
    np.testing.assert_array_equal(ts.row, ref.row)
    np.testing.assert_array_equal(ts.col, ref.col)
    np.testing.assert_allclose(ts.position, ref.position)
    assert np.all(cornell.triangle_object[tris[ts.triangle]] == index)


def test_the_bake_reuses_the_texels_its_check_rasterised(cornell, monkeypatch):
    """One rasterisation per object (the check's, overlaps included), none in the bake; past
    TEXEL_CACHE_LIMIT an object is rasterised again when baked, with the same result."""
    calls = []
    original = checks.rasterize_texels
    monkeypatch.setattr(checks, "rasterize_texels", lambda *a, **k: calls.append(1) or original(*a, **k))
    names = ["Floor", "TallBox"]
    cached = driver.bake(cornell, names, small())
    assert len(calls) == len(names)
    calls.clear()
    monkeypatch.setattr(checks, "TEXEL_CACHE_LIMIT", 0)
    again = driver.bake(cornell, names, small())
    assert len(calls) == 2 * len(names)
    for a, b in zip(cached.objects, again.objects):
        np.testing.assert_array_equal(a.image, b.image)


def test_a_bake_given_its_plan_checks_nothing_again(cornell, monkeypatch):
    """The plan of check_bake carries the texels and warnings to the bake (the operators check on
    the main thread and bake on a worker): the bake neither checks nor rasterises, and bakes
    what a bake that checks for itself bakes."""
    settings = small(seed=5)
    plan = check_bake(cornell, ["Floor", "TallBox"], settings)
    assert plan.names == ["Floor", "TallBox"] and plan.resolution == 16 and plan.warnings == []
    assert plan.indices == [cornell.object_names.index(n) for n in plan.names]
    assert sorted(plan.texels) == sorted(plan.indices)
    checked = driver.bake(cornell, plan.names, settings)

    def refuse(*args, **kwargs):
        raise AssertionError("checked or rasterised again")

    monkeypatch.setattr(driver, "check_bake", refuse)
    monkeypatch.setattr(checks, "rasterize_texels", refuse)
    planned = driver.bake(cornell, plan.names, settings, plan=plan)
    for a, b in zip(checked.objects, planned.objects):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.standard_error, b.standard_error)


# -- bad input ---------------------------------------------------------------------------------------


class _StopAfterRasterising(Progress):
    """Asks to stop once ``calls`` holds ``after`` rasterisations (Esc during the texel checks)."""

    def __init__(self, calls, after):
        super().__init__()
        self.calls, self.after = calls, after

    def should_cancel(self):
        return len(self.calls) >= self.after


def test_texel_checks_wait_for_the_worker_and_cancel_between_objects(cornell, monkeypatch):
    """Issue 22, class 11: the operators' main-thread check rasterises nothing (check_bake with
    rasterise=False); the bake runs the texel checks first, as a step whose progress can cancel
    them between objects, and bakes the same lightmaps from the texels they rasterised."""
    calls = []
    original = checks.rasterize_texels
    monkeypatch.setattr(checks, "rasterize_texels", lambda *a, **k: calls.append(1) or original(*a, **k))
    names = scenes.state_part_names("CORNELL_BOX")
    settings = small(seed=2)
    plan = check_bake(cornell, names, settings, rasterise=False)
    assert calls == [] and not plan.texels_checked and plan.texels == {}
    with pytest.raises(Cancelled):
        driver.bake(cornell, names, settings, progress=_StopAfterRasterising(calls, 1), plan=plan)
    assert len(calls) == 1                      # stopped after the first object, nothing baked
    calls.clear()
    plan = check_bake(cornell, names, settings, rasterise=False)
    deferred = driver.bake(cornell, names, settings, plan=plan)
    assert len(calls) == len(names) and plan.texels_checked
    checked = driver.bake(cornell, names, settings)
    for a, b in zip(checked.objects, deferred.objects):
        np.testing.assert_array_equal(a.image, b.image)


def test_deferred_texel_checks_raise_the_same_errors(cornell):
    scene = overlapping(cornell, "TallBox")
    plan = check_bake(scene, ["Floor", "TallBox"], small(), rasterise=False)
    with pytest.raises(SceneError, match="Overlapping UVs on TallBox"):
        checks.check_texels(scene, plan)


def test_bad_resolution_samples_and_bounces(cornell):
    with pytest.raises(SceneError, match="resolution must be at least 1"):
        check_bake(cornell, ["Floor"], small(bake_resolution=0))
    with pytest.raises(SceneError, match="samples must be at least 1"):
        check_bake(cornell, ["Floor"], small(bake_samples=0))
    with pytest.raises(SceneError, match="bounces"):
        check_bake(cornell, ["Floor"], small(max_bounces=0))


def test_missing_uv_map_names_the_objects(cornell):
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    scene.object_has_uv[[0, 5]] = False
    with pytest.raises(SceneError, match=r"No UV map on Floor, TallBox: add one"):
        check_bake(scene, ["Floor", "TallBox", "Ceiling"], small())


def overlapping(scene, name):
    """Give every face of ``name`` the same chart: all its UVs overlap."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    mask = scene.triangle_object == scene.object_names.index(name)
    uv = scene.triangle_uv[mask]
    quad = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], np.float32)
    scene.triangle_uv[mask] = np.tile(quad, (len(uv) // 2, 1, 1))
    return scene


def test_overlapping_uvs_are_detected_and_named(cornell):
    scene = overlapping(cornell, "TallBox")
    count, example = checks.uv_overlaps(scene, scene.object_names.index("TallBox"), 16)
    assert count == 256 and example is not None
    with pytest.raises(SceneError, match=r"Overlapping UVs on TallBox \(256 texels"):
        check_bake(scene, ["Floor", "TallBox"], small())


def _overlaps_from_both_orders(scene, index, R):
    """The overlap count and first example found by rasterising in both triangle orders (the
    last triangle wins a texel): the triangles differ exactly where several cover its centre."""
    tris = np.flatnonzero(scene.triangle_object == index)
    normals, _ = scene.triangle_geometry()
    a = rasterize_texels(scene.triangle_uv[tris], scene.corners()[tris], normals[tris], R)
    r = tris[::-1]
    b = rasterize_texels(scene.triangle_uv[r], scene.corners()[r], normals[r], R)
    differs = tris[a.triangle] != r[b.triangle]
    count = int(np.count_nonzero(differs))
    return count, ((int(a.row[differs][0]), int(a.col[differs][0])) if count else None)


@pytest.mark.parametrize("name, resolution", [("TallBox", 16), ("TallBox", 61), ("Floor", 32), ("ShortBox", 128)])
def test_one_rasterisation_finds_the_overlaps_of_both_triangle_orders(cornell, name, resolution):
    """The single-pass overlap flags count the same texels, with the same first example, as
    comparing the two triangle orders, on overlapping and partly overlapping charts."""
    scene = overlapping(cornell, name)
    index = scene.object_names.index(name)
    half = np.flatnonzero(scene.triangle_object == index)[::2]
    scene.triangle_uv[half] = scene.triangle_uv[half][..., ::-1] * 0.7   # onto the other halves, in part
    for s in (scene, cornell):
        assert checks.uv_overlaps(s, index, resolution) == _overlaps_from_both_orders(s, index, resolution)
    assert checks.uv_overlaps(scene, index, resolution)[0] > 0


@pytest.mark.parametrize("name", ["Floor", "TallBox", "ShortBox", "LeftWall"])
def test_demo_charts_do_not_overlap(cornell, name):
    for R in (16, 64, 128):
        assert checks.uv_overlaps(cornell, cornell.object_names.index(name), R)[0] == 0


def test_uvs_outside_the_image_are_an_error(cornell):
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    mask = scene.triangle_object == 0
    scene.triangle_uv[mask] += 5.0
    with pytest.raises(SceneError, match="covers no texel"):
        check_bake(scene, ["Floor"], small())


def test_no_light_is_an_error():
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    scene.triangle_emission[:] = 0.0
    with pytest.raises(SceneError, match="no light to bake"):
        check_bake(scene, ["Floor"], small())


def test_guided_modes_need_a_solution(cornell, cornell_solved):
    for mode in ("GUIDED", "FINAL_GATHER"):
        with pytest.raises(StageOrderError, match="Solve first"):
            check_bake(cornell, ["Floor"], small(bake_mode=mode))
    assert check_bake(cornell, ["Floor"], small(bake_mode="GUIDED"), cornell_solved).warnings == []


def test_final_gather_needs_physical_mode_and_the_same_scene(cornell):
    thesis = pipeline.run_all(cornell, Settings(point_count=256, cost_mode="THESIS"))
    with pytest.raises(SceneError, match="PHYSICAL"):
        check_bake(cornell, ["Floor"], small(bake_mode="FINAL_GATHER"), thesis)
    physical = pipeline.run_all(cornell, Settings(point_count=256))
    moved = scenes.build_scene_arrays("CORNELL_BOX")
    moved.vertices[moved.triangles[moved.triangle_object == 5]] += 0.01
    with pytest.raises(SceneError, match="scene changed"):
        check_bake(moved, ["Floor"], small(bake_mode="FINAL_GATHER"), physical)
    warnings = check_bake(moved, ["Floor"], small(bake_mode="GUIDED"), physical).warnings
    assert any("scene changed" in w for w in warnings)


def test_objects_without_states_are_reported(cornell):
    lmdp = pipeline.run_all(scenes.build_scene_arrays("CORNELL_BOX", selected=["Floor"]),
                            Settings(point_count=128))
    warnings = check_bake(cornell, ["Floor", "TallBox"], small(bake_mode="GUIDED"), lmdp).warnings
    assert any("No states on TallBox" in w for w in warnings)


def test_fingerprint_ignores_the_selection_only():
    a = scenes.build_scene_arrays("CORNELL_BOX")
    b = scenes.build_scene_arrays("CORNELL_BOX", selected=["Floor"])
    assert checks.scene_fingerprint(a) == checks.scene_fingerprint(b)
    b.triangle_albedo[0] *= 0.5
    assert checks.scene_fingerprint(a) != checks.scene_fingerprint(b)


def _tiny_islands(name, size=1e-4):
    """The Cornell box with every UV triangle of ``name`` shrunk around its own centroid: islands
    inside [0, 1] that cover no texel centre (issue 18: the tiny islands of a real atlas)."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    mask = scene.triangle_object == scene.object_names.index(name)
    uv = scene.triangle_uv[mask]
    centre = uv.mean(axis=1, keepdims=True)
    scene.triangle_uv[mask] = centre + size * (uv - centre)
    return scene


def test_objects_whose_islands_cover_no_texel_are_left_out_with_a_warning():
    """Issue 18, item 7: objects whose UV islands are too small for any texel centre do not stop
    the bake: they are named in a warning that says why, and the others are baked, whether the
    texel checks run in check_bake or later in the bake."""
    scene = _tiny_islands("TallBox")
    for rasterise in (True, False):
        plan = check_bake(scene, ["Floor", "TallBox"], small(), rasterise=rasterise)
        result = driver.bake(scene, ["Floor", "TallBox"], small(), plan=plan)
        assert [o.name for o in result.objects] == ["Floor"]
        warning = [w for w in result.warnings if "TallBox" in w]
        assert len(warning) == 1 and "smaller than a texel" in warning[0], result.warnings
    with pytest.raises(SceneError, match="TallBox .its UV islands inside \\[0, 1\\] are all smaller"):
        check_bake(scene, ["TallBox"], small())
