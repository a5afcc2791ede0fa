"""The tracer on glossy surfaces (issue 18, item 3): analytic answers and unbiased modes.

A white Multiscatter GGX Glossy patch under a uniform sky reflects the sky's radiance L towards
every direction (white furnace: its directional albedo is 1), so the receiver below it sees
L F, F the point-to-square form factor, for every roughness, down to a mirror; GUIDED (the
guide mixed with the BSDF at glossy vertices) and FINAL_GATHER (glossy hits continue as paths)
agree with it.
A Lambertian scene that carries a material table traces bit for bit as without one.
"""
import numpy as np
import pytest

from bake_scenes import SKY, assert_within, patch_under_sky, trace_at
from lmdp_addon import bsdf
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import tracer as tracer_module
from lmdp_addon.bake.gather import build_gather
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings


def glossy_patch(roughness, lobes=None):
    scene = patch_under_sky()
    patch = scene.triangle_object == scene.object_names.index("Patch")
    scene.materials = bsdf.MaterialTable.from_lobes([lobes or [dict(kind=bsdf.GLOSSY, weight=1.0,
                                                                     roughness=roughness)]])
    scene.triangle_material = np.where(patch, 0, -1).astype(np.int32)
    scene.triangle_albedo[patch] = 0.0
    return scene


def expected():
    return SKY * scenes.point_to_parallel_square_form_factor(1.0, 1.0, (0.0, 0.0))


@pytest.mark.parametrize("roughness", [0.0, 0.05, 0.4, 0.9])
def test_white_glossy_patch_reflects_the_sky(roughness):
    scene = glossy_patch(roughness)
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 100_000)
    assert stats.glossy_vertices > 0
    # 1 % for the recomputed energy-compensation tables (white furnace within 1 %)
    assert_within(values, expected(), extra=0.01 * expected())


def test_lambertian_scene_with_a_material_table_traces_bit_for_bit():
    plain = patch_under_sky()
    tabled = patch_under_sky()
    tabled.materials = bsdf.MaterialTable.lambertian(1)
    tabled.triangle_material = np.zeros(tabled.n_triangles, np.int32)
    a, _ = trace_at(IndirectTracer(plain, "UNGUIDED", max_bounces=4), (0, 0, 0), (0, 0, 1), 5000, seed=3)
    b, _ = trace_at(IndirectTracer(tabled, "UNGUIDED", max_bounces=4), (0, 0, 0), (0, 0, 1), 5000, seed=3)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("mode,fraction,cap", [("GUIDED", 0.5, None), ("GUIDED", 0.9, None), ("GUIDED", 0.9, 1.0),
                                              ("FINAL_GATHER", 0.5, None)])
def test_guided_and_final_gather_on_a_glossy_patch(mode, fraction, cap, monkeypatch):
    """GUIDED mixes the guide with the BSDF at glossy vertices (exact mixture pdf, the guide's
    share capped at ``GLOSSY_GUIDE_FRACTION``; ``cap`` 1: not capped): unbiased for every guide
    fraction."""
    if cap is not None:
        monkeypatch.setattr(tracer_module, "GLOSSY_GUIDE_FRACTION", cap)
    scene = glossy_patch(0.3)
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp, max_bounces=4) if mode == "FINAL_GATHER" else None
    tracer = IndirectTracer(scene, mode, max_bounces=4, guide=guide, gather=gather, guide_fraction=fraction)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 100_000, state=state)
    assert stats.glossy_vertices > 0
    if mode == "FINAL_GATHER":
        assert stats.gathered == 0 and stats.gather_fallback > 0   # glossy hits go on as paths
    assert_within(values, expected(), extra=0.01 * expected())
