"""The environment map (lmdp_addon.world): Cycles' equirectangular convention, the importance
sampling's pdf, and the tracer's world next-event estimation against analytic indirect light.

Monte Carlo tolerances are 5 standard errors (``bake_scenes.assert_within``); the histogram test
bounds every pixel's count by 5 binomial standard deviations.
"""
import numpy as np
import pytest

from bake_scenes import PATCH_ALBEDO, SKY, assert_within, expected_patch_indirect, patch_under_sky, trace_at
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.world import EnvironmentMap, bin_of_direction, WORLD_BINS_PHI, WORLD_BINS_Z


def random_map(h=16, w=32, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, 3)).astype(np.float32) ** 4
    img[3, 5] = (40.0, 30.0, 20.0)          # a "sun"
    img[:, 7] = 0.0                          # a black column: pdf 0 there
    return img


def rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def sphere_grid(n):
    """n x 2n equal-area directions (z uniform, φ uniform) and the solid angle of each."""
    z = 1.0 - 2.0 * (np.arange(n) + 0.5) / n
    phi = 2.0 * np.pi * (np.arange(2 * n) + 0.5) / (2 * n)
    Z, P = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1.0 - Z ** 2)
    d = np.stack([r * np.cos(P), r * np.sin(P), Z], axis=-1).reshape(-1, 3)
    return d, 4.0 * np.pi / len(d)


def test_cycles_equirectangular_convention():
    """u = (π - atan2(y, x)) / 2π, v = 1 - acos(z)/π (Cycles' direction_to_equirectangular):
    +x is the centre of the image, +y a quarter from its left edge, +z its top row (row 0 is the
    bottom, as Blender stores pixels)."""
    env = EnvironmentMap(np.ones((8, 16, 3)))
    u, v = env.map_uv(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]))
    np.testing.assert_allclose(u[:3], [0.5, 0.25, 0.75], atol=1e-6)
    np.testing.assert_allclose(v, [0.5, 0.5, 0.5, 1.0, 0.0], atol=1e-6)
    img = np.zeros((8, 16, 3), np.float32)
    img[7, :] = 5.0                          # the top row
    img[4, 8] = 3.0                          # just above the horizon, right of the centre column
    closest = EnvironmentMap(img, interpolation="CLOSEST")
    np.testing.assert_allclose(closest.radiance_at(np.array([[0, 0, 1.0]])), [[5.0] * 3])
    d = np.array([[np.cos(-0.1), np.sin(-0.1), 0.1]])   # u slightly > 0.5: column 8
    np.testing.assert_allclose(closest.radiance_at(d), [[3.0] * 3])
    # a rotation R takes world directions into the map: the world direction R^T m sees pixel m
    rotated = EnvironmentMap(img, rotation=rotation_z(0.7), interpolation="CLOSEST")
    np.testing.assert_allclose(rotated.radiance_at(d @ rotation_z(0.7)), [[3.0] * 3])


def test_bilinear_lookup_is_cycles_linear():
    """Pixel centres return the pixel, half-way between two centres the mean (periodic in u)."""
    img = np.zeros((4, 8, 3), np.float32)
    img[2, 0] = 8.0
    env = EnvironmentMap(img)
    u = np.array([0.5 / 8, 0.0, 1.0 / 8, 1.0 - 0.5 / 8], np.float32)
    v = np.full(4, 2.5 / 4, np.float32)
    np.testing.assert_allclose(env._lookup(u, v)[:, 0], [8.0, 4.0, 4.0, 0.0], atol=1e-5)


@pytest.mark.parametrize("rotation", [np.eye(3), rotation_z(1.3) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])])
def test_pdf_integrates_to_one_and_matches_the_samples(rotation):
    env = EnvironmentMap(random_map(), rotation=rotation)
    d, omega = sphere_grid(1000)
    assert abs(env.pdf(d).astype(np.float64).sum() * omega - 1.0) < 2e-3
    rng = np.random.default_rng(1)
    dirs, pdf, radiance = env.sample(rng.random((200_000, 3)))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-5)
    # the float32 direction may round into the neighbouring pixel right at a pixel edge
    same = np.isclose(pdf, env.pdf(dirs), rtol=2e-3)
    assert same.mean() > 1.0 - 1e-4, same.mean()
    np.testing.assert_allclose(radiance, env.radiance_at(dirs), rtol=1e-4, atol=1e-5)
    assert np.all(pdf > 0)


def test_sample_histogram_matches_the_pixel_probabilities():
    env = EnvironmentMap(random_map(), rotation=rotation_z(-0.4))
    n = 400_000
    dirs, _, _ = env.sample(np.random.default_rng(2).random((n, 3)))
    u, v = env.map_uv(dirs)
    pixel = np.clip((v * env.height).astype(int), 0, env.height - 1) * env.width + \
        np.minimum((u * env.width).astype(int), env.width - 1)
    counts = np.bincount(pixel, minlength=env.height * env.width)
    p = env.pixel_prob
    sigma = np.sqrt(n * p * (1 - p))
    assert np.all(np.abs(counts - n * p) <= 5 * sigma + 1), np.max(np.abs(counts - n * p) / (sigma + 1))
    # the black column is drawn only for the bilinear spill of its neighbours, never with CLOSEST
    assert p[7::env.width].sum() < p[6::env.width].sum() / 4
    closest = EnvironmentMap(random_map(), interpolation="CLOSEST")
    dirs, _, _ = closest.sample(np.random.default_rng(3).random((100_000, 3)))
    u, _ = closest.map_uv(dirs)
    assert not np.any(np.floor(u * closest.width) == 7)
    # importance: the "sun" pixel takes its share (radiance x sin θ), far above uniform sampling
    sun = 3 * env.width + 5
    assert counts[sun] / n > 20.0 / (env.height * env.width)


def test_mean_radiance_is_the_solid_angle_mean():
    """(1/4π) ∫ L dω by a midpoint rule in (u, v), 8 x 8 points per pixel, dω = 2π² sin θ du dv."""
    img = random_map()
    closest = EnvironmentMap(img, interpolation="CLOSEST")
    H, W, k = closest.height, closest.width, 8
    u, v = np.meshgrid((np.arange(W * k) + 0.5) / (W * k), (np.arange(H * k) + 0.5) / (H * k))
    theta, phi = np.pi * (1.0 - v.ravel()), np.pi - 2.0 * np.pi * u.ravel()
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    weight = 2.0 * np.pi ** 2 * np.sin(theta) / (W * k * H * k) / (4.0 * np.pi)
    expected = (closest.radiance_at(d).astype(np.float64) * weight[:, None]).sum(axis=0)
    np.testing.assert_allclose(closest.mean_radiance(), expected, rtol=2e-3)


def test_world_bins_are_equal_area_and_average_the_map():
    d, _ = sphere_grid(200)
    b = bin_of_direction(d)
    counts = np.bincount(b, minlength=WORLD_BINS_Z * WORLD_BINS_PHI)
    assert counts.min() == counts.max()            # equal solid angle
    img = np.zeros((32, 64, 3), np.float32)
    img[16:] = 2.0                                  # the upper hemisphere
    means = EnvironmentMap(img, interpolation="CLOSEST").bin_radiance()
    upper = np.arange(WORLD_BINS_Z * WORLD_BINS_PHI) < WORLD_BINS_Z // 2 * WORLD_BINS_PHI
    np.testing.assert_allclose(means[upper], 2.0)
    np.testing.assert_allclose(means[~upper], 0.0)


# ---- the tracer with an environment map ---------------------------------------------------------

def with_environment(scene, img, rotation=np.eye(3)):
    env = EnvironmentMap(img, rotation=rotation, interpolation="CLOSEST")
    scene.environment = env
    scene.world_radiance = env.mean_radiance().astype(np.float32)
    return scene


def ground_east_map(H=32, W=64):
    """(H, W, 3) a map of radiance SKY only below the horizon and towards +x (u in [1/4, 3/4)),
    black elsewhere."""
    img = np.full((H, W, 3), SKY, np.float32)
    img[H // 2:] = 0.0                            # the sky above the horizon is black
    img[:, :W // 4] = 0.0                         # u < 1/4 and u >= 3/4: -x
    img[:, 3 * W // 4:] = 0.0
    return img


@pytest.mark.parametrize("mode", ["constant", "ground", "ground_east"])
def test_patch_under_environment(mode):
    """The patch of ``bake_scenes.patch_under_sky`` faces down 1 m above the receiver: its
    radiance is ρ x (1/π) ∫ L_env cos over the lower hemisphere. A constant map gives ρ L F (as
    the uniform world); a map bright only below the horizon the same (the receiver sees its
    black sky directly: direct light); bright only below the horizon and towards +x, half of it.
    A map turned upside down by the orientation would give 0."""
    H, W = 32, 64
    img = np.full((H, W, 3), SKY, np.float32)
    share = 1.0
    if mode != "constant":
        img[H // 2:] = 0.0                            # the sky above the horizon is black
    if mode == "ground_east":
        img[:, :W // 4] = 0.0                         # u < 1/4 and u >= 3/4: -x
        img[:, 3 * W // 4:] = 0.0
        share = 0.5
    scene = with_environment(patch_under_sky(), img)
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 200_000, seed=3)
    expected = expected_patch_indirect() * share
    assert_within(values, expected, extra=1e-3 * expected)
    assert stats.shadow_rays > 0.4 * stats.vertices    # world next-event estimation ran


# ---- the LMDP's directional world terminal -----------------------------------------------------

def test_lmdp_world_terminal_is_directional():
    """PHYSICAL build of the patch under a map bright only below the horizon towards +x (bins
    aligned with the bright region): escapes go to 32 world terminals, z of the patch's underside
    is ρ L / 2 (it sees half of its hemisphere lit), where the one mean-radiance world terminal
    would give ρ L / 4; the passive dynamics' rows still sum to 1."""
    from lmdp_addon.model import pipeline
    from lmdp_addon.settings import Settings
    scene = with_environment(patch_under_sky(), ground_east_map())
    result = pipeline.run_all(scene, Settings(point_count=256, cost_mode="PHYSICAL"))
    dyn = result.dynamics
    assert dyn.n_world == WORLD_BINS_Z * WORLD_BINS_PHI
    assert dyn.void_column == dyn.n_points + dyn.n_emitters + dyn.n_world
    assert dyn.row_sum_error < 1e-4
    labels = dyn.terminal_labels()
    assert labels[-1] == "void" and labels[dyn.n_emitters] == "world:0"
    patch = result.states.point_object == scene.object_names.index("Patch")
    under = patch & (result.states.normals[:, 2] < 0)
    z = result.solution.z[under].mean(axis=0)
    np.testing.assert_allclose(z, np.asarray(PATCH_ALBEDO) * SKY * 0.5, rtol=0.03)


@pytest.mark.parametrize("mode", ["GUIDED", "FINAL_GATHER"])
def test_solved_modes_under_environment(mode):
    """GUIDED and FINAL_GATHER on the PHYSICAL solution of the patch under the +x ground map:
    the receiver's indirect light is ρ L F / 2 (as UNGUIDED's). FINAL_GATHER samples the map's
    direct light at the patch itself and reads no world terminal in ẑ (which holds no light
    here: the patch sees nothing but the world), so it is unbiased too; reading both would
    double it."""
    from lmdp_addon.bake.gather import build_gather
    from lmdp_addon.bake.guide import build_guide
    from lmdp_addon.model import pipeline
    from lmdp_addon.settings import Settings
    scene = with_environment(patch_under_sky(), ground_east_map())
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp, 4) if mode == "FINAL_GATHER" else None
    tracer = IndirectTracer(scene, mode, max_bounces=4, guide=guide, gather=gather)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 100_000, seed=4, state=state)
    expected = expected_patch_indirect() * 0.5
    assert_within(values, expected, extra=2e-3 * expected)
    if mode == "FINAL_GATHER":
        patch = lmdp.states.point_object == scene.object_names.index("Patch")
        assert stats.gathered > 0 and np.abs(gather.irradiance[patch]).max() < 1e-2 * SKY
