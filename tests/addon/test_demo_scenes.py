"""Demo scenes in Blender (operators/adapters/demo_scenes.py, operators/ops/scenes.py) and the Cycles
conventions they rely on, measured with real Cycles bakes (docs/cycles_conventions.md).

Monte Carlo tolerances: every Cycles comparison bakes twice with different seeds; the RMS
per-texel standard error of the mean of the two is sigma = std(a - b) / 2 (see
assert_matches_monte_carlo); image means agree within 5 sigma / sqrt(n).
"""
import os
import tempfile

import bpy
import numpy as np
import pytest

from helpers import add_material, select


@pytest.fixture
def library(lmdp_ext):
    return lmdp_ext.sub("lmdp_addon.demo_geometry")


@pytest.fixture
def texels(lmdp_ext):
    return lmdp_ext.sub("lmdp_addon.bake.texels")


@pytest.fixture
def add_operator(lmdp_ext):
    """lmdp.add_demo_scene, registered by the add-on when ops_scenes is in MODULE_NAMES."""
    ops_scenes = lmdp_ext.sub("operators.ops.scenes")
    registered_here = not hasattr(bpy.types, "LMDP_OT_add_demo_scene")
    if registered_here:
        ops_scenes.register()
    yield ops_scenes
    if registered_here:
        ops_scenes.unregister()


def two_bakes(demo, obj, **kwargs):
    """Mean of two Cycles bakes with different seeds and the per-texel standard error."""
    a = demo.bake_cycles(bpy.context, obj, seed=1, **kwargs)
    b = demo.bake_cycles(bpy.context, obj, seed=2, **kwargs)
    mean = (a + b) / 2
    sigma = float(np.std(a[..., :3] - b[..., :3])) / 2 + 1e-7
    return mean, sigma


def assert_matches_monte_carlo(measured, expected, sigma):
    """A Cycles estimate equals ``expected`` within its noise.

    ``sigma`` is the RMS per-texel standard error (from two seeds): the texel errors must have an
    RMS of about sigma (< 1.5 sigma), their mean must be within 5 sigma / sqrt(n) of 0, and no
    texel may be off by more than 8 sigma (the noise differs between texels, so the largest
    error is not Gaussian in the global sigma; a 0.5 % model error is still > 8 sigma here).
    """
    err = np.asarray(measured, dtype=np.float64) - np.asarray(expected, dtype=np.float64)
    n = err.size
    assert np.sqrt(np.mean(err ** 2)) < 1.5 * sigma, f"RMS error {np.sqrt(np.mean(err ** 2)):.3g} vs sigma {sigma:.3g}"
    assert abs(err.mean()) < 5 * sigma / np.sqrt(n), f"mean error {err.mean():.3g} vs sigma {sigma:.3g}"
    assert np.abs(err).max() < 8 * sigma, f"max error {np.abs(err).max():.3g} vs sigma {sigma:.3g}"


def texel_points(texels, obj, resolution):
    """Texel positions (engine rasterisation) of a single-object demo mesh."""
    mesh = obj.data
    m = np.asarray(obj.matrix_world)
    v = np.array([m[:3, :3] @ x.co + m[:3, 3] for x in mesh.vertices])
    tris = np.array([t.vertices[:] for t in mesh.loop_triangles])
    uv = np.array([[mesh.uv_layers.active.data[l].uv[:] for l in t.loops] for t in mesh.loop_triangles])
    c = v[tris]
    n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    return texels.rasterize_texels(uv, c, n, resolution)


@pytest.mark.parametrize("kind", ["CORNELL_BOX", "NARROW_OPENING", "PLANE_UNDER_SKY",
                                  "PARALLEL_SQUARES", "HEAVY"])
def test_demo_scene_objects_materials_uvs_camera_and_settings(fresh_scene, demo, library, kind):
    parts = library.scene_parts(kind)
    carriers = demo.build_demo_scene(kind, bpy.context)
    assert [o.name for o in carriers] == [p.name for p in parts if not p.is_emitter]
    collection = bpy.data.collections[f"LMDP {demo.SCENE_LABELS[kind]}"]
    for part in parts:
        obj = bpy.data.objects[part.name]
        assert obj.users_collection[0] == collection
        mesh = obj.data
        assert len(mesh.polygons) == len(part.faces)
        assert mesh.uv_layers.active.name == "UVMap"
        uv = np.empty(len(mesh.loops) * 2, np.float32)
        mesh.uv_layers["UVMap"].data.foreach_get("uv", uv)
        np.testing.assert_allclose(uv.reshape(-1, 2), part.face_uv.reshape(-1, 2), atol=1e-7)
        tree = mesh.materials[0].node_tree
        shader = tree.get_output_node('CYCLES').inputs["Surface"].links[0].from_node
        if part.is_emitter:
            assert shader.type == 'EMISSION'
            radiance = np.array(shader.inputs["Color"].default_value[:3]) * shader.inputs["Strength"].default_value
            np.testing.assert_allclose(radiance, part.emission, rtol=1e-6)
        else:
            assert shader.type == 'BSDF_DIFFUSE'
            np.testing.assert_allclose(shader.inputs["Color"].default_value[:3], part.albedo, rtol=1e-6)
    scene = bpy.context.scene
    assert scene.camera is not None and scene.camera.type == 'CAMERA'
    assert scene.render.engine == 'CYCLES' and scene.cycles.device == 'CPU'
    assert scene.view_settings.view_transform == 'Standard'
    assert scene.cycles.samples == demo.RENDER_SAMPLES and not scene.cycles.use_adaptive_sampling
    background = scene.world.node_tree.get_output_node('CYCLES').inputs["Surface"].links[0].from_node
    world = np.array(background.inputs["Color"].default_value[:3]) * background.inputs["Strength"].default_value
    np.testing.assert_allclose(world, library.world_radiance(kind), rtol=1e-6)


def test_camera_looks_into_the_cornell_box(fresh_scene, demo):
    demo.build_demo_scene("CORNELL_BOX", bpy.context)
    cam = bpy.context.scene.camera
    forward = cam.matrix_world.to_3x3() @ __import__("mathutils").Vector((0, 0, -1))
    np.testing.assert_allclose(forward[:], (0, 1, 0), atol=1e-6)
    assert cam.location.y < -0.5 and 0.3 < cam.location.z < 0.7


def test_add_demo_scene_operator_selects_the_state_carriers(fresh_scene, add_operator, library):
    assert 'UNDO' in bpy.types.LMDP_OT_add_demo_scene.bl_options
    kinds = [item.identifier for item in
             bpy.ops.lmdp.add_demo_scene.get_rna_type().properties["kind"].enum_items]
    assert kinds == list(library.SCENE_KINDS)
    result = bpy.ops.lmdp.add_demo_scene(kind='NARROW_OPENING')
    assert result == {'FINISHED'}
    selected = sorted(o.name for o in bpy.context.selected_objects)
    assert selected == sorted(library.state_part_names("NARROW_OPENING"))
    assert bpy.context.view_layer.objects.active.name == library.state_part_names("NARROW_OPENING")[0]
    assert "Light" in bpy.data.objects and not bpy.data.objects["Light"].select_get()
    draw_functions = bpy.types.VIEW3D_MT_add._dyn_ui_initialize()
    assert add_operator.draw_add_menu in draw_functions


def test_cornell_box_render_is_neither_black_nor_blown_out(fresh_scene, demo):
    demo.build_demo_scene("CORNELL_BOX", bpy.context)
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = 48
    scene.cycles.samples = 16
    scene.render.image_settings.file_format = 'PNG'
    with tempfile.TemporaryDirectory() as tmp:
        scene.render.filepath = os.path.join(tmp, "cornell.png")
        bpy.ops.render.render(write_still=True)
        image = bpy.data.images.load(scene.render.filepath)
        px = np.empty(48 * 48 * image.channels, np.float32)
        image.pixels.foreach_get(px)
        bpy.data.images.remove(image)
    rgb = px.reshape(48, 48, -1)[..., :3]
    # Standard view transform: display values in [0, 1]. The walls are mid-tones, only the lamp
    # saturates, the left wall is red and the right wall green.
    assert 0.15 < rgb.mean() < 0.7
    assert (rgb.max(axis=-1) > 0.99).mean() < 0.05
    left, right = rgb[20:28, 2:5].mean(axis=(0, 1)), rgb[20:28, -5:-2].mean(axis=(0, 1))
    assert left[0] > 2 * left[1] and right[1] > 1.5 * right[0]


# -- Cycles conventions measured on the demo scenes -----------------------------------------------

def test_plane_under_sky_direct_bake_is_the_sky_radiance(fresh_scene, demo, library):
    demo.build_demo_scene("PLANE_UNDER_SKY", bpy.context)
    plane = bpy.data.objects["Plane"]
    direct, sigma = two_bakes(demo, plane, pass_filter=('DIRECT',), resolution=8, samples=64)
    indirect = demo.bake_cycles(bpy.context, plane, pass_filter=('INDIRECT',), resolution=8, samples=16)
    np.testing.assert_allclose(direct[..., :3], np.broadcast_to(library.SKY_RADIANCE, (8, 8, 3)), atol=5 * sigma + 1e-5)
    assert np.abs(indirect[..., :3]).max() == 0.0  # nothing else to bounce off
    colour = demo.bake_cycles(bpy.context, plane, pass_filter=('COLOR',), resolution=4, samples=1)
    np.testing.assert_allclose(colour[..., :3].reshape(-1, 3).mean(0), library.scene_parts("PLANE_UNDER_SKY")[0].albedo, atol=1e-6)


@pytest.mark.parametrize("flip", [False, True])
def test_emissive_mesh_is_two_sided_and_counts_as_direct_light(fresh_scene, demo, library, texels, flip):
    """PARALLEL_SQUARES: DIFFUSE DIRECT = L F at every texel, whichever side the emitter faces."""
    demo.build_demo_scene("PARALLEL_SQUARES", bpy.context)
    receiver, emitter = bpy.data.objects["Receiver"], bpy.data.objects["Emitter"]
    if flip:
        emitter.data.flip_normals()
    R = 12
    direct, sigma = two_bakes(demo, receiver, pass_filter=('DIRECT',), resolution=R, samples=256)
    indirect = demo.bake_cycles(bpy.context, receiver, pass_filter=('INDIRECT',), resolution=R, samples=16)
    ts = texel_points(texels, receiver, R)
    p = library.PARALLEL_SQUARES
    # Cycles averages each texel over its footprint (texels.sample_footprint): so does the reference.
    footprint = texels.sample_footprint(ts, 4000, np.random.default_rng(0))
    F = library.point_to_parallel_square_form_factor(p["emitter_side"], p["height"],
                                                     -footprint.position[..., :2]).mean(axis=1)
    expected = np.outer(F, p["radiance"])
    measured = direct[ts.row, ts.col, :3]
    assert_matches_monte_carlo(measured, expected, sigma)
    assert np.abs(indirect[..., :3]).max() == 0.0  # the emitter seen directly is DIRECT light


def test_indirect_bake_is_bounced_irradiance_over_pi_without_albedo(fresh_scene, demo, library):
    """A 1 m patch of albedo rho, 1 m above a tiny receiver, under a uniform sky of radiance L.

    The patch's underside sees the sky: radiance rho L. The receiver's INDIRECT bake must be
    rho L F (E_ind / pi, F = point-to-square form factor), its INDIRECT+COLOR bake 0.8 times that
    (the receiver's own albedo), its DIRECT bake L (1 - F).
    """
    L, rho = 1.5, 0.5
    world = bpy.data.worlds.new("Sky")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1, 1, 1, 1)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = L
    bpy.context.scene.world = world
    demo.configure_cycles(bpy.context.scene)
    bpy.ops.mesh.primitive_plane_add(size=0.01)
    receiver = bpy.context.object
    receiver.data.materials.append(add_material("Receiver", color=(0.8, 0.8, 0.8)))
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0, 0, 1), rotation=(np.pi, 0, 0))
    bpy.context.object.data.materials.append(add_material("Patch", color=(rho, rho, rho)))
    F = library.point_to_parallel_square_form_factor(1.0, 1.0)
    kw = dict(resolution=4, samples=512)
    indirect, s_i = two_bakes(demo, receiver, pass_filter=('INDIRECT',), **kw)
    coloured, s_c = two_bakes(demo, receiver, pass_filter=('INDIRECT', 'COLOR'), **kw)
    direct, s_d = two_bakes(demo, receiver, pass_filter=('DIRECT',), **kw)
    n = 16
    # The receiver is 1 cm wide: F varies by < 1e-4 over it; second bounces via the receiver
    # are below 1e-4 of the signal.
    assert indirect[..., 0].mean() == pytest.approx(rho * L * F, abs=5 * s_i / np.sqrt(n) + 2e-3 * rho * L * F)
    assert coloured[..., 0].mean() == pytest.approx(0.8 * indirect[..., 0].mean(), rel=1e-3, abs=5 * s_c / np.sqrt(n))
    assert direct[..., 0].mean() == pytest.approx(L * (1 - F), abs=5 * s_d / np.sqrt(n) + 1e-3)


def test_bake_cycles_restores_selection_active_nodes_and_settings(fresh_scene, demo):
    carriers = demo.build_demo_scene("CORNELL_BOX", bpy.context)
    floor, box = bpy.data.objects["Floor"], bpy.data.objects["TallBox"]
    tree = floor.data.materials[0].node_tree
    user_image_node = tree.nodes.new("ShaderNodeTexImage")
    tree.nodes.active = user_image_node
    select([box], active=box)
    scene = bpy.context.scene
    before = (scene.cycles.samples, scene.cycles.use_adaptive_sampling, scene.cycles.seed,
              len(bpy.data.images), len(tree.nodes), len(bpy.data.materials))
    demo.bake_cycles(bpy.context, floor, 'POSITION', resolution=8, samples=1)
    after = (scene.cycles.samples, scene.cycles.use_adaptive_sampling, scene.cycles.seed,
             len(bpy.data.images), len(tree.nodes), len(bpy.data.materials))
    assert before == after
    assert tree.nodes.active == user_image_node
    assert [o.name for o in bpy.context.selected_objects] == ["TallBox"]
    assert bpy.context.view_layer.objects.active == box
    # An object without material bakes through a scratch material that is removed afterwards.
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    bare = bpy.context.object
    colour = demo.bake_cycles(bpy.context, bare, pass_filter=('COLOR',), resolution=4, samples=1)
    np.testing.assert_allclose(colour[..., :3], 0.8, atol=1e-6)  # Cycles' default surface
    assert len(bare.data.materials) == 0 and len(bpy.data.materials) == before[-1]
