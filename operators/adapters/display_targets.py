"""What Show Desirability reads from Blender: which selected meshes it can write, their world
vertices, the display lattice at the resolution of the states, and the record it leaves in the
session (:class:`DisplayRecord`, the panel's legend)."""
import hashlib
from dataclasses import dataclass, field

import bpy
import numpy as np

from ...lmdp_addon.display import vertex_field
from ...lmdp_addon.display.colormap import ColorScale
from ...lmdp_addon.errors import SceneError
from ..common import mode_holding_mesh, selected_meshes
from ..session import captured_lookup, changed_since_capture
from .display_data import foreign_attributes, longest_edge, world_vertices

#: Largest number of display-lattice nodes per object (memory / update-time guard).
MAX_LATTICE_NODES = 2_000_000


@dataclass
class DisplayRecord:
    """What Show Desirability did (the session's ``display`` stage; the panel's legend).

    objects  {name: {"vertices": V, "level": modifier level (0: none), "nodes": lattice nodes}}
    weights  {session_uid: (geometry key, [FieldWeights])}: the interpolation weights of the last run,
             reused while the states (``states_id``) and the mesh are the same, so that switching
             the quantity or the colour map skips the neighbour search (a new solution clears the
             record, and with it the weights)
    """

    quantity: str
    colormap: str
    scale: ColorScale
    objects: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    coarse: list = field(default_factory=list)
    seconds: float = 0.0
    states_id: int = 0
    weights: dict = field(default_factory=dict)

    def summary(self):
        vertices = sum(o["vertices"] for o in self.objects.values())
        nodes = sum(o["nodes"] for o in self.objects.values())
        text = f"{self.quantity} on {len(self.objects)} meshes, {vertices:,} vertices"
        if nodes:
            text += f" + {nodes:,} display nodes"
        return text


def _selected_mesh_objects(context):
    """``(meshes, skipped)``: the selected meshes, including selected ones that are hidden (so
    they can be reported), and messages naming those without faces."""
    selection = selected_meshes(context)  # raises for an empty selection
    meshes = {obj.name: obj for obj in selection}
    skipped = [f"{obj.name}: {reason} (it carries no states)" for obj, reason in selection.skipped]
    left_out = {obj.name for obj, _ in selection.skipped}
    view_layer = context.view_layer
    for obj in view_layer.objects:
        if obj.type == 'MESH' and obj.select_get(view_layer=view_layer) and obj.name not in left_out:
            meshes.setdefault(obj.name, obj)
    return [meshes[name] for name in sorted(meshes)], skipped


def _skip_reason(context, obj, scene, index, carriers, mesh_owner):
    """Why Show Desirability cannot write ``obj`` (object ``index`` of the captured ``scene``,
    None if it is not part of it): a message naming it, or None."""
    mesh = obj.data
    if obj.library is not None or mesh.library is not None or not mesh.is_editable:
        source = (obj.library or mesh.library)
        where = f" from '{source.filepath}'" if source is not None else ""
        return f"{obj.name}: linked{where} and not editable (make it local to show z on it)"
    if not obj.visible_get(view_layer=context.view_layer):
        return f"{obj.name}: hidden (unhide it to show z on it)"
    mode = mode_holding_mesh(obj)
    if mode is not None:
        tab = ", Tab," if mode == "Edit Mode" else ""
        return f"{obj.name}: in {mode} (switch to Object Mode{tab} to show z on it)"
    if len(mesh.vertices) == 0:
        return f"{obj.name}: has no vertices"
    if index is None or carriers[index] == 0:
        return f"{obj.name}: carries no states (select it and Sample again)"
    if changed_since_capture(scene, index, obj):
        return (f"{obj.name}: its mesh or transform changed since the states were sampled "
                "(run Sample again, or Run All)")
    if foreign_attributes(mesh):
        names = ", ".join(foreign_attributes(mesh))
        return (f"{obj.name}: its mesh '{mesh.name}' has its own attribute {names}; "
                "rename it to let LMDP write its colours")
    if mesh.name in mesh_owner:
        return f"{obj.name}: shares its mesh '{mesh.name}' with {mesh_owner[mesh.name]}, which shows the colours"
    return None


def display_targets(context, scene, states):
    """``(targets, skipped)``: the selected meshes Show Desirability can write, as
    ``[(object, object index in scene)]`` (``scene``: the session's captured scene; objects are
    matched by ``session_uid``, not by name), and one message per skipped mesh naming it."""
    targets, mesh_owner = [], {}
    carriers = np.bincount(states.point_object, minlength=len(scene.object_names))
    meshes, skipped = _selected_mesh_objects(context)
    captured_index = captured_lookup(scene)
    for obj in meshes:
        index = captured_index(obj)
        reason = _skip_reason(context, obj, scene, index, carriers, mesh_owner)
        if reason is not None:
            skipped.append(reason)
        else:
            mesh_owner[obj.data.name] = obj.name
            targets.append((obj, index))
    # Hiding an object deselects it: name the hidden meshes that carry states, so their
    # (possibly stale) colours are not silently left behind.
    chosen = {obj.session_uid for obj in meshes}
    for obj in context.view_layer.objects:
        index = captured_index(obj) if obj.type == 'MESH' else None
        if index is not None and carriers[index] and obj.session_uid not in chosen \
                and not obj.visible_get(view_layer=context.view_layer):
            skipped.append(f"{obj.name}: hidden (it carries states; unhide and select it to show z on it)")
    return targets, skipped


def check_targets(inputs):
    """Raise ``SceneError`` (before anything is written) when an object read by
    :func:`read_targets` is gone, renamed into another, in Edit Mode or changed since."""
    by_uid = {obj.session_uid: obj for obj in bpy.data.objects}
    for target in inputs:
        obj = by_uid.get(target["uid"])
        if obj is None:
            raise SceneError(f"{target['name']} was deleted while Show Desirability ran: nothing was "
                             "written; run Show again")
        if mode_holding_mesh(obj) or len(obj.data.vertices) != len(target["points"]) or \
                world_vertices(obj)[0].tobytes() != target["points"].tobytes():
            raise SceneError(f"{obj.name} changed (or entered Edit / Sculpt Mode) while Show Desirability ran: "
                             "nothing was written; run Show again")
        target["object"] = obj


def display_lattice(scene, geometry, obj_index, spacing, max_level):
    """World lattice (points, normals, triangles) over the object's captured triangles at the
    resolution of its states (the triangles themselves when they are already that fine, e.g. when
    the states were sampled on an earlier LMDP Display subdivision). ``geometry``: the scene's
    ``triangle_geometry()`` (normals, areas), computed once."""
    normals, areas = geometry
    tri = np.flatnonzero((scene.triangle_object == obj_index) & (areas > 0))
    if tri.size == 0:
        return None
    corners = scene.corners()[tri]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max()
    n = 2 ** vertex_field.subdivision_level(edges, spacing, max_level)
    while n > 1 and len(tri) * (n + 1) * (n + 2) // 2 > MAX_LATTICE_NODES:
        n //= 2
    points, triangles, source = vertex_field.triangle_lattice(corners, n)
    return points, normals[tri][source], triangles


def geometry_key(points, normals, lattice):
    """A digest of what the interpolation weights depend on (besides the states)."""
    digest = hashlib.blake2b(digest_size=16)
    for array in (points, normals) + (tuple(lattice[:2]) if lattice is not None else ()):
        digest.update(np.ascontiguousarray(array).tobytes())
    return (len(points), None if lattice is None else len(lattice[0]), digest.hexdigest())


def read_targets(targets, scene, states, props, previous):
    """Per target, what the worker needs: ``{"name", "uid", "index", "points", "normals", "level",
    "lattice", "spacing", "edge", "key", "weights"}``. ``props``: ``scene.lmdp``; ``previous``:
    the session's last DisplayRecord, whose weights are reused when neither the mesh nor the
    states changed."""
    spacing = vertex_field.state_spacing(states.point_area)
    geometry = scene.triangle_geometry() if props.display_subdivide else None
    cache = previous.weights if previous is not None and previous.states_id == id(states) else {}
    inputs = []
    for obj, index in targets:
        points, normals = world_vertices(obj)
        object_spacing = float(np.median(spacing[states.point_object == index]))
        edge = longest_edge(obj, points)
        level = vertex_field.subdivision_level(edge, object_spacing, props.display_max_level)
        lattice = display_lattice(scene, geometry, index, object_spacing, props.display_max_level) \
            if props.display_subdivide and level > 0 else None
        key = geometry_key(points, normals, lattice)
        cached_key, cached_weights = cache.get(obj.session_uid, (None, None))
        inputs.append({"name": obj.name, "uid": obj.session_uid, "index": index, "points": points, "normals": normals,
                       "level": level, "lattice": lattice, "spacing": object_spacing, "edge": edge,
                       "key": key, "weights": cached_weights if cached_key == key else None})
    return inputs
