"""Operators that show the solution: z as vertex colours, u* as arrows, a probe, shading presets.

* ``lmdp.show_desirability``: z (or J, or the residual: ``scene.lmdp.display_quantity``) of the
  states, interpolated to the vertices of every selected mesh (``lmdp_addon.display.vertex_field``) and
  written as point attributes; with ``scene.lmdp.display_subdivide`` also at the resolution of the
  states through the non-destructive "LMDP Display" modifier (``display_data``).
* ``lmdp.view_desirability``: one-click presets that make the colours visible: the 3D viewport
  in Solid shading with Attribute colours and flat lighting, or the render override material.
* ``lmdp.show_policy``: u* of a subset of states as arrows, drawn by the viewport overlay
  (``gizmos.py``) and, with ``as_mesh=True``, as an "LMDP Policy" object that renders.
* ``lmdp.probe_policy``: the whole u* distribution of the state nearest to the 3D cursor (or to
  a clicked surface point), as in the thesis's Figure 5.
* ``lmdp.clear_display``: removes everything the display operators wrote.

Operators are thin (``jobs.EngineJob``): ``prepare`` reads Blender data into arrays, ``compute``
calls the engine, ``apply`` writes Blender data and the session's ``display`` / ``policy`` stages.
"""
import hashlib
from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty

from ...lmdp_addon.display import arrows as arrow_geometry
from ...lmdp_addon.display import vertex_field
from ...lmdp_addon.display.colormap import ColorScale
from ...lmdp_addon.errors import SceneError
from ...lmdp_addon.model.policy import optimal_policy, stratum_policy
from ...lmdp_addon.model.solvers import state_residuals
from ..adapters import display_data as data
from ..common import report_error, selected_meshes
from ..jobs import EngineJob, ready
from ..session import format_seconds, peek, session_for

#: log10 of the smallest normal float32: attributes cannot hold smaller z.
FLOAT32_LOG10_MIN = float(np.log10(np.finfo(np.float32).tiny))
#: Largest number of display-lattice nodes per object (memory / update-time guard).
MAX_LATTICE_NODES = 2_000_000


@dataclass
class DisplayRecord:
    """What Show Desirability did (the session's ``display`` stage; the panel's legend).

    objects  {name: {"vertices": V, "level": modifier level (0: none), "nodes": lattice nodes}}
    weights  {name: (geometry key, [FieldWeights])}: the interpolation weights of the last run,
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


# -- which objects ----------------------------------------------------------------------------------

def _selected_mesh_objects(context):
    """Selected meshes, including selected ones that are hidden (so they can be reported)."""
    meshes = {obj.name: obj for obj in selected_meshes(context)}  # raises for an empty selection
    view_layer = context.view_layer
    for obj in view_layer.objects:
        if obj.type == 'MESH' and obj.select_get(view_layer=view_layer):
            meshes.setdefault(obj.name, obj)
    return [meshes[name] for name in sorted(meshes)]


def display_targets(context, scene_arrays, states):
    """``(targets, skipped)``: the selected meshes Show Desirability can write, as
    ``[(object, object index in scene_arrays)]``, and one message per skipped mesh naming it."""
    targets, skipped, mesh_owner = [], [], {}
    carriers = np.bincount(states.point_object, minlength=len(scene_arrays.object_names))
    for obj in _selected_mesh_objects(context):
        mesh = obj.data
        if obj.library is not None or mesh.library is not None or not mesh.is_editable:
            source = (obj.library or mesh.library)
            where = f" from '{source.filepath}'" if source is not None else ""
            skipped.append(f"{obj.name}: linked{where} and not editable (make it local to show z on it)")
        elif not obj.visible_get(view_layer=context.view_layer):
            skipped.append(f"{obj.name}: hidden (unhide it to show z on it)")
        elif len(mesh.vertices) == 0:
            skipped.append(f"{obj.name}: has no vertices")
        elif obj.name not in scene_arrays.object_names or \
                carriers[scene_arrays.object_names.index(obj.name)] == 0:
            skipped.append(f"{obj.name}: carries no states (select it and Sample again)")
        elif data.foreign_attributes(mesh):
            names = ", ".join(data.foreign_attributes(mesh))
            skipped.append(f"{obj.name}: its mesh '{mesh.name}' has its own attribute {names}; "
                           "rename it to let LMDP write its colours")
        elif mesh.name in mesh_owner:
            skipped.append(f"{obj.name}: shares its mesh '{mesh.name}' with {mesh_owner[mesh.name]}, "
                           "which shows the colours")
        else:
            mesh_owner[mesh.name] = obj.name
            targets.append((obj, scene_arrays.object_names.index(obj.name)))
    # Hiding an object deselects it: name the hidden meshes that carry states, so their
    # (possibly stale) colours are not silently left behind.
    chosen = {obj.name for obj, _ in targets} | {m.split(":")[0] for m in skipped}
    for index, name in enumerate(scene_arrays.object_names):
        obj = bpy.data.objects.get(name)
        if carriers[index] and name not in chosen and obj is not None and obj.type == 'MESH' \
                and name in context.view_layer.objects and not obj.visible_get(view_layer=context.view_layer):
            skipped.append(f"{name}: hidden (it carries states; unhide and select it to show z on it)")
    return targets, skipped


def _lattice(scene_arrays, geometry, obj_index, spacing, max_level):
    """World lattice (points, normals, triangles) over the object's captured triangles at the
    resolution of its states (the triangles themselves when they are already that fine, e.g. when
    the states were sampled on an earlier LMDP Display subdivision). ``geometry``: the scene's
    ``triangle_geometry()`` (normals, areas), computed once."""
    normals, areas = geometry
    tri = np.flatnonzero((scene_arrays.triangle_object == obj_index) & (areas > 0))
    if tri.size == 0:
        return None
    corners = scene_arrays.corners()[tri]
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


def _tag_redraw(context):
    for window in getattr(context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type == 'VIEW_3D':
                area.tag_redraw()


# -- viewport shading preset ------------------------------------------------------------------------------

def apply_shading_preset(shading):
    """Solid shading, colours from the active colour attribute, flat lighting (the colours are
    the colour map, unshaded)."""
    shading.type = 'SOLID'
    shading.color_type = 'VERTEX'  # shown as "Attribute" in the Shading popover
    shading.light = 'FLAT'


def reset_shading(shading):
    shading.color_type = 'MATERIAL'
    shading.light = 'STUDIO'


def view3d_spaces(context):
    """Every 3D viewport space of every window (none in background mode)."""
    spaces = []
    for window in getattr(context.window_manager, "windows", ()):
        screen = window.screen
        for area in (screen.areas if screen is not None else ()):
            if area.type == 'VIEW_3D':
                spaces.extend(space for space in area.spaces if space.type == 'VIEW_3D')
    return spaces


def shade_viewports(context, enable=True):
    """Apply (or undo) the preset in every 3D viewport; returns how many were changed."""
    spaces = view3d_spaces(context)
    for space in spaces:
        (apply_shading_preset if enable else reset_shading)(space.shading)
    return len(spaces)


PREVIOUS_OVERRIDE_KEY = "lmdp_previous_override"


def set_render_override(context, enable=True):
    """Make the view layer render the desirability colours (material override "LMDP
    Desirability"), or restore the override it had before. Object materials are not touched."""
    view_layer = context.view_layer
    scene = context.scene
    if enable:
        material = data.render_material()
        if view_layer.material_override is not material:
            previous = view_layer.material_override
            scene[PREVIOUS_OVERRIDE_KEY] = previous.name if previous is not None else ""
            view_layer.material_override = material
        return material
    current = view_layer.material_override
    if current is not None and current.get(data.MARK) == "render_material":
        previous = scene.get(PREVIOUS_OVERRIDE_KEY, "")
        view_layer.material_override = bpy.data.materials.get(previous) if previous else None
    if PREVIOUS_OVERRIDE_KEY in scene:
        del scene[PREVIOUS_OVERRIDE_KEY]
    return None


# -- operators ----------------------------------------------------------------------------------------------

class LMDP_OT_show_desirability(EngineJob, bpy.types.Operator):
    """Write the desirability z (or the cost-to-go J, or the residual) of the solution as colour
    attributes of the selected meshes (lmdp_z, lmdp_z_color, lmdp_quantity, lmdp_z_rgb)"""

    bl_idname = "lmdp.show_desirability"
    bl_label = "Show Desirability"
    bl_options = {'REGISTER', 'UNDO'}
    stage = "show"

    shade_viewport: BoolProperty(
        name="Shade Viewport",
        description="Also switch the 3D viewports to Solid shading with Attribute colours",
        default=True,
    )

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True, stage="solution")

    def prepare(self, context):
        selected_meshes(context)
        session = session_for(context.scene)
        solution = session.require("solution")
        states = session.require("states")
        scene_arrays = session.require("scene")
        lmdp = session.require("lmdp")
        props = context.scene.lmdp
        targets, skipped = display_targets(context, scene_arrays, states)
        if not targets:
            raise SceneError("Nothing to show z on: " + "; ".join(skipped))
        spacing = vertex_field.state_spacing(states.point_area)
        geometry = scene_arrays.triangle_geometry() if props.display_subdivide else None
        previous = session.get("display")
        cache = previous.weights if previous is not None and previous.states_id == id(states) else {}
        inputs = []
        for obj, index in targets:
            points, normals = data.world_vertices(obj)
            own = states.point_object == index
            object_spacing = float(np.median(spacing[own]))
            edge = data.longest_edge(obj, points)
            level = vertex_field.subdivision_level(edge, object_spacing, props.display_max_level)
            lattice = _lattice(scene_arrays, geometry, index, object_spacing, props.display_max_level) \
                if props.display_subdivide and level > 0 else None
            key = geometry_key(points, normals, lattice)
            inputs.append({"name": obj.name, "index": index, "points": points, "normals": normals,
                           "level": level, "lattice": lattice, "spacing": object_spacing, "edge": edge,
                           "key": key, "weights": cache.get(obj.name, (None, None))[1]
                           if cache.get(obj.name, (None,))[0] == key else None})
        # Buried states (inside or pressed against other geometry: locator.buried_points) get no
        # light; they colour no vertex, or the floor beside a box would darken towards it.
        locator = session.require("dynamics").locator
        shown = locator.targets if locator is not None else None
        state_objects = states.point_object if shown is None else np.where(shown, states.point_object, -1)
        # apply() needs these too (the jobs protocol hands it only compute's result).
        self._inputs = {"targets": inputs, "skipped": skipped, "states": states, "solution": solution,
                        "lmdp": lmdp, "quantity": props.display_quantity, "state_objects": state_objects,
                        "colormap": props.display_colormap}
        return self._inputs

    def compute(self, inputs, settings, progress):
        states, solution = inputs["states"], inputs["solution"]
        residuals = state_residuals(inputs["lmdp"], solution) if inputs["quantity"] == "RESIDUAL" else None
        sq = vertex_field.state_quantity(solution, inputs["quantity"], residuals)
        spacing = vertex_field.state_spacing(states.point_area)
        results = []
        targets = inputs["targets"]
        for i, target in enumerate(targets):
            samples = [(target["points"], target["normals"])]
            if target["lattice"] is not None:
                samples.append(target["lattice"][:2])
            weights = target["weights"]  # reused when neither the mesh nor the states changed
            if weights is None:
                weights = [vertex_field.interpolation_weights(
                    points, normals, np.full(len(points), target["index"]), states.points, states.normals,
                    inputs["state_objects"], spacing) for points, normals in samples]
            fields = [vertex_field.vertex_field(w, sq, inputs["colormap"]) for w in weights]
            results.append((fields, weights))
            progress.update((i + 1) / len(targets), target["name"])
        return sq, results

    def apply(self, context, result):
        sq, results = result
        inputs = self._inputs
        record = DisplayRecord(inputs["quantity"], inputs["colormap"], sq.scale, skipped=list(inputs["skipped"]),
                               states_id=id(inputs["states"]))
        for target, (fields, weights) in zip(inputs["targets"], results):
            obj = bpy.data.objects[target["name"]]
            record.weights[obj.name] = (target["key"], weights)
            vertex = fields[0]
            data.write_point_attributes(obj.data, _attribute_values(vertex))
            obj[data.DISPLAY_FLAG] = 1.0
            nodes = 0
            if target["lattice"] is not None:
                lattice_field = fields[1]
                points, _, triangles = target["lattice"]
                data.set_display_modifier(obj, target["level"], data.to_local(obj, points), triangles,
                                          _attribute_values(lattice_field))
                nodes = len(points)
            else:
                data.remove_display_modifier(obj)
                if target["level"] > 0:
                    record.coarse.append(obj.name)
            record.objects[obj.name] = {"vertices": len(target["points"]),
                                        "level": target["level"] if nodes else 0, "nodes": nodes}
        underflow = sum(int(np.count_nonzero(np.isfinite(f[0].log10_z) & (f[0].log10_z < FLOAT32_LOG10_MIN)))
                        for f, _ in results)
        if underflow:
            self.report({'INFO'}, f"z is below float32's range on {underflow:,} vertices (THESIS mode with "
                                  f"λ = {sq.lambda_:.4g}): lmdp_z holds 0 there; lmdp_log10_z and the colours "
                                  "hold the exact values")
        record.seconds = self.compute_seconds
        session = session_for(context.scene)
        session.store("display", record, seconds=self.compute_seconds)
        for message in record.skipped:
            self.report({'WARNING'}, f"Skipped {message}")
        if record.coarse:
            self.report({'INFO'}, f"{len(record.coarse)} meshes have faces larger than the spacing of their "
                                  f"states ({', '.join(record.coarse[:4])}{' ...' if len(record.coarse) > 4 else ''}): "
                                  "their vertex colours are a coarse summary; turn on Subdivide Coarse "
                                  "Meshes (display_subdivide) for a faithful picture")
        if self.shade_viewport:
            shade_viewports(context)
        _tag_redraw(context)
        return f"Showed {record.summary()} in {format_seconds(self.compute_seconds)}: {sq.scale.describe()}"


def _attribute_values(vf):
    return {"lmdp_z": vf.z, "lmdp_z_color": vf.color, "lmdp_quantity": vf.quantity,
            "lmdp_z_rgb": vf.z_rgb, "lmdp_log10_z": vf.log10_z}


class LMDP_OT_view_desirability(bpy.types.Operator):
    """Make the desirability colours visible in one click: Solid shading with Attribute colours
    in the 3D viewports, or the "LMDP Desirability" override material for renders"""

    bl_idname = "lmdp.view_desirability"
    bl_label = "View Desirability"
    bl_options = {'REGISTER', 'UNDO'}

    target: EnumProperty(
        name="Target",
        items=(("VIEWPORT", "Viewport", "Solid shading, Attribute colours, flat lighting in every 3D viewport"),
               ("RENDER", "Render", "Render the colours (Cycles / EEVEE): the view layer's material "
                                    "override becomes the emissive 'LMDP Desirability' material; "
                                    "object materials are not changed")),
        default='VIEWPORT',
    )
    enable: BoolProperty(
        name="Enable",
        description="Turn the preset on (off: back to Material colours / the previous override)",
        default=True,
    )

    def execute(self, context):
        try:
            if self.target == 'VIEWPORT':
                count = shade_viewports(context, self.enable)
                if count == 0:
                    self.report({'INFO'}, "No 3D viewport to shade (Blender runs in background mode): "
                                          "nothing changed. In the UI this sets Solid shading with "
                                          "Attribute colours")
                    return {'FINISHED'}
                where = " stored in the file (background mode: it shows when the file is opened in Blender)" \
                    if bpy.app.background else ""
                self.report({'INFO'}, f"{'Set' if self.enable else 'Reset'} the shading of {count} 3D viewport(s){where}")
            else:
                material = set_render_override(context, self.enable)
                self.report({'INFO'}, f"Renders show the LMDP colours ({material.name} override)" if material
                            else "Renders use the object materials again")
        except Exception as error:
            return report_error(self, error)
        return {'FINISHED'}


class LMDP_OT_show_policy(EngineJob, bpy.types.Operator):
    """Show the optimal policy u* of a subset of states as arrows along the hemisphere strata,
    with length proportional to u* (policy_subset, policy_max_points, policy_arrow_scale)"""

    bl_idname = "lmdp.show_policy"
    bl_label = "Show Policy"
    bl_options = {'REGISTER', 'UNDO'}
    stage = "policy"

    as_mesh: BoolProperty(
        name="As Mesh",
        description="Also create (or replace) the object 'LMDP Policy': the arrows as a mesh with "
                    "an emissive material, which renders in Cycles / EEVEE and exports",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True, stage="solution")

    def prepare(self, context):
        meshes = selected_meshes(context)
        session = session_for(context.scene)
        solution = session.require("solution")
        dynamics = session.require("dynamics")
        states = session.require("states")
        names = session.require("scene").object_names
        props = context.scene.lmdp
        if props.policy_subset == 'ACTIVE_OBJECT':
            active = context.view_layer.objects.active
            if active is None or active.name not in names or \
                    not np.any(states.point_object == names.index(active.name)):
                what = f"the active object '{active.name}' carries" if active is not None else "there is no active object with"
                raise SceneError(f"Show Policy (Active Object): {what} no states; make a sampled mesh "
                                 "active or choose Most Informative")
            candidates = np.flatnonzero(states.point_object == names.index(active.name))
        else:
            chosen = [names.index(o.name) for o in meshes if o.name in names]
            candidates = np.flatnonzero(np.isin(states.point_object, chosen))
            if candidates.size == 0:
                raise SceneError("Show Policy: none of the selected meshes carries states; select "
                                 "meshes that were sampled")
        previous = session.get("policy")
        return {"states": states, "dynamics": dynamics, "solution": solution, "candidates": candidates,
                "subset": props.policy_subset, "max_points": props.policy_max_points,
                "scale": props.policy_arrow_scale, "probe": previous.probe if previous is not None else None,
                "as_mesh": self.as_mesh}

    def compute(self, inputs, settings, progress):
        states = inputs["states"]
        u = stratum_policy(inputs["dynamics"], inputs["solution"], "all")
        view = arrow_geometry.policy_view(states, u, inputs["subset"], inputs["max_points"], inputs["scale"],
                                          inputs["candidates"], probe=inputs["probe"])
        mesh = arrow_mesh_arrays(view.arrows, inputs["scale"]) if inputs["as_mesh"] else None
        return view, mesh

    def apply(self, context, result):
        view, mesh = result
        session_for(context.scene).store("policy", view, seconds=self.compute_seconds)
        if mesh is not None:
            data.set_generated_mesh_object(context, "policy", "LMDP Policy", *mesh)
        _tag_redraw(context)
        where = " and the object 'LMDP Policy'" if mesh is not None else ""
        if bpy.app.background and mesh is None:
            where = " (drawn in the 3D viewport only: use as_mesh=True for an object that renders)"
        return f"u* arrows: {view.summary()}{where}"


def arrow_mesh_arrays(arrows, scale, extra=None):
    """Mesh arrays of ``arrows`` (+ optional ``extra`` markers): vertices, triangles, colours,
    probabilities, for :func:`display_data.set_generated_mesh_object`."""
    scale = max(float(scale), 1e-6)
    radius = np.clip(0.05 * arrows.lengths, 0.006 * scale, 0.03 * scale)
    verts, tris, which = arrow_geometry.arrow_mesh(arrows, radius)
    colors = arrow_geometry.arrow_colors(arrows.probability)[which]
    prob = arrows.probability[which]
    if extra is not None:
        mverts, mtris, mcolors, mprob = extra
        tris = np.concatenate([tris, mtris + len(verts)])
        verts = np.concatenate([verts, mverts])
        colors = np.concatenate([colors, mcolors])
        prob = np.concatenate([prob, mprob])
    return verts, tris, colors, prob


class LMDP_OT_probe_policy(EngineJob, bpy.types.Operator):
    """Show the whole optimal policy u* of the state nearest to the 3D cursor (or to a surface
    point you click): arrows over its strata and markers at its most likely next states"""

    bl_idname = "lmdp.probe_policy"
    bl_label = "Probe Policy"
    bl_options = {'REGISTER', 'UNDO'}
    stage = "probe"

    use_cursor: BoolProperty(
        name="Use 3D Cursor", description="Probe at the 3D cursor (off: at Location)", default=True)
    location: FloatVectorProperty(
        name="Location", description="Where to probe when not using the 3D cursor (metres)",
        subtype='XYZ', unit='LENGTH', size=3)
    pick: BoolProperty(
        name="Pick", description="In the viewport: click a surface to probe it (Esc cancels)",
        default=False, options={'SKIP_SAVE'})
    next_states: IntProperty(
        name="Next States", description="Most likely next states x' to mark (count)",
        default=24, min=0, max=10000)
    arrow_scale: FloatProperty(
        name="Arrow Scale", description="Length of a probability-1 arrow (metres); 0: the most "
                                        "probable stratum's arrow is as long as the scene's policy "
                                        "Arrow Scale",
        default=0.0, min=0.0, soft_max=10.0, subtype='DISTANCE', unit='LENGTH')
    as_mesh: BoolProperty(
        name="As Mesh", description="Also create (or replace) the object 'LMDP Probe' (arrows and "
                                    "next-state markers as a mesh that renders)", default=False)

    @classmethod
    def poll(cls, context):
        return ready(cls, context, stage="solution")

    def invoke(self, context, event):
        if self.pick and not bpy.app.background and getattr(context, "area", None) is not None \
                and context.area.type == 'VIEW_3D':
            self._picking = True
            context.window_manager.modal_handler_add(self)
            context.workspace.status_text_set("LMDP Probe: click a surface (Esc / right click to cancel)")
            return {'RUNNING_MODAL'}
        return super().invoke(context, event)

    def modal(self, context, event):
        if not getattr(self, "_picking", False):
            return super().modal(context, event)
        if event.type in {'ESC', 'RIGHTMOUSE'} and event.value == 'PRESS':
            context.workspace.status_text_set(None)
            return {'CANCELLED'}
        if event.type == 'LEFTMOUSE' and event.value == 'PRESS':
            context.workspace.status_text_set(None)
            hit = _surface_under_mouse(context, event)
            if hit is None:
                self.report({'WARNING'}, "No surface under the mouse: click on a mesh")
                return {'CANCELLED'}
            self._picking = False
            self.location = hit
            self.use_cursor = False
            return self.execute(context)
        return {'RUNNING_MODAL'} if event.type not in {'MIDDLEMOUSE', 'WHEELUPMOUSE', 'WHEELDOWNMOUSE'} \
            else {'PASS_THROUGH'}

    def prepare(self, context):
        session = session_for(context.scene)
        solution = session.require("solution")
        location = np.array(context.scene.cursor.location if self.use_cursor else self.location, dtype=np.float64)
        scale = self.arrow_scale if self.arrow_scale > 0 else context.scene.lmdp.policy_arrow_scale
        self._inputs = {"states": session.require("states"), "dynamics": session.require("dynamics"),
                        "lmdp": session.require("lmdp"), "solution": solution, "location": location,
                        "scale": scale, "longest": self.arrow_scale <= 0,
                        "next_states": self.next_states, "as_mesh": self.as_mesh,
                        "names": session.require("scene").object_names,
                        "view": session.get("policy")}
        return self._inputs

    def compute(self, inputs, settings, progress):
        states, dynamics = inputs["states"], inputs["dynamics"]
        u = stratum_policy(dynamics, inputs["solution"], "all")
        U = optimal_policy(inputs["lmdp"], inputs["solution"])

        def row(i):
            return U.indices[U.indptr[i]:U.indptr[i + 1]], U.data[U.indptr[i]:U.indptr[i + 1]]
        probe = arrow_geometry.probe(states, u, row, inputs["location"], inputs["scale"], inputs["next_states"],
                                     longest=inputs["longest"])
        cols, vals = row(probe.state)
        m = states.n_points
        to_lights = float(vals[(cols >= m) & (cols < m + dynamics.n_emitters)].sum())
        mesh = None
        if inputs["as_mesh"]:
            extra = None
            if len(probe.targets):
                spacing = float(np.median(vertex_field.state_spacing(states.point_area)))
                share = probe.target_probability / probe.target_probability.max()
                radius = 0.6 * spacing * np.maximum(np.sqrt(share), 0.3)
                mverts, mtris, which = arrow_geometry.marker_mesh(probe.target_points, radius)
                colors = arrow_geometry.arrow_colors(probe.target_probability)
                links = probe.links(shorten=0.0)
                lverts, ltris, lwhich = arrow_geometry.arrow_mesh(links, 0.06 * spacing, head_radius=0.06 * spacing,
                                                                  head_length=0.0, sides=4)
                extra = (np.concatenate([mverts, lverts]), np.concatenate([mtris, ltris + len(mverts)]),
                         np.concatenate([colors[which], colors[lwhich]]),
                         np.concatenate([probe.target_probability[which], probe.target_probability[lwhich]]))
            mesh = arrow_mesh_arrays(probe.arrows, float(probe.arrows.lengths.max()) if probe.arrows.count
                                     else inputs["scale"], extra)
        return probe, to_lights, mesh

    def apply(self, context, result):
        probe, to_lights, mesh = result
        inputs = self._inputs
        view = inputs["view"] if inputs["view"] is not None else arrow_geometry.PolicyView(arrow_geometry.Arrows.empty())
        view = arrow_geometry.PolicyView(view.arrows, view.subset, view.points, probe)
        session_for(context.scene).store("policy", view, seconds=self.compute_seconds)
        if mesh is not None:
            data.set_generated_mesh_object(context, "probe", "LMDP Probe", *mesh)
        _tag_redraw(context)
        states = inputs["states"]
        name = inputs["names"][states.point_object[probe.state]]
        distance = float(np.linalg.norm(states.points[probe.state] - probe.location))
        text = (f"Probe: state {probe.state} on {name}, {distance * 1000:.0f} mm from the probe; u* sends "
                f"{to_lights:.0%} of paths straight to a light")
        if len(probe.targets):
            top = inputs["names"][states.point_object[probe.targets[0]]]
            text += f", {probe.target_probability[0]:.1%} to its likeliest next state (on {top})"
        return text


def _surface_under_mouse(context, event):
    from bpy_extras import view3d_utils
    region, rv3d = context.region, context.region_data
    if region is None or rv3d is None:
        return None
    coord = (event.mouse_region_x, event.mouse_region_y)
    origin = view3d_utils.region_2d_to_origin_3d(region, rv3d, coord)
    direction = view3d_utils.region_2d_to_vector_3d(region, rv3d, coord)
    hit, location, *_ = context.scene.ray_cast(context.evaluated_depsgraph_get(), origin, direction)
    return tuple(location) if hit else None


class LMDP_OT_clear_display(bpy.types.Operator):
    """Remove everything Show Desirability / Show Policy / Probe wrote: the lmdp_* attributes
    (restoring the previous active colour attribute), the LMDP Display modifiers, the LMDP Policy
    and LMDP Probe objects and the render override"""

    bl_idname = "lmdp.clear_display"
    bl_label = "Clear Display"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        try:
            set_render_override(context, False)
            counts = data.clear_all(context)
            session = peek(context.scene)
            if session is not None:
                session.invalidate_from("display")
                session.invalidate_from("policy")
            _tag_redraw(context)
        except Exception as error:
            return report_error(self, error)
        self.report({'INFO'}, f"Removed LMDP colours from {counts['attributes']} meshes, "
                              f"{counts['modifiers']} LMDP Display modifiers, {counts['objects']} arrow objects")
        return {'FINISHED'}


classes = (
    LMDP_OT_show_desirability,
    LMDP_OT_view_desirability,
    LMDP_OT_show_policy,
    LMDP_OT_probe_policy,
    LMDP_OT_clear_display,
)
register, unregister = bpy.utils.register_classes_factory(classes)
