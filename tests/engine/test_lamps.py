"""Lamps (lmdp_addon.lamps): point, spot, sun and area lights against closed forms, their
terminals in the LMDP build, and what a scene lit only by lamps does in the bake.

Monte Carlo estimates must lie within 5 standard errors (of the samples themselves) of the
closed form; delta lamps are exact to float32 rounding.
"""
import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver as baking
from lmdp_addon.errors import SceneError
from lmdp_addon.lamps import AREA, POINT, SPOT, SUN, Lamps
from lmdp_addon.model import pipeline
from lmdp_addon.raycast import RayCaster
from lmdp_addon.settings import Settings

from bake_scenes import assert_within, small

H = 0.8   # lamp height above the floor (m)


def floor_scene(lamps=None, blocker=False):
    """A 4 x 4 m floor (albedo 0.5), optionally a 0.2 m square blocker 0.4 m up at the origin."""
    parts = [scenes._quad_part("Floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)], (0.5, 0.5, 0.5))]
    if blocker:
        parts.append(scenes._quad_part("Blocker", [(-0.1, -0.1, 0.4), (-0.1, 0.1, 0.4), (0.1, 0.1, 0.4),
                                                   (0.1, -0.1, 0.4)], (0.5, 0.5, 0.5)))
    scene = scenes.parts_to_scene_arrays(parts, selected=["Floor"])
    scene.lamps = lamps if lamps is not None else Lamps()
    return scene


def estimates(scene, points, n=4000, seed=0):
    """(n, k, 3) single-sample estimates of the lamps' D at floor points ``points (k, 3)``."""
    caster = RayCaster(scene)
    rng = np.random.default_rng(seed)
    k = len(points)
    pos = np.repeat(np.asarray(points, np.float32), n, axis=0)
    nrm = np.tile(np.float32([0, 0, 1]), (k * n, 1))
    values, _ = scene.lamps.next_event(pos, nrm, rng, caster, lift=np.full(k * n, 1e-7))
    return values.reshape(k, n, 3).transpose(1, 0, 2)


def test_delta_point_lamp_is_its_intensity_over_distance_squared():
    P = 30.0
    lamps = Lamps(names=["Bulb"], kind=[POINT], position=[[0, 0, H]], strength=[[P, P / 2, P / 4]])
    np.testing.assert_allclose(lamps.emission[0], np.array([P, P / 2, P / 4]) / (4 * np.pi))  # W/sr
    x = np.array([[0.0, 0, 0], [0.5, 0.3, 0], [1.5, -1.0, 0]])
    d2 = (x[:, :2] ** 2).sum(1) + H * H
    expected = lamps.emission[0] * (H / np.sqrt(d2) / d2 / np.pi)[:, None]
    np.testing.assert_allclose(estimates(floor_scene(lamps), x, n=2)[0], expected, rtol=1e-5)
    # the blocker shadows the point below it, unless the lamp casts no shadow
    shadowed = estimates(floor_scene(lamps, blocker=True), x[:1], n=2)[0]
    assert np.all(shadowed == 0)
    free = Lamps(names=["Bulb"], kind=[POINT], position=[[0, 0, H]], strength=[[P, P / 2, P / 4]],
                 cast_shadow=[False])
    np.testing.assert_allclose(estimates(floor_scene(free, blocker=True), x[:1], n=2)[0], expected[:1], rtol=1e-5)


@pytest.mark.parametrize("sphere", [True, False], ids=["sphere", "soft_falloff_disk"])
def test_point_lamp_with_a_radius(sphere):
    """Straight below a lamp of radiance L and radius r: a sphere gives E/π = L r²/h², the
    soft-falloff disk facing the receiver E/π = L r²/(h² + r²)."""
    r = 0.3
    lamps = Lamps(names=["Ball"], kind=[POINT], position=[[0, 0, H]], radius=[r], sphere=[sphere],
                  strength=[[50.0, 50.0, 50.0]])
    L = 50.0 / (np.pi * 4 * np.pi * r * r)
    np.testing.assert_allclose(lamps.emission[0], L)
    expected = L * r * r / (H * H if sphere else H * H + r * r)
    assert_within(estimates(floor_scene(lamps), [[0.0, 0.0, 0.0]])[:, 0, 0], expected)


def test_spot_cone_mask_is_cycles_smoothstep():
    size, blend = np.radians(60), 0.5
    lamps = Lamps(names=["Spot"], kind=[SPOT], position=[[0, 0, H]], axis=[[0, 0, -1]], spot_size=[size],
                  spot_blend=[blend], strength=[[10.0, 10.0, 10.0]])
    cos_half = np.cos(size / 2)
    angles = np.radians([0.0, 15.0, 26.0, 29.0, 35.0])
    x = np.column_stack([H * np.tan(angles), np.zeros(5), np.zeros(5)])
    t = np.clip((np.cos(angles) - cos_half) / ((1 - cos_half) * blend), 0, 1)
    mask = t * t * (3 - 2 * t)
    d2 = H * H / np.cos(angles) ** 2
    expected = 10.0 / (4 * np.pi) * np.cos(angles) / d2 / np.pi * mask
    np.testing.assert_allclose(estimates(floor_scene(lamps), x, n=2)[0, :, 0], expected, rtol=1e-5, atol=1e-9)
    assert mask[1] == 1 > mask[2] > mask[3] > 0 == mask[4]


@pytest.mark.parametrize("angle", [0.0, 10.0])
def test_sun_gives_its_strength_times_cosine(angle):
    """E/π = S cos θ / π for a parallel sun; a sun of angular diameter 2θ has radiance
    S / (π sin² θ) over its cone, so at normal incidence E/π = S / π still."""
    S = 2.0
    tilt = np.radians(30.0)
    axis = [[0.0, np.sin(tilt), -np.cos(tilt)]] if angle == 0 else [[0.0, 0.0, -1.0]]
    lamps = Lamps(names=["Sun"], kind=[SUN], axis=axis, angle=[np.radians(angle)], strength=[[S, S, S]])
    values = estimates(floor_scene(lamps), [[0.3, 0.2, 0.0]], n=4000 if angle else 2)[:, 0, 0]
    if angle == 0:
        np.testing.assert_allclose(values, S * np.cos(tilt) / np.pi, rtol=1e-6)
    else:
        half = np.radians(angle) / 2
        np.testing.assert_allclose(lamps.emission[0], S / (np.pi * np.sin(half) ** 2))
        # ∫_cone cos θ dω = π sin² θ_h exactly: the radiance times it is S
        assert_within(values, S / np.pi)


@pytest.mark.parametrize("shape", ["rectangle", "rectangle_near", "ellipse", "spread"])
def test_area_lamp_gives_its_form_factor(shape):
    """Rectangles seen from closer than their diagonal are sampled in solid angle
    ("rectangle_near", 0.15 m below), the others on their area."""
    a, b = 0.6, 0.4
    h = 0.15 if shape == "rectangle_near" else H
    ellipse = shape == "ellipse"
    spread = np.radians(90.0) if shape == "spread" else np.pi
    lamps = Lamps(names=["Panel"], kind=[AREA], position=[[0, 0, h]], axis=[[0, 0, -1]],
                  extent_u=[[a, 0, 0]], extent_v=[[0, b, 0]], ellipse=[ellipse], spread=[spread],
                  strength=[[20.0, 20.0, 20.0]])
    area = a * b * (np.pi / 4 if ellipse else 1.0)
    L = 20.0 / (np.pi * area)
    np.testing.assert_allclose(lamps.emission[0], L)
    values = estimates(floor_scene(lamps), [[0.0, 0.0, 0.0], [0.3, 0.1, 0.0]], n=20000)
    if shape.startswith("rectangle"):
        F = scenes.point_to_parallel_square_form_factor(a, h, np.array([[0.0, 0.0], [-0.3, -0.1]]), side_y=b)
    else:   # quadrature over the shape: (1/π) ∫ cos θ_x cos θ_l / d² x attenuation dA
        u, v = np.meshgrid((np.arange(400) + 0.5) / 400 - 0.5, (np.arange(400) + 0.5) / 400 - 0.5)
        inside = (u * u + v * v <= 0.25) if ellipse else np.ones_like(u, bool)
        F = []
        for x0, y0 in [(0.0, 0.0), (0.3, 0.1)]:
            dx, dy = a * u - x0, b * v - y0
            d2 = dx * dx + dy * dy + H * H
            cos = H / np.sqrt(d2)
            tan = np.sqrt(dx * dx + dy * dy) / H
            half = spread / 2
            att = np.maximum((np.tan(half) - tan) / (np.tan(half) - half), 0) if spread < np.pi else 1.0
            F.append(np.sum(inside * cos * cos / d2 * att) * a * b / 400 ** 2 / np.pi)
        F = np.array(F)
    for i in range(2):
        assert_within(values[:, i, 0], L * F[i], extra=1e-4 * L * F[i])
    # one-sided: nothing above the panel
    above = estimates(floor_scene(Lamps(names=["Panel"], kind=[AREA], position=[[0, 0, -0.5]], axis=[[0, 0, -1]],
                                        extent_u=[[a, 0, 0]], extent_v=[[0, b, 0]], strength=[[20.0] * 3])),
                      [[0.0, 0.0, 0.0]], n=100)
    assert np.all(above == 0)


def test_many_lamps_one_sample_each_vertex_is_unbiased():
    """Beyond ALL_LAMPS lamps a vertex samples one lamp (by the mixture of ``Lamps.choose``):
    the mean still is the sum of the lamps' exact direct light, with one shadow ray per vertex."""
    from lmdp_addon.lamps import ALL_LAMPS
    n = ALL_LAMPS + 3
    rng = np.random.default_rng(7)
    pos = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0.3, 1.2, n)])
    power = rng.uniform(1, 20, (n, 1)) * [1.0, 0.8, 0.6]
    kinds = [POINT] * (n - 2) + [SPOT, SUN]
    lamps = Lamps(names=[f"L{i}" for i in range(n)], kind=kinds, position=pos, strength=power,
                  axis=[[0, 0, -1]] * (n - 1) + [[0.3, 0.0, -1.0]], spot_size=[np.pi] * (n - 2) + [1.2, np.pi],
                  spot_blend=[0.0] * (n - 2) + [0.5, 0.0])
    x = np.array([[0.2, -0.3, 0.0], [-0.8, 0.5, 0.0]])
    scene = floor_scene(lamps)
    exact = sum(estimates(floor_scene(Lamps(names=["one"], kind=[kinds[i]], position=[pos[i]], strength=[power[i]],
                                            axis=[lamps.axis[i]], spot_size=[lamps.spot_size[i]],
                                            spot_blend=[lamps.spot_blend[i]])), x, n=1)[0]
                for i in range(n))
    caster = RayCaster(scene)
    _, rays = lamps.next_event(np.float32(x), np.float32([[0, 0, 1]] * 2), np.random.default_rng(0), caster,
                               lift=np.full(2, 1e-7))
    assert rays <= 2
    values = estimates(scene, x, n=20000)
    for i in range(2):
        assert_within(values[:, i], exact[i])


def test_no_lamps_draw_no_random_numbers():
    scene = floor_scene()
    rng = np.random.default_rng(3)
    state = rng.bit_generator.state
    values, rays = scene.lamps.next_event(np.zeros((5, 3), np.float32), np.tile(np.float32([0, 0, 1]), (5, 1)),
                                          rng, RayCaster(scene))
    assert rays == 0 and not values.any() and rng.bit_generator.state == state


def test_a_scene_lit_only_by_lamps_has_light():
    dark = floor_scene()
    with pytest.raises(SceneError, match="no light"):
        dark.check_for_lmdp()
    lit = floor_scene(Lamps(names=["Bulb"], kind=[POINT], position=[[0, 0, H]], strength=[[10.0] * 3]))
    assert lit.has_light()
    lit.check_for_lmdp()
    assert lit.total_emitted_power_density() > 0   # the thesis's λ counts the lamps


def lamp_room():
    """The Cornell box without its light, lit by a delta point lamp and a sphere lamp."""
    parts = [p for p in scenes.scene_parts("CORNELL_BOX") if p.name != "Light"]
    scene = scenes.parts_to_scene_arrays(parts)
    scene.lamps = Lamps(names=["Bulb", "Ball"], kind=[POINT, POINT], position=[[0.1, -0.1, 0.85], [-0.2, 0.2, 0.7]],
                        radius=[0.0, 0.08], sphere=[False, True], strength=[[15.0, 12.0, 9.0], [8.0, 8.0, 8.0]])
    return scene


def test_lamp_terminals_carry_the_lamps_direct_light():
    """PHYSICAL mode: the build's transition mass into a lamp's terminal times its z_T is the
    lamp's direct light / π at the state point (exactly for the delta lamp)."""
    scene = lamp_room()
    result = pipeline.run_all(scene, Settings(point_count=400, cost_mode="PHYSICAL"))
    dyn, states, lmdp = result.dynamics, result.states, result.lmdp
    m, E = dyn.n_points, dyn.n_emitters
    assert dyn.n_lamps == 2 and dyn.terminal_labels()[-2:] == ["lamp:Bulb", "lamp:Ball"]
    np.testing.assert_allclose(lmdp.z_terminal[-2:], scene.lamps.emission)
    drive = np.asarray(dyn.P[:, m + E + 2:].todense()) @ scene.lamps.emission   # (m, 3)
    caster = dyn.caster
    live = dyn.locator.targets
    lift = caster.offset(states.point_triangle)
    pos = states.points.astype(np.float32)
    nrm = states.normals.astype(np.float32)
    bulb = Lamps(names=["Bulb"], kind=[POINT], position=[scene.lamps.position[0]], strength=[scene.lamps.strength[0]])
    exact = bulb.next_event(pos, nrm, np.random.default_rng(0), caster, lift=lift)[0]
    mass_bulb = np.asarray(dyn.P[:, m + E + 2].todense()).ravel()
    np.testing.assert_allclose((mass_bulb[:, None] * scene.lamps.emission[0])[live], exact[live],
                               rtol=2e-4, atol=1e-6)
    # the sphere lamp: the build's K samples per point against many more, summed over the room
    ball = Lamps(names=["Ball"], kind=[POINT], position=[scene.lamps.position[1]], radius=[0.08], sphere=[True],
                 strength=[scene.lamps.strength[1]])
    rng = np.random.default_rng(1)
    many = np.mean([ball.next_event(pos, nrm, rng, caster, lift=lift)[0] for _ in range(64)], axis=0)
    built = drive - mass_bulb[:, None] * scene.lamps.emission[0]
    assert abs(built[live].sum() / many[live].sum() - 1) < 0.01


def test_lamp_room_bakes_agree_across_modes():
    """UNGUIDED (path tracing with lamp NEE) and FINAL_GATHER (the solution's ẑ, whose source
    holds the lamps' light one bounce on, plus the lamps' direct light at the gather point)
    agree on the floor of a room lit only by lamps."""
    scene = lamp_room()
    s = small(bake_resolution=12, bake_samples=256, max_bounces=4, point_count=1500)
    a = baking.bake(scene, ["Floor"], s).objects[0]
    result = pipeline.run_all(scene, s)
    g = baking.bake(scene, ["Floor"], s.__class__(**{**s.__dict__, "bake_mode": "FINAL_GATHER"}),
                    lmdp=result).objects[0]
    (mean_a, se_a), (mean_g, se_g) = a.mean_and_error(), g.mean_and_error()   # path reuse: batch errors
    se = np.hypot(se_a, se_g)
    assert np.all(mean_a > 0.05)
    # FINAL_GATHER's discretisation bias (a few %, see design.md) on top of the noise
    assert np.all(np.abs(mean_g - mean_a) <= 5 * se + 0.04 * mean_a), (mean_a, mean_g, se)
