"""Showing the solution in Blender: z as colour attributes, the LMDP Display modifier, policy
arrows, the probe, the shading presets, and what happens to the user's data."""
import bpy
import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree

from helpers import select

ATTRIBUTES = {"lmdp_z", "lmdp_z_color", "lmdp_z_rgb", "lmdp_quantity", "lmdp_log10_z"}


@pytest.fixture
def cornell(fresh_scene):
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    props = fresh_scene.lmdp
    props.point_count = 600
    props.rays_per_stratum = 2
    return fresh_scene


@pytest.fixture
def solved(cornell):
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    return cornell


def session(lmdp_ext, scene=None):
    return lmdp_ext.sub("operators.session").session_for(scene or bpy.context.scene)


def point_values(mesh, name):
    attribute = mesh.attributes[name]
    n = len(attribute.data)
    if attribute.data_type == 'FLOAT_COLOR':
        out = np.empty(4 * n, np.float32)
        attribute.data.foreach_get("color", out)
        return out.reshape(n, 4)
    out = np.empty(n, np.float32)
    attribute.data.foreach_get("value", out)
    return out


def evaluated(obj, name):
    """(world positions, values, domain) of attribute ``name`` on the evaluated mesh of ``obj``."""
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    values = point_values(mesh, name)
    co = np.empty(3 * len(mesh.vertices), np.float32)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3) @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
    domain = mesh.attributes[name].domain
    if domain == 'CORNER':
        loops = np.empty(len(mesh.loops), np.int32)
        mesh.loops.foreach_get("vertex_index", loops)
        co = co[loops]
    return co, values, domain


def state_values(lmdp_ext, name):
    """The object's states that colour it (not the buried ones under the boxes): positions, z
    (luminance), spacing."""
    s = session(lmdp_ext)
    states, solution = s.require("states"), s.require("solution")
    own = states.point_object == s.require("scene").object_names.index(name)
    targets = s.require("dynamics").locator.targets      # None when nothing is buried
    if targets is not None:
        own &= targets
    luminance = lmdp_ext.sub("lmdp_addon.scene_arrays").luminance
    return states.points[own], luminance(solution.z[own]), float(np.median(np.sqrt(states.point_area[own])))


# -- desirability ---------------------------------------------------------------------------------------

def test_show_before_solve_is_refused_and_changes_nothing(cornell, lmdp_ext):
    floor = bpy.data.objects["Floor"]
    with pytest.raises(RuntimeError, match="Solve first"):
        bpy.ops.lmdp.show_desirability()
    assert not ATTRIBUTES & {a.name for a in floor.data.attributes}
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    with pytest.raises(RuntimeError, match="Solve first"):
        bpy.ops.lmdp.show_policy()
    with pytest.raises(RuntimeError, match="Solve first"):
        bpy.ops.lmdp.probe_policy()
    assert not session(lmdp_ext).has("display") and not session(lmdp_ext).has("policy")


def test_physical_mode_writes_z_rgb_luminance_and_colours(solved, lmdp_ext):
    colormap = lmdp_ext.sub("lmdp_addon.display.colormap")
    vf = lmdp_ext.sub("lmdp_addon.display.vertex_field")
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    record = session(lmdp_ext).require("display")
    s = session(lmdp_ext)
    states = s.require("states")
    for name in ("Floor", "TallBox", "BackWall"):
        obj = bpy.data.objects[name]
        mesh = obj.data
        assert ATTRIBUTES <= {a.name for a in mesh.attributes}
        assert all(mesh.attributes[a].domain == 'POINT' for a in ATTRIBUTES)
        assert mesh.color_attributes.active_color_name == "lmdp_z_color"
        assert mesh.color_attributes.default_color_name == "lmdp_z_color"
        z, rgb, color = point_values(mesh, "lmdp_z"), point_values(mesh, "lmdp_z_rgb"), point_values(mesh, "lmdp_z_color")
        assert np.allclose(z, rgb[:, :3] @ [0.2126, 0.7152, 0.0722], rtol=1e-5)     # Rec.709 luminance
        assert np.allclose(point_values(mesh, "lmdp_quantity"), z)
        expected = colormap.colormap_linear(record.scale.position(z), "VIRIDIS")
        assert np.allclose(color, expected, atol=2e-3)
        # The values are the engine's interpolation of the states of this object only.
        index = s.require("scene").object_names.index(name)
        points = np.array([obj.matrix_world @ v.co for v in mesh.vertices])
        normals = np.array([(obj.matrix_world.to_3x3().inverted().transposed() @ v.normal).normalized()
                            for v in mesh.vertices])
        w = vf.interpolation_weights(points, normals, np.full(len(points), index), states.points, states.normals,
                                     states.point_object, vf.state_spacing(states.point_area))
        assert np.all(states.point_object[w.matrix.indices] == index)
        reference = vf.interpolate(w, s.require("solution").z)
        assert np.allclose(rgb[:, :3], reference, rtol=1e-4, atol=1e-7)
    assert record.quantity == "Z" and record.scale.log and "radiance" in record.scale.label
    assert set(record.objects) == {o.name for o in bpy.context.selected_objects}
    assert bpy.data.objects["Floor"].get("lmdp_display") == 1.0


def test_thesis_mode_and_quantities(solved, lmdp_ext):
    floor = bpy.data.objects["Floor"].data
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert "lmdp_z_rgb" in floor.attributes
    solved.lmdp.cost_mode = 'THESIS'
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    lam = session(lmdp_ext).require("solution").lambda_
    solved.lmdp.display_quantity = 'COST_TO_GO'
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert "lmdp_z_rgb" not in floor.attributes          # the add-on's own stale attribute is gone
    log10_z, J = point_values(floor, "lmdp_log10_z").astype(float), point_values(floor, "lmdp_quantity")
    # J and log z are interpolated with the same weights, and J is linear in log z.
    assert np.allclose(J, -np.log(10.0) * log10_z / lam, rtol=1e-4)
    # With λ ~ 100, z itself is far below float32's range: lmdp_z holds 0, lmdp_log10_z the truth.
    assert lam > 20 and np.all(point_values(floor, "lmdp_z") == 0.0) and np.all(log10_z < -40)
    record = session(lmdp_ext).require("display")
    assert record.quantity == "COST_TO_GO" and not record.scale.log
    solved.lmdp.display_quantity = 'RESIDUAL'
    solved.lmdp.display_colormap = 'INFERNO'
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    residual = point_values(floor, "lmdp_quantity")
    assert np.all(residual >= 1e-16) and np.all(residual < 1e-3)
    record = session(lmdp_ext).require("display")
    assert record.scale.log and record.colormap == "INFERNO"


def test_subdivided_display_is_faithful_on_the_cornell_floor(solved, lmdp_ext):
    """The floor is one quad (4 vertices) carrying ~90 states. With Subdivide Coarse Meshes, the
    colours a renderer interpolates between the evaluated mesh's corners agree with the z of the
    states around each point; with the 4 vertices alone they cannot."""
    floor = bpy.data.objects["Floor"]
    points, z, spacing = state_values(lmdp_ext, "Floor")
    tree = cKDTree(points)
    s = session(lmdp_ext)
    states = s.require("states")
    targets = s.require("dynamics").locator.targets
    assert targets is not None                       # the floor under the boxes is buried
    buried = (states.point_object == s.require("scene").object_names.index("Floor")) & ~targets
    under = cKDTree(states.points[buried])

    def agreement(positions, shown, radius):
        """Over the positions with no buried state (under the boxes: they colour nothing, so the
        field there comes from one side) within ``radius`` spacings: the share shown within the
        range of the states within ``radius``, and the median relative deviation from their mean."""
        d, i = tree.query(positions, k=40)
        seen = (d[:, 0] <= radius * spacing) & (under.query(positions)[0] > radius * spacing)
        near = np.where(d[seen] <= radius * spacing, z[i[seen]], np.nan)
        lo, hi, mean = np.nanmin(near, 1), np.nanmax(near, 1), np.nanmean(near, 1)
        inside = (shown[seen] >= lo * (1 - 1e-4)) & (shown[seen] <= hi * (1 + 1e-4))
        assert seen.sum() > 1000
        return inside.mean(), np.median(np.abs(shown[seen] - mean) / mean)

    solved.lmdp.display_subdivide = True
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert [m.name for m in floor.modifiers] == ["LMDP Display"]
    assert len(floor.data.vertices) == 4                    # the user's mesh is unchanged
    positions, shown, domain = evaluated(floor, "lmdp_z")
    assert domain == 'CORNER' and len(positions) >= 16 * 16 * 4
    inside, median = agreement(positions, shown, 2.5)
    assert inside > 0.999
    inside, median = agreement(positions, shown, 1.5)
    assert inside > 0.95 and median < 0.10
    color_positions, colors, _ = evaluated(floor, "lmdp_z_color")
    assert np.allclose(colors[:, 3], 1.0) and len(colors) == len(positions)

    solved.lmdp.display_subdivide = False
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert not floor.modifiers                               # the add-on's modifier is removed
    corners, values, domain = evaluated(floor, "lmdp_z")
    assert domain == 'POINT' and len(corners) == 4
    coarse = LinearNDInterpolator(corners[:, :2], values)(positions[:, :2])
    inside, median = agreement(positions, coarse, 1.5)
    assert inside < 0.8 and median > 0.2
    assert "Floor" in session(lmdp_ext).require("display").coarse


def test_dense_mesh_gets_no_modifier_and_thin_walls_do_not_bleed(fresh_scene, lmdp_ext):
    """A finely subdivided 2 cm thick slab under a light: each face shows its own side."""
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0), scale=(1.0, 1.0, 0.02))
    slab = bpy.context.object
    slab.name = "Slab"
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=24)
    bpy.ops.object.mode_set(mode='OBJECT')
    bpy.ops.mesh.primitive_plane_add(size=0.5, location=(0, 0, 1.0), rotation=(3.14159265, 0, 0))
    lamp = bpy.context.object
    from helpers import add_material
    lamp.data.materials.append(add_material("Lamp", emission=20.0))
    select([slab])
    fresh_scene.lmdp.point_count = 300            # states ~8 cm apart, edges 4 cm: dense enough
    fresh_scene.lmdp.rays_per_stratum = 2
    fresh_scene.lmdp.display_subdivide = True
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert not slab.modifiers                                # fine enough already
    mesh = slab.data
    z = point_values(mesh, "lmdp_z")
    co = np.array([v.co for v in mesh.vertices])
    top, bottom = co[:, 2] > 0.009, co[:, 2] < -0.009
    inner = np.abs(co[:, :2]).max(axis=1) < 0.4
    assert z[top & inner].min() > 10 * max(z[bottom & inner].max(), 1e-12)   # lit top, dark bottom


def test_rerun_replaces_only_the_addons_data(solved, lmdp_ext):
    floor = bpy.data.objects["Floor"]
    mesh = floor.data
    user = mesh.color_attributes.new("Paint", 'BYTE_COLOR', 'CORNER')
    mesh.color_attributes.active_color_name = "Paint"
    mesh.color_attributes.default_color_name = "Paint"
    floor.modifiers.new("Bevel", 'BEVEL')
    solved.lmdp.display_subdivide = True
    for _ in range(2):
        assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert [m.name for m in floor.modifiers] == ["Bevel", "LMDP Display"]
    fields = [o for o in bpy.data.objects if o.get("lmdp_generated") == "display_field"]
    assert len(fields) == sum(1 for r in session(lmdp_ext).require("display").objects.values() if r["nodes"])
    assert "Paint" in mesh.color_attributes and mesh.color_attributes.active_color_name == "lmdp_z_color"
    assert bpy.ops.lmdp.clear_display() == {'FINISHED'}
    assert not ATTRIBUTES & {a.name for a in mesh.attributes}
    assert mesh.color_attributes.active_color_name == "Paint" and mesh.color_attributes.default_color_name == "Paint"
    assert [m.name for m in floor.modifiers] == ["Bevel"]
    assert not [o for o in bpy.data.objects if o.get("lmdp_generated")]
    assert "lmdp_display" not in floor.keys() and user.name == "Paint"
    assert not session(lmdp_ext).has("display")


def test_skipped_objects_are_named_and_untouched(solved, lmdp_ext, tmp_path):
    # A user attribute with the add-on's name: that mesh is skipped, its attribute kept.
    back = bpy.data.objects["BackWall"]
    own = back.data.attributes.new("lmdp_z", 'INT', 'POINT')
    own.data.foreach_set("value", [7, 7, 7, 7])
    # A mesh without vertices, and one added after sampling (no states).
    empty = bpy.data.objects.new("NoVertices", bpy.data.meshes.new("NoVertices"))
    solved.collection.objects.link(empty)
    bpy.ops.mesh.primitive_plane_add(size=0.2, location=(0, 0, 0.5))
    late = bpy.context.object
    late.name = "AddedLater"
    # A linked (library) mesh.
    library_file = tmp_path / "library.blend"
    lib_mesh = bpy.data.meshes.new("LibPlane")
    lib_mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    lib_obj = bpy.data.objects.new("LibPlane", lib_mesh)
    bpy.data.libraries.write(str(library_file), {lib_obj}, fake_user=True)
    bpy.data.objects.remove(lib_obj)
    bpy.data.meshes.remove(lib_mesh)
    with bpy.data.libraries.load(str(library_file), link=True) as (src, dst):
        dst.objects = ["LibPlane"]
    linked = dst.objects[0]
    solved.collection.objects.link(linked)
    # The ceiling carries states but is hidden.
    bpy.data.objects["Ceiling"].hide_set(True)
    floor = bpy.data.objects["Floor"]
    select([floor, back, empty, late, linked], active=floor)
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    skipped = " | ".join(session(lmdp_ext).require("display").skipped)
    for name, why in (("BackWall", "own attribute lmdp_z"), ("NoVertices", "no vertices"),
                      ("AddedLater", "carries no states"), ("LibPlane", "linked"), ("Ceiling", "hidden")):
        assert f"{name}: " in skipped and why in skipped, (name, skipped)
    assert list(session(lmdp_ext).require("display").objects) == ["Floor"]
    assert back.data.attributes["lmdp_z"].data_type == 'INT'
    assert [a.value for a in back.data.attributes["lmdp_z"].data] == [7, 7, 7, 7]
    assert not ATTRIBUTES & {a.name for a in late.data.attributes}
    # Nothing showable at all: an error naming why, nothing written.
    select([back, late])
    with pytest.raises(RuntimeError, match="Nothing to show z on: ") as error:
        bpy.ops.lmdp.show_desirability()
    assert "AddedLater: carries no states" in str(error.value) and "BackWall: its mesh" in str(error.value)


def test_display_survives_save_and_reload(solved, lmdp_ext, tmp_path):
    solved.lmdp.display_subdivide = True
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    _, before, _ = evaluated(bpy.data.objects["Floor"], "lmdp_z")
    path = tmp_path / "shown.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    _, after, _ = evaluated(bpy.data.objects["Floor"], "lmdp_z")
    assert np.array_equal(before, after)


# -- presets -----------------------------------------------------------------------------------------

def test_viewport_preset(solved, lmdp_ext):
    ops = lmdp_ext.sub("operators.adapters.viewport")
    from types import SimpleNamespace
    shading = SimpleNamespace(type='MATERIAL', color_type='MATERIAL', light='STUDIO')
    ops.apply_shading_preset(shading)
    assert (shading.type, shading.color_type, shading.light) == ('SOLID', 'VERTEX', 'FLAT')
    # The factory startup file has a 3D viewport even in background mode: it is set for real.
    spaces = ops.view3d_spaces(bpy.context)
    assert bpy.ops.lmdp.view_desirability(target='VIEWPORT') == {'FINISHED'}
    for space in spaces:
        assert space.shading.type == 'SOLID' and space.shading.color_type == 'VERTEX'
    assert bpy.ops.lmdp.view_desirability(target='VIEWPORT', enable=False) == {'FINISHED'}
    assert all(space.shading.color_type == 'MATERIAL' for space in spaces)
    # Without any 3D viewport (background Blender with an empty window manager) it is a no-op.
    assert ops.shade_viewports(SimpleNamespace(window_manager=SimpleNamespace(windows=[]))) == 0


def test_render_override_shows_the_colours_and_restores_the_users(solved, lmdp_ext):
    """A Cycles render (Standard view transform) of the floor seen from above shows exactly the
    colour attribute; turning the preset off restores the user's own override."""
    scene = solved
    mine = bpy.data.materials.new("UserOverride")
    scene.view_layers[0].material_override = mine
    scene.lmdp.display_subdivide = True
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert bpy.ops.lmdp.view_desirability(target='RENDER') == {'FINISHED'}
    assert scene.view_layers[0].material_override.name == "LMDP Desirability"
    camera = bpy.data.objects.new("Top", bpy.data.cameras.new("Top"))
    scene.collection.objects.link(camera)
    camera.data.type = 'ORTHO'
    camera.data.ortho_scale = 0.5
    camera.location = (0.0, 0.0, 0.5)         # under the ceiling, above the floor's centre
    scene.camera = camera
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.cycles.samples = 4
    scene.view_settings.view_transform = 'Standard'
    for name in ("TallBox", "ShortBox", "Light"):
        bpy.data.objects[name].hide_render = True
    scene.render.filepath = str(lmdp_ext and (bpy.app.tempdir or "/tmp")) + "/lmdp_override_test.png"
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(scene.render.filepath)
    pixels = np.empty(16 * 16 * 4, np.float32)
    image.pixels.foreach_get(pixels)
    srgb = pixels.reshape(16, 16, 4)[..., :3]
    # Expected: the floor's colour attribute at each pixel centre (linear over the fine triangles).
    floor = bpy.data.objects["Floor"]
    corners, colors, _ = evaluated(floor, "lmdp_z_color")
    corners, first = np.unique(np.round(corners, 6), axis=0, return_index=True)
    colors = colors[first]
    xy = (np.arange(16) + 0.5) / 16 * 0.5 - 0.25
    X, Y = np.meshgrid(xy, xy)                 # image rows start at the bottom (y up)
    expected = LinearNDInterpolator(corners[:, :2], colors[:, :3])(np.column_stack([X.ravel(), Y.ravel()]))
    to_srgb = lmdp_ext.sub("lmdp_addon.display.colormap").linear_to_srgb
    assert np.abs(srgb.reshape(-1, 3) - to_srgb(expected)).max() < 0.03
    assert bpy.ops.lmdp.view_desirability(target='RENDER', enable=False) == {'FINISHED'}
    assert scene.view_layers[0].material_override == mine


# -- policy -------------------------------------------------------------------------------------------

def test_show_policy_active_object_and_most_informative(solved, lmdp_ext):
    s = session(lmdp_ext)
    states = s.require("states")
    names = s.require("scene").object_names
    floor = bpy.data.objects["Floor"]
    select(list(bpy.context.selected_objects), active=floor)
    solved.lmdp.policy_max_points = 25
    assert bpy.ops.lmdp.show_policy() == {'FINISHED'}
    view = s.require("policy")
    assert len(view.points) == 25 and np.all(states.point_object[view.points] == names.index("Floor"))
    assert view.arrows.count > 25
    gizmos = lmdp_ext.sub("operators.ui.gizmos")
    assert gizmos.LMDP_GGT_policy.poll(bpy.context)
    solved.lmdp.show_policy_arrows = False
    assert not gizmos.LMDP_GGT_policy.poll(bpy.context)
    solved.lmdp.show_policy_arrows = True
    solved.lmdp.policy_subset = 'MOST_INFORMATIVE'
    assert bpy.ops.lmdp.show_policy(as_mesh=True) == {'FINISHED'}
    view = s.require("policy")
    assert len(view.points) == 25 and len(set(states.point_object[view.points])) > 2
    obj = bpy.data.objects["LMDP Policy"]
    assert len(obj.data.vertices) == view.arrows.count * 19        # 6-sided arrows: 3 x 6 + 1
    assert "lmdp_arrow_color" in obj.data.color_attributes and "lmdp_probability" in obj.data.attributes
    assert obj.active_material.name == "LMDP Arrows" and obj.users_collection[0].name == "LMDP"
    # Re-running replaces the arrows in the same object; a user's object of that name is left alone.
    obj.name = "Renamed Arrows"
    user = bpy.data.objects.new("LMDP Policy", None)
    solved.collection.objects.link(user)
    solved.lmdp.policy_max_points = 5
    assert bpy.ops.lmdp.show_policy(as_mesh=True) == {'FINISHED'}
    assert bpy.data.objects["Renamed Arrows"].get("lmdp_generated") == "policy"
    assert len(bpy.data.objects["Renamed Arrows"].data.vertices) == s.require("policy").arrows.count * 19
    assert bpy.data.objects["LMDP Policy"] is user and user.type == 'EMPTY'
    # Active object without states.
    solved.lmdp.policy_subset = 'ACTIVE_OBJECT'
    select([floor], active=bpy.data.objects["Light"])
    with pytest.raises(RuntimeError, match="active object 'Light' carries no states"):
        bpy.ops.lmdp.show_policy()


def test_probe_at_the_cursor(solved, lmdp_ext):
    s = session(lmdp_ext)
    states = s.require("states")
    solved.lmdp.policy_max_points = 10
    assert bpy.ops.lmdp.show_policy() == {'FINISHED'}
    i = int(np.flatnonzero(states.points[:, 2] < 1e-6)[3])     # a state on the floor
    solved.cursor.location = tuple(states.points[i] + [0.0, 0.0, 0.001])
    assert bpy.ops.lmdp.probe_policy(as_mesh=True, next_states=12) == {'FINISHED'}
    view = s.require("policy")
    assert view.probe.state == i and view.arrows.count > 0           # the subset's arrows are kept
    assert len(view.probe.targets) == 12
    probe = bpy.data.objects["LMDP Probe"]
    # Stratum arrows (6 sides: 19 vertices), 12 octahedra and 12 links (4 sides: 13 vertices).
    assert len(probe.data.vertices) == view.probe.arrows.count * 19 + 12 * 6 + 12 * 13
    # Probing at an explicit location.
    j = int(np.flatnonzero(states.points[:, 0] < -0.499)[0])        # on the red wall
    assert bpy.ops.lmdp.probe_policy(use_cursor=False, location=tuple(states.points[j] + [0.001, 0, 0])) == {'FINISHED'}
    assert s.require("policy").probe.state == j


def test_display_operators_support_undo(lmdp_ext):
    for idname in ("show_desirability", "show_policy", "probe_policy", "clear_display", "view_desirability"):
        assert 'UNDO' in getattr(bpy.types, f"LMDP_OT_{idname}").bl_options


def test_overlay_is_registered(lmdp_ext):
    gizmos = lmdp_ext.sub("operators.ui.gizmos")
    for cls in (gizmos.LMDP_GGT_policy, gizmos.LMDP_GT_policy_arrows):
        assert "bl_rna" in cls.__dict__ and cls.bl_rna.identifier == cls.bl_idname   # registered
    assert {'3D', 'PERSISTENT'} <= gizmos.LMDP_GGT_policy.bl_options


# -- the demo's pictures ---------------------------------------------------------------------------------

def test_picture_render_settings(fresh_scene):
    import lmdp_pictures
    lmdp_pictures.configure_render(fresh_scene, 16)
    assert fresh_scene.render.engine == 'CYCLES' and fresh_scene.view_settings.view_transform == 'Standard'
    assert fresh_scene.render.resolution_x == fresh_scene.render.resolution_y == lmdp_pictures.PICTURE_SIZE
    assert not fresh_scene.cycles.use_denoising            # emission-only colour renders need none
    lmdp_pictures.configure_render(fresh_scene, 32)
    assert fresh_scene.cycles.use_denoising or fresh_scene.cycles.samples == 64
    assert fresh_scene.render.image_settings.file_format == 'PNG'


@pytest.mark.slow
def test_headless_demo_renders_the_pictures(repo_root, tmp_path):
    import json
    import os
    import subprocess
    import sys
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    output = tmp_path / "demo"
    run = subprocess.run([sys.executable, str(repo_root / "scripts" / "lmdp_headless.py"), "--demo", "cornell",
                          "--output", str(output), "--set", "point_count=400", "--set", "rays_per_stratum=2"],
                         capture_output=True, text=True, env=env, timeout=1800)
    assert run.returncode == 0, run.stderr[-2000:]
    summary = json.loads((output / "summary.json").read_text())
    for kind in ("z", "policy", "probe"):
        path = summary["pictures"][kind]
        assert os.path.getsize(path) > 10_000
        image = bpy.data.images.load(path)
        assert tuple(image.size) == (320, 320)
        pixels = np.empty(320 * 320 * 4, np.float32)
        image.pixels.foreach_get(pixels)
        assert pixels.reshape(-1, 4)[:, :3].std() > 0.05            # not a blank picture


def test_sampling_again_on_the_subdivided_display_keeps_it(solved, lmdp_ext):
    """States sampled on an object that already shows the LMDP Display subdivision (its evaluated
    mesh is fine): showing again keeps the modifier, on the new states."""
    solved.lmdp.display_subdivide = True
    floor = bpy.data.objects["Floor"]
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    corners_before = len(evaluated(floor, "lmdp_z")[0])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    arrays = session(lmdp_ext).require("scene")
    assert np.count_nonzero(arrays.triangle_object == arrays.object_names.index("Floor")) > 2  # subdivided
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert [m.name for m in floor.modifiers] == ["LMDP Display"]
    positions, shown, _ = evaluated(floor, "lmdp_z")
    assert len(positions) == corners_before
    _, z, _ = state_values(lmdp_ext, "Floor")
    assert shown.min() >= z.min() * (1 - 1e-4) and shown.max() <= z.max() * (1 + 1e-4)
