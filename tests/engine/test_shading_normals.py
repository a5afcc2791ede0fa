"""Smooth / custom shading normals in the tracer, the light sampling and the states (issue 18, item 1).

The scene: a tiny receiver at the origin facing up, a large plane 1 m above it facing down
(albedo ρ), a uniform world L all around. The plane's underside sees the world, so its radiance
is ρ L; the receiver's indirect light is ρ L times the cosine-weighted share of its shading
hemisphere that lies above its geometric surface (Cycles absorbs the directions below Ng). A
shading normal tilted by θ from the geometric one gives

    I = ρ L ∫_{Ng·ω > 0} max(N·ω, 0)/π dω = ρ L (1 + cos θ)/2,

the textbook sky factor of a tilted plane. Bounds: 5 standard errors of the path values plus
the plane's finite size (its edge at 200 m hides less than 1e-4 of the cosine mass).
"""
import dataclasses

import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.lights import EmitterSampler
from lmdp_addon.model.states import sample_states
from lmdp_addon.raycast import RayCaster

SKY = 2.0
RHO = 0.5
HALF = 200.0


def sky_scene(receiver_tilt=None, plane_tilt=None):
    """The scene above; ``*_tilt`` (degrees about x) sets that part's corner normals to its face
    normal turned by the angle (None: no corner normals on it, flat)."""
    r = 0.01
    parts = [scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.7,) * 3),
             scenes._quad_part("Plane", [(-HALF, -HALF, 1), (-HALF, HALF, 1), (HALF, HALF, 1), (HALF, -HALF, 1)],
                               (RHO,) * 3)]
    scene = scenes.parts_to_scene_arrays(parts, world=(SKY,) * 3)
    if receiver_tilt is None and plane_tilt is None:
        return scene
    face = scene.triangle_geometry()[0]
    corner = np.repeat(face[:, None, :], 3, axis=1).astype(np.float32)
    for name, tilt in (("Receiver", receiver_tilt), ("Plane", plane_tilt)):
        if tilt is None:
            continue
        t = np.radians(tilt)
        rot = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
        mask = scene.triangle_object == scene.object_names.index(name)
        corner[mask] = corner[mask] @ rot.T
    return dataclasses.replace(scene, corner_normals=corner)


def trace_receiver(scene, n=200_000, seed=1, bounces=2):
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=bounces)
    rng = np.random.default_rng(seed)
    tri = np.zeros(n, dtype=np.int64)                  # the receiver's first triangle
    points = np.tile(scene.corners()[0].mean(axis=0), (n, 1))
    normals = np.tile(scene.triangle_geometry()[0][0], (n, 1))
    values, _ = tracer.trace(points, normals, np.full(n, -1), rng.random((n, 2)), rng.random(n), rng,
                             triangles=tri)
    return values[:, 0].astype(np.float64)


def assert_close(values, expected, model=1e-4):
    se = values.std() / np.sqrt(len(values))
    assert abs(values.mean() - expected) <= 5 * se + model * expected, (values.mean(), expected, se)


def test_flat_corner_normals_change_nothing():
    """Corner normals equal to the face normals (a flat-shaded mesh) bake bit for bit as without."""
    plain = sky_scene()
    flat = sky_scene(receiver_tilt=0.0, plane_tilt=0.0)
    assert not flat.has_smooth_normals()
    np.testing.assert_array_equal(trace_receiver(plain, 20_000), trace_receiver(flat, 20_000))


def test_without_tilt_the_receiver_sees_the_lit_plane():
    assert_close(trace_receiver(sky_scene()), RHO * SKY)


@pytest.mark.parametrize("tilt", [30.0, 60.0])
def test_tilted_shading_normal_at_the_texel(tilt):
    """The texel's cosine is the shading normal's, and its directions below Ng are absorbed."""
    scene = sky_scene(receiver_tilt=tilt)
    assert scene.smooth_triangles()[scene.triangle_object == 0].all()
    assert_close(trace_receiver(scene), RHO * SKY * (1 + np.cos(np.radians(tilt))) / 2)


@pytest.mark.parametrize("tilt", [45.0])
def test_tilted_shading_normal_at_a_path_vertex(tilt):
    """At the vertex on the plane the BSDF shades with its shading normal:
    its reflected radiance is ρ L (1 + cos θ)/2, and the flat receiver sees that."""
    scene = sky_scene(plane_tilt=tilt)
    assert_close(trace_receiver(scene), RHO * SKY * (1 + np.cos(np.radians(tilt))) / 2)


def test_next_event_uses_the_shading_cosine_and_the_geometric_side():
    """A small emitter straight above a point: D = L Ω cos(N, up)/π with the shading normal N;
    a light below the geometric surface (but above N) gives nothing."""
    r = 0.05
    light = scenes._quad_part("Light", [(-r, -r, 1), (-r, r, 1), (r, r, 1), (r, -r, 1)], (0, 0, 0), (3.0,) * 3)
    floor = scenes._quad_part("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], (0.5,) * 3)
    scene = scenes.parts_to_scene_arrays([floor, light])
    lights, caster = EmitterSampler(scene), RayCaster(scene)
    n = 20_000
    p = np.zeros((n, 3), np.float32)
    up = np.tile(np.float32([0, 0, 1]), (n, 1))
    t = np.radians(40.0)
    tilted = np.tile(np.float32([0, np.sin(t), np.cos(t)]), (n, 1))
    rng = np.random.default_rng(3)
    flat = lights.direct_light(p, up, rng, caster)[0][:, 0].astype(np.float64)
    shaded = lights.direct_light(p, tilted, rng, caster, geometric=up)[0][:, 0].astype(np.float64)
    ratio = shaded.mean() / flat.mean()
    assert abs(ratio - np.cos(t)) < 0.01, ratio                    # the light is ~a point straight above
    below = lights.direct_light(p, up, rng, caster, geometric=-up)[0]
    assert not below.any()


def test_states_carry_their_shading_normal():
    """States sample the shading normal at their point; their strata keep the geometric frame."""
    scene = sky_scene(receiver_tilt=30.0)
    states = sample_states(dataclasses.replace(scene, object_carries_states=np.array([True, False])), 256)
    on = states.point_object == 0
    assert on.all()
    t = np.radians(30.0)
    np.testing.assert_allclose(states.shading_normals[on], np.tile([0, -np.sin(t), np.cos(t)], (on.sum(), 1)),
                               atol=1e-6)
    np.testing.assert_allclose(states.normals[on], np.tile([0, 0, 1.0], (on.sum(), 1)))
    plane = sample_states(dataclasses.replace(scene, object_carries_states=np.array([False, True])), 64)
    np.testing.assert_allclose(plane.bsdf_normals, plane.normals, atol=1e-6)   # flat part of a smooth scene
    assert sample_states(sky_scene(), 64).shading_normals is None


def test_scene_fingerprint_includes_the_shading_normals():
    """The Cycles reference cache and the solution's same-scene check key on the fingerprint:
    smooth / custom normals change it, corner normals equal to the face normals do not."""
    from lmdp_addon.bake.checks import scene_fingerprint
    plain = scene_fingerprint(sky_scene())
    assert scene_fingerprint(sky_scene(receiver_tilt=0.0, plane_tilt=0.0)) == plain
    tilted = {scene_fingerprint(sky_scene(receiver_tilt=t)) for t in (30.0, 35.0, -35.0)}
    assert len(tilted) == 3 and plain not in tilted
    assert scene_fingerprint(sky_scene(receiver_tilt=30.0)) == scene_fingerprint(sky_scene(receiver_tilt=30.0))
