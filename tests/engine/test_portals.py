"""World portals (lmdp_addon/bake/portals.py): the environment map's light samples drawn by block
probabilities a probe learned. The sampler's density must be the one it samples with, the learned
tables must keep every direction the map can draw, and the bake must stay unbiased (against the
analytic patch under a map, and against the map's own sampling in a box open on one side) while its
variance falls where the world is seen through an opening."""
from dataclasses import replace

import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import auto, driver, portals
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.world import EnvironmentMap

from bake_scenes import SKY, assert_within, expected_patch_indirect, patch_under_sky, small, trace_at
from test_world import ground_east_map, random_map, sphere_grid, with_environment


def probe_of(scene, rows, values, directions, triangles):
    """A :class:`portals.PortalProbe` of ``scene`` that recorded ``values`` at ``directions``."""
    probe = portals.PortalProbe(scene)
    probe.recorder(np.asarray(triangles), np.ones(len(rows), np.float32))(
        np.asarray(rows), np.asarray(directions, np.float32), np.asarray(values, np.float32))
    return probe


# ---- the sampler -------------------------------------------------------------------------------

@pytest.mark.parametrize("region", [0, 1, 2])
def test_sampler_density_is_the_one_it_samples_with(region):
    """Per region: the returned pdf equals pdf() at the drawn direction, the pixels are drawn
    with probability table[r, b] x P(pixel) / P(b), and the density integrates to one."""
    H, W = 32, 64                  # blocks of 2 x 2 pixels
    env = EnvironmentMap(random_map(H, W, seed=1), interpolation="CLOSEST")
    nb = int(np.prod(portals.block_shape(H, W)))
    rng = np.random.default_rng(region)
    table = rng.random((3, nb)) ** 4 + 1e-3
    table /= table.sum(axis=1, keepdims=True)
    sampler = portals.PortalSampler(env, table)
    n = 400_000
    regions = np.full(n, region)
    d, p, L = sampler.sample(rng.random((n, 3)), regions)
    np.testing.assert_allclose(sampler.pdf(d, regions), p, rtol=1e-4)
    np.testing.assert_allclose(L, env.radiance_at(d), rtol=1e-6)
    u, v = env.map_uv(d)
    pixel = env.pixel_of_uv(u, v)
    blocks = portals.pixel_blocks(H, W)
    mass = np.bincount(blocks, weights=env.pixel_prob, minlength=nb)
    seen = mass[blocks] > 0
    expected = np.zeros(H * W)
    expected[seen] = sampler.table[region, blocks[seen]] * env.pixel_prob[seen] / mass[blocks[seen]]
    counts = np.bincount(pixel, minlength=H * W) / n
    assert np.all(np.abs(counts - expected) <= 5 * np.sqrt(expected * (1 - expected) / n) + 1e-6)
    assert counts[~(env.pixel_prob > 0)].sum() == 0
    dirs, weights = sphere_grid(400)
    integral = np.sum(sampler.pdf(dirs, np.full(len(dirs), region)).astype(np.float64) * weights)
    assert abs(integral - 1.0) < 0.02


def test_learned_tables_keep_the_maps_share_of_every_block():
    """Everything the probe saw came through one block: the tables give it most of the
    probability, and every other block the map can draw keeps δ times its own (eq. 1)."""
    scene = with_environment(patch_under_sky(), random_map(16, 32, seed=2))
    env = scene.environment
    d = np.array([[1.0, 0.0, -0.2]]) / np.linalg.norm([1.0, 0.0, -0.2])
    blocks = portals.pixel_blocks(16, 32)
    nb = int(np.prod(portals.block_shape(16, 32)))
    u, v = env.map_uv(d)
    b = blocks[env.pixel_of_uv(u, v)][0]
    n = 600
    directions = np.repeat(d, n, axis=0)
    learned = portals.learn(probe_of(scene, np.arange(n), np.ones(n), directions, np.zeros(n, int)))
    mass = np.bincount(blocks, weights=env.pixel_prob, minlength=nb)
    for row in learned.table:
        assert row[b] > 0.8
        np.testing.assert_allclose(row.sum(), 1.0)
        assert np.all(row >= portals.DEFENSIVE * mass - 1e-12)
    assert len(learned.table) == 2                        # the group of triangle 0 had enough samples
    assert learned.regions(scene)[0] == 1 and learned.info["probe_visible"] == 1.0


def test_a_probe_that_saw_too_little_learns_nothing():
    """Fewer than MIN_VISIBLE samples that saw the world: no portals (their tables would be noise)."""
    scene = with_environment(patch_under_sky(), random_map(16, 32, seed=2))
    n = portals.MIN_VISIBLE - 1
    d = np.tile([[1.0, 0.0, 0.0]], (n, 1))
    assert portals.learn(probe_of(scene, np.arange(n), np.ones(n), d, np.zeros(n, int))) is None
    n += 1
    assert portals.learn(probe_of(scene, np.arange(n), np.ones(n), np.tile([[1.0, 0.0, 0.0]], (n, 1)),
                                  np.zeros(n, int))) is not None


def test_a_probe_that_saw_nothing_learns_nothing():
    scene = with_environment(patch_under_sky(), random_map(16, 32, seed=2))
    probe = probe_of(scene, np.arange(10), np.zeros(10), np.tile([[0.0, 0.0, 1.0]], (10, 1)), np.zeros(10, int))
    assert portals.learn(probe) is None


# ---- unbiased -----------------------------------------------------------------------------------

DIM = 0.01


def dim_sky_east_ground_map(H=32, W=64):
    """:func:`test_world.ground_east_map` with a dim sky (DIM x SKY) above the horizon."""
    img = ground_east_map(H, W)
    img[H // 2:] = DIM * SKY
    return img


@pytest.mark.parametrize("misled", [False, True])
def test_patch_under_a_map_is_unbiased_with_portals(misled):
    """The patch under a map bright below the horizon towards +x, dim above it: the patch's
    underside sees only the ground, so the receiver's indirect light is ρ L F / 2, with the
    portals a probe learned and with portals that send all of eq. 1's mass to the dim sky the
    patch never faces (only the defensive share δ then finds its light)."""
    scene = with_environment(patch_under_sky(), dim_sky_east_ground_map())
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    probe = portals.PortalProbe(scene)
    tracer.world_probe = probe
    trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 20_000, seed=1)
    tracer.world_probe = None
    learned = portals.learn(probe)
    assert learned is not None
    env = scene.environment
    blocks = portals.pixel_blocks(env.height, env.width)
    mass = np.bincount(blocks, weights=env.pixel_prob, minlength=learned.table.shape[1])
    sky = np.zeros(len(mass), bool)
    sky[blocks.reshape(env.height, env.width)[env.height // 2:].ravel()] = True
    if misled:
        table = np.where(sky, mass, 0.0)[None, :].repeat(len(learned.table), axis=0)
        table = (1 - portals.DEFENSIVE) * table / table.sum(axis=1, keepdims=True) + portals.DEFENSIVE * mass
        learned = portals.Portals(table=table, region_of_group=learned.region_of_group)
    else:     # the probe learned to leave the sky the patch never faces
        assert learned.table[0][sky].sum() < 0.5 * mass[sky].sum()
    tracer.use_portals(learned)
    values, _ = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 200_000, seed=3)
    expected = expected_patch_indirect() * 0.5
    assert_within(values, expected, extra=1e-3 * expected)


def open_box_under_a_sun():
    """The Cornell box (open towards -y) without its lamp under a map: a sky of radiance 1 and
    a sun of 2 % of the sphere's light per pixel x 200 towards -y, 40° up."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    scene.triangle_emission = np.zeros_like(scene.triangle_emission)
    H, W = 32, 64
    img = np.ones((H, W, 3), np.float32)
    img[: H // 2] *= 0.3                                # a darker ground
    # map direction -y: φ = -π/2, u = (π + π/2) / 2π = 3/4; 40° up: v = 1 - (90 - 40) / 180
    img[int((1 - 50 / 180) * H), int(0.75 * W)] = 400.0
    return with_environment(scene, img)


def test_portals_through_an_opening_are_unbiased_and_less_noisy():
    """The floor of the box open at its front under a sun seen through the opening: UNGUIDED
    with the world portals (the default) and with the map's own world samples (world_portals
    off) agree within 5 standard errors per texel mean, and the portals' relative variance per
    path is lower (the sky behind the box is never seen from inside it)."""
    scene = open_box_under_a_sun()
    base = small(bake_resolution=24, bake_samples=64, light_share=0.0, seed=5)
    with_portals = driver.bake(scene, ["Floor"], base)
    without = driver.bake(scene, ["Floor"], replace(base, world_portals=False))
    a, b = with_portals.objects[0], without.objects[0]
    assert with_portals.portals["used"] and not without.portals
    assert with_portals.portals["probe_visible"] < 0.6     # most world samples hit the box from inside
    (mean_a, se_a), (mean_b, se_b) = a.mean_and_error(), b.mean_and_error()   # path reuse: batch errors
    se = np.hypot(se_a, se_b)
    assert np.all(np.abs(mean_a - mean_b) <= 5 * se), (mean_a, mean_b, se)
    assert auto.relative_variance([a]) < 0.85 * auto.relative_variance([b])


def test_portal_bakes_are_deterministic_whatever_the_threads():
    scene = open_box_under_a_sun()
    settings = small(bake_resolution=16, bake_samples=8, seed=3)
    one = driver.bake(scene, ["Floor", "BackWall"], settings, threads=1)
    two = driver.bake(scene, ["Floor", "BackWall"], settings, threads=2)
    for x, y in zip(one.objects, two.objects):
        assert np.array_equal(x.image, y.image)
    assert one.portals == two.portals and one.portals["used"]


def test_auto_learns_its_portals_from_its_unguided_pilot(monkeypatch):
    """AUTO runs no probe of its own when it pilots: the unguided pilot recorded the world
    samples; below MIN_SAMPLES (no pilot) it runs the probe. Both bakes use portals."""
    scene = open_box_under_a_sun()
    calls = []
    real = driver._run_portal_probe
    monkeypatch.setattr(driver, "_run_portal_probe", lambda *a, **k: calls.append(1) or real(*a, **k))
    piloted = driver.bake(scene, ["Floor"], small(bake_mode="AUTO", bake_resolution=16, bake_samples=16))
    assert piloted.portals["used"] and calls == []
    assert piloted.portals["probe_samples"] > 1000
    small_bake = driver.bake(scene, ["Floor"], small(bake_mode="AUTO", bake_resolution=48, bake_samples=4))
    assert small_bake.portals["used"] and calls == [1]
    tiny = driver.bake(scene, ["Floor"], small(bake_mode="AUTO", bake_resolution=8, bake_samples=4))
    assert calls == [1, 1] and not tiny.portals["used"]      # 256 paths: too few saw the world
    assert 0 < tiny.portals["probe_seen"] < portals.MIN_VISIBLE


@pytest.mark.parametrize("mode", ["UNGUIDED", "AUTO"])
def test_a_sample_clamp_turns_the_portals_off(mode):
    """With Cycles' sample clamp the world samples keep the map's own density (the clamped values
    must be distributed as Cycles'), byte for byte the bake without portals, and the result says why."""
    scene = open_box_under_a_sun()
    settings = small(bake_mode=mode, bake_resolution=16, bake_samples=16, clamp_indirect=10.0)
    clamped = driver.bake(scene, ["Floor"], settings)
    assert clamped.portals == {"used": False, "off": driver.PORTALS_CLAMPED}
    plain = driver.bake(scene, ["Floor"], replace(settings, world_portals=False))
    assert np.array_equal(clamped.objects[0].image, plain.objects[0].image) and plain.portals == {}


def test_no_environment_map_no_probe():
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    result = driver.bake(scene, ["Floor"], small(bake_resolution=8, bake_samples=4))
    assert result.portals == {}
    assert "portals" not in result.stats()
