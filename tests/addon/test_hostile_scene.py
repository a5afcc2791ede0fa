"""Scene capture, modes and identity under a hostile-but-realistic user (issue 22, classes 2, 12
and 15): objects in Edit Mode, results that must follow objects rather than names, and meshes
without faces in the selection. Every refusal names the object and what to do, returns
``{'CANCELLED'}`` and leaves the user's data as it was."""
import bpy
import numpy as np
import pytest

from helpers import select

ATTRIBUTES = {"lmdp_z", "lmdp_z_color", "lmdp_z_rgb", "lmdp_quantity", "lmdp_log10_z"}
KEYS = {"lmdp_attributes", "lmdp_previous_colors"}


@pytest.fixture
def small(lit_scene):
    """``lit_scene`` with few states and a tiny unguided bake (a fraction of a second each)."""
    props = bpy.context.scene.lmdp
    props.point_count = 300
    props.rays_per_stratum = 2
    props.bake_resolution = 8
    props.bake_samples = 2
    props.bake_mode = 'UNGUIDED'
    return lit_scene


def session(lmdp_ext):
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene)


def lmdp_data(mesh):
    """The add-on's attributes and custom properties on ``mesh`` (what must never be left behind)."""
    return {a.name for a in mesh.attributes} & ATTRIBUTES | set(mesh.keys()) & KEYS


def point_values(mesh, name):
    out = np.empty(len(mesh.attributes[name].data), np.float32)
    mesh.attributes[name].data.foreach_get("value", out)
    return out


def solve(objects):
    select(objects)
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}


def edit_mode(objects, active=None):
    """Put exactly ``objects`` into Edit Mode (the others stay in Object Mode)."""
    select(objects, active)
    bpy.ops.object.mode_set(mode='EDIT')


def object_mode():
    bpy.ops.object.mode_set(mode='OBJECT')


# -- class 2: objects in Edit Mode ---------------------------------------------------------------------------

def test_show_in_edit_mode_is_refused_and_writes_nothing(small, lmdp_ext):
    """Show on meshes in Edit Mode used to fail with foreach_set's length mismatch and leave an
    unowned lmdp_z in the edit mesh, which then blocked Show and survived Clear."""
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    edit_mode([floor, box])
    with pytest.raises(RuntimeError, match="Nothing to show z on") as error:
        bpy.ops.lmdp.show_desirability()
    assert "Box: in Edit Mode" in str(error.value) and "Floor: in Edit Mode" in str(error.value)
    assert "Tab" in str(error.value)
    object_mode()
    for obj in (floor, box):
        assert not lmdp_data(obj.data), obj.name
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert sorted(session(lmdp_ext).require("display").objects) == ["Box", "Floor"]


def test_show_skips_only_the_object_in_edit_mode(small, lmdp_ext):
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    edit_mode([floor])
    select([floor, box], active=floor)            # Box is selected too, in Object Mode
    assert (floor.mode, box.mode) == ('EDIT', 'OBJECT')
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    record = session(lmdp_ext).require("display")
    assert list(record.objects) == ["Box"]
    assert any(s.startswith("Floor: in Edit Mode") for s in record.skipped), record.skipped
    object_mode()
    assert not lmdp_data(floor.data) and ATTRIBUTES & {a.name for a in box.data.attributes}


def test_clear_and_show_recover_a_half_written_display(small, lmdp_ext):
    """A mesh the add-on began to write (lmdp_previous_colors) but never recorded its
    attributes for, as an interrupted Show of the earlier version left it."""
    floor = small["Floor"]
    solve([floor])
    mesh = floor.data
    mesh["lmdp_previous_colors"] = "\n"
    mesh.attributes.new("lmdp_z", 'FLOAT', 'POINT')
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}   # not "its own attribute lmdp_z"
    assert list(session(lmdp_ext).require("display").objects) == ["Floor"]
    assert bpy.ops.lmdp.clear_display() == {'FINISHED'}
    assert not lmdp_data(mesh)
    mesh["lmdp_previous_colors"] = "\n"                       # the same state, cleared directly
    mesh.attributes.new("lmdp_z", 'FLOAT', 'POINT')
    assert bpy.ops.lmdp.clear_display() == {'FINISHED'}
    assert not lmdp_data(mesh)


def test_point_attributes_are_checked_before_anything_is_written(small, lmdp_ext):
    data = lmdp_ext.sub("operators.adapters.display_data")
    errors = lmdp_ext.sub("lmdp_addon.errors")
    mesh = small["Floor"].data
    paint = mesh.color_attributes.new("Paint", 'BYTE_COLOR', 'POINT')
    mesh.color_attributes.active_color_name = "Paint"
    good = np.zeros(len(mesh.vertices), np.float32)
    with pytest.raises(errors.SceneError, match="Mesh .Plane.: 5 values of lmdp_quantity for 4 vertices"):
        data.write_point_attributes(mesh, {"lmdp_z": good, "lmdp_quantity": np.zeros(5)})
    assert not lmdp_data(mesh) and mesh.color_attributes.active_color_name == paint.name
    # A failure while writing (colours of the wrong shape, here) removes what was written.
    with pytest.raises((TypeError, RuntimeError)):
        data.write_point_attributes(mesh, {"lmdp_z": good, "lmdp_z_color": np.zeros((4, 2))}, "Floor")
    assert not lmdp_data(mesh) and mesh.color_attributes.active_color_name == "Paint"
    # A user attribute of one of the names is never replaced, nor shadowed by a ".001".
    mesh.attributes.new("lmdp_quantity", 'INT', 'POINT')
    with pytest.raises(errors.SceneError, match="Floor: its mesh 'Plane' has its own attribute lmdp_quantity"):
        data.write_point_attributes(mesh, {"lmdp_z": good, "lmdp_quantity": good}, "Floor")
    assert {a.name for a in mesh.attributes} & ATTRIBUTES == {"lmdp_quantity"}
    assert not any(a.name.startswith("lmdp_quantity.") for a in mesh.attributes)
    assert not set(mesh.keys()) & KEYS


def test_occluder_emitter_and_carrier_in_edit_mode_are_captured_as_seen(small, lmdp_ext):
    """Edit Mode objects used to vanish from the captured scene (or stop the capture with a UV
    length mismatch): the evaluated mesh of an object in Edit Mode has no faces of its own."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    floor, box, lamp = small["Floor"], small["Box"], small["Lamp"]
    edit_mode([floor, box, lamp], active=floor)
    bpy.ops.mesh.select_all(action='SELECT')
    bpy.ops.mesh.subdivide(number_cuts=2)                     # 9 faces per face, not yet in .data
    bpy.ops.transform.translate(value=(0.1, 0.0, 0.0))
    select([floor])
    scene = extract.extract_scene(bpy.context, [floor])
    assert sorted(scene.object_names) == ["Box", "Floor", "Lamp"]
    counts = dict(zip(scene.object_names, np.bincount(scene.triangle_object)))
    assert counts == {"Floor": 18, "Box": 108, "Lamp": 18}
    lamp_x = scene.vertices[scene.triangles[scene.triangle_object == scene.object_names.index("Lamp")]][..., 0]
    np.testing.assert_allclose([lamp_x.min(), lamp_x.max()], [-0.15, 0.35], atol=1e-6)
    assert scene.has_light() and scene.object_carries_states.tolist() == [n == "Floor" for n in scene.object_names]
    assert floor.mode == 'EDIT' and lamp.mode == 'EDIT'       # nothing left Edit Mode
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=True) == {'FINISHED'}
    assert session(lmdp_ext).require("states").n_points > 0


def test_faces_made_in_edit_mode_carry_states(small, lmdp_ext):
    """A mesh whose faces exist only in its edit mesh so far (drawn from scratch in Edit Mode)."""
    mesh = bpy.data.meshes.new("Drawn")
    drawn = bpy.data.objects.new("Drawn", mesh)
    bpy.context.scene.collection.objects.link(drawn)
    edit_mode([drawn])
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0.0, 0.0, 1.0))
    assert len(mesh.polygons) == 0                            # not in drawn.data yet
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    s = session(lmdp_ext)
    assert np.all(s.require("states").point_object == s.require("scene").object_names.index("Drawn"))
    assert drawn.mode == 'EDIT'


def test_show_skips_a_mesh_in_dynamic_topology_sculpting(small, lmdp_ext):
    """Dynamic topology keeps the mesh in a BMesh that replaces the mesh on leaving Sculpt Mode:
    attributes written meanwhile used to vanish then, silently."""
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    select([floor])
    bpy.ops.object.mode_set(mode='SCULPT')
    assert bpy.ops.sculpt.dynamic_topology_toggle() == {'FINISHED'}
    select([floor, box], active=floor)
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    record = session(lmdp_ext).require("display")
    assert list(record.objects) == ["Box"]
    assert any(s.startswith("Floor: in Sculpt Mode with Dynamic Topology") for s in record.skipped)
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    assert any("Floor' is in Sculpt Mode with Dynamic Topology" in w
               for w in session(lmdp_ext).require("scene").warnings)
    object_mode()
    assert not lmdp_data(floor.data)


# -- class 12: results follow objects, not names -------------------------------------------------------------

def swap_names(a, b):
    a_name, b_name = a.name, b.name
    a.name = "lmdp swap"
    b.name = a_name
    a.name = b_name


def test_swapped_names_keep_each_objects_states(small, lmdp_ext):
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    before = {obj.session_uid: point_values(obj.data, "lmdp_z") for obj in (floor, box)}
    assert bpy.ops.lmdp.clear_display() == {'FINISHED'}
    swap_names(floor, box)
    assert (floor.name, box.name) == ("Box", "Floor")
    select([floor, box])
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    for obj in (floor, box):
        np.testing.assert_array_equal(point_values(obj.data, "lmdp_z"), before[obj.session_uid])


def test_swapped_names_keep_each_objects_policy_and_probe(small, lmdp_ext):
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    s = session(lmdp_ext)
    box_index = s.require("scene").object_names.index("Box")
    swap_names(floor, box)
    bpy.context.scene.lmdp.policy_subset = 'ACTIVE_OBJECT'
    select([floor, box], active=box)                          # the cube, now named "Floor"
    assert bpy.ops.lmdp.show_policy() == {'FINISHED'}
    points = s.require("policy").points
    assert len(points) and np.all(s.require("states").point_object[points] == box_index)
    bpy.context.scene.cursor.location = (0.0, 0.0, 0.5)       # on top of the cube
    assert bpy.ops.lmdp.probe_policy() == {'FINISHED'}
    assert "on Floor," in s.last_message                      # the cube's name now


def test_show_refuses_stale_and_replaced_objects(small, lmdp_ext):
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    floor.location.x += 0.5                                   # moved since sampling
    box.data.vertices[0].co.z += 0.1                          # edited since sampling
    select([floor, box])
    with pytest.raises(RuntimeError, match="Nothing to show z on") as error:
        bpy.ops.lmdp.show_desirability()
    for name in ("Floor", "Box"):
        assert f"{name}: its mesh or transform changed since the states were sampled" in str(error.value)
    assert "Sample again" in str(error.value)
    assert not lmdp_data(floor.data) and not lmdp_data(box.data)
    # A new object that took the name of a sampled one carries no states.
    floor.name = "Old Floor"
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    new = bpy.context.object
    new.name = "Floor"
    select([new])
    with pytest.raises(RuntimeError, match="Floor: carries no states"):
        bpy.ops.lmdp.show_desirability()
    assert not lmdp_data(new.data)


def test_objects_changed_during_the_job_are_refused_before_writing(small, lmdp_ext):
    targets = lmdp_ext.sub("operators.adapters.display_targets")
    errors = lmdp_ext.sub("lmdp_addon.errors")
    floor, box = small["Floor"], small["Box"]
    solve([floor, box])
    s = session(lmdp_ext)
    found, _ = targets.display_targets(bpy.context, s.require("scene"), s.require("states"))
    read = targets.read_targets(found, s.require("scene"), s.require("states"), bpy.context.scene.lmdp, None)
    targets.check_targets(read)                               # nothing changed yet
    box.name = "Renamed"                                      # a rename is fine
    targets.check_targets(read)
    assert read[0]["object"] == box
    floor.location.z += 0.1
    bpy.context.view_layer.update()
    with pytest.raises(errors.SceneError, match="Floor changed .* while Show Desirability ran"):
        targets.check_targets(read)
    floor.location.z -= 0.1
    bpy.context.view_layer.update()
    bpy.data.objects.remove(box)
    with pytest.raises(errors.SceneError, match="Box was deleted while Show Desirability ran"):
        targets.check_targets(read)


# -- class 15: meshes without faces in the selection ---------------------------------------------------------

def faceless(name, vertices=((0, 0, 0), (1, 0, 0)), edges=((0, 1),)):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in vertices], [tuple(e) for e in edges], [])
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def nothing_out(obj):
    """A geometry-nodes modifier whose output is empty: faces in the mesh, none after it."""
    tree = bpy.data.node_groups.new("Nothing", 'GeometryNodeTree')
    tree.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    tree.nodes.new('NodeGroupOutput')
    obj.modifiers.new("Nothing", 'NODES').node_group = tree


def test_faceless_meshes_in_the_selection_are_skipped_and_named(small, lmdp_ext, tmp_path):
    floor, box = small["Floor"], small["Box"]
    edges = faceless("Edges")
    points = faceless("Points", vertices=((0, 0, 1),), edges=())
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0.5, 0.5, 0.1))
    gone = bpy.context.object
    gone.name = "Gone"
    nothing_out(gone)
    bpy.ops.mesh.primitive_plane_add(size=0.3, location=(-0.6, 0.0, 0.01))
    unrendered = bpy.context.object
    unrendered.name = "NoRender"
    unrendered.hide_render = True                             # the capture ignores it, as Cycles does
    selection = [floor, box, edges, points, gone, unrendered]
    select(selection, active=floor)
    messages = {"Edges": "'Edges': it has no faces", "Points": "'Points': it has no faces",
                "Gone": "'Gone': it has no faces after its modifiers",
                "NoRender": "'NoRender': it is disabled in renders (camera icon off)"}
    assert bpy.ops.lmdp.bake() == {'FINISHED'}                # not "not part of the captured scene"
    assert sorted(o.name for o in session(lmdp_ext).require("bake").objects) == ["Box", "Floor"]
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    warnings = " | ".join(session(lmdp_ext).require("scene").warnings)
    assert all(text in warnings for text in messages.values()), warnings
    assert bpy.ops.lmdp.build_dynamics() == {'FINISHED'} and bpy.ops.lmdp.solve() == {'FINISHED'}
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    skipped = " | ".join(session(lmdp_ext).require("display").skipped)
    assert "Edges: has no faces" in skipped and "Gone: has no faces after its modifiers" in skipped, skipped
    assert bpy.ops.lmdp.show_policy() == {'FINISHED'}
    select(selection, active=floor)
    assert bpy.ops.lmdp.run_pipeline(show=True, bake=True) == {'FINISHED'}
    assert sorted(session(lmdp_ext).object_names) == ["Box", "Floor"]


def test_a_selection_of_only_faceless_meshes_is_refused_by_name(small, lmdp_ext):
    common = lmdp_ext.sub("operators.common")
    edges = faceless("Edges")
    empty = faceless("NoVertices", vertices=(), edges=())
    small["Box"].hide_render = True
    select([edges, empty, small["Box"], small["Camera"]])
    for idname in common.available_operators(common.SELECTION_OPERATORS):
        with pytest.raises(RuntimeError, match="Select at least one mesh object that can carry states: "
                                               "'Box' is disabled in renders .camera icon off.; "
                                               "'Edges' has no faces; 'NoVertices' has no vertices"):
            common.call_operator(idname)
    assert not session(lmdp_ext).results


def test_a_faceless_mesh_whose_modifiers_make_faces_carries_states(small, lmdp_ext):
    """An edge profile with a Screw modifier (a lathe) has faces where it counts: after its
    modifiers."""
    profile = faceless("Lathe", vertices=((0.3, 0.0, 0.2), (0.3, 0.0, 0.6)))
    profile.modifiers.new("Screw", 'SCREW')
    select([profile, small["Floor"]])
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    s = session(lmdp_ext)
    scene = s.require("scene")
    assert np.any(s.require("states").point_object == scene.object_names.index("Lathe"))
    assert not any("no faces" in w for w in scene.warnings), scene.warnings


def test_a_faceless_instancer_keeps_its_instances_carrying_states(small, lmdp_ext):
    """Vertex instancing from a mesh of points: the instances, not the instancer, have faces."""
    points = faceless("Scatter", vertices=((0.6, 0.6, 0.05), (-0.6, 0.6, 0.05)), edges=())
    bpy.ops.mesh.primitive_cube_add(size=0.1)
    pebble = bpy.context.object
    pebble.name = "Pebble"
    pebble.parent = points
    points.instance_type = 'VERTS'
    select([points, small["Floor"]])
    assert bpy.ops.lmdp.sample_states() == {'FINISHED'}
    scene = session(lmdp_ext).require("scene")
    carried = dict(zip(scene.object_names, scene.object_carries_states))
    assert carried["Scatter/Pebble#0"] and carried["Scatter/Pebble#1"] and not carried["Pebble"], (carried, scene.warnings)
