"""RESIDUAL on geometry nobody here made: the glTF sample "Suzanne" (02_suzanne.gltf of the
glTF-Blender-IO test files, imported with ``bpy.ops.import_scene.gltf``), given a plain grey
Diffuse BSDF and set on the Cornell box's floor, baked by lmdp.bake in RESIDUAL mode (which
samples, builds and solves the scene itself) and by Cycles (DIFFUSE / INDIRECT, clamping off, 8
bounces on both sides, two seeds), compared as in ``test_bake_vs_cycles``: the mean within 2 %
and within 5 standard errors of both estimates. Skipped where the glTF file is not present."""
import os

import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import assert_means_agree, build, compare, lmdp_bake, reference

SUZANNE = os.environ.get("LMDP_GLTF_SUZANNE", "/work/fp/gltf/02_suzanne/02_suzanne.gltf")
RESOLUTION = 32


def import_suzanne():
    """The glTF's mesh, 0.18 m tall on the floor, with a grey Diffuse BSDF (the engine models
    no glossy lobes or textures of its own: the comparison is about light transport)."""
    before = set(bpy.data.objects)
    assert bpy.ops.import_scene.gltf(filepath=SUZANNE) == {'FINISHED'}
    meshes = [o for o in set(bpy.data.objects) - before if o.type == 'MESH']
    for o in set(bpy.data.objects) - before:
        if o.type != 'MESH':
            bpy.data.objects.remove(o)
    obj = meshes[0]
    obj.parent = None
    obj.name = "Suzanne"
    obj.rotation_euler = (np.radians(90.0), 0.0, np.radians(20.0))   # glTF is y-up
    obj.scale = (0.12, 0.12, 0.12)
    obj.location = (-0.12, -0.12, 0.13)
    material = bpy.data.materials.new("SuzanneGrey")
    if material.node_tree is None:     # Blender before 5: materials get nodes on request
        material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.clear()
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (0.6, 0.6, 0.6, 1.0)
    output = nodes.new("ShaderNodeOutputMaterial")
    material.node_tree.links.new(diffuse.outputs["BSDF"], output.inputs["Surface"])
    obj.data.materials.clear()
    obj.data.materials.append(material)
    select([obj])
    bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
    return obj


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(SUZANNE), reason=f"no glTF sample at {SUZANNE}")
def test_residual_on_an_imported_gltf_matches_cycles(fresh_scene, lmdp_ext, demo):
    build("CORNELL_BOX", lmdp_ext)
    import_suzanne()
    refs = reference(lmdp_ext, demo, "Suzanne", RESOLUTION, 2048)
    ob = lmdp_bake(lmdp_ext, "Suzanne", "RESIDUAL", RESOLUTION, 2048)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"RESIDUAL vs Cycles, glTF Suzanne ({len(ours)} texels): {np.round(100 * rel, 2)} % "
          f"± {np.round(100 * rel_sigma, 2)} % (1 s.e.)")
    assert np.all(np.abs(rel) < 0.02), rel
