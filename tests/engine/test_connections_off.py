"""When the bake traces no light connections although ``light_share`` asks for them, it says why
(``connections.off_reason``, the sentence the Bake operator's report adds), and the reasons
are the tracer's own: a bake in those cases traces no light vertex."""
from dataclasses import replace

import pytest

from bake_scenes import small
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import connections, driver


@pytest.fixture(scope="module")
def cornell():
    return scenes.build_scene_arrays("CORNELL_BOX")


def light_vertices(scene, settings):
    result = driver.bake(scene, ["Floor"] if "Floor" in scene.object_names else [scene.object_names[0]],
                         settings, threads=1)
    return sum(ob.stats.light_vertices for ob in result.objects)


def test_on_by_default_in_unguided(cornell):
    settings = small(bake_samples=4)
    assert settings.light_share == 0.5 and settings.bake_mode == "UNGUIDED"
    assert connections.off_reason(cornell, settings) is None
    assert light_vertices(cornell, settings) > 0


def test_a_sample_clamp_turns_them_off_and_says_so(cornell):
    settings = replace(small(bake_samples=4), clamp_indirect=10.0)
    assert "sample clamp" in connections.off_reason(cornell, settings)
    assert light_vertices(cornell, settings) == 0


def test_a_scene_without_emissive_meshes_says_so():
    sky = scenes.build_scene_arrays("PLANE_UNDER_SKY")
    settings = small(bake_samples=4)
    assert "no emissive mesh" in connections.off_reason(sky, settings)
    assert light_vertices(sky, settings) == 0


def test_nothing_to_say_when_not_asked_for(cornell):
    assert connections.off_reason(cornell, replace(small(), light_share=0.0)) is None
    assert connections.off_reason(cornell, replace(small(), bake_mode="FINAL_GATHER", clamp_indirect=10.0)) is None
