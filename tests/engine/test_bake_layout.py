"""Per-object lightmap sizes and atlases in the engine (lmdp_addon.bake.resolution, checks,
driver.compose_atlas), on the Cornell box's own UV charts."""
import numpy as np
import pytest

from lmdp_addon.bake import checks, driver, resolution
from lmdp_addon.errors import SceneError
from lmdp_addon.settings import Settings


def test_density_resolution_is_the_side_that_holds_the_density():
    s = Settings(resolution_mode="DENSITY", texel_density=10.0, power_of_two=False, min_resolution=1,
                 max_resolution=4096)
    assert resolution.density_resolution(4.0, 1.0, s) == 20           # 2 m x 2 m on the whole square
    assert resolution.density_resolution(4.0, 0.25, s) == 40          # a quarter of the square: 2x the side
    assert resolution.density_resolution(4.0, 0.0, s) == 1            # no UV area: the smallest
    s.power_of_two = True
    assert resolution.density_resolution(4.0, 1.0, s) == 32
    s.min_resolution, s.max_resolution = 64, 128
    assert resolution.density_resolution(4.0, 1.0, s) == 64
    assert resolution.density_resolution(400.0, 1.0, s) == 128


@pytest.mark.parametrize("changes, words", [
    (dict(resolution_mode="TEXELS"), "Unknown resolution mode"),
    (dict(resolution_mode="DENSITY", texel_density=0.0), "Texel density must be above 0"),
    (dict(resolution_mode="DENSITY", min_resolution=64, max_resolution=32), "Min / Max Resolution"),
])
def test_bad_resolution_settings_are_refused(cornell, changes, words):
    with pytest.raises(SceneError, match=words):
        checks.check_bake(cornell, ["Floor"], Settings(bake_mode="UNGUIDED", **changes))


def test_density_plan_gives_each_object_its_side(cornell):
    s = Settings(bake_mode="UNGUIDED", resolution_mode="DENSITY", texel_density=64.0, power_of_two=False,
                 min_resolution=1, max_resolution=4096)
    plan = checks.check_bake(cornell, ["Floor", "TallBox"], s)
    for name in ("Floor", "TallBox"):
        i = cornell.object_names.index(name)
        world, uv = resolution.surface_areas(cornell, i)
        assert plan.resolution_of(i) == int(np.ceil(64.0 * np.sqrt(world / uv)))
        assert plan.texels[i][0].resolution == plan.resolution_of(i)


def test_an_atlas_whose_objects_share_texels_is_refused(cornell):
    """The demo's objects each fill their own unit square: in one image they overlap."""
    with pytest.raises(SceneError, match="atlas's objects overlap.*Floor"):
        checks.check_bake(cornell, ["Floor", "TallBox"], Settings(bake_mode="UNGUIDED", atlas=True))
    problems = checks.lightmap_uv_problems(cornell, ["Floor", "TallBox"],
                                           [cornell.object_names.index(n) for n in ("Floor", "TallBox")],
                                           {cornell.object_names.index(n): 32 for n in ("Floor", "TallBox")},
                                           atlas=True)
    assert list(problems) == ["TallBox"] and "Floor" in problems["TallBox"]


def test_compose_atlas_keeps_every_objects_texels_and_fills_the_margin_once(cornell):
    s = Settings(bake_mode="UNGUIDED", bake_resolution=16, bake_samples=2, bake_margin=2)
    result = driver.bake(cornell, ["Floor", "TallBox"], s)
    a, b = result.objects
    keep = ~np.isin(b.texels.flat_index, a.texels.flat_index)      # make them disjoint by hand
    b.texels = b.texels.subset(np.flatnonzero(keep))
    b.value = b.value[keep]
    atlas = driver.compose_atlas("Atlas", [a, b], margin=2)
    for ob in (a, b):
        np.testing.assert_array_equal(atlas.image[ob.texels.row, ob.texels.col, :3], ob.value)
        assert ob.image is atlas.image and ob.image_name == "Atlas_lmdp_indirect"
    assert atlas.image[..., 3].sum() >= len(a.texels) + len(b.texels)
