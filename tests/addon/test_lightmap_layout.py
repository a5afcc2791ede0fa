"""Lightmap sizes and atlases (issue 21, items 2 and 3).

* Texel density: each object's side R = density x sqrt(world area / UV area), rounded up
  (optionally to a power of two), clamped; reported in bake_stats.json and the image size.
* Atlas: three cubes packed together into "LMDP Lightmap" share one image without overlap, and
  each cube's texels in it are exactly its per-object bake on the same map (same seed, same
  order); a material the cubes share is hooked up through the atlas, and without the atlas it is
  left alone with a warning that names it and its users.
"""
import json

import bpy
import numpy as np
import pytest

from helpers import add_material, select

LIGHTMAP = "LMDP Lightmap"


def density_scene():
    """Floor: 2 x 2 m plane, UVs the unit square (R = 2 d); Box: 0.25 m cube, Blender's default
    cube UVs (6 squares of 1/16: UV area 0.375, world area 0.375 m², R = d); an emitter."""
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    floor = bpy.context.object
    floor.name = "Floor"
    floor.data.materials.append(add_material("White"))
    bpy.ops.mesh.primitive_cube_add(size=0.25, location=(0.0, 0.0, 0.5))
    box = bpy.context.object
    box.name = "Box"
    box.data.materials.append(add_material("Red", color=(0.8, 0.1, 0.1)))
    bpy.ops.mesh.primitive_plane_add(size=0.5, location=(0.0, 0.0, 1.9), rotation=(np.pi, 0.0, 0.0))
    lamp = bpy.context.object
    lamp.name = "Lamp"
    lamp.data.materials.append(add_material("Light", emission=10.0))
    return floor, box


def bake(lmdp_ext, objects, **settings):
    s = bpy.context.scene.lmdp
    s.bake_mode = "UNGUIDED"
    s.bake_samples = 2
    s.bake_margin = 1
    s.light_paths = 'CUSTOM'
    s.max_bounces = 2
    s.seed = 3
    hook_up = settings.pop("hook_up", 'NONE')
    for key, value in settings.items():
        setattr(s, key, value)
    select(objects)
    assert bpy.ops.lmdp.bake(hook_up=hook_up) == {'FINISHED'}
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake")


@pytest.mark.parametrize("settings, sizes", [
    (dict(power_of_two=False, min_resolution=1, max_resolution=1024), {"Floor": 40, "Box": 20}),
    (dict(power_of_two=True, min_resolution=1, max_resolution=1024), {"Floor": 64, "Box": 32}),
    (dict(power_of_two=False, min_resolution=24, max_resolution=36), {"Floor": 36, "Box": 24}),
], ids=["exact", "power_of_two", "clamped"])
def test_texel_density_gives_each_object_its_size(fresh_scene, lmdp_ext, tmp_path, settings, sizes):
    floor, box = density_scene()
    result = bake(lmdp_ext, [floor, box], resolution_mode='DENSITY', texel_density=20.0,
                  output_dir=str(tmp_path), **settings)
    stats = json.loads((tmp_path / "bake_stats.json").read_text())
    for name, R in sizes.items():
        assert result.object(name).resolution == R
        assert stats["objects"][name]["resolution"] == R
        image = bpy.data.images[f"{name}_lmdp_indirect"]
        assert tuple(image.size) == (R, R)
    assert stats["settings"]["resolution_mode"] == "DENSITY"


def test_texel_density_of_an_atlas_sums_the_areas(fresh_scene, lmdp_ext):
    """One side for the atlas: density x sqrt(sum of world areas / sum of UV areas) of its
    objects' jointly packed "LMDP Lightmap"."""
    cubes = atlas_cubes()
    result = bake(lmdp_ext, cubes, resolution_mode='DENSITY', texel_density=100.0, power_of_two=False,
                  min_resolution=1, max_resolution=4096, atlas=True)
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, cubes, uv_maps={o.name: LIGHTMAP for o in cubes})
    world = uv = 0.0
    for obj in cubes:
        own = arrays.triangle_object == arrays.object_names.index(obj.name)
        world += 6 * 0.14 ** 2 / 12 * np.count_nonzero(own)          # 12 triangles per cube
        t = arrays.triangle_uv[own].astype(np.float64)
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        uv += 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    R = int(np.ceil(100.0 * np.sqrt(world / uv)))
    assert {o.resolution for o in result.objects} == {R}
    assert result.atlases[0].resolution == R


def test_fixed_resolution_stays_the_default(fresh_scene, lmdp_ext):
    floor, box = density_scene()
    result = bake(lmdp_ext, [floor, box], bake_resolution=24)
    assert [o.resolution for o in result.objects] == [24, 24]


def test_bad_density_settings_are_refused(fresh_scene, lmdp_ext):
    floor, _ = density_scene()
    s = fresh_scene.lmdp
    s.resolution_mode = 'DENSITY'
    s.min_resolution, s.max_resolution = 64, 32
    s.bake_mode = "UNGUIDED"
    select([floor])
    with pytest.raises(RuntimeError, match=r"Min / Max Resolution"):
        bpy.ops.lmdp.bake()


# ---- atlas ---------------------------------------------------------------------------------------

def atlas_cubes():
    """Three cubes in the Cornell box, each with Blender's default cube UVs (all three overlap
    in a shared image); Left and Middle share one material, Right has its own."""
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    shared = add_material("Shared grey", color=(0.6, 0.6, 0.6))
    own = add_material("Own grey", color=(0.5, 0.5, 0.5))
    cubes = []
    for name, x, mat in (("Left", -0.28, shared), ("Middle", 0.0, shared), ("Right", 0.28, own)):
        bpy.ops.mesh.primitive_cube_add(size=0.14, location=(x, -0.3, 0.78))
        obj = bpy.context.active_object
        obj.name = name
        obj.data.materials.append(mat)
        cubes.append(obj)
    return cubes


def test_atlas_packs_three_objects_without_overlap_and_matches_per_object_bakes(fresh_scene, lmdp_ext, tmp_path):
    cubes = atlas_cubes()
    R = 32
    atlas = bake(lmdp_ext, cubes, bake_resolution=R, bake_samples=8, max_bounces=3, atlas=True,
                 output_dir=str(tmp_path))
    stats = json.loads((tmp_path / "bake_stats.json").read_text())
    assert stats["atlases"]["LMDP Atlas"]["file"] == "LMDP Atlas_lmdp_indirect.exr"
    assert sorted(stats["atlases"]["LMDP Atlas"]["objects"]) == ["Left", "Middle", "Right"]
    assert {stats["objects"][o.name]["file"] for o in cubes} == {"LMDP Atlas_lmdp_indirect.exr"}
    assert (tmp_path / "LMDP Atlas_lmdp_indirect.exr").is_file()
    assert not any((tmp_path / f"{o.name}_lmdp_indirect.exr").exists() for o in cubes)
    assert [a.name for a in atlas.atlases] == ["LMDP Atlas"]
    image = atlas.atlases[0].image
    covered = np.zeros((R, R), int)
    for ob in atlas.objects:
        assert ob.atlas == "LMDP Atlas" and ob.image is image
        covered[ob.texels.row, ob.texels.col] += 1
        # every object's texels hold its own values in the shared image (no margin over them)
        np.testing.assert_array_equal(image[ob.texels.row, ob.texels.col, :3], ob.value)
    assert covered.max() == 1, "two objects share texels of the atlas"
    assert (covered > 0).sum() >= 0.2 * R * R
    assert "LMDP Atlas_lmdp_indirect" in bpy.data.images
    assert not any(f"{o.name}_lmdp_indirect" in bpy.data.images for o in cubes)
    # the same objects baked one by one on the same (now existing) map, in the same order
    separate = bake(lmdp_ext, cubes, bake_resolution=R, bake_samples=8, max_bounces=3, atlas=False, output_dir="")
    for ob in atlas.objects:
        one = separate.object(ob.name)
        assert not one.atlas
        np.testing.assert_array_equal(one.texels.flat_index, ob.texels.flat_index)
        np.testing.assert_array_equal(one.value, ob.value)


def test_shared_material_is_hooked_up_through_the_atlas(fresh_scene, lmdp_ext):
    cubes = atlas_cubes()
    shared = bpy.data.materials["Shared grey"]
    result = bake(lmdp_ext, cubes, bake_resolution=24, atlas=True, hook_up='MULTIPLY')
    nodes = shared.node_tree.nodes
    assert nodes["LMDP Lightmap"].image == bpy.data.images["LMDP Atlas_lmdp_indirect"]
    assert nodes["LMDP Lightmap UV"].uv_map == LIGHTMAP        # each cube's own "LMDP Lightmap"
    assert nodes["LMDP Lightmap"].inputs["Vector"].links[0].from_node == nodes["LMDP Lightmap UV"]
    assert not any("Shared grey" in w for w in result.warnings)
    for obj in cubes:   # the render UV map is still the user's
        assert [l.name for l in obj.data.uv_layers if l.active_render] == ["UVMap"]


def test_shared_material_without_atlas_is_named_with_its_users(fresh_scene, lmdp_ext):
    """Each cube has its own image: the shared material cannot show both, so it is left alone;
    one warning names it and its users; the unshared material is hooked up."""
    cubes = atlas_cubes()
    result = bake(lmdp_ext, cubes, bake_resolution=24)
    materials = lmdp_ext.sub("operators.adapters.materials")
    images = {o.name: bpy.data.images[f"{o.name}_lmdp_indirect"] for o in cubes}
    warnings = materials.hook_up([(o, images[o.name]) for o in cubes], 'MULTIPLY',
                                 {o.name: LIGHTMAP for o in cubes})
    assert "LMDP Lightmap Multiply" not in bpy.data.materials["Shared grey"].node_tree.nodes
    assert "LMDP Lightmap Multiply" in bpy.data.materials["Own grey"].node_tree.nodes
    shared = [w for w in warnings if "Shared grey" in w]
    assert len(shared) == 1 and "Left" in shared[0] and "Middle" in shared[0], warnings
    assert result.objects


def test_warnings_beyond_the_limit_are_named(lmdp_ext):
    """The operator's report names every warning (the old one ended in "... and N more warnings")."""
    common = lmdp_ext.sub("operators.common")

    class Reports:
        def __init__(self):
            self.lines = []

        def report(self, kind, text):
            self.lines.append(text)

    op = Reports()
    common.report_warnings(op, [f"warning {k}" for k in range(8)])
    text = " ".join(op.lines)
    assert all(f"warning {k}" in text for k in range(8)), op.lines


def test_an_atlas_of_objects_sharing_a_mesh_is_refused_by_name(fresh_scene, lmdp_ext):
    cubes = atlas_cubes()
    twin = cubes[0].copy()                  # same mesh data
    twin.name = "Twin"
    twin.location.x += 0.1
    bpy.context.collection.objects.link(twin)
    s = fresh_scene.lmdp
    s.bake_mode, s.atlas = "UNGUIDED", True
    select([cubes[0], twin])
    with pytest.raises(RuntimeError, match="Left, Twin share one mesh"):
        bpy.ops.lmdp.bake()
    assert cubes[0].data.uv_layers.get(LIGHTMAP) is None
