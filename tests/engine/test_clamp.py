"""Cycles' sample clamp (``bake/clamp.py``) in the tracer, against analytic answers.

Under a uniform sky every cosine-sampled contribution of the patch scene is a constant (the sky
times the path's albedos), so the clamped estimate is known exactly: each contribution c is
scaled by ``min(1, 3 C / Σ_c |ρ(x0) c|)``, C the limit of its bounce (Cycles' ``film_clamp_light``
with ``scene/integrator.cpp``'s factor 3), ρ(x0) the receiver's colour that Cycles' throughput
holds and the DIFFUSE pass divides out again.
"""
import numpy as np
import pytest

from bake_scenes import PATCH_ALBEDO, SKY, assert_within, patch_under_sky, small, solved_patch_under_sky, trace_at
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver
from lmdp_addon.bake.clamp import SampleClamp, clamp_light, clamp_warnings
from lmdp_addon.bake.content import BakeContent
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.errors import SceneError
from lmdp_addon.settings import LightPaths, Settings
from test_tracer import furnace

RECEIVER_ALBEDO = 0.7   # patch_under_sky's receiver


def receiver_paths(scene, tracer, n, seed=0, state=-1):
    """``(values, stats)`` of n paths from the receiver's centre, with its triangle (its ρ(x0))."""
    rng = np.random.default_rng(seed)
    receiver = int(np.flatnonzero(scene.triangle_object == scene.object_names.index("Receiver"))[0])
    return tracer.trace(np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, state), rng.random((n, 2)),
                        rng.random(n), rng, triangles=np.full(n, receiver))


def test_clamp_light_scales_rows_over_three_times_the_limit():
    light = np.array([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [-4.0, 0.0, 4.0]], np.float32)
    weight = np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5]], np.float32)
    limit = SampleClamp(indirect=1.0).limit(1)           # Cycles stores 3 x the setting
    assert limit == 3.0 and SampleClamp(indirect=1.0).limit(0) == np.inf
    out, count = clamp_light(light, limit, weight)
    np.testing.assert_allclose(out[0], light[0] * 3.0 / 6.0, rtol=1e-6)   # sum 6 > 3
    np.testing.assert_array_equal(out[1], light[1])                       # 2 x 1.5 = 3, not over
    np.testing.assert_allclose(out[2], light[2] * 3.0 / 4.0, rtol=1e-6)   # |-2| + 0 + 2 = 4 > 3
    assert count == 2
    same, none = clamp_light(light, np.inf)
    assert same is light and none == 0


@pytest.mark.parametrize("c_direct, c_indirect", [(0.5, 0.0), (0.0, 0.4), (0.6, 0.3)])
def test_clamped_direct_and_indirect_under_the_sky(c_direct, c_indirect):
    """D + I at the receiver: its rays that escape carry L (direct, bounce 0), the patch's rays
    that escape carry ρ_patch L (bounce 1); each scaled by its limit as Cycles does."""
    scene = patch_under_sky()
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, (0.0, 0.0))
    rho = np.asarray(PATCH_ALBEDO)
    sky = np.full(3, SKY)

    def scale(c, light):
        seen = RECEIVER_ALBEDO * np.abs(light).sum()
        return min(1.0, 3 * c / seen) if c > 0 else 1.0
    expected = sky * (1 - F) * scale(c_direct, sky) + rho * sky * F * scale(c_indirect, rho * sky)
    assert not np.allclose(expected, sky * (1 - F) + rho * sky * F)   # the clamp binds
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4, content=BakeContent(direct=True),
                            clamp=SampleClamp(direct=c_direct, indirect=c_indirect))
    values, stats = receiver_paths(scene, tracer, 100_000)
    assert_within(values, expected, extra=1e-3 * expected)
    assert stats.clamped > 0


def test_indirect_clamp_at_the_patch_and_direct_clamp_ignored_by_an_indirect_bake():
    scene = patch_under_sky()
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, (0.0, 0.0))
    rho = np.asarray(PATCH_ALBEDO)
    seen = RECEIVER_ALBEDO * rho.sum() * SKY
    expected = rho * SKY * F * (3 * 0.25 / seen)
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4, clamp=SampleClamp(direct=0.01, indirect=0.25))
    values, _ = receiver_paths(scene, tracer, 100_000, seed=3)
    assert_within(values, expected, extra=1e-3 * expected)
    direct_only = IndirectTracer(scene, "UNGUIDED", max_bounces=4, clamp=SampleClamp(direct=0.01))
    unclamped = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    a, _ = receiver_paths(scene, direct_only, 20_000, seed=4)
    b, _ = receiver_paths(scene, unclamped, 20_000, seed=4)
    assert_within(a, rho * SKY * F, extra=1e-3 * rho * SKY * F)     # no bounce-0 light in an indirect bake
    assert_within(b, rho * SKY * F, extra=1e-3 * rho * SKY * F)


def test_guided_clamps_cycles_samples():
    """GUIDED draws the receiver's directions from u*, so its contributions vary with the guide's
    weight cos θ / (π p) where Cycles' (cosine) ones are the constant ρ_patch L; the clamp judges
    each by Cycles' value (the path's value x p / p_cos) and so keeps the clamped mean of Cycles'
    samples: the same analytic value as UNGUIDED, though every guided value differs from it."""
    scene, lmdp = solved_patch_under_sky()
    guide = build_guide(scene, lmdp)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    assert state >= 0
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, (0.0, 0.0))
    rho = np.asarray(PATCH_ALBEDO)
    expected = rho * SKY * F * (3 * 0.25 / (RECEIVER_ALBEDO * rho.sum() * SKY))
    tracer = IndirectTracer(scene, "GUIDED", max_bounces=4, guide=guide, guide_fraction=0.7,
                            clamp=SampleClamp(indirect=0.25))
    values, stats = receiver_paths(scene, tracer, 200_000, seed=5, state=state)
    assert stats.guided_vertices > 0
    assert_within(values, expected, extra=1e-3 * expected)


@pytest.mark.parametrize("bounces", [2, 8])
def test_cycles_roulette_of_the_clamp_is_unbiased(bounces):
    """A clamp that never binds leaves the furnace's geometric series; the paths end by Cycles'
    Russian roulette (from the second vertex on), so they are shorter than without a clamp."""
    scene = furnace()
    clamped = IndirectTracer(scene, "UNGUIDED", max_bounces=bounces, clamp=SampleClamp(indirect=1e9))
    values, stats = trace_at(clamped, (0.1, 0.2, -0.5), (0, 0, 1), 100_000, seed=bounces)
    assert_within(values[:, 0], sum(0.5 ** k for k in range(1, bounces + 1)))
    assert stats.clamped == 0
    _, plain = trace_at(IndirectTracer(scene, "UNGUIDED", max_bounces=bounces), (0.1, 0.2, -0.5), (0, 0, 1),
                        100_000, seed=bounces)
    assert stats.vertices < plain.vertices
    late = IndirectTracer(scene, "UNGUIDED", max_bounces=bounces, clamp=SampleClamp(indirect=1e9), min_light_bounces=3)
    values, spared = trace_at(late, (0.1, 0.2, -0.5), (0, 0, 1), 100_000, seed=bounces + 1)
    assert_within(values[:, 0], sum(0.5 ** k for k in range(1, bounces + 1)))
    assert spared.vertices > stats.vertices          # Min Light Bounces 3: no roulette before y_5


def test_no_clamp_is_the_unclamped_bake_bit_for_bit(cornell):
    base = driver.bake(cornell, ["Floor"], small(bake_samples=8), threads=1).object("Floor")
    off = driver.bake(cornell, ["Floor"], small(bake_samples=8, clamp_direct=0.0, clamp_indirect=0.0),
                      threads=1).object("Floor")
    np.testing.assert_array_equal(base.image, off.image)
    on = driver.bake(cornell, ["Floor"], small(bake_samples=8, clamp_indirect=0.05), threads=1).object("Floor")
    assert on.value.mean() < 0.95 * base.value.mean() and on.stats.clamped > 0


@pytest.mark.parametrize("mode", ["UNGUIDED", "FINAL_GATHER"])
def test_clamped_bakes_are_the_same_on_one_and_two_threads(cornell, mode):
    lmdp = None
    if mode != "UNGUIDED":
        from lmdp_addon.model import pipeline
        lmdp = pipeline.run_all(cornell, Settings(point_count=256, cost_mode="PHYSICAL"))
    settings = small(bake_mode=mode, bake_samples=16, clamp_indirect=0.5, clamp_direct=1.0,
                     bake_content="DIRECT_INDIRECT")
    one = driver.bake(cornell, ["Floor"], settings, lmdp=lmdp, threads=1)
    two = driver.bake(cornell, ["Floor"], settings, lmdp=lmdp, threads=2)
    np.testing.assert_array_equal(one.object("Floor").image, two.object("Floor").image)
    stats = one.stats()
    assert stats["light_paths"]["clamp_indirect"] == 0.5 and stats["light_paths"]["clamp_applied"] is True
    assert stats["objects"]["Floor"]["trace"]["clamped"] > 0
    assert any("Final Gather" in w and "not clamped" in w for w in one.warnings) == (mode == "FINAL_GATHER")


def test_light_paths_carry_both_clamps():
    scene = LightPaths.from_cycles(12, 4, clamp_indirect=10, clamp_direct=0)
    assert scene.clamped and scene.as_dict()["clamp_applied"] is True
    assert "indirect clamped at 10 (biased, like Cycles)" in scene.summary()
    settings = scene.apply(Settings(clamp_direct=3.0, clamp_indirect=0.0))
    assert (settings.clamp_direct, settings.clamp_indirect, settings.max_bounces) == (0.0, 10.0, 4)
    custom = LightPaths.custom(6, clamp_direct=2.0)
    assert custom.apply(Settings()).clamp_direct == 2.0 and "direct clamped at 2" in custom.summary()
    assert not LightPaths.from_cycles(12, 4, clamp_indirect=-1.0).clamped   # Cycles: <= 0 is off
    assert LightPaths.custom(6).summary().endswith("no clamp")


def test_clamp_warnings_name_the_modes_and_light_kinds(cornell):
    assert clamp_warnings(cornell, Settings()) == []
    assert clamp_warnings(cornell, Settings(clamp_indirect=10.0)) == []      # UNGUIDED: Cycles' samples
    assert clamp_warnings(cornell, Settings(clamp_indirect=10.0, bake_mode="GUIDED")) == []
    assert clamp_warnings(cornell, Settings(clamp_indirect=10.0, bake_mode="RESIDUAL")) == []
    gather = clamp_warnings(cornell, Settings(clamp_direct=1.0, bake_mode="FINAL_GATHER"))
    assert len(gather) == 1 and "direct clamp 1" in gather[0] and "not clamped" in gather[0]


@pytest.mark.parametrize("name, value", [("clamp_indirect", -1.0), ("clamp_direct", float("nan"))])
def test_a_negative_or_nan_clamp_is_refused_naming_the_setting(cornell, name, value):
    label = {"clamp_indirect": "Clamp Indirect", "clamp_direct": "Clamp Direct"}[name]
    with pytest.raises(SceneError, match=f"{label} must be 0 \\(off\\) or a positive"):
        driver.bake(cornell, ["Floor"], small(**{name: value}))


def test_several_kinds_of_light_are_named_once(cornell):
    """The Cornell box's emitter and a lit world: Cycles draws one light sample among both."""
    from dataclasses import replace
    lit = replace(cornell, world_radiance=np.array([0.5, 0.5, 0.5]))
    warnings = clamp_warnings(lit, Settings(clamp_indirect=10.0))
    assert len(warnings) == 1 and "emissive meshes and the world" in warnings[0]
    assert clamp_warnings(cornell, Settings(clamp_indirect=10.0)) == []
    from lmdp_addon.lamps import POINT, Lamps
    two = replace(cornell, triangle_emission=np.zeros_like(cornell.triangle_emission),
                  lamps=Lamps(names=["A", "B"], kind=[POINT, POINT], position=[[0, 0, 0.9], [0.2, 0, 0.9]],
                              strength=[[5.0] * 3] * 2))
    warnings = clamp_warnings(two, Settings(clamp_indirect=10.0))
    assert len(warnings) == 1 and "2 lights" in warnings[0] and "one of every light" in warnings[0]
