"""What Blender's glTF exporter keeps of a baked lightmap (issue 21, item 6), checked on the
exported ``.gltf`` itself (its JSON and its images, read back with Blender's image reader):

* ``hook_up='GLTF'``: ``occlusionTexture`` with the ``texCoord`` of the baked UV map (a second
  "LMDP Lightmap" map: ``texCoord`` 1 and the mesh's ``TEXCOORD_1``), its PNG's red channel the
  lightmap's (linear, 8 bits, clipped at 1); the base colour stays the material's own, and the
  capture of the scene (albedo, emission) is the same as without the hook-up;
* ``hook_up='MULTIPLY'``: the lightmap becomes the ``baseColorTexture`` with the surface colour as
  ``baseColorFactor`` (a viewer lights it again);
* ``hook_up='PREVIEW'``: ``emissiveTexture`` over a black base colour, the PNG holding the linear
  values as bytes (a viewer decodes emissive textures as sRGB, so it shows them darker).
"""
import json
import os

import bpy
import numpy as np
import pytest

from helpers import select


def principled(obj, color=(0.8, 0.5, 0.2)):
    """A Principled BSDF material of ``color`` with no specular layer (a diffuse surface)."""
    mat = bpy.data.materials.new(obj.name + " Principled")
    tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*color, 1)
    bsdf.inputs["Metallic"].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    tree.links.new(bsdf.outputs[0], out.inputs["Surface"])
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    return mat


@pytest.fixture
def room(fresh_scene, tmp_path):
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    s = fresh_scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin = 'UNGUIDED', 16, 16, 2
    s.bake_content, s.multiply_color = 'DIRECT_INDIRECT', True
    s.output_dir = str(tmp_path / "bake")
    for name in ("Floor", "TallBox", "BackWall"):
        principled(bpy.data.objects[name])
    return fresh_scene


def export(tmp_path, objects):
    select(objects)
    path = str(tmp_path / "export" / "scene.gltf")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    assert bpy.ops.export_scene.gltf(filepath=path, export_format='GLTF_SEPARATE', use_selection=True) == {'FINISHED'}
    with open(path, encoding="utf-8") as fh:
        return json.load(fh), os.path.dirname(path)


def material(gltf, name):
    return next(m for m in gltf["materials"] if m["name"] == name)


def texture_pixels(gltf, folder, index):
    uri = gltf["images"][gltf["textures"][index]["source"]]["uri"]
    image = bpy.data.images.load(os.path.join(folder, uri))
    image.colorspace_settings.name = 'Non-Color'
    px = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(px)
    out = px.reshape(image.size[1], image.size[0], 4)
    bpy.data.images.remove(image)
    return out


def test_gltf_hook_up_is_exported_as_occlusion_on_texcoord_1(room, lmdp_ext, tmp_path):
    extract = lmdp_ext.sub("operators.adapters.extract")
    box = bpy.data.objects["TallBox"]
    uv = box.data.uv_layers.new(name="LMDP Lightmap")    # a copy of the UV map, baked on
    uv.active_render = True
    before = extract.extract_scene(bpy.context, [box])
    select([box])
    assert bpy.ops.lmdp.bake(hook_up='GLTF') == {'FINISHED'}
    ob = lmdp_ext.sub("operators.session").session_for(room).require("bake").object("TallBox")
    after = extract.extract_scene(bpy.context, [box])
    np.testing.assert_array_equal(after.triangle_albedo, before.triangle_albedo)
    np.testing.assert_array_equal(after.triangle_emission, before.triangle_emission)
    gltf, folder = export(tmp_path, [box])
    mat = material(gltf, "TallBox Principled")
    assert mat["occlusionTexture"]["texCoord"] == 1
    assert "baseColorTexture" not in mat["pbrMetallicRoughness"] and "emissiveTexture" not in mat
    assert mat["pbrMetallicRoughness"]["baseColorFactor"][:3] == pytest.approx([0.8, 0.5, 0.2])
    assert "TEXCOORD_1" in gltf["meshes"][0]["primitives"][0]["attributes"]
    red = texture_pixels(gltf, folder, mat["occlusionTexture"]["index"])[..., 0]
    expected = np.clip(ob.image[..., 0], 0, 1)
    assert np.abs(red - expected).max() <= 0.5 / 255 + 1e-6
    # removed again by Remove Bake Hook-up, nothing left in the material
    select([box])
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert not any(n.name.startswith("LMDP glTF") for n in box.data.materials[0].node_tree.nodes)


def test_what_the_exporter_keeps_of_multiply_and_preview(room, lmdp_ext, tmp_path):
    floor, wall = bpy.data.objects["Floor"], bpy.data.objects["BackWall"]
    select([floor])
    assert bpy.ops.lmdp.bake(hook_up='MULTIPLY') == {'FINISHED'}
    select([wall])
    assert bpy.ops.lmdp.bake(hook_up='PREVIEW') == {'FINISHED'}
    gltf, folder = export(tmp_path, [floor, wall])
    mult = material(gltf, "Floor Principled")["pbrMetallicRoughness"]
    assert "baseColorTexture" in mult and mult["baseColorFactor"][:3] == pytest.approx([0.8, 0.5, 0.2])
    preview = material(gltf, "BackWall_lmdp_preview")
    assert "emissiveTexture" in preview and preview["pbrMetallicRoughness"]["baseColorFactor"][:3] == [0, 0, 0]
    wall_image = lmdp_ext.sub("operators.session").session_for(room).require("bake").object("BackWall").image
    png = texture_pixels(gltf, folder, preview["emissiveTexture"]["index"])[..., :3]
    assert np.abs(png - np.clip(wall_image[..., :3], 0, 1)).max() <= 0.5 / 255 + 1e-6   # linear bytes


def test_a_room_imported_from_gltf_bakes_like_cycles_and_exports_its_lightmap(fresh_scene, lmdp_ext, tmp_path):
    """As a new user: the Cornell box (its walls as diffuse Principled BSDFs: the exporter drops
    a Diffuse BSDF, and glTF's default is then white metal) exported to .glb, a fresh file, the
    .glb imported with Blender's importer (its materials and emissive light, nothing of ours), the
    floor baked direct + indirect times colour, denoised, hooked up for glTF: the raw texels match
    Cycles' {'DIRECT', 'INDIRECT', 'COLOR'} bake within 2 % and 5 s.e., and the re-exported floor
    carries the lightmap as its occlusion texture."""
    from test_bake_content import agree, reference
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    for obj in [o for o in bpy.context.scene.objects if o.type == 'MESH' and o.name != "Light"]:
        principled(obj, tuple(obj.data.materials[0].diffuse_color[:3]))
    glb = str(tmp_path / "room.glb")
    assert bpy.ops.export_scene.gltf(filepath=glb, export_format='GLB') == {'FINISHED'}
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.import_scene.gltf(filepath=glb) == {'FINISHED'}
    scene = bpy.context.scene
    scene.cycles.sample_clamp_indirect = 0.0
    floor = bpy.data.objects["Floor"]
    assert floor.data.materials[0].node_tree.nodes.get("Principled BSDF") is not None
    s = scene.lmdp
    s.bake_mode, s.bake_content, s.multiply_color, s.denoise = 'UNGUIDED', 'DIRECT_INDIRECT', True, True
    s.light_paths, s.bake_margin = 'CUSTOM', 0
    select([o for o in scene.objects if o.type == 'MESH'], active=floor)
    demo = lmdp_ext.sub("operators.adapters.demo_scenes")
    refs = reference(lmdp_ext, demo, "Floor", ("DIRECT", "INDIRECT", "COLOR"))
    ob = lmdp_bake_selected(lmdp_ext, floor)
    agree(ob, refs, "imported glTF floor (D+I) x colour")
    gltf, _ = export(tmp_path, [floor])
    assert "occlusionTexture" in gltf["materials"][0]


def lmdp_bake_selected(lmdp_ext, obj):
    from test_bake_vs_cycles import BOUNCES
    s = bpy.context.scene.lmdp
    s.bake_resolution, s.bake_samples, s.max_bounces, s.seed = 16, 1024, BOUNCES, 11
    select([obj])
    assert bpy.ops.lmdp.bake(hook_up='GLTF') == {'FINISHED'}
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake").object(obj.name)


def test_gltf_emissive_hook_up_exports_the_baked_radiance(room, lmdp_ext, tmp_path):
    """GLTF_EMISSIVE: emissiveTexture over black with KHR_materials_emissive_strength S = the
    brightest texel; the PNG decoded as sRGB times S is the lightmap to 8 bits (the bytes are the
    sRGB encoding of value / S, ±1), and the capture of the scene does not change."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    gltf_lightmap = lmdp_ext.sub("operators.adapters.gltf_lightmap")
    wall = bpy.data.objects["BackWall"]
    before = extract.extract_scene(bpy.context, [wall])
    select([wall])
    assert bpy.ops.lmdp.bake(hook_up='GLTF_EMISSIVE') == {'FINISHED'}
    ob = lmdp_ext.sub("operators.session").session_for(room).require("bake").object("BackWall")
    after = extract.extract_scene(bpy.context, [wall])
    np.testing.assert_array_equal(after.triangle_emission, before.triangle_emission)
    gltf, folder = export(tmp_path, [wall])
    mat = material(gltf, "BackWall_lmdp_preview")
    S = float(ob.image[..., :3].max())
    assert S > 1
    assert mat["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] == pytest.approx(S, rel=1e-5)
    assert mat["pbrMetallicRoughness"]["baseColorFactor"][:3] == [0, 0, 0]
    png = texture_pixels(gltf, folder, mat["emissiveTexture"]["index"])[..., :3]
    expected = gltf_lightmap.srgb_encode(ob.image[..., :3] / S)
    assert np.abs(png - expected).max() <= 1.0 / 255 + 1e-6
    # a second bake refreshes the copy and the strength
    room.lmdp.seed = 5
    select([wall])
    assert bpy.ops.lmdp.bake(hook_up='GLTF_EMISSIVE') == {'FINISHED'}
    ob = lmdp_ext.sub("operators.session").session_for(room).require("bake").object("BackWall")
    copy = bpy.data.images["BackWall_lmdp_indirect_gltf"]
    px = np.empty(copy.size[0] * copy.size[1] * 4, np.float32)
    copy.pixels.foreach_get(px)
    S = float(ob.image[..., :3].max())
    assert np.abs(px.reshape(ob.image.shape)[..., :3] - gltf_lightmap.srgb_encode(ob.image[..., :3] / S)).max() \
        <= 0.5 / 255 + 1e-6
    emission = next(n for n in bpy.data.materials["BackWall_lmdp_preview"].node_tree.nodes if n.type == 'EMISSION')
    assert emission.inputs["Strength"].default_value == pytest.approx(S, rel=1e-6)
    # a Preview bake afterwards shows the float lightmap at strength 1 again
    select([wall])
    assert bpy.ops.lmdp.bake(hook_up='PREVIEW') == {'FINISHED'}
    nodes = bpy.data.materials["BackWall_lmdp_preview"].node_tree.nodes
    assert next(n for n in nodes if n.type == 'EMISSION').inputs["Strength"].default_value == 1.0
    assert nodes["LMDP Lightmap"].image.name == "BackWall_lmdp_indirect"
