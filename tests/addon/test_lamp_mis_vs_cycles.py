"""Lamps hit by BSDF rays, with MIS, against Cycles' bake of the same texels (issue 19, item 1).

The Cornell box without its light, the floor a sharp Glossy BSDF (roughness 0.1), lit by a
disk area light or by a point light with a radius (soft falloff, Blender's default, or a
sphere): the
ceiling sees the lamp in the floor. It is baked by lmdp.bake (UNGUIDED) with the lamp's Multiple
Importance on (Cycles' default: BSDF rays hit the lamp, MIS with its light samples) and off
(light sampling alone), and by Cycles (DIFFUSE / INDIRECT, clamping off, 8 total / diffuse /
glossy bounces, Blur Glossy off, two seeds); compared as in ``test_bake_vs_cycles``: the mean
within 2 % and within 5 standard errors of both estimates. Both are unbiased; with MIS the
standard error is lower (per-texel standard errors of the same samples).

A lamp in front of a lit wall does not hide it: Cycles' rays cross a light and go on
(``shade_light.h`` counts it as a transparent bounce), and so do the engine's.
"""
import bpy
import numpy as np
import pytest

from test_bake_vs_cycles import assert_means_agree, compare, lmdp_bake, reference
from test_glossy_vs_cycles import assign, cycles_glossy_settings, new_material
from test_lamps_vs_cycles import add_light, cornell_without_light, window_wall

RESOLUTION = 24

LAMPS = {
    "disk_area": [dict(kind='AREA', location=(0.0, 0.05, 0.9), energy=15.0, shape='DISK', size=0.3)],
    "point_radius": [dict(kind='POINT', location=(-0.1, 0.1, 0.75), energy=20.0, shadow_soft_size=0.12)],
    "point_sphere": [dict(kind='POINT', location=(-0.1, 0.1, 0.75), energy=20.0, shadow_soft_size=0.12,
                          use_soft_falloff=False)],
    "spot_radius": [dict(kind='SPOT', location=(0.0, -0.1, 0.9), rotation=(np.radians(20), 0.0, 0.0), energy=40.0,
                         shadow_soft_size=0.1, spot_size=np.radians(80), spot_blend=0.3)],
    # more than ALL_LAMPS: one lamp per vertex, its selection probability in both MIS weights
    "six_spheres": [dict(kind='POINT', location=(x, y, z), energy=5.0, shadow_soft_size=0.06, use_soft_falloff=False)
                    for x, y, z in ((-0.3, -0.3, 0.8), (0.3, -0.3, 0.7), (-0.3, 0.3, 0.85), (0.3, 0.3, 0.75),
                                    (0.0, -0.35, 0.9), (0.05, 0.35, 0.65))],
}
#: Variants beyond the ones the issue asks for run with the slow tests (LMDP_SLOW_TESTS=1).
SLOW = {"point_sphere", "spot_radius", "six_spheres"}


def check(lmdp_ext, demo, receiver, samples, reference_samples, label, two_percent=True):
    refs = reference(lmdp_ext, demo, receiver, RESOLUTION, reference_samples)
    ob = lmdp_bake(lmdp_ext, receiver, "UNGUIDED", RESOLUTION, samples)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"{label}: s.e. of the means ours {np.sqrt(var_o.sum(0)) / len(ours)} cycles {np.sqrt(var_c.sum(0)) / len(ours)}")
    print(f"{label} / {receiver}: ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}, "
          f"rel {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} % (1 s.e.)")
    if two_percent:
        assert np.all(np.abs(rel) < 0.02), rel
    return var_o


@pytest.mark.parametrize("lamp", [pytest.param(k, marks=pytest.mark.slow) if k in SLOW else k for k in LAMPS])
def test_glossy_floor_under_a_lamp_matches_cycles_and_mis_lowers_the_noise(fresh_scene, lmdp_ext, demo, lamp):
    cornell_without_light(lmdp_ext)
    cycles_glossy_settings(fresh_scene)
    fresh_scene.cycles.sample_clamp_indirect = 0.0
    assign(bpy.data.objects["Floor"], new_material("Glossy 0.1", "ShaderNodeBsdfGlossy",
                                                   Color=(0.8, 0.8, 0.8, 1.0), Roughness=0.1))
    lights = []
    for i, spec in enumerate(LAMPS[lamp]):
        spec = dict(spec)
        lights.append(add_light(spec.pop("kind"), f"{lamp}{i}", spec.pop("location"), spec.pop("rotation", (0.0, 0.0, 0.0)),
                                **spec))
    assert all(light.data.cycles.use_multiple_importance_sampling for light in lights)   # Cycles' default
    extract = lmdp_ext.sub("operators.adapters.extract")
    lamps = extract.extract_scene(bpy.context, [bpy.data.objects["Ceiling"]]).lamps
    assert lamps.hittable.all() and len(lamps) == len(lights)
    var_mis = check(lmdp_ext, demo, "Ceiling", 512, 1024, f"{lamp} MIS")
    for light in lights:
        light.data.cycles.use_multiple_importance_sampling = False
    assert not extract.extract_scene(bpy.context, [bpy.data.objects["Ceiling"]]).lamps.hittable.any()
    # unbiased too (5 s.e.), but its standard error is about 2 %: no 2 % bound
    var_nee = check(lmdp_ext, demo, "Ceiling", 512, 1024, f"{lamp} light sampling alone", two_percent=False)
    ratio = np.sqrt(var_mis.mean() / var_nee.mean())
    print(f"{lamp}: standard error with MIS / light sampling alone = {ratio:.2f}")
    assert ratio < 0.75, ratio   # measured 0.24 disk, 0.42 soft falloff, 0.62 sphere, 0.31 spot, 0.23 six


def test_a_lamp_in_front_of_a_lit_wall_does_not_hide_it(fresh_scene, lmdp_ext, demo):
    """The Cornell box with its ceiling light and a 0.7 m square area light just in front of the
    back wall, facing into the room (weak: most of the floor's indirect light through it is the
    lit wall's): the floor bakes as in Cycles, where rays cross the lamp to the wall."""
    from test_bake_vs_cycles import build
    build("CORNELL_BOX", lmdp_ext)
    add_light('AREA', "Panel", (0.0, 0.45, 0.45), (np.radians(-90), 0.0, 0.0), energy=0.5, shape='SQUARE',
              size=0.7)
    extract = lmdp_ext.sub("operators.adapters.extract")
    lamps = extract.extract_scene(bpy.context, [bpy.data.objects["Floor"]]).lamps
    np.testing.assert_allclose(lamps.axis[0], [0.0, -1.0, 0.0], atol=1e-6)   # facing the room
    check(lmdp_ext, demo, "Floor", 512, 1024, "lamp before the back wall")


CLOSE = {   # above the boxes, below the ceiling (the sphere: a slow test)
    "square_close": dict(kind='AREA', location=(0.0, 0.0, 0.75), rotation=(np.pi, 0.0, 0.0), energy=10.0,
                         shape='SQUARE', size=0.6),
    "sphere_close": dict(kind='POINT', location=(0.1, -0.1, 0.78), energy=10.0, shadow_soft_size=0.15,
                         use_soft_falloff=False),
}


@pytest.mark.parametrize("lamp", ["square_close", pytest.param("sphere_close", marks=pytest.mark.slow)])
def test_direct_light_from_a_large_close_lamp_matches_cycles(fresh_scene, lmdp_ext, demo, lamp):
    """Direct + indirect on the ceiling over a 0.6 m square 0.25 m below it, facing up (sampled
    in its solid angle), or a 0.15 m sphere 0.22 m below it: the texel's first rays hit the lamp
    (MIS at x0, as at every later vertex); Cycles' {'DIRECT', 'INDIRECT'}, MIS on and off."""
    from test_bake_content import reference as content_reference
    cornell_without_light(lmdp_ext)
    fresh_scene.cycles.sample_clamp_indirect = 0.0
    spec = dict(CLOSE[lamp])
    light = add_light(spec.pop("kind"), lamp, spec.pop("location"), spec.pop("rotation", (0.0, 0.0, 0.0)), **spec)
    refs = content_reference(lmdp_ext, demo, "Ceiling", ("DIRECT", "INDIRECT"), resolution=RESOLUTION,
                             samples=1024)
    var = []
    for mis in (True, False):
        light.data.cycles.use_multiple_importance_sampling = mis
        ob = lmdp_bake(lmdp_ext, "Ceiling", "UNGUIDED", RESOLUTION, 512, bake_content="DIRECT_INDIRECT")
        ours, cyc, var_o, var_c = compare(ob, refs)
        rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
        print(f"{lamp} MIS {mis} / Ceiling direct + indirect: rel {np.round(rel * 100, 2)} % "
              f"± {np.round(rel_sigma * 100, 2)} % (1 s.e.)")
        assert np.all(np.abs(rel) < 0.02), rel
        var.append(var_o.mean())
    print(f"{lamp}: standard error with MIS / light sampling alone = {np.sqrt(var[0] / var[1]):.2f}")


def test_sun_seen_in_a_glossy_floor_through_a_window_matches_cycles(fresh_scene, lmdp_ext, demo):
    """A sun of 20° through the back wall's window onto a Glossy 0.1 floor: the ceiling sees the
    sun in the floor, through rays that escape by the window inside the sun's cone (Cycles'
    ``integrate_distant_lights``) and by its light samples; MIS on and off against Cycles."""
    cornell_without_light(lmdp_ext)
    window_wall()
    cycles_glossy_settings(fresh_scene)
    fresh_scene.cycles.sample_clamp_indirect = 0.0
    assign(bpy.data.objects["Floor"], new_material("Glossy 0.1", "ShaderNodeBsdfGlossy",
                                                   Color=(0.8, 0.8, 0.8, 1.0), Roughness=0.1))
    sun = add_light('SUN', "Sun", (0.0, 2.0, 2.0), (np.radians(-50), 0.0, np.radians(180)), energy=3.0,
                    angle=np.radians(20.0))
    var_mis = check(lmdp_ext, demo, "Ceiling", 1024, 4096, "sun MIS")
    sun.data.cycles.use_multiple_importance_sampling = False
    var_nee = check(lmdp_ext, demo, "Ceiling", 1024, 4096, "sun light sampling alone", two_percent=False)
    ratio = np.sqrt(var_mis.mean() / var_nee.mean())
    print(f"sun: standard error with MIS / light sampling alone = {ratio:.2f}")
    assert ratio < 0.5, ratio   # measured 0.16
