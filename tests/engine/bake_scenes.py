"""Scenes with a known answer and Monte Carlo bounds, shared by the bake's engine tests
(test_tracer, test_guide, test_gather, test_lights).

Tolerances are Monte Carlo bounds computed from the samples themselves: an estimate m of n
independent path values with sample standard deviation s must lie within 5 s / sqrt(n) of the
analytic value (plus the analytic model's own error where it has one, stated at the test).
"""
import numpy as np

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.guide import StateGuide
from lmdp_addon.model import pipeline
from lmdp_addon.model.hemisphere import tangent_frame
from lmdp_addon.settings import Settings

K = 5.0  # standard errors


def small(**kw):
    """Settings of a small, fast UNGUIDED bake (``kw`` overrides)."""
    base = dict(bake_mode="UNGUIDED", bake_resolution=16, bake_samples=8, bake_margin=2)
    base.update(kw)
    return Settings(**base)


def assert_within(values, expected, extra=0.0, k=K):
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    mean = values.mean(axis=0)
    se = values.std(axis=0, ddof=1) / np.sqrt(n)
    bound = k * se + extra
    assert np.all(np.abs(mean - expected) <= bound), f"mean {mean} expected {expected} bound {bound}"
    return mean, se


def trace_at(tracer, point, normal, n, seed=0, state=-1):
    rng = np.random.default_rng(seed)
    p = np.tile(np.asarray(point, dtype=np.float64), (n, 1))
    nn = np.tile(np.asarray(normal, dtype=np.float64), (n, 1))
    values, stats = tracer.trace(p, nn, np.full(n, state), rng.random((n, 2)), rng.random(n), rng)
    return values, stats


SKY = 1.5
PATCH_ALBEDO = (0.5, 0.6, 0.8)


def patch_under_sky():
    """A 1 m square patch (albedo ρ) facing down 1 m above a 4 cm receiver, uniform sky L.

    The patch's underside sees the sky (the receiver's 0.0016 m² change that by < 1e-3 in
    relative terms), so its radiance is ρ L and the receiver's indirect light is ρ L F, F the
    point-to-parallel-square form factor. Nothing else bounces.
    """
    e, r = 0.5, 0.02
    parts = [
        scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.7, 0.7, 0.7)),
        scenes._quad_part("Patch", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], PATCH_ALBEDO),
    ]
    return scenes.parts_to_scene_arrays(parts, world=(SKY, SKY, SKY))


def solved_patch_under_sky():
    """``(scene, LMDPResult)`` of :func:`patch_under_sky`, 512 points, PHYSICAL."""
    scene = patch_under_sky()
    return scene, pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))


def expected_patch_indirect(offset=(0.0, 0.0)):
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, offset)
    return np.asarray(PATCH_ALBEDO) * SKY * F


def patch_over_lamp(gap=0.005):
    """The patch of :func:`patch_under_sky` lit by a two-sided 0.2 m lamp ``gap`` below it, over
    a black receiver, in a black world: the patch's radiance is ρ D_e(y), all of it direct, and
    D_e is large only in the gap above the lamp (which the receiver cannot see)."""
    e, r, lx = 0.5, 0.02, 0.1
    z = 1.0 - gap
    parts = [
        scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.0, 0.0, 0.0)),
        scenes._quad_part("Patch", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], PATCH_ALBEDO),
        scenes._quad_part("Lamp", [(-lx, -lx, z), (-lx, lx, z), (lx, lx, z), (lx, -lx, z)], emission=(10.0,) * 3),
    ]
    return scenes.parts_to_scene_arrays(parts)


def random_guide(strata_u=3, strata_v=5, m=4, seed=0):
    """A :class:`StateGuide` of ``m`` states with random normals and random policies (no
    locator), and the normals."""
    rng = np.random.default_rng(seed)
    S = strata_u * strata_v
    u = rng.random((m, S)) ** 3
    u[:, 2] = 0.0  # a stratum the guide never picks
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return StateGuide(locator=None, frames=tangent_frame(normals), first=u, later=u[::-1].copy(),
                      strata_u=strata_u, strata_v=strata_v), normals


def unit_vector(v):
    return v / np.linalg.norm(v)
