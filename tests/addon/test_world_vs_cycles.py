"""Worlds against Cycles' bake of the same texels (issue 19, item 2): a uniform world, an HDRI
(Blender's bundled ``city.exr``) turned by a Mapping node, a single bright pixel (the map's
orientation), an HDRI-lit room and a world tree only a render can read.

Everything is lit by the world alone. Both sides bake DIFFUSE / INDIRECT with clamping off and
8 bounces (``test_bake_vs_cycles.reference`` / ``lmdp_bake``: two Cycles seeds, the engine's
batch standard errors); the means must agree within 2 % and 5 standard errors of both.
"""
import os

import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import BOUNCES, K, assert_means_agree, compare, lmdp_bake, reference

RESOLUTION = 24


def bundled_hdri(name):
    path = os.path.join(bpy.utils.system_resource('DATAFILES', path="studiolights/world"), name)
    assert os.path.exists(path), f"Blender's bundled {name} is not in this bpy ({path})"
    return path


def cycles_scene(scene):
    scene.render.engine = 'CYCLES'
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.max_bounces = scene.cycles.diffuse_bounces = BOUNCES
    return scene


def diffuse(name, colour):
    """A Diffuse BSDF material (a Principled BSDF adds its specular layer in Cycles)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (*colour, 1.0)
    mat.node_tree.links.new(bsdf.outputs["BSDF"], nodes["Material Output"].inputs["Surface"])
    return mat


def plane(name, size, location, rotation=(0.0, 0.0, 0.0), colour=(0.8, 0.8, 0.8)):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location, rotation=rotation)
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(diffuse(name, colour))
    return obj


def courtyard():
    """A 2 m floor, a 1 m wall at x = -0.5 facing +x over y in [-1, 0] (reddish) and one at
    y = 0.6 facing -y (bluish): which parts of the floor they light depends on where the sky is
    bright."""
    floor = plane("Floor", 2.0, (0.0, 0.0, 0.0))
    plane("WallX", 1.0, (-0.5, -0.5, 0.5), rotation=(0.0, np.pi / 2, 0.0), colour=(0.8, 0.3, 0.2))
    plane("WallY", 1.0, (0.3, 0.6, 0.5), rotation=(np.pi / 2, 0.0, 0.0), colour=(0.2, 0.4, 0.8))
    return floor


def world_background(colour, strength=1.0):
    world = bpy.data.worlds.new("Sky")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*colour, 1.0)
    bg.inputs["Strength"].default_value = strength
    bpy.context.scene.world = world
    return world


def world_image(image, strength=1.0, rotation=None, interpolation='Linear'):
    """A world whose Background Color is an Environment Texture of ``image``; with
    ``rotation`` (Euler XYZ) through Texture Coordinate (Generated) -> Mapping (Point)."""
    world = world_background((0.0, 0.0, 0.0), strength)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = image
    tex.interpolation = interpolation
    links.new(tex.outputs["Color"], nodes["Background"].inputs["Color"])
    if rotation is not None:
        coords = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.inputs["Rotation"].default_value = rotation
        links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    return world


def check(lmdp_ext, demo, name, samples=512, ref_samples=1024, label="", resolution=RESOLUTION):
    refs = reference(lmdp_ext, demo, name, resolution, ref_samples)
    ob = lmdp_bake(lmdp_ext, name, "UNGUIDED", resolution, samples)
    ours, cyc, var_o, var_c = compare(ob, refs)
    n = len(ours)
    print(f"{label or name}: s.e. of the means: ours {np.sqrt(var_o.sum(axis=0)) / n / ours.mean(axis=0)}, "
          f"Cycles {np.sqrt(var_c.sum(axis=0)) / n / cyc.mean(axis=0)} (relative)")
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"{label or name}: ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}: "
          f"{np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} % (1 s.e.)")
    assert np.all(np.abs(rel) < 0.02), rel
    return ob, ours, cyc, var_o, var_c


def test_uniform_world_matches_cycles(fresh_scene, lmdp_ext, demo):
    cycles_scene(fresh_scene)
    courtyard()
    world_background((0.6, 0.7, 1.0), 1.5)
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert arrays.environment is None
    np.testing.assert_allclose(arrays.world_radiance, [0.9, 1.05, 1.5], rtol=1e-6)
    check(lmdp_ext, demo, "Floor", label="uniform world")


def test_single_bright_pixel_lights_the_side_cycles_lights(fresh_scene, lmdp_ext, demo):
    """One bright pixel of a 32 x 16 map, up and towards +x+y (azimuth 33.75°, elevation
    28°): the floor's quadrants next to the walls it lights must match Cycles', each within
    5 standard errors; a map read mirrored in u or v lights other walls (the test says by how
    much the quadrants would differ)."""
    cycles_scene(fresh_scene)
    courtyard()
    img = bpy.data.images.new("Dot", 32, 16, alpha=True, float_buffer=True)
    px = np.zeros((16, 32, 4), np.float32)
    px[..., 3] = 1.0
    px[11, 13, :3] = 400.0       # v = 11.5/16: elevation 28°; u = 13.5/32: azimuth 33.75°
    img.pixels.foreach_set(px.ravel())
    img.pack()
    world_image(img)
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert arrays.environment is not None
    ob, ours, cyc, var_o, var_c = check(lmdp_ext, demo, "Floor", label="bright pixel")
    ts = ob.texels
    quadrant = (ts.row >= RESOLUTION // 2) * 2 + (ts.col >= RESOLUTION // 2)
    for q in range(4):
        sel = quadrant == q
        diff = ours[sel].mean(axis=0) - cyc[sel].mean(axis=0)
        sigma = np.sqrt((var_o[sel].sum(axis=0) + var_c[sel].sum(axis=0))) / sel.sum()
        print(f"quadrant {q}: ours {ours[sel].mean(axis=0)} cycles {cyc[sel].mean(axis=0)}")
        assert np.all(np.abs(diff) <= K * sigma), (q, diff, sigma)


def test_rotated_hdri_matches_cycles(fresh_scene, lmdp_ext, demo):
    """city.exr turned 70° about z (and 10° about x) by a Mapping node: the rotation is read
    exactly, and the HDRI's sun lights the walls where Cycles' does."""
    cycles_scene(fresh_scene)
    courtyard()
    world_image(bpy.data.images.load(bundled_hdri("city.exr")), strength=0.5,
                rotation=(np.radians(10.0), 0.0, np.radians(70.0)))
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    env = arrays.environment
    assert env is not None and env.width == 1024 and env.height == 512
    assert not np.allclose(env.rotation, np.eye(3))
    check(lmdp_ext, demo, "Floor", label="city.exr rotated")


def room_with_opening():
    """A 3 x 3 x 2.4 m room (inward normals, UVs by Smart UV Project) with a 1.2 x 1 m window
    in its +x wall, a 0.6 m table-like block inside."""
    import bmesh
    mesh = bpy.data.meshes.new("Room")
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.scale(bm, vec=(3.0, 3.0, 2.4), verts=bm.verts)
    bmesh.ops.translate(bm, vec=(0.0, 0.0, 1.2), verts=bm.verts)
    bmesh.ops.reverse_faces(bm, faces=bm.faces)             # normals inward
    bm.to_mesh(mesh)
    bm.free()
    room = bpy.data.objects.new("Room", mesh)
    bpy.context.collection.objects.link(room)
    room.data.materials.append(diffuse("RoomWhite", (0.7, 0.7, 0.7)))
    # the window: a hole cut by a boolean, applied
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(1.5, 0.2, 1.3))
    cutter = bpy.context.active_object
    cutter.scale = (0.6, 1.2, 1.0)
    modifier = room.modifiers.new("Window", 'BOOLEAN')
    modifier.object = cutter
    modifier.operation = 'DIFFERENCE'
    select([room])
    bpy.context.view_layer.objects.active = room
    bpy.ops.object.modifier_apply(modifier=modifier.name)
    bpy.data.objects.remove(cutter)
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='SELECT')
    bpy.ops.uv.smart_project(island_margin=0.05)
    bpy.ops.object.mode_set(mode='OBJECT')
    return room


def test_hdri_lit_room_matches_cycles(fresh_scene, lmdp_ext, demo):
    """A room lit through a window by city.exr, its sun (21 % of the map's light) turned to shine
    in: walls, floor and ceiling baked as one object (32 px, 4096 samples on both sides: a
    standard error of about 0.6 %)."""
    cycles_scene(fresh_scene)
    room_with_opening()
    world_image(bpy.data.images.load(bundled_hdri("city.exr")), strength=0.5,
                rotation=(0.0, 0.0, np.radians(-36.0)))   # the sun (azimuth -36°, 48° up) towards +x
    check(lmdp_ext, demo, "Room", samples=4096, ref_samples=4096, label="HDRI-lit room", resolution=32)


def test_world_tree_rendered_into_a_map(fresh_scene, lmdp_ext, demo):
    """A Gradient Texture world (bright towards azimuth 50°): not readable node by node, so it is rendered
    into an equirectangular map once, with a warning naming the world and the node; the bake then
    matches Cycles'."""
    cycles_scene(fresh_scene)
    courtyard()
    world = world_background((0.0, 0.0, 0.0), 2.0)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    coords = nodes.new("ShaderNodeTexCoord")
    turn = nodes.new("ShaderNodeMapping")                 # bright towards azimuth 50°: not symmetric in y
    turn.inputs["Rotation"].default_value = (0.0, 0.0, np.radians(-50.0))
    gradient = nodes.new("ShaderNodeTexGradient")
    gradient.gradient_type = 'LINEAR'
    gradient.name = "Glow"
    ramp = nodes.new("ShaderNodeMix")
    ramp.data_type = 'RGBA'
    ramp.inputs["A"].default_value = (0.05, 0.05, 0.1, 1.0)
    ramp.inputs["B"].default_value = (1.0, 0.8, 0.5, 1.0)
    links.new(coords.outputs["Generated"], turn.inputs["Vector"])
    links.new(turn.outputs["Vector"], gradient.inputs["Vector"])
    links.new(gradient.outputs["Fac"], ramp.inputs["Factor"])
    links.new(ramp.outputs["Result"], nodes["Background"].inputs["Color"])
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert arrays.environment is not None
    assert any("World 'Sky'" in w and "renders the world" in w for w in arrays.warnings), arrays.warnings
    assert len(bpy.data.scenes) == 1 and not any(o.type == 'CAMERA' for o in bpy.data.objects)
    check(lmdp_ext, demo, "Floor", label="rendered world")


def test_world_render_has_the_environment_texture_orientation(fresh_scene, lmdp_ext):
    """The fallback's equirectangular render of a world that *can* be read directly (city.exr)
    reproduces the directly read map: same sun pixel (within one pixel of the 64 x 32 block
    means) and the same block means (correlation > 0.99)."""
    capture = lmdp_ext.sub("operators.adapters.world_capture")
    world = world_image(bpy.data.images.load(bundled_hdri("city.exr")))
    direct = capture.WorldReader([]).capture(world)[1]
    rendered = capture.render_world(world, 256, 128, 16)
    assert len(bpy.data.scenes) == 1 and len(bpy.data.cameras) == 0

    def blocks(img):
        h, w = img.shape[:2]
        return img.reshape(32, h // 32, 64, w // 64, 3).mean(axis=(1, 3)).max(axis=2)
    a, b = blocks(direct.radiance), blocks(rendered)
    assert np.corrcoef(np.log1p(a).ravel(), np.log1p(b).ravel())[0, 1] > 0.99
    ia, ib = np.unravel_index(a.argmax(), a.shape), np.unravel_index(b.argmax(), b.shape)
    assert abs(ia[0] - ib[0]) <= 1 and abs(ia[1] - ib[1]) <= 1, (ia, ib)


@pytest.mark.parametrize("mode", ["GUIDED", "FINAL_GATHER"])
def test_hdri_lit_room_solved_modes(fresh_scene, lmdp_ext, demo, mode):
    """The HDRI-lit room baked with the solution (PHYSICAL, directional world terminals): GUIDED
    is unbiased (within 2 % and 5 standard errors of Cycles), FINAL_GATHER within its
    discretisation bias."""
    cycles_scene(fresh_scene)
    room = room_with_opening()
    world_image(bpy.data.images.load(bundled_hdri("city.exr")), strength=0.5,
                rotation=(0.0, 0.0, np.radians(-36.0)))
    s = fresh_scene.lmdp
    s.point_count = 2048
    s.cost_mode = 'PHYSICAL'
    select([room])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    refs = reference(lmdp_ext, demo, "Room", 32, 4096)
    ob = lmdp_bake(lmdp_ext, "Room", mode, 32, 1024)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel = ours.mean(axis=0) / cyc.mean(axis=0) - 1.0
    sigma = np.sqrt(var_o.sum(axis=0) + var_c.sum(axis=0)) / len(ours) / cyc.mean(axis=0)
    print(f"HDRI-lit room {mode}: {np.round(rel * 100, 2)} % ± {np.round(sigma * 100, 2)} % (1 s.e.)")
    if mode == "GUIDED":
        assert_means_agree(ours, cyc, var_o, var_c)
        assert np.all(np.abs(rel) < 0.02), rel
    else:
        assert np.all(np.abs(rel) < 0.05), rel


def test_warping_mapping_matches_cycles(fresh_scene, lmdp_ext, demo):
    """city.exr through a Mapping that squashes directions (scale z 2, turned 40° about z): not
    a rotation, so the capture evaluates it for every direction of a table (with a warning);
    the bake still matches Cycles'."""
    cycles_scene(fresh_scene)
    courtyard()
    world = world_image(bpy.data.images.load(bundled_hdri("city.exr")), strength=0.5,
                        rotation=(0.0, 0.0, np.radians(40.0)))
    world.node_tree.nodes["Mapping"].inputs["Scale"].default_value = (1.0, 1.0, 2.0)
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert any("Mapping" in w and "every direction" in w for w in arrays.warnings), arrays.warnings
    check(lmdp_ext, demo, "Floor", label="city.exr warped")


def test_sky_texture_world_matches_cycles(fresh_scene, lmdp_ext, demo):
    """A physical Sky Texture (multiple scattering) (its sun disc 35° up, towards -x+y) is rendered into the map: the
    sun disc's light is kept by the render's box filter, and the bake matches Cycles'."""
    cycles_scene(fresh_scene)
    courtyard()
    world = world_background((0.0, 0.0, 0.0), 0.2)
    nodes, links = world.node_tree.nodes, world.node_tree.links
    sky = nodes.new("ShaderNodeTexSky")
    sky.sky_type = 'MULTIPLE_SCATTERING'
    sky.sun_elevation = np.radians(35.0)
    sky.sun_rotation = np.radians(130.0)
    links.new(sky.outputs["Color"], nodes["Background"].inputs["Color"])
    arrays = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert arrays.environment is not None
    assert any("Sky Texture" in w and "renders the world" in w for w in arrays.warnings), arrays.warnings
    check(lmdp_ext, demo, "Floor", label="sky texture")
