"""Lamps hit by BSDF-sampled rays (lmdp_addon.lamp_hits) and their MIS with the light samples.

* The light-sample half (``Lamps.next_event(mis=True)``) plus the hit half of cosine rays
  (``lamp_hits.emission_hits``) estimate the same D(y) as light sampling alone, for every lamp
  Cycles lets rays hit (within 5 standard errors of both): the densities of the two halves agree.
* Rays meet the lamps where Cycles' ``lights_intersect`` does (one-sided area lights and spots,
  sphere entry / exit, disks facing the ray, a sun's cone for escaping rays, nothing behind the
  closest surface, nothing for delta lamps or lamps with Multiple Importance off).
* A white mirror shows a lamp only to the rays that hit it: the receiver below gets the form
  factor of the lamp's mirror image (light sampling alone cannot reach it: 0 before).
* On a sharp glossy surface (roughness 0.1) MIS cuts the noise of the reflected lamp.
"""
import numpy as np
import pytest

from bake_scenes import assert_within, trace_at
from lmdp_addon import bsdf, lamp_hits
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.lamps import AREA, POINT, SPOT, SUN, Lamps, _cosine_hemisphere
from lmdp_addon.raycast import RayCaster

from test_lamps import H, floor_scene

K = 5.0

LAMPS = {
    "disk_area": dict(kind=[AREA], position=[[0, 0, H]], extent_u=[[1, 0, 0]], extent_v=[[0, 1, 0]],
                      ellipse=[True], strength=[[10] * 3]),
    "rectangle_close_spread": dict(kind=[AREA], position=[[0, 0, 0.3]], extent_u=[[1.5, 0, 0]],
                                   extent_v=[[0, 0.8, 0]], spread=[1.0], strength=[[10] * 3]),
    "sphere": dict(kind=[POINT], position=[[0, 0, H]], radius=[0.3], sphere=[True], strength=[[50] * 3]),
    "inside_sphere": dict(kind=[POINT], position=[[0, 0, 0.2]], radius=[0.5], sphere=[True], strength=[[50] * 3]),
    "soft_falloff_disk": dict(kind=[POINT], position=[[0, 0, 0.5]], radius=[0.3], strength=[[50] * 3]),
    "spot_sphere": dict(kind=[SPOT], position=[[0, 0, 0.6]], radius=[0.2], sphere=[True], spot_size=[1.2],
                        spot_blend=[0.3], strength=[[50] * 3]),
    "sun_20_degrees": dict(kind=[SUN], axis=[[0.3, 0, -1]], angle=[0.35], strength=[[3] * 3]),
    "six_lamps": dict(kind=[AREA, POINT, POINT, SPOT, SUN, POINT],
                      position=[[0, 0, 0.5], [0.5, 0, 0.4], [-0.5, 0.3, 0.3], [0, 0.5, 0.5], [0, 0, 0], [0.2, 0.2, 0.2]],
                      axis=[[0, 0, -1]] * 4 + [[0.2, 0.1, -1], [0, 0, -1]],
                      extent_u=[[0.6, 0, 0]] + [[0, 0, 0]] * 5, extent_v=[[0, 0.4, 0]] + [[0, 0, 0]] * 5,
                      radius=[0, 0.1, 0.2, 0.1, 0, 0], sphere=[False, True, False, True, False, False],
                      angle=[0, 0, 0, 0, 0.3, 0], strength=[[10] * 3, [20] * 3, [20] * 3, [20] * 3, [2] * 3, [5] * 3]),
}


def lamps_of(case, **extra):
    columns = dict(LAMPS[case], **extra)
    return Lamps(names=[f"L{i}" for i in range(len(columns["kind"]))], **columns)


def halves(lamps, points, n, seed=1):
    """(light sampling alone, light-sample half, hit half) (3, k, n) red channel at floor points."""
    scene = floor_scene(lamps)
    caster = RayCaster(scene)
    rng = np.random.default_rng(seed)
    k = len(points)
    pos = np.repeat(np.asarray(points, np.float32), n, axis=0)
    nrm = np.tile(np.float32([0, 0, 1]), (k * n, 1))
    lift = np.full(k * n, 1e-6, np.float32)
    alone, _ = lamps.next_event(pos, nrm, rng, caster, lift=lift)
    light_half, _ = lamps.next_event(pos, nrm, rng, caster, lift=lift, mis=True)
    origin = pos + lift[:, None] * nrm
    d = _cosine_hemisphere(nrm.astype(np.float64), rng.random((k * n, 2))).astype(np.float32)
    tri, dist = caster.intersect(origin, d)[:2]
    rays, value = lamp_hits.emission_hits(lamps, origin, nrm, d, np.where(tri >= 0, dist, np.inf), tri == -1,
                                          d[:, 2])
    hit_half = np.zeros_like(light_half)
    hit_half[rays] = value          # cosine sampling: β w = 1
    return np.stack([v[:, 0].reshape(k, n) for v in (alone, light_half, hit_half)])


@pytest.mark.parametrize("case", list(LAMPS))
def test_light_sample_and_hit_halves_sum_to_the_lamps_light(case):
    lamps = lamps_of(case)
    assert lamps.hittable[0] or case == "six_lamps"
    alone, light_half, hit_half = halves(lamps, [[0.0, 0.0, 0.0], [0.9, 0.4, 0.0]], n=40000)
    n = alone.shape[1]
    mis = light_half + hit_half
    for i in range(2):
        if alone[i].mean() == 0:
            assert np.all(mis[i] == 0)
            continue
        diff = mis[i].mean() - alone[i].mean()
        sigma = np.sqrt(mis[i].var() / n + alone[i].var() / n)
        assert abs(diff) <= K * sigma + 1e-6 * alone[i].mean(), (i, diff, sigma)
    assert abs(mis[0].mean() - alone[0].mean()) <= 0.02 * alone[0].mean()
    assert hit_half[0].mean() > 0   # the rays do find the lamps


def test_rays_hit_lamps_where_cycles_intersects_them():
    up, down = [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]
    lamps = Lamps(names=["rect", "ellipse", "sphere", "disk", "spot", "sun", "bulb", "no_mis"],
                  kind=[AREA, AREA, POINT, POINT, SPOT, SUN, POINT, POINT],
                  position=[[0, 0, 1], [5, 0, 1], [10, 0, 1], [15, 0, 1], [20, 0, 1], [0, 0, 0], [25, 0, 1],
                            [30, 0, 1]],
                  axis=[down, down, down, down, down, [0, 0, -1], down, down],
                  extent_u=[[1, 0, 0], [1, 0, 0]] + [[0, 0, 0]] * 6, extent_v=[[0, 1, 0], [0, 1, 0]] + [[0, 0, 0]] * 6,
                  ellipse=[False, True] + [False] * 6, radius=[0, 0, 0.3, 0.3, 0.3, 0, 0, 0.3],
                  sphere=[False, False, True, False, True, False, False, True], angle=[0, 0, 0, 0, 0, 0.2, 0, 0],
                  strength=[[1] * 3] * 8, mis=[True] * 7 + [False])
    assert list(lamps.hittable) == [True] * 6 + [False, False]   # a delta lamp, MIS off
    o = np.array([
        [0, 0, 0], [0.45, 0.45, 0], [0, 0, 2],                  # rect: front, corner, from behind
        [5.45, 0.45, 0], [5, 0, 0],                               # ellipse: outside its corner, centre
        [10, 0, 0], [10, 0, 1], [10, 0, 2],                       # sphere: entry, exit from inside, away
        [15, 0, 0],                                               # disk facing the origin
        [20, 0, 0], [20, 0, 1.1],                                 # spot: towards the centre, away
        [25, 0, 0], [30, 0, 0],                                   # delta bulb, MIS off
    ], float)
    d = np.array([up, up, down] + [up] * 2 + [up, up, up] + [up] + [up, up] + [up, up])
    ray, lamp, t = lamp_hits.intersect(lamps, o, d, np.full(len(o), np.inf), np.zeros(len(o), bool))
    expected = {0: (0, 1.0), 1: (0, 1.0), 4: (1, 1.0), 5: (2, 0.7), 6: (2, 0.3), 8: (3, 1.0), 9: (4, 0.7)}
    assert list(ray) == sorted(expected)
    for i, row in enumerate(ray):
        assert lamp[i] == expected[row][0], row
        np.testing.assert_allclose(t[i], expected[row][1], rtol=1e-9)
    # a surface before the lamp hides it; the sun only for rays that escape, inside its cone
    ray, _, _ = lamp_hits.intersect(lamps, o[:1], d[:1], np.array([0.5]), np.zeros(1, bool))
    assert len(ray) == 0
    tilt = np.array([[np.sin(0.09), 0, np.cos(0.09)], [np.sin(0.11), 0, np.cos(0.11)]] * 2)
    ray, lamp, t = lamp_hits.intersect(lamps, np.array([[40.0, 0, 0]] * 4), tilt, np.full(4, np.inf),
                                       np.array([True, True, False, False]))
    assert list(ray) == [0] and list(lamp) == [5] and np.isinf(t[0])


def mirror_scene(lamps, roughness=0.0):
    """A white Glossy 1 m square facing down 1 m above a 4 cm receiver, black world, ``lamps``."""
    e, r = 0.5, 0.02
    parts = [scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.7, 0.7, 0.7)),
             scenes._quad_part("Patch", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], (0.5, 0.5, 0.5))]
    scene = scenes.parts_to_scene_arrays(parts, world=(0.0, 0.0, 0.0))
    patch = scene.triangle_object == scene.object_names.index("Patch")
    scene.materials = bsdf.MaterialTable.from_lobes([[dict(kind=bsdf.GLOSSY, weight=1.0, roughness=roughness)]])
    scene.triangle_material = np.where(patch, 0, -1).astype(np.int32)
    scene.triangle_albedo[patch] = 0.0
    scene.lamps = lamps
    return scene


def sphere_lamp(mis=True):
    return Lamps(names=["Ball"], kind=[POINT], position=[[0.25, 0, 0.2]], radius=[0.1], sphere=[True],
                 strength=[[10.0] * 3], mis=[mis])


def disk_lamp(mis=True):
    return Lamps(names=["Panel"], kind=[AREA], position=[[0.0, 0, 0.05]], axis=[[0, 0, 1]], extent_u=[[0.3, 0, 0]],
                 extent_v=[[0, 0.3, 0]], ellipse=[True], strength=[[10.0] * 3], mis=[mis])


@pytest.mark.parametrize("lamp", ["sphere", "disk"])
def test_a_mirror_shows_a_lamp_only_through_the_rays_that_hit_it(lamp):
    """The receiver sees the lamp's mirror image (about z = 1) through the white mirror: E/π =
    L (r/d)² cos θ for the sphere's image, L ρ²/(ρ² + h²) for the disk's (coaxial, facing down)."""
    lamps = sphere_lamp() if lamp == "sphere" else disk_lamp()
    L = lamps.emission[0, 0]
    if lamp == "sphere":
        c = np.array([0.25, 0.0, 1.8])
        d = np.linalg.norm(c)
        expected = L * (0.1 / d) ** 2 * c[2] / d
    else:
        expected = L * 0.15 ** 2 / (0.15 ** 2 + 1.95 ** 2)
    values, stats = trace_at(IndirectTracer(mirror_scene(lamps), "UNGUIDED", max_bounces=4), (0, 0, 0), (0, 0, 1),
                             100_000)
    assert stats.glossy_vertices > 0
    assert_within(values[:, 0], expected, extra=0.01 * expected)
    # light sampling alone (Multiple Importance off) cannot reach the lamp through a mirror; what
    # is left is the light of the lit receiver seen in the mirror
    off = sphere_lamp(False) if lamp == "sphere" else disk_lamp(False)
    values, _ = trace_at(IndirectTracer(mirror_scene(off), "UNGUIDED", max_bounces=4), (0, 0, 0), (0, 0, 1), 20_000)
    assert values[:, 0].mean() < 0.01 * expected   # measured 0.3 %


@pytest.mark.parametrize("lamp", ["sphere", "disk"])
def test_mis_lowers_the_noise_of_a_sharp_glossy_reflection(lamp):
    """Roughness 0.1: the same paths with the lamp's Multiple Importance on and off agree, and
    on has less than half the standard error (measured 0.22-0.30 x)."""
    make = sphere_lamp if lamp == "sphere" else disk_lamp
    out = []
    for mis in (True, False):
        values, _ = trace_at(IndirectTracer(mirror_scene(make(mis), 0.1), "UNGUIDED", max_bounces=4), (0, 0, 0),
                             (0, 0, 1), 100_000, seed=2)
        v = values[:, 0].astype(np.float64)
        out.append((v.mean(), v.std() / np.sqrt(len(v))))
    (m_on, se_on), (m_off, se_off) = out
    print(f"{lamp}: MIS {m_on:.5f} ± {se_on:.5f}, light sampling alone {m_off:.5f} ± {se_off:.5f}")
    assert abs(m_on - m_off) <= K * np.hypot(se_on, se_off)
    assert se_on < 0.5 * se_off


@pytest.mark.parametrize("lamp", ["disk_area", "sphere", "sun_20_degrees"])
def test_direct_light_at_the_texel_combines_its_first_ray_and_its_light_sample(lamp):
    """DIRECT + INDIRECT on the bare floor (nothing bounces): the texel's light sample and the
    lamp its first ray meets add up to the closed form (disk: L ρ²/(ρ² + h²); sphere: L r²/h²;
    sun: S / π)."""
    from lmdp_addon.bake.content import BakeContent
    lamps = lamps_of(lamp)
    L = lamps.emission[0, 0]
    expected = {"disk_area": L * 0.25 / (0.25 + H * H), "sphere": L * 0.09 / (H * H), "sun_20_degrees": 3.0 / np.pi}
    tracer = IndirectTracer(floor_scene(lamps), "UNGUIDED", max_bounces=2, content=BakeContent(direct=True))
    assert tracer.lamp_hits
    if lamp == "sun_20_degrees":   # the sun's axis is tilted: cos of the angle to its centre
        axis = lamps.axis[0]
        expected[lamp] *= -axis[2]
    values, _ = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 40_000)
    assert_within(values[:, 0], expected[lamp], extra=2e-3 * expected[lamp])


def test_guided_paths_with_a_hittable_lamp_agree_with_unguided():
    """GUIDED draws from the mixture of the guide and the cosine (or the BSDF) and weights lamp
    hits with the cosine / BSDF half: unbiased, as UNGUIDED, in a room lit by an area light and a
    sphere lamp over a Glossy 0.2 floor."""
    from lmdp_addon.bake import driver as baking
    from lmdp_addon.model import pipeline
    from test_lamps import small
    parts = [p for p in scenes.scene_parts("CORNELL_BOX") if p.name != "Light"]
    scene = scenes.parts_to_scene_arrays(parts)
    floor = scene.triangle_object == scene.object_names.index("Floor")
    scene.materials = bsdf.MaterialTable.from_lobes([[dict(kind=bsdf.GLOSSY, weight=1.0, roughness=0.2)]])
    scene.triangle_material = np.where(floor, 0, -1).astype(np.int32)
    scene.lamps = Lamps(names=["Panel", "Ball"], kind=[AREA, POINT], position=[[0, 0, 0.9], [-0.2, 0.2, 0.6]],
                        extent_u=[[0.3, 0, 0], [0, 0, 0]], extent_v=[[0, 0.3, 0], [0, 0, 0]], ellipse=[True, False],
                        radius=[0.0, 0.08], sphere=[False, True], strength=[[10.0] * 3, [8.0, 6.0, 4.0]])
    s = small(bake_resolution=12, bake_samples=256, max_bounces=4, point_count=1500)
    a = baking.bake(scene, ["Ceiling"], s).objects[0]
    g = baking.bake(scene, ["Ceiling"], s.__class__(**{**s.__dict__, "bake_mode": "GUIDED"}),
                    lmdp=pipeline.run_all(scene, s)).objects[0]
    (mean_a, se_a), (mean_g, se_g) = a.mean_and_error(), g.mean_and_error()   # path reuse: batch errors
    se = np.hypot(se_a, se_g)
    assert np.all(mean_a > 0.05)
    assert np.all(np.abs(mean_g - mean_a) <= K * se), (mean_a, mean_g, se)


def test_many_rays_and_lamps_are_intersected_in_chunks_with_the_same_result(monkeypatch):
    rng = np.random.default_rng(0)
    n = 30
    lamps = Lamps(names=[f"l{i}" for i in range(n)], kind=[POINT] * 20 + [AREA] * 10, position=rng.uniform(-1, 1, (n, 3)),
                  radius=[0.2] * 20 + [0] * 10, sphere=[i % 2 == 0 for i in range(n)],
                  extent_u=[[0, 0, 0]] * 20 + [[0.5, 0, 0]] * 10, extent_v=[[0, 0, 0]] * 20 + [[0, 0.5, 0]] * 10,
                  axis=rng.normal(size=(n, 3)), strength=[[1.0] * 3] * n)
    k = 20000
    o = rng.uniform(-1, 1, (k, 3))
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tmax = rng.uniform(0, 3, k)
    whole = lamp_hits.intersect(lamps, o, d, tmax, np.zeros(k, bool))
    monkeypatch.setattr(lamp_hits, "PAIRS_PER_CHUNK", 1000 * n)   # 20 chunks of 1000 rays
    chunked = lamp_hits.intersect(lamps, o, d, tmax, np.zeros(k, bool))
    assert len(whole[0]) > 1000
    for a, b in zip(whole, chunked):
        np.testing.assert_array_equal(a, b)
