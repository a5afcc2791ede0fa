"""What is baked (``bake/content``): the direct term at the texel and the diffuse colour, against
analytic values, and bakes that stay deterministic whatever the thread count."""
import numpy as np
import pytest

from bake_scenes import PATCH_ALBEDO, SKY, assert_within, patch_under_sky, small, trace_at
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver
from lmdp_addon.bake.content import BakeContent
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.settings import Settings


def test_direct_plus_indirect_under_the_sky_patch():
    """The receiver sees the sky except through the patch (form factor F): D = L (1 - F); the
    patch reflects ρ L: I = ρ L F. Traced with the start triangle, times the receiver's colour."""
    scene = patch_under_sky()
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, (0.0, 0.0))
    expected = SKY * (1 - F) + np.asarray(PATCH_ALBEDO) * SKY * F
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4, content=BakeContent(direct=True))
    values, _ = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 100_000)
    assert_within(values, expected, extra=1e-3 * expected)
    colour = IndirectTracer(scene, "UNGUIDED", max_bounces=4, content=BakeContent(direct=True, multiply_color=True))
    rng = np.random.default_rng(1)
    n = 100_000
    receiver = int(np.flatnonzero(scene.triangle_object == scene.object_names.index("Receiver"))[0])
    v, _ = colour.trace(np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, -1), rng.random((n, 2)),
                        rng.random(n), rng, triangles=np.full(n, receiver))
    assert_within(v, expected * scene.triangle_albedo[receiver], extra=1e-3 * expected)


def test_direct_light_of_a_parallel_square_emitter():
    """PARALLEL_SQUARES at the receiver's centre: D = L_e F (NEE + MIS at x0), nothing bounces
    back (the emitter is black)."""
    p = scenes.PARALLEL_SQUARES
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    F = scenes.point_to_parallel_square_form_factor(p["emitter_side"], p["height"])
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=2, content=BakeContent(direct=True))
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 50_000)
    assert_within(values, np.asarray(p["radiance"]) * F, extra=1e-3 * p["radiance"][0] * F)
    assert stats.shadow_rays >= 50_000
    indirect, _ = trace_at(IndirectTracer(scene, "UNGUIDED", max_bounces=2), (0.0, 0.0, 0.0), (0, 0, 1), 50_000)
    assert np.abs(indirect).max() < 1e-3 * p["radiance"][0] * F


def test_unknown_content_is_refused():
    with pytest.raises(ValueError, match="bake_content"):
        BakeContent.from_settings(Settings(bake_content="COMBINED"))
    assert BakeContent.from_settings(Settings(bake_content="DIRECT_INDIRECT", multiply_color=True)).pass_filter == \
        ("DIRECT", "INDIRECT", "COLOR")


@pytest.mark.parametrize("content, colour", [("DIRECT_INDIRECT", True), ("INDIRECT", True)])
def test_content_bakes_are_the_same_on_one_and_two_threads(cornell, content, colour):
    settings = small(bake_content=content, multiply_color=colour, bake_samples=16)
    one = driver.bake(cornell, ["Floor"], settings, threads=1).object("Floor")
    two = driver.bake(cornell, ["Floor"], settings, threads=2).object("Floor")
    np.testing.assert_array_equal(one.image, two.image)
    plain = driver.bake(cornell, ["Floor"], small(bake_samples=16), threads=2).object("Floor")
    assert not np.array_equal(plain.image, two.image)
