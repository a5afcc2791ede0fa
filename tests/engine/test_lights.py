"""Light sampling (lmdp_addon.lights): the one emitter table of the build and the bake, and the
bake's next-event estimates against analytic form factors."""
import numpy as np
import pytest

from bake_scenes import assert_within
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.lights import EmitterSampler
from lmdp_addon.raycast import RayCaster
from lmdp_addon.sampling import cosine_directions, spherical_triangle_sample


def square_emitter(height):
    p = scenes.PARALLEL_SQUARES
    parts = [scenes._quad_part("Emitter", [(-.5, -.5, height), (-.5, .5, height), (.5, .5, height), (.5, -.5, height)],
                               emission=p["radiance"])]
    return scenes.parts_to_scene_arrays(parts), p["radiance"][0]


@pytest.mark.parametrize("height", [0.02, 0.3, 1.0, 3.0])
def test_light_sampling_gives_the_form_factor_near_and_far(height):
    """D_e = (1/π) ∫ L cos θ dω below a square emitter (both MIS halves: light samples with
    solid-angle sampling close to the light, area sampling far from it, and cosine rays that hit
    it) equals L F, F the analytic point-to-square form factor; light sampling alone
    (``direct_light``) too."""
    scene, radiance = square_emitter(height)
    lights, caster = EmitterSampler(scene), RayCaster(scene)
    face_normals = scene.triangle_geometry()[0].astype(np.float32)
    n = 200_000
    rng = np.random.default_rng(7)
    pts = np.tile(np.array([0.2, 0.1, 0.0], np.float32), (n, 1))
    nrm = np.tile(np.array([0, 0, 1], np.float32), (n, 1))
    light, shadow_rays = lights.next_event(pts, nrm, rng, caster)
    assert 0 < shadow_rays <= n
    d = cosine_directions(nrm, rng.random((n, 2)), stratified=False)
    origin = pts + np.float32(caster.offset()) * nrm
    tri, dist = caster.intersect(origin, d)
    hit = tri >= 0
    rays = np.zeros(n)
    cos = np.einsum("ij,ij->i", nrm, d)
    lit, value = lights.emission_hits(origin, d, tri, dist, cos, np.flatnonzero(hit), face_normals)
    rays[lit] = value[:, 0]
    near = lights.near(origin[:1].astype(np.float64), np.array([0]))[0]
    assert near == (height < np.sqrt(2.0))
    F = scenes.point_to_parallel_square_form_factor(1.0, height, (-0.2, -0.1))
    assert_within(light[:, 0].astype(np.float64) + rays, radiance * F)
    alone, _ = lights.direct_light(pts, nrm, rng, caster)
    assert_within(alone[:, 0].astype(np.float64), radiance * F)
    # Every solid-angle sample points into its triangle.
    c = scene.corners()[:1] - origin[:1].astype(np.float64)[:, None, :]
    dirs, omega = spherical_triangle_sample(np.repeat(c, 1000, axis=0), rng.random(1000), rng.random(1000))
    assert np.all(omega > 0)
    e1, e2 = c[0, 1] - c[0, 0], c[0, 2] - c[0, 0]
    M = np.stack([np.broadcast_to(e1, dirs.shape), np.broadcast_to(e2, dirs.shape), -dirs], axis=2)
    bary = np.linalg.solve(M, np.broadcast_to(-c[0, 0], dirs.shape)[..., None])[..., 0]
    assert np.all(bary[:, 0] >= -1e-7) and np.all(bary[:, 1] >= -1e-7) and np.all(bary[:, :2].sum(1) <= 1 + 1e-7)


def test_one_table_serves_the_build_by_area_and_the_bake_by_power():
    """Two lamps of equal area, one three times as bright: the build draws their points by
    area (half each), the bake's next-event estimation by area x radiance (1/4 and 3/4); both
    over the same emitter triangles, the scene's emissive ones."""
    parts = [scenes._quad_part("Dim", [(0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 0, 1)], emission=(1.0,) * 3),
             scenes._quad_part("Bright", [(2, 0, 1), (2, 1, 1), (3, 1, 1), (3, 0, 1)], emission=(3.0,) * 3),
             scenes._quad_part("Floor", [(0, 0, 0), (3, 0, 0), (3, 1, 0), (0, 1, 0)], (0.5,) * 3)]
    scene = scenes.parts_to_scene_arrays(parts)
    lights = EmitterSampler(scene)
    np.testing.assert_array_equal(lights.triangles, np.flatnonzero(scene.is_emissive()))
    np.testing.assert_array_equal(lights.triangle_emitter[lights.triangles], np.arange(4))
    bright = scene.triangle_object[lights.triangles] == scene.object_names.index("Bright")
    np.testing.assert_allclose(lights.power_prob[bright].sum(), 0.75)
    np.testing.assert_allclose(lights.pdf_area32 * lights.areas, lights.power_prob, rtol=1e-6)
    assert lights.triangle_pdf_area[scene.triangle_object == scene.object_names.index("Floor")].max() == 0
    rng = np.random.default_rng(0)
    sample = lights.stratified(1000, 8, rng)
    assert abs(bright[sample.triangle_index].mean() - 0.5) < 1e-9   # stratified by area: exactly half
