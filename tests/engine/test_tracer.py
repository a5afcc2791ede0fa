"""The wavefront tracer (lmdp_addon.bake.tracer) against analytic indirect light.

Tolerances are Monte Carlo bounds (``bake_scenes.assert_within``: 5 standard errors of the
path values, plus the analytic model's own error where it has one, stated at the test).
"""
import numpy as np
import pytest

from bake_scenes import (assert_within, expected_patch_indirect, patch_under_sky, random_guide,
                         solved_patch_under_sky, trace_at)
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.tracer import IndirectTracer, TraceStats


def furnace(albedo=0.5, radiance=1.0):
    """A closed unit cube whose inside walls both emit L (two-sided) and reflect ρ.

    The radiance everywhere inside is L (1 + ρ + ρ² + ...); the indirect light at a wall point is
    what has bounced at least once: L (ρ + ... + ρ^N) with N bounces.
    """
    box = scenes._box_part("Box", (0, 0, 0), (1, 1, 1), (albedo,) * 3)
    inward = scenes.Part("Box", box.vertices, box.faces[:, ::-1], box.face_uv[:, ::-1], (albedo,) * 3,
                         (radiance,) * 3)
    return scenes.parts_to_scene_arrays([inward])


@pytest.mark.parametrize("bounces", [1, 2, 8])
def test_furnace_indirect_is_the_geometric_series(bounces):
    scene = furnace()
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=bounces)
    values, stats = trace_at(tracer, (0.1, 0.2, -0.5), (0, 0, 1), 100_000, seed=bounces)
    expected = sum(0.5 ** k for k in range(1, bounces + 1))
    assert_within(values[:, 0], expected)
    # Russian roulette starts at vertex 3: at most one closest-hit ray per vertex, plus the last.
    assert stats.rays <= stats.paths * (bounces + 1)
    assert stats.vertices > 0 and stats.shadow_rays > 0


def test_direct_light_is_excluded():
    """Parallel squares: the receiver sees only the (black, emitting) square: no indirect light."""
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    tracer = IndirectTracer(scene, "UNGUIDED")
    values, stats = trace_at(tracer, (0.1, 0.0, 0.0), (0, 0, 1), 20_000)
    assert np.all(values == 0.0)
    assert stats.rays > 0


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.015, -0.01)])
def test_patch_under_sky_unguided(offset):
    scene = patch_under_sky()
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    values, _ = trace_at(tracer, (*offset, 0.0), (0, 0, 1), 200_000)
    assert_within(values, expected_patch_indirect(offset), extra=1e-3 * expected_patch_indirect(offset))


def test_patch_under_sky_guided_is_unbiased():
    scene, lmdp = solved_patch_under_sky()
    guide = build_guide(scene, lmdp)
    tracer = IndirectTracer(scene, "GUIDED", max_bounces=4, guide=guide, guide_fraction=0.7)
    n = 200_000
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    assert state >= 0
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), n, state=state)
    assert_within(values, expected_patch_indirect(), extra=1e-3 * expected_patch_indirect())
    assert stats.guided_vertices > 0


def test_trace_stats_add_up():
    a = TraceStats(paths=2, rays=3, shadow_rays=1)
    a.add(TraceStats(paths=1, rays=1, shadow_rays=4, gathered=2))
    assert a.as_dict()["paths"] == 3 and a.total_rays == 9 and a.gathered == 2


def test_modes_need_their_inputs():
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    with pytest.raises(ValueError):
        IndirectTracer(scene, "GUIDED")
    with pytest.raises(ValueError):
        IndirectTracer(scene, "FINAL_GATHER", guide=random_guide()[0])
    with pytest.raises(ValueError):
        IndirectTracer(scene, "PHOTON")
