"""Texture lookups, colour nodes and transparency of the engine (lmdp_addon.textures,
lmdp_addon.transparency), against values worked out by hand from Cycles' conventions (the
Blender-side comparison with Cycles' own bakes is tests/addon/test_textures_vs_cycles.py)."""
import numpy as np
import pytest

from bake_scenes import K, trace_at
from lmdp_addon import demo_geometry as scenes
from lmdp_addon import textures as tx
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.lights import EmitterSampler
from lmdp_addon.raycast import RayCaster
from lmdp_addon.transparency import ABSORBED, Transparency


def table(rows, srgb=False):
    """An ImageTable from rows of RGB values, ``rows[0]`` the bottom row."""
    px = np.ones((len(rows), len(rows[0]), 4), np.float32)
    px[..., :3] = np.asarray(rows, np.float32)
    return tx.ImageTable(px, srgb=srgb)


GREY = table([[[0.0] * 3, [1.0] * 3], [[0.25] * 3, [0.5] * 3]])   # 2 x 2, rows bottom to top


def at(t, uv, interpolation="LINEAR", extension="REPEAT"):
    return tx.sample_image(t, np.asarray(uv, np.float32).reshape(-1, 2), interpolation, extension)[:, 0]


def test_row_zero_is_the_bottom_and_closest_takes_the_texel_under_the_point():
    np.testing.assert_allclose(at(GREY, [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]], "CLOSEST"),
                               [0.0, 1.0, 0.25, 0.5])
    np.testing.assert_allclose(at(GREY, [[0.49, 0.01], [0.51, 0.99]], "CLOSEST"), [0.0, 0.5])


def test_linear_reaches_texel_centres_and_interpolates_between():
    np.testing.assert_allclose(at(GREY, [[0.25, 0.25], [0.75, 0.75]]), [0.0, 0.5], atol=1e-7)
    np.testing.assert_allclose(at(GREY, [[0.5, 0.25], [0.25, 0.5], [0.5, 0.5]]),
                               [0.5, 0.125, (0 + 1 + 0.25 + 0.5) / 4], atol=1e-7)


@pytest.mark.parametrize("extension, expected", [
    ("REPEAT", [1.0, 1.0, 0.0, 0.5]),      # texel indices 3, -1, -2 wrap to 1, 1, 0; u = 0 mixes 1 and 0
    ("EXTEND", [1.0, 0.0, 0.0, 0.0]),
    ("CLIP", [0.0, 0.0, 0.0, 0.0]),
    ("MIRROR", [0.0, 0.0, 1.0, 0.0]),      # Cycles' wrap_mirror: 3 -> 0, -1 -> 0, -2 -> 1
])
def test_extension_modes(extension, expected):
    """The bottom row (0, 1) at v = 1/4 (only that row counts), u = 1.75, -0.25, -0.75, 0."""
    got = at(GREY, [[1.75, 0.25], [-0.25, 0.25], [-0.75, 0.25], [0.0, 0.25]], extension=extension)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    if extension == "CLIP":    # half a texel beyond the right edge: half the edge texel
        np.testing.assert_allclose(at(GREY, [[1.0, 0.25]], extension="CLIP"), [0.5], atol=1e-7)


def test_srgb_bytes_are_interpolated_before_linearising():
    t = table([[[0.0] * 3, [1.0] * 3]], srgb=True)
    mid = at(t, [[0.5, 0.5]])[0]
    np.testing.assert_allclose(mid, ((0.5 + 0.055) / 1.055) ** 2.4, rtol=1e-6)   # not (0 + 1) / 2


class _P:
    k = 1

    def memo(self, key, compute):
        return compute()


def value(expr):
    return expr.evaluate(_P())[0]


def test_mix_blends_follow_cycles():
    a, b, t = np.array([0.2, 0.5, 0.8]), np.array([0.6, 0.0, 0.4]), 0.25
    A, B, T = tx.Const(a), tx.Const(b), tx.Const([t])
    expected = {
        "MIX": a + t * (b - a), "MULTIPLY": a * (1 - t + t * b), "ADD": a + t * b, "SUBTRACT": a - t * b,
        "SCREEN": 1 - (1 - t + t * (1 - b)) * (1 - a), "DIFFERENCE": a + t * (np.abs(a - b) - a),
        "DARKEN": a + t * (np.minimum(a, b) - a), "LIGHTEN": np.maximum(a, t * b),
        "DIVIDE": np.where(b != 0, (1 - t) * a + t * a / np.where(b != 0, b, 1), a),
    }
    for blend, want in expected.items():
        np.testing.assert_allclose(value(tx.Mix(blend, T, A, B)), want, rtol=1e-6, err_msg=blend)
    np.testing.assert_allclose(value(tx.Mix("ADD", tx.Const([1.0]), A, B, clamp=True)), np.minimum(a + b, 1))


def test_colour_nodes():
    c = tx.Const([0.2, 0.5, 0.8])
    np.testing.assert_allclose(value(tx.Invert(tx.Const([1.0]), c)), [0.8, 0.5, 0.2], rtol=1e-6)
    np.testing.assert_allclose(value(tx.Gamma(c, tx.Const([2.0]))), [0.04, 0.25, 0.64], rtol=1e-6)
    np.testing.assert_allclose(value(tx.BrightContrast(c, tx.Const([0.1]), tx.Const([0.0]))), [0.3, 0.6, 0.9],
                               rtol=1e-6)
    identity = tx.HueSaturation(tx.Const([0.5]), tx.Const([1.0]), tx.Const([1.0]), tx.Const([1.0]), c)
    np.testing.assert_allclose(value(identity), [0.2, 0.5, 0.8], rtol=1e-5)
    grey = tx.HueSaturation(tx.Const([0.5]), tx.Const([0.0]), tx.Const([1.0]), tx.Const([1.0]), c)
    np.testing.assert_allclose(value(grey), [0.8, 0.8, 0.8], rtol=1e-5)   # saturation 0: the value
    ramp = np.linspace(0, 1, 5)
    curves = tx.Curves(np.stack([ramp, ramp ** 2, 1 - ramp]), tx.Const([1.0]), c)
    np.testing.assert_allclose(value(curves), [0.2, 0.5 ** 2 + 0.0, 0.2], atol=0.02)
    np.testing.assert_allclose(value(tx.Luminance(c)), [0.2 * 0.2126 + 0.5 * 0.7152 + 0.8 * 0.0722], rtol=1e-6)


def test_constants_fold_and_untextured_triangles_keep_their_albedo():
    assert isinstance(tx.product(tx.Const([0.5, 0.5, 0.5]), tx.Const([0.5])), tx.Const)
    assert isinstance(tx.lerp(tx.Const([0.25]), tx.Const([1, 0, 0]), tx.Const([0, 0, 1])), tx.Const)
    np.testing.assert_allclose(tx.lerp(tx.Const([0.25]), tx.Const([1, 0, 0]), tx.Const([0, 0, 1])).value,
                               [0.75, 0, 0.25])
    img = table([[[0.1, 0.2, 0.3]]])
    uv = np.zeros((2, 3, 2), np.float32)
    surface = tx.SurfaceTextures(images=[img], uv_maps=[uv],
                                 materials=[tx.MaterialShading(albedo=tx.ImageTexture(0, 0))],
                                 triangle_material=[-1, 0])
    base = np.array([[0.9, 0.8, 0.7], [0.0, 0.0, 0.0]], np.float32)
    got = surface.albedo(np.array([0, 1, 1]), np.array([0.2, 0.2, 0.5]), np.array([0.3, 0.3, 0.1]), base)
    np.testing.assert_allclose(got, [[0.9, 0.8, 0.7], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3]], rtol=1e-6)
    np.testing.assert_allclose(surface.alpha(np.array([0, 1]), np.zeros(2), np.zeros(2)), [1.0, 1.0])


# ---- transparency ----------------------------------------------------------------------------

def cornell_with_leaf(alpha=None, z=0.75, layers=1):
    """The Cornell box with ``layers`` 0.5 m leaf quads at heights ``z``, ``z + 0.05``, ...
    (above both boxes) whose alpha is the constant ``alpha`` (None: no leaves)."""
    parts = scenes.scene_parts("CORNELL_BOX")
    for k in range(layers if alpha is not None else 0):
        h = z + 0.05 * k
        parts = parts + [scenes._quad_part(f"Leaf{k}", [(-0.15, -0.4, h), (0.35, -0.4, h), (0.35, 0.1, h),
                                                        (-0.15, 0.1, h)], (0.15, 0.6, 0.1))]
    sa = scenes.parts_to_scene_arrays(parts)
    if alpha is not None:
        leaf = np.isin(sa.triangle_object, [sa.object_names.index(f"Leaf{k}") for k in range(layers)])
        sa.surface = tx.SurfaceTextures(materials=[tx.MaterialShading(alpha=tx.Const([alpha]))],
                                        triangle_material=np.where(leaf, 0, -1))
    return sa


def test_a_clear_leaf_changes_nothing_and_an_opaque_one_is_a_surface():
    point, n = (0.1, -0.42, 0.0), 200_000
    values = {}
    for name, scene in (("none", cornell_with_leaf(None)), ("clear", cornell_with_leaf(0.0)),
                        ("opaque", cornell_with_leaf(1.0)), ("plain", None)):
        if scene is None:   # the leaf as an ordinary opaque surface, no SurfaceTextures
            scene = cornell_with_leaf(1.0)
            scene.surface = None
        values[name] = trace_at(IndirectTracer(scene, "UNGUIDED", max_bounces=6), point, (0, 0, 1), n, seed=7)[0]

    def agree(a, b):
        diff = a.mean(0) - b.mean(0)
        sigma = np.sqrt(a.var(0) / len(a) + b.var(0) / len(b))
        assert np.all(np.abs(diff) <= K * sigma), (diff, sigma)

    agree(values["clear"], values["none"])
    agree(values["opaque"], values["plain"])
    assert values["plain"].mean(0)[0] < 0.9 * values["none"].mean(0)[0]   # the leaf matters


def test_rays_stop_with_probability_alpha_and_are_absorbed_past_the_limit():
    scene = cornell_with_leaf(0.3, layers=3)
    scene.surface.transparent_max_bounces = 2
    caster = RayCaster(scene)
    t = Transparency.of(scene)
    n = 40_000
    origin = np.tile(np.float32([0.1, -0.15, 0.5]), (n, 1))
    up = np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1))
    tri, dist, bu, bv, extra, tint = t.intersect(caster, origin, up, np.random.default_rng(1))
    assert tint is None
    leaf = np.isin(scene.triangle_object[np.maximum(tri, 0)], [scene.object_names.index(f"Leaf{k}")
                                                               for k in range(3)]) & (tri >= 0)
    first = leaf & (np.abs(dist - 0.25) < 1e-4)
    for fraction, p in ((first.mean(), 0.3), ((leaf & (np.abs(dist - 0.30) < 1e-4)).mean(), 0.7 * 0.3),
                        ((tri == ABSORBED).mean(), 0.7 ** 2 * 0.7)):
        assert abs(fraction - p) <= K * np.sqrt(p * (1 - p) / n), (fraction, p)
    assert extra > 0
    # shadow rays: 0.7 per layer, 0 beyond the limit
    shadow = t.transmittance(caster, origin[:2], up[:2], np.float32([0.27, 0.32]))
    np.testing.assert_allclose(shadow, [0.7, 0.49], rtol=1e-6)
    assert t.transmittance(caster, origin[:1], up[:1], np.float32([0.4]))[0] == 0.0


@pytest.mark.parametrize("alpha", [0.0, 0.25, 1.0])
def test_shadow_rays_through_a_leaf_carry_one_minus_alpha(alpha):
    """Direct light under the leaf by light sampling alone (same random numbers): (1 - alpha)
    times the light without the leaf, exactly."""
    n = 2000
    points = np.tile(np.float32([-0.1, -0.45, 0.0]), (n, 1))   # every light point behind the leaf
    normals = np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1))
    out = {}
    for name, scene in (("none", cornell_with_leaf(None)), ("leaf", cornell_with_leaf(alpha))):
        out[name] = EmitterSampler(scene).direct_light(points, normals, np.random.default_rng(3),
                                                       RayCaster(scene))[0]
    assert out["none"].sum() > 0
    np.testing.assert_allclose(out["leaf"], (1 - alpha) * out["none"], rtol=1e-5, atol=1e-9)


def test_the_build_sees_through_a_clear_leaf_and_not_through_an_opaque_one():
    """The passive dynamics of the floor's states: with a clear leaf (alpha 0) as without it,
    with an opaque one (alpha 1) as with the same leaf as a plain surface, transition for
    transition (the rays and shadow rays are the same; only where they start after the leaf
    differs by the ray offset)."""
    from lmdp_addon.model.dynamics import build_passive_dynamics
    from lmdp_addon.model.states import sample_states

    def dense(alpha, plain=False):
        scene = cornell_with_leaf(alpha)
        if plain:
            scene.surface = None
        scene.object_carries_states[:] = [n == "Floor" for n in scene.object_names]
        states = sample_states(scene, 128, seed=2)
        return build_passive_dynamics(scene, states, rays_per_stratum=2, seed=5, light_samples=8).P.toarray()

    np.testing.assert_allclose(dense(0.0), dense(None), atol=1e-6)
    np.testing.assert_array_equal(dense(1.0), dense(1.0, plain=True))


def test_zero_colour_channels_follow_cycles_pass_division():
    """Cycles divides the DIFFUSE INDIRECT pass by the diffuse colour with
    ``safe_divide_even_color``: a channel whose colour is 0 takes the other one (two zeros) or
    the mean of the two others (one zero); the bake's texel values do the same."""
    from lmdp_addon.bake.tracer import _even_colour
    L = np.array([[0.2, 0.4, 0.6]] * 4, np.float32)
    colour = np.array([[0.5, 0.5, 0.5], [0.6, 0.0, 0.0], [0.0, 0.3, 0.1], [0.0, 0.0, 0.0]], np.float32)
    np.testing.assert_allclose(_even_colour(L.copy(), colour),
                               [[0.2, 0.4, 0.6], [0.2, 0.2, 0.2], [0.5, 0.4, 0.6], [0.0, 0.0, 0.0]], rtol=1e-6)


def test_cubic_is_cycles_b_spline():
    """The cubic B-spline weights sum to 1 and reproduce a linear ramp inside the image; at a
    texel centre the value is (a + 4 b + c) / 6 of the texel and its neighbours."""
    ramp = table([[[i / 7.0] * 3 for i in range(8)]])
    u = np.array([[0.3, 0.5], [0.55, 0.5], [0.61, 0.5]], np.float32)
    np.testing.assert_allclose(at(ramp, u, "CUBIC", "EXTEND"), u[:, 0] * 8 / 7 - 0.5 / 7, atol=1e-6)
    spike = table([[[0.0] * 3, [1.0] * 3, [0.0] * 3, [0.0] * 3]])
    np.testing.assert_allclose(at(spike, [[0.375, 0.5]], "CUBIC"), [4 / 6], atol=1e-6)
    np.testing.assert_allclose(at(spike, [[0.125, 0.5]], "CUBIC"), [1 / 6], atol=1e-6)


def test_bakes_through_transparency_do_not_depend_on_the_thread_count():
    """The pass / stop decisions draw from each work unit's own generator: a bake of the floor
    under a half-transparent leaf is byte-identical with 1 and 3 threads."""
    from lmdp_addon.bake.driver import bake
    from lmdp_addon.settings import Settings
    scene = cornell_with_leaf(0.5)
    settings = Settings(bake_mode="UNGUIDED", bake_resolution=12, bake_samples=16, bake_margin=0)
    one = bake(scene, ["Floor"], settings, threads=1).object("Floor").value
    three = bake(scene, ["Floor"], settings, threads=3).object("Floor").value
    assert one.sum() > 0
    np.testing.assert_array_equal(one, three)


def test_rays_absorbed_past_the_transparent_limit_go_to_the_void_under_an_environment_map():
    """Under an environment map (W world-bin columns) the build's rays absorbed by too many
    transparent surfaces land in the void, not in a world bin: with Transparent Max Bounces 0 a
    clear leaf stops every ray, so the world columns hold what they hold with the leaf as an
    opaque surface that carries no states (whose hits are void too)."""
    from lmdp_addon.model.dynamics import build_passive_dynamics
    from lmdp_addon.model.states import sample_states
    from lmdp_addon.world import EnvironmentMap

    sky = np.ones((8, 16, 3), np.float32) * np.linspace(0.5, 2.0, 16)[None, :, None]

    def build(plain):
        scene = cornell_with_leaf(0.0, z=0.5)
        scene.surface.transparent_max_bounces = 0
        if plain:
            scene.surface = None
        scene.environment = EnvironmentMap(sky)
        scene.world_radiance = scene.environment.mean_radiance().astype(np.float32)
        scene.object_carries_states[:] = [n == "Floor" for n in scene.object_names]
        states = sample_states(scene, 128, seed=2)
        return build_passive_dynamics(scene, states, rays_per_stratum=2, seed=5, light_samples=8)

    absorbed, plain = build(False), build(True)
    assert absorbed.n_world > 1
    world = absorbed.world_columns
    np.testing.assert_allclose(absorbed.P[:, world].toarray(), plain.P[:, world].toarray(), atol=1e-6)
    void = absorbed.void_column
    np.testing.assert_allclose(absorbed.P[:, void].toarray(), plain.P[:, void].toarray(), atol=1e-6)
