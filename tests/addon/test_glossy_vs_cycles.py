"""Glossy, metallic and Principled-specular surfaces against Cycles' bake (issue 18, item 3).

In the Cornell box: a rough (0.4) and a sharp (0.05) Glossy BSDF floor, a metallic Principled
sphere floating above the floor, and Principled BSDFs with the default specular layer
(IOR 1.5, IOR Level 0.5, roughness 0.5) on every wall. Each receiver is baked by lmdp.bake
(UNGUIDED) and by Cycles (DIFFUSE / INDIRECT, clamping off, 8 total / diffuse / glossy bounces,
Blur Glossy off, two seeds) and compared as in ``test_bake_vs_cycles``: the mean within 2 % and
within 5 standard errors of both estimates, the per-texel squared differences equal to the two
variance estimates. Before the BSDFs were modelled the Glossy floors were diffuse surfaces of
their colour, the metal black and the specular layers ignored: each case fails there (measured:
see the commit that added this file).
"""
import hashlib
import os

import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import CACHE, K, assert_means_agree, build, compare, lmdp_bake, reference

RESOLUTION = 24
#: A glTF sample nobody here made: a white metallic plane (glTF defaults: metallic 1, roughness 1)
#: under a smooth metallic sphere (roughness 0.2), as Blender's importer builds them.
GLTF_METAL = "/work/fp/gltf/05_metallic_sphere_light/05_metallic_sphere_light.gltf"


def scene_reference(lmdp_ext, demo, name, resolution, samples, seeds=(1, 2)):
    """Cycles' DIFFUSE/INDIRECT bakes of ``name`` with the scene's own Light Paths (``reference``
    sets 8 bounces), cached under a key that includes them; (len(seeds), R, R, 3)."""
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    extract = lmdp_ext.sub("operators.adapters.extract")
    c = bpy.context.scene.cycles
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects[name]])
    out = []
    for seed in seeds:
        key = "|".join(map(str, (checks.scene_fingerprint(arrays), name, resolution, samples, seed, c.max_bounces,
                                 c.diffuse_bounces, c.glossy_bounces, c.blur_glossy, c.sample_clamp_indirect,
                                 bpy.app.version_string, "scene-light-paths")))
        path = os.path.join(CACHE, hashlib.sha1(key.encode()).hexdigest()[:20] + ".npy")
        if not os.path.exists(path):
            px = demo.bake_cycles(bpy.context, bpy.data.objects[name], 'DIFFUSE', ('INDIRECT',), resolution,
                                  samples=samples, margin=0, seed=seed)[..., :3]
            os.makedirs(CACHE, exist_ok=True)
            np.save(path, px.astype(np.float32))
        out.append(np.load(path))
    return np.stack(out)


def cycles_glossy_settings(scene):
    """Cycles' glossy path settings that the engine follows: glossy bounces as many as the
    total (8), Blur Glossy off (its roughening of glossy lobes after diffuse bounces is not
    modelled)."""
    scene.cycles.glossy_bounces = 8
    scene.cycles.blur_glossy = 0.0
    scene.cycles.caustics_reflective = True


def import_metals_under_area_light(demo):
    """The glTF sample's metals (GLTF_METAL) imported by Blender's importer, Cycles configured as
    the comparisons need, and a 2 m, 1500 W area light 4 m up (the sample's lights import as
    empties)."""
    assert bpy.ops.import_scene.gltf(filepath=GLTF_METAL) == {'FINISHED'}
    scene = bpy.context.scene
    demo.configure_cycles(scene)
    cycles_glossy_settings(scene)
    light = bpy.data.lights.new("Area", 'AREA')
    light.size, light.energy = 2.0, 1500.0
    lamp = bpy.data.objects.new("Area", light)
    lamp.location = (0.0, 0.0, 4.0)
    scene.collection.objects.link(lamp)


def new_material(name, kind, **inputs):
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    node = tree.nodes.new(kind)
    for key, value in inputs.items():
        node.inputs[key].default_value = value
    tree.links.new(node.outputs[0], out.inputs["Surface"])
    return mat


def assign(obj, mat):
    obj.data.materials.clear()
    obj.data.materials.append(mat)


def glossy_floor(roughness):
    def make():
        assign(bpy.data.objects["Floor"], new_material(f"Glossy {roughness}", "ShaderNodeBsdfGlossy",
                                                       Color=(0.8, 0.8, 0.8, 1.0), Roughness=roughness))
        return "TallBox"
    return make


def metallic_sphere():
    bpy.ops.mesh.primitive_uv_sphere_add(segments=24, ring_count=12, radius=0.14, location=(0.2, -0.28, 0.45))
    sphere = bpy.context.active_object
    sphere.name = "MetalSphere"
    assign(sphere, new_material("Metal", "ShaderNodeBsdfPrincipled", Metallic=1.0, Roughness=0.25,
                                **{"Base Color": (0.95, 0.64, 0.54, 1.0)}))
    return "ShortBox"


def principled_walls():
    for name in ("Floor", "BackWall", "LeftWall", "RightWall", "TallBox", "ShortBox"):
        obj = bpy.data.objects[name]
        colour = tuple(obj.active_material.node_tree.nodes["Diffuse BSDF"].inputs["Color"].default_value)
        assign(obj, new_material(f"Principled {name}", "ShaderNodeBsdfPrincipled", **{"Base Color": colour}))
    return "Floor"


CASES = {
    "rough_glossy_floor": glossy_floor(0.4),
    "sharp_glossy_floor": glossy_floor(0.05),
    "metallic_sphere": metallic_sphere,
    "principled_specular": principled_walls,
}


@pytest.mark.parametrize("case", list(CASES))
def test_glossy_surfaces_match_cycles(fresh_scene, lmdp_ext, demo, case):
    scene = build("CORNELL_BOX", lmdp_ext)
    cycles_glossy_settings(scene)
    receiver = CASES[case]()
    select([bpy.data.objects[receiver]])
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects[receiver]])
    assert arrays.has_glossy()
    refs = reference(lmdp_ext, demo, receiver, RESOLUTION, 1024)
    ob = lmdp_bake(lmdp_ext, receiver, "UNGUIDED", RESOLUTION, 512)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"{case} / {receiver}: {len(ours)} texels, ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}, "
          f"mean rel. diff {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} % (1 s.e.), "
          f"per-texel excess {excess.mean():.3g} ± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()


def test_cycles_settings_that_change_glossy_bakes_are_captured_or_named(fresh_scene, lmdp_ext):
    """Blender's default Filter Glossy (1) is captured (the tracer blurs as Cycles does),
    Reflective Caustics off is named; the demo scenes' settings (Filter Glossy 0) say nothing."""
    scene = build("CORNELL_BOX", lmdp_ext)
    assert scene.cycles.blur_glossy == 0.0 and scene.cycles.glossy_bounces == 8
    scene.cycles.blur_glossy = 1.0                # Blender's default
    scene.cycles.caustics_reflective = False
    glossy_floor(0.05)()
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects["TallBox"]])
    assert arrays.materials.filter_glossy == 1.0
    assert any("Reflective Caustics is off" in w for w in arrays.warnings), arrays.warnings
    cycles_glossy_settings(scene)
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects["TallBox"]])
    assert arrays.materials.filter_glossy == 0.0
    assert not any("Caustics" in w for w in arrays.warnings), arrays.warnings


def test_glossy_bounces_count_apart_as_in_cycles(fresh_scene, lmdp_ext, demo):
    """Cycles' Light Paths Max 12, Diffuse 2, Glossy 2 on GLOSSY_BOX: a path may make 2 diffuse
    and 2 glossy bounces (Cycles' path_state_next); the bake follows the scene's Light Paths
    (LightPaths -> Settings.glossy_bounces / total_bounces) and matches Cycles' bake of the
    floor: -0.5 / -0.3 / -0.6 % ± 0.6-0.8 % (with every bounce counted alike, N = 2 in all, it was
    -3.1 / -2.4 / -1.2 % ± 1.0 %, measured at 512 samples against 2 x 1024)."""
    scene = build("GLOSSY_BOX", lmdp_ext)
    cycles = scene.cycles
    cycles.max_bounces, cycles.diffuse_bounces, cycles.glossy_bounces = 12, 2, 2
    floor = bpy.data.objects["Floor"]
    refs = scene_reference(lmdp_ext, demo, "Floor", RESOLUTION, 2048)
    s = scene.lmdp
    s.light_paths = 'SCENE'
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin, s.seed = 'UNGUIDED', RESOLUTION, 1024, 0, 11
    select([floor])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    ob = lmdp_ext.sub("operators.session").session_for(scene).require("bake").object("Floor")
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"GLOSSY_BOX Floor, Cycles 12 / 2 / 2: {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} %")
    assert np.all(np.abs(rel) < 0.02), rel


def test_filter_glossy_blurs_as_in_cycles(fresh_scene, lmdp_ext, demo):
    """Cycles' default Filter Glossy (1) roughens the sharp floor's lobe after the texel's diffuse
    bounce (α ≥ 0.5 √(1 - p_min)); the tracer does the same: TallBox within 2 % and 5 standard
    errors of Cycles' bake with Filter Glossy 1."""
    scene = build("CORNELL_BOX", lmdp_ext)
    cycles_glossy_settings(scene)
    scene.cycles.blur_glossy = 1.0
    receiver = glossy_floor(0.05)()
    refs = reference(lmdp_ext, demo, receiver, RESOLUTION, 1024)
    ob = lmdp_bake(lmdp_ext, receiver, "UNGUIDED", RESOLUTION, 512)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"Filter Glossy 1 / {receiver}: mean rel. diff {np.round(rel * 100, 2)} % ± "
          f"{np.round(rel_sigma * 100, 2)} %, per-texel excess {excess.mean():.3g} ± "
          f"{excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()


def test_glossy_box_extracts_as_built(fresh_scene, lmdp_ext):
    """The bench's GLOSSY_BOX in Blender (Principled checker floor, metallic sphere) is captured
    as demo_geometry builds it: per-triangle albedo and microfacet lobes alike."""
    library = lmdp_ext.sub("lmdp_addon.demo_geometry")
    build("GLOSSY_BOX", lmdp_ext)
    extract = lmdp_ext.sub("operators.adapters.extract")
    got = extract.extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    want = library.build_scene_arrays("GLOSSY_BOX")
    assert got.object_names == want.object_names
    np.testing.assert_allclose(got.corners(), want.corners(), atol=1e-6)
    np.testing.assert_allclose(got.triangle_albedo, want.triangle_albedo, atol=1e-6)
    for name in ("kind", "weight", "alpha", "eta", "f0", "b", "multiscatter"):
        a = getattr(got.materials, name)[np.maximum(got.triangle_material, 0)]
        b = getattr(want.materials, name)[np.maximum(want.triangle_material, 0)]
        glossy = want.triangle_material >= 0
        np.testing.assert_array_equal(got.triangle_material >= 0, glossy)
        np.testing.assert_allclose(a[glossy].astype(float), b[glossy].astype(float), atol=1e-6, err_msg=name)
    assert not [w for w in got.warnings if "Glossy" in w or "Filter" in w]


def test_glossy_box_floor_matches_cycles(fresh_scene, lmdp_ext, demo):
    """The bench's textured glossy scene: its checkered Principled floor reflects the metallic
    sphere and receives the light the sphere reflects."""
    build("GLOSSY_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", RESOLUTION, 1024)
    ob = lmdp_bake(lmdp_ext, "Floor", "UNGUIDED", RESOLUTION, 512)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"GLOSSY_BOX Floor: mean rel. diff {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} %, "
          f"per-texel excess {excess.mean():.3g} ± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()


@pytest.mark.skipif(not os.path.exists(GLTF_METAL), reason="the glTF sample is not on this machine")
def test_imported_gltf_metals_light_a_receiver_as_in_cycles(fresh_scene, lmdp_ext, demo):
    """The glTF importer's Principled metals (a rough white metal floor, a smooth-shaded metal
    sphere of roughness 0.2) reflect an area light onto a diffuse panel facing the sphere; the
    panel's DIFFUSE / INDIRECT bake matches Cycles'. (The sample's lights import as empties.)"""
    import_metals_under_area_light(demo)
    bpy.ops.mesh.primitive_plane_add(size=3.0, location=(0.0, 2.5, 0.6), rotation=(np.pi / 2, 0.0, 0.0))
    panel = bpy.context.active_object
    panel.name = "Panel"
    panel.data.materials.append(new_material("Panel", "ShaderNodeBsdfDiffuse", Color=(0.8, 0.8, 0.8, 1.0)))
    select([panel])
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, [panel])
    assert arrays.has_glossy() and arrays.has_smooth_normals()
    refs = reference(lmdp_ext, demo, "Panel", RESOLUTION, 1024)
    ob = lmdp_bake(lmdp_ext, "Panel", "UNGUIDED", RESOLUTION, 512)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"glTF metals / Panel: {len(ours)} texels, ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}, mean rel. diff {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} %, "
          f"per-texel excess {excess.mean():.3g} ± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()


@pytest.mark.parametrize("mode", ["GUIDED", "FINAL_GATHER"])
def test_glossy_box_guided_and_final_gather_match_cycles(fresh_scene, lmdp_ext, demo, mode):
    """GUIDED (BSDF sampling at glossy vertices) is unbiased; FINAL_GATHER's solution gives glossy
    points one unknown per outgoing stratum (``model/unknowns.py``) and continues glossy hits as
    paths: its bias within 2 % plus 2 standard errors of Cycles (with the diffuse albedo alone,
    as once: -5.3 / -5.1 / -4.0 % ± 1.0 / 0.9 / 1.3 %, outside that bound)."""
    build("GLOSSY_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", RESOLUTION, 1024)
    fresh_scene.lmdp.point_count = 2048
    fresh_scene.lmdp.cost_mode = 'PHYSICAL'
    select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    ob = lmdp_bake(lmdp_ext, "Floor", mode, RESOLUTION, 256)
    warnings = lmdp_ext.sub("operators.session").session_for(fresh_scene).require("bake").warnings
    assert any("one unknown per outgoing stratum" in w for w in warnings), warnings
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel = ours.mean(axis=0) / cyc.mean(axis=0) - 1.0
    sigma = np.sqrt((var_o.sum(axis=0) + var_c.sum(axis=0)) / len(ours) ** 2) / cyc.mean(axis=0)
    print(f"GLOSSY_BOX Floor {mode}: {np.round(rel * 100, 2)} % ± {np.round(sigma * 100, 2)} % (1 s.e.)")
    if mode == "GUIDED":
        assert_means_agree(ours, cyc, var_o, var_c)
    assert np.all(np.abs(rel) < 0.02 + 2.0 * sigma), rel


def test_hostile_glossy_inputs_are_named_and_bake(fresh_scene, lmdp_ext):
    """A non-finite Roughness (named in a warning), an infinite IOR (Blender clamps it), a huge
    Specular IOR Level, a negative Glossy colour and a Glossy BSDF with the Beckmann distribution
    (named): the bake runs and gives finite values."""
    build("CORNELL_BOX", lmdp_ext)
    floor = new_material("Odd", "ShaderNodeBsdfPrincipled", Roughness=float("nan"), IOR=float("inf"),
                         **{"Specular IOR Level": 50.0})
    assign(bpy.data.objects["Floor"], floor)
    glossy = new_material("Beckmann", "ShaderNodeBsdfGlossy", Color=(-1.0, 0.5, 2.0, 1.0), Roughness=0.3)
    glossy.node_tree.nodes["Glossy BSDF"].distribution = 'BECKMANN'
    assign(bpy.data.objects["BackWall"], glossy)
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects["TallBox"]])
    text = "\n".join(arrays.warnings)
    assert "'Principled BSDF' Roughness is not a finite number" in text
    assert "Beckmann" in text
    assert np.all(np.isfinite(arrays.materials.weight)) and np.all(np.isfinite(arrays.materials.eta))
    ob = lmdp_bake(lmdp_ext, "TallBox", "UNGUIDED", 8, 16)
    assert np.all(np.isfinite(ob.value)) and ob.value.mean() > 0


def test_glossy_box_with_cycles_default_light_paths(fresh_scene, lmdp_ext, demo):
    """GLOSSY_BOX under Blender's default Cycles Light Paths (Max 12, Diffuse 4, Glossy 4, Filter
    Glossy 1; clamping off, which the engine never applies): the floor's bake with the add-on's
    defaults (light paths from the scene) matches Cycles'."""
    scene = build("GLOSSY_BOX", lmdp_ext)
    cycles = scene.cycles
    cycles.max_bounces, cycles.diffuse_bounces, cycles.glossy_bounces, cycles.blur_glossy = 12, 4, 4, 1.0
    floor = bpy.data.objects["Floor"]
    refs = scene_reference(lmdp_ext, demo, "Floor", RESOLUTION, 1024)
    s = scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin, s.seed = 'UNGUIDED', RESOLUTION, 512, 0, 11
    select([floor])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    ob = lmdp_ext.sub("operators.session").session_for(scene).require("bake").object("Floor")
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"GLOSSY_BOX Floor, Cycles defaults: {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} %")
    assert np.all(np.abs(rel) < 0.02), rel


@pytest.mark.slow
@pytest.mark.parametrize("case", ["rough_glossy_floor", "sharp_glossy_floor", "metallic_sphere"])
def test_glossy_surfaces_match_cycles_at_high_samples(fresh_scene, lmdp_ext, demo, case):
    """The cases above at 32 px, Cycles 2 x 4096 and the engine 4096 samples: the mean within
    5 standard errors of both and within 1 % plus 2 of them (measured, seed 11: rough -0.1 /
    -0.1 / +0.0 % ± 0.2 %, sharp -0.6 / -0.7 / -1.0 % ± 0.3-0.4 % (seed 12: +0.3 / +0.4 /
    +0.4 %), metal +0.0 / +0.0 / -0.1 % ± 0.2-0.3 %)."""
    scene = build("CORNELL_BOX", lmdp_ext)
    cycles_glossy_settings(scene)
    receiver = CASES[case]()
    refs = reference(lmdp_ext, demo, receiver, 32, 4096)
    ob = lmdp_bake(lmdp_ext, receiver, "UNGUIDED", 32, 4096)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"{case} / {receiver} at 4096 spp: {np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} %")
    assert np.all(np.abs(rel) < 0.01 + 2.0 * rel_sigma), rel
