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
    mat = bpy.data.materials.new(obj.name + " Principled")
    tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*color, 1)
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
