"""The desirability field as mesh data: point attributes and the LMDP Display modifier.

Everything the add-on writes is marked so that re-running replaces it and
:func:`.display_objects.clear_all` removes it, and nothing else is ever touched:

* mesh point attributes ``lmdp_z`` (FLOAT), ``lmdp_z_color`` (FLOAT_COLOR), ``lmdp_z_rgb``
  (FLOAT_COLOR, PHYSICAL mode), ``lmdp_quantity`` (FLOAT) and ``lmdp_log10_z`` (FLOAT: exact
  where z is below float32's range, as in THESIS mode with a large λ); the mesh's custom property
  ``lmdp_attributes`` lists the ones the add-on owns. An attribute of the same name that the
  add-on did not write is the user's: the object is skipped, never overwritten.
  ``lmdp_z_color`` becomes the active and render colour attribute; the previous ones are
  remembered (``lmdp_previous_colors``) and restored by :func:`remove_point_attributes`.
* the object custom property ``lmdp_display`` (1.0) on displayed objects: the render material
  reads it (Attribute node, type Object) to tell displayed surfaces from the others.
* the geometry-nodes modifier "LMDP Display" (node group "LMDP Display Field", marked
  ``lmdp_generated``): it subdivides the evaluated mesh (simple subdivision, ``Level``) and samples
  the fine field from a hidden "LMDP Field <object>" mesh object (not linked to any scene,
  referenced only by the modifier) with Sample Nearest Surface. The user's mesh data never
  changes; removing the modifier shows the vertex colours of the original mesh again.

The arrow objects and the add-on's materials are in :mod:`.display_objects`.
"""
import bpy
import numpy as np

from ...lmdp_addon.errors import SceneError

MARK = "lmdp_generated"
#: Point attributes the add-on writes: name -> data type.
ATTRIBUTES = {"lmdp_z": 'FLOAT', "lmdp_z_color": 'FLOAT_COLOR', "lmdp_z_rgb": 'FLOAT_COLOR',
              "lmdp_quantity": 'FLOAT', "lmdp_log10_z": 'FLOAT'}
COLOR_ATTRIBUTE = "lmdp_z_color"
OWNED_KEY = "lmdp_attributes"
PREVIOUS_COLORS_KEY = "lmdp_previous_colors"
DISPLAY_FLAG = "lmdp_display"
MODIFIER_NAME = "LMDP Display"
FIELD_GROUP = "LMDP Display Field"
FIELD_GROUP_VERSION = 2
FIELD_OBJECT_PREFIX = "LMDP Field "


# -- reading meshes ---------------------------------------------------------------------------------

def world_vertices(obj):
    """World positions (V, 3) and unit world normals (V, 3) of the vertices of ``obj.data``."""
    mesh = obj.data
    n = len(mesh.vertices)
    co = np.empty(3 * n, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    normals = np.empty(3 * n, dtype=np.float32)
    mesh.vertex_normals.foreach_get("vector", normals)
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    linear = matrix[:3, :3]
    points = co.reshape(-1, 3).astype(np.float64) @ linear.T + matrix[:3, 3]
    try:
        normal_matrix = np.linalg.inv(linear).T
    except np.linalg.LinAlgError:  # a zero scale: no meaningful normals
        normal_matrix = np.zeros((3, 3))
    world_normals = normals.reshape(-1, 3).astype(np.float64) @ normal_matrix.T
    length = np.linalg.norm(world_normals, axis=1, keepdims=True)
    world_normals = np.where(length > 0, world_normals / np.where(length > 0, length, 1.0), 0.0)
    return points, world_normals


def longest_edge(obj, points=None):
    """Longest edge of ``obj.data`` in world space (metres; ``points``: its world vertices if
    already read); 0 without edges."""
    mesh = obj.data
    if not len(mesh.edges):
        return 0.0
    if points is None:
        points, _ = world_vertices(obj)
    ends = np.empty(2 * len(mesh.edges), dtype=np.int32)
    mesh.edges.foreach_get("vertices", ends)
    ends = ends.reshape(-1, 2)
    return float(np.linalg.norm(points[ends[:, 0]] - points[ends[:, 1]], axis=1).max())


def to_local(obj, points):
    """World points (n, 3) into ``obj``'s object space."""
    matrix = np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
    return np.asarray(points, dtype=np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


# -- point attributes ---------------------------------------------------------------------------------

def owned_attributes(mesh):
    """Names of the add-on's attributes on ``mesh``: those listed in ``lmdp_attributes``; on a
    mesh the add-on began to write (``lmdp_previous_colors``) without finishing (no list, as an
    interrupted write of an earlier version left it), every attribute of :data:`ATTRIBUTES`."""
    if OWNED_KEY not in mesh and PREVIOUS_COLORS_KEY in mesh:
        return {name for name in ATTRIBUTES if mesh.attributes.get(name) is not None}
    return set(mesh.get(OWNED_KEY, "").split(",")) - {""}


def foreign_attributes(mesh):
    """Names of the add-on's attributes that exist on ``mesh`` but were not written by it."""
    owned = owned_attributes(mesh)
    return sorted(name for name in ATTRIBUTES if mesh.attributes.get(name) is not None and name not in owned)


def check_point_values(mesh, values, owner):
    """Raise ``SceneError`` naming ``owner`` unless ``values`` ({name: array or None}) fit the
    points of ``mesh``, it is not in Edit Mode (where its attributes cannot be written) and no
    attribute of the user's has one of their names."""
    if mesh.is_editmode:
        raise SceneError(f"{owner} is in Edit Mode: switch to Object Mode (Tab) and run it again")
    foreign = [name for name in foreign_attributes(mesh) if values.get(name) is not None]
    if foreign:
        raise SceneError(f"{owner}: its mesh '{mesh.name}' has its own attribute {', '.join(foreign)}; "
                         "rename it to let LMDP write its colours")
    for name, data in values.items():
        if data is not None and len(data) != len(mesh.vertices):
            raise SceneError(f"{owner}: {len(data)} values of {name} for {len(mesh.vertices)} vertices "
                             "(the mesh changed): run it again")


def _set_attribute(mesh, name, values):
    data_type = ATTRIBUTES[name]
    attribute = mesh.attributes.new(name, data_type, 'POINT')
    if attribute.name != name:  # Blender made the name unique: never own a ".001"
        mesh.attributes.remove(attribute)
        raise SceneError(f"Mesh '{mesh.name}' already has an attribute '{name}'")
    if data_type == 'FLOAT_COLOR':
        rgba = np.asarray(values, dtype=np.float32)
        if rgba.shape[1] == 3:
            rgba = np.concatenate([rgba, np.ones((len(rgba), 1), np.float32)], axis=1)
        attribute.data.foreach_set("color", np.ascontiguousarray(rgba).ravel())
    else:
        attribute.data.foreach_set("value", np.ascontiguousarray(values, dtype=np.float32).ravel())
    return attribute


def _set_attributes(mesh, values):
    for name, data in values.items():
        if data is not None:
            _set_attribute(mesh, name, np.nan_to_num(np.asarray(data), nan=0.0, posinf=3.0e38, neginf=-3.0e38))


def write_point_attributes(mesh, values, owner=None):
    """Replace the add-on's point attributes of ``mesh`` by ``values`` ({name: (V,) or (V, 3|4)}).

    Attributes of :data:`ATTRIBUTES` that the add-on wrote before and that are not in ``values``
    are removed (e.g. ``lmdp_z_rgb`` after switching to THESIS mode). Call
    :func:`foreign_attributes` first: user attributes of the same names must not be replaced.
    ``lmdp_z_color`` becomes the active and render colour attribute. Every length is checked
    before anything changes (:func:`check_point_values`, ``owner`` names the object), the names
    are recorded as the add-on's before they are created, and a failure removes them again, so
    no attribute is ever left half-written or unowned.
    """
    check_point_values(mesh, values, owner or f"Mesh '{mesh.name}'")
    colors = mesh.color_attributes
    if PREVIOUS_COLORS_KEY not in mesh:
        mesh[PREVIOUS_COLORS_KEY] = f"{colors.active_color_name or ''}\n{colors.default_color_name or ''}"
    _remove_owned(mesh)
    mesh[OWNED_KEY] = ",".join(name for name, data in values.items() if data is not None)
    try:
        _set_attributes(mesh, values)
    except Exception:
        remove_point_attributes(mesh)
        raise
    if COLOR_ATTRIBUTE in values:
        colors.active_color_name = COLOR_ATTRIBUTE
        colors.default_color_name = COLOR_ATTRIBUTE
    mesh.update()


def _remove_owned(mesh):
    for name in owned_attributes(mesh):
        attribute = mesh.attributes.get(name)
        if attribute is not None:
            mesh.attributes.remove(attribute)


def remove_point_attributes(mesh):
    """Remove the add-on's attributes and restore the previous active / render colour attribute."""
    if OWNED_KEY not in mesh and PREVIOUS_COLORS_KEY not in mesh:
        return False
    _remove_owned(mesh)
    previous = str(mesh.get(PREVIOUS_COLORS_KEY, "\n")).split("\n")
    colors = mesh.color_attributes
    if len(previous) == 2:
        active, default = previous
        if active and colors.get(active) is not None:
            colors.active_color_name = active
        if default and colors.get(default) is not None:
            colors.default_color_name = default
    for key in (OWNED_KEY, PREVIOUS_COLORS_KEY):
        if key in mesh:
            del mesh[key]
    mesh.update()
    return True


# -- the LMDP Display modifier (subdivision carrying the fine field) -----------------------------------------

def marked(idblock, kind=None):
    """True when ``idblock`` was written by the add-on (as ``kind``, if given)."""
    value = idblock.get(MARK) if idblock is not None else None
    return value is not None and (kind is None or value == kind)


def field_node_group():
    """The node group "LMDP Display Field" (created, or rebuilt if an older version exists).

    Inputs: Geometry, Level (simple subdivision level), Field (the field object). For every
    attribute of :data:`ATTRIBUTES` it stores, on the face corners of the subdivided mesh, the
    value sampled from the field object's surface (Sample Nearest Surface interpolates
    barycentrically) at the corner's position moved 2 % towards its face's centre: a vertex on a
    box edge belongs to two faces with different light, and each face keeps its own (a point
    attribute would take one of them at random and smear it into the other face). Attributes
    missing on the field object are not written.
    """
    for tree in bpy.data.node_groups:
        if marked(tree, "display_field") and tree.get("lmdp_version") == FIELD_GROUP_VERSION:
            return tree
    tree = bpy.data.node_groups.new(FIELD_GROUP, 'GeometryNodeTree')
    tree[MARK] = "display_field"
    tree["lmdp_version"] = FIELD_GROUP_VERSION
    tree.description = "LMDP Light Transport: subdivides the mesh and samples the desirability " \
                       "field of the Field object onto it (written by Show Desirability)"
    interface = tree.interface
    interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    level = interface.new_socket("Level", in_out='INPUT', socket_type='NodeSocketInt')
    level.default_value, level.min_value, level.max_value = 0, 0, 8
    interface.new_socket("Field", in_out='INPUT', socket_type='NodeSocketObject')
    nodes, links = tree.nodes, tree.links
    group_in = nodes.new('NodeGroupInput')
    group_out = nodes.new('NodeGroupOutput')
    subdivide = nodes.new('GeometryNodeSubdivideMesh')
    info = nodes.new('GeometryNodeObjectInfo')
    info.transform_space = 'ORIGINAL'  # the field object's mesh is in the target's object space
    position = nodes.new('GeometryNodeInputPosition')
    face_center = nodes.new('GeometryNodeFieldOnDomain')
    face_center.domain = 'FACE'
    face_center.data_type = 'FLOAT_VECTOR'
    inward = nodes.new('ShaderNodeMix')
    inward.data_type = 'VECTOR'
    socket_by_id(inward.inputs, "Factor_Float").default_value = 0.02
    links.new(position.outputs["Position"], face_center.inputs[0])
    links.new(position.outputs["Position"], socket_by_id(inward.inputs, "A_Vector"))
    links.new(face_center.outputs[0], socket_by_id(inward.inputs, "B_Vector"))
    sample_position = socket_by_id(inward.outputs, "Result_Vector")
    links.new(group_in.outputs["Geometry"], subdivide.inputs["Mesh"])
    links.new(group_in.outputs["Level"], subdivide.inputs["Level"])
    links.new(group_in.outputs["Field"], info.inputs["Object"])
    geometry = subdivide.outputs["Mesh"]
    for i, (name, data_type) in enumerate(ATTRIBUTES.items()):
        read = nodes.new('GeometryNodeInputNamedAttribute')
        read.data_type = data_type
        read.inputs["Name"].default_value = name
        sample = nodes.new('GeometryNodeSampleNearestSurface')
        sample.data_type = data_type
        store = nodes.new('GeometryNodeStoreNamedAttribute')
        store.data_type = data_type
        store.domain = 'CORNER'
        store.inputs["Name"].default_value = name
        links.new(info.outputs["Geometry"], sample.inputs["Mesh"])
        links.new(read.outputs["Attribute"], sample.inputs["Value"])
        links.new(sample_position, sample.inputs["Sample Position"])
        links.new(geometry, store.inputs["Geometry"])
        links.new(sample.outputs["Value"], store.inputs["Value"])
        # Only where the field object has the attribute (lmdp_z_rgb exists in PHYSICAL mode only).
        links.new(read.outputs["Exists"], store.inputs["Selection"])
        geometry = store.outputs["Geometry"]
        for node, x in ((read, 200), (sample, 400), (store, 600)):
            node.location = (x + 220 * i, -200 * i)
    links.new(geometry, group_out.inputs["Geometry"])
    subdivide.location, info.location, group_in.location = (0, 200), (0, -100), (-250, 0)
    group_out.location = (600 + 220 * len(ATTRIBUTES), 0)
    return tree


def _socket_id(tree, name):
    for item in tree.interface.items_tree:
        if getattr(item, "in_out", None) == 'INPUT' and item.name == name:
            return item.identifier
    raise KeyError(name)


def display_modifier(obj):
    """The add-on's "LMDP Display" modifier of ``obj`` or None."""
    for modifier in obj.modifiers:
        if modifier.type == 'NODES' and marked(modifier.node_group, "display_field"):
            return modifier
    return None


def _field_object_of(modifier):
    try:
        field = modifier[_socket_id(modifier.node_group, "Field")]
    except (KeyError, TypeError):
        return None
    return field if isinstance(field, bpy.types.Object) and marked(field, "display_field") else None


def mesh_from_triangles(name, vertices, triangles):
    """A new mesh of ``vertices (V, 3)`` and ``triangles (T, 3)`` (fast: foreach_set)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    triangles = np.ascontiguousarray(triangles, dtype=np.int32).reshape(-1, 3)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", vertices.ravel())
    mesh.loops.add(3 * len(triangles))
    mesh.loops.foreach_set("vertex_index", triangles.ravel())
    mesh.polygons.add(len(triangles))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(triangles), 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    return mesh


def set_display_modifier(obj, level, local_points, triangles, values):
    """Add or update ``obj``'s "LMDP Display" modifier at ``level`` with a field object holding
    ``local_points (N, 3)`` (object space), ``triangles`` and point attributes ``values``."""
    mesh = mesh_from_triangles(FIELD_OBJECT_PREFIX + obj.name, local_points, triangles)
    try:
        check_point_values(mesh, values, f"The display field of {obj.name}")
        _set_attributes(mesh, values)
    except Exception:
        bpy.data.meshes.remove(mesh)
        raise
    modifier = display_modifier(obj)
    tree = field_node_group()
    if modifier is None:
        modifier = obj.modifiers.new(MODIFIER_NAME, 'NODES')
    modifier.node_group = tree
    field = _field_object_of(modifier)
    if field is None:
        field = bpy.data.objects.new(FIELD_OBJECT_PREFIX + obj.name, mesh)
        field[MARK] = "display_field"
        field.hide_render = True
        field.hide_viewport = True
    else:
        old = field.data
        field.data = mesh
        if old is not None and old.users == 0:
            bpy.data.meshes.remove(old)
    modifier[_socket_id(tree, "Level")] = int(level)
    modifier[_socket_id(tree, "Field")] = field
    modifier.show_viewport = modifier.show_render = True
    obj.update_tag()
    return modifier


def remove_display_modifier(obj):
    """Remove ``obj``'s "LMDP Display" modifier and its field object; True if there was one."""
    modifier = display_modifier(obj)
    if modifier is None:
        return False
    field = _field_object_of(modifier)
    obj.modifiers.remove(modifier)
    if field is not None:
        mesh = field.data
        bpy.data.objects.remove(field)
        if mesh is not None and mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    return True


def socket_by_id(sockets, identifier):
    """The socket of ``sockets`` whose identifier is ``identifier`` (names repeat on Mix nodes)."""
    for socket in sockets:
        if socket.identifier == identifier:
            return socket
    raise KeyError(identifier)


def field_attributes(vf):
    """The point attributes of a ``vertex_field.VertexField``: {name: values}."""
    return {"lmdp_z": vf.z, "lmdp_z_color": vf.color, "lmdp_quantity": vf.quantity,
            "lmdp_z_rgb": vf.z_rgb, "lmdp_log10_z": vf.log10_z}


def show_field(obj, fields, level, lattice):
    """Write ``fields`` (the vertex field, and the lattice field when ``lattice`` (points,
    normals, triangles) is given) on ``obj``: point attributes, the display flag and, with a
    lattice, the LMDP Display modifier at ``level`` (removed without). Returns the lattice nodes."""
    write_point_attributes(obj.data, field_attributes(fields[0]), obj.name)
    obj[DISPLAY_FLAG] = 1.0
    if lattice is None:
        remove_display_modifier(obj)
        return 0
    points, _, triangles = lattice
    set_display_modifier(obj, level, to_local(obj, points), triangles, field_attributes(fields[1]))
    return len(points)
