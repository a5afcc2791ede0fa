"""RESIDUAL (lmdp_addon.bake.residual): the solution as a control variate of the first bounce.

Unbiasedness against UNGUIDED at equal samples on a scene made here (a closed room lit only
through a slot in one wall, the lamp behind it facing away), determinism for a seed whatever the
thread count, and the control samples' footprint."""
import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver as baking
from lmdp_addon.bake import residual
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings

from bake_scenes import K, small

GREY = (0.7, 0.7, 0.7)


def slot_room():
    """A closed 0.8 x 0.6 x 0.5 m room (its floor: "Floor") whose only light comes through a
    0.06 x 0.3 m slot in its right wall: the lamp sits in a closed annex behind that wall, below
    the slot and facing up (one-sided mesh emission), so no light reaches the room without a
    bounce in the annex and a way through the slot."""
    t = 0.05
    parts = [
        scenes._box_part("Floor", (0.0, 0.0, -t / 2), (0.8, 0.6, t), GREY),
        scenes._box_part("Ceiling", (0.0, 0.0, 0.5 + t / 2), (0.8, 0.6, t), GREY),
        scenes._box_part("Back", (0.0, 0.3 + t / 2, 0.25), (0.8, t, 0.5), (0.6, 0.7, 0.8)),
        scenes._box_part("Front", (0.0, -0.3 - t / 2, 0.25), (0.8, t, 0.5), GREY),
        scenes._box_part("Left", (-0.4 - t / 2, 0.0, 0.25), (t, 0.7, 0.6), (0.8, 0.5, 0.4)),
        scenes._holed_slab_part("Slotted", (0.4, 0.4 + t), (-0.35, 0.35), (-t, 0.5 + t),
                                hole_y=(-0.15, 0.15), hole_z=(0.30, 0.36), albedo=GREY),
        scenes._box_part("AnnexFloor", (0.6, 0.0, -t / 2), (0.3, 0.6, t), GREY),
        scenes._box_part("AnnexCeiling", (0.6, 0.0, 0.5 + t / 2), (0.3, 0.6, t), GREY),
        scenes._box_part("AnnexBack", (0.6, 0.3 + t / 2, 0.25), (0.3, t, 0.5), GREY),
        scenes._box_part("AnnexFront", (0.6, -0.3 - t / 2, 0.25), (0.3, t, 0.5), GREY),
        scenes._box_part("AnnexEnd", (0.75 + t / 2, 0.0, 0.25), (t, 0.7, 0.6), GREY),
    ]
    lz = 0.2
    light = scenes._quad_part("Light", [(0.55, -0.1, lz), (0.7, -0.1, lz), (0.7, 0.1, lz), (0.55, 0.1, lz)],
                              emission=(200.0, 190.0, 170.0))
    light.two_sided_emission = False
    return scenes.parts_to_scene_arrays(parts + [light])


@pytest.fixture(scope="module")
def room():
    scene = slot_room()
    return scene, pipeline.run_all(scene, Settings(point_count=768))


def _texel_mean(ob):
    """Mean over the texels (n, 3) and its standard error from the texels' own errors."""
    n = len(ob.value)
    return ob.value.astype(float).mean(axis=0), np.sqrt((ob.standard_error.astype(float) ** 2).sum(axis=0)) / n


def test_residual_is_unbiased_against_unguided_through_a_slot(room):
    scene, lmdp = room
    settings = small(bake_resolution=16, bake_samples=1024, seed=7)
    unguided = baking.bake(scene, ["Floor"], settings).objects[0]
    res = baking.bake(scene, ["Floor"], small(bake_mode="RESIDUAL", bake_resolution=16, bake_samples=1024, seed=8),
                      lmdp).objects[0]
    mu, su = _texel_mean(unguided)
    mr, sr = _texel_mean(res)
    assert np.all(mu > 0) and np.all(su < 0.03 * mu), (mu, su)          # lit, and resolved
    bound = K * np.sqrt(su ** 2 + sr ** 2)
    assert np.all(np.abs(mr - mu) <= bound), (mr, mu, bound)
    assert res.stats.paths > unguided.stats.paths                        # the control samples ran


def test_residual_bake_is_deterministic_whatever_the_threads(cornell_solved, monkeypatch):
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 96)                     # many units, out of order
    scene = cornell_solved.scene
    a = baking.bake(scene, ["Floor"], small(bake_mode="RESIDUAL", seed=3), cornell_solved, threads=1).objects[0]
    b = baking.bake(scene, ["Floor"], small(bake_mode="RESIDUAL", seed=3), cornell_solved, threads=2).objects[0]
    c = baking.bake(scene, ["Floor"], small(bake_mode="RESIDUAL", seed=4), cornell_solved, threads=2).objects[0]
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)


def test_control_samples_weigh_the_texel_point_as_the_paths_do(cornell):
    """In the first batch the paths' sample 0 is the texel point (weight 1/N): the first
    ``ratio`` of the ratio x N control samples are, so it weighs ratio / (ratio N) there too."""
    from lmdp_addon.bake.checks import object_texels
    ts, _ = object_texels(cornell, cornell.object_names.index("Floor"), 8)
    rng = np.random.default_rng(0)
    fp = residual.control_footprint(ts, 4, 3, rng, first_batch=True)
    assert fp.position.shape == (len(ts), 12, 3)
    np.testing.assert_allclose(fp.position[:, :3], np.repeat(ts.position[:, None], 3, axis=1), atol=1e-12)
    assert np.all(fp.position[:, 1:3] == fp.position[:, :1])
    assert not np.any(np.all(np.abs(fp.position[:, 3:] - ts.position[:, None]) < 1e-9, axis=2))
    later = residual.control_footprint(ts, 4, 3, rng, first_batch=False)
    assert not np.any(np.all(np.abs(later.position - ts.position[:, None]) < 1e-9, axis=2))


def test_residual_needs_a_physical_solution(cornell):
    from lmdp_addon.errors import SceneError, StageOrderError
    with pytest.raises(StageOrderError, match="Solve first"):
        baking.bake(cornell, ["Floor"], small(bake_mode="RESIDUAL"))
    thesis = pipeline.run_all(cornell, Settings(point_count=256, cost_mode="THESIS"))
    with pytest.raises(SceneError, match="PHYSICAL"):
        baking.bake(cornell, ["Floor"], small(bake_mode="RESIDUAL"), thesis)
