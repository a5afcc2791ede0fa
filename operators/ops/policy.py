"""Operators that show the optimal policy u*: arrows over the strata of a subset of states, and
a probe of one state's whole u* distribution (as in the thesis's Figure 5).

* ``lmdp.show_policy``: u* of a subset of states as arrows, drawn by the viewport overlay
  (:mod:`..ui.gizmos`) and, with ``as_mesh=True``, as an "LMDP Policy" object that renders.
* ``lmdp.probe_policy``: the whole u* distribution of the state nearest to the 3D cursor (or to
  a clicked surface point): arrows over its strata and markers at its likeliest next states.

Both are ``jobs.EngineJob``s that write the session's ``policy`` stage (a ``PolicyView``). On a
glossy point (one unknown per outgoing stratum) both show the u* of its unknown looking straight
down on it (``arrows.directional_policy``).
"""
import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, FloatVectorProperty, IntProperty

from ...lmdp_addon.display import arrows as arrow_geometry
from ...lmdp_addon.display import vertex_field
from ...lmdp_addon.errors import SceneError
from ...lmdp_addon.model.policy import optimal_policy, stratum_policy
from ..adapters.display_objects import set_generated_mesh_object
from ..adapters.viewport import tag_redraw
from ..common import selected_meshes, skipped_mesh_messages
from ..jobs import EngineJob, ready
from ..session import captured_index, current_names, session_for


def arrow_mesh_arrays(arrows, scale, extra=None):
    """Mesh arrays of ``arrows`` (+ optional ``extra`` markers): vertices, triangles, colours,
    probabilities, for :func:`..adapters.display_objects.set_generated_mesh_object`."""
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


def next_state_markers(probe, states):
    """Mesh arrays (vertices, triangles, colours, probabilities) of the probe's next-state
    markers, sized by their probability, and the thin links to them."""
    spacing = float(np.median(vertex_field.state_spacing(states.point_area)))
    share = probe.target_probability / probe.target_probability.max()
    radius = 0.6 * spacing * np.maximum(np.sqrt(share), 0.3)
    mverts, mtris, which = arrow_geometry.marker_mesh(probe.target_points, radius)
    colors = arrow_geometry.arrow_colors(probe.target_probability)
    links = probe.links(shorten=0.0)
    lverts, ltris, lwhich = arrow_geometry.arrow_mesh(links, 0.06 * spacing, head_radius=0.06 * spacing,
                                                      head_length=0.0, sides=4)
    return (np.concatenate([mverts, lverts]), np.concatenate([mtris, ltris + len(mverts)]),
            np.concatenate([colors[which], colors[lwhich]]),
            np.concatenate([probe.target_probability[which], probe.target_probability[lwhich]]))


def policy_candidates(context, scene, states, subset, meshes):
    """The states that may get arrows: those on the active object (``ACTIVE_OBJECT``) or on the
    selected ``meshes`` (matched to the captured ``scene`` by object, not by name); raises
    ``SceneError`` naming the problem when there are none."""
    if subset == 'ACTIVE_OBJECT':
        active = context.view_layer.objects.active
        index = captured_index(scene, active) if active is not None else None
        if index is None or not np.any(states.point_object == index):
            what = f"the active object '{active.name}' carries" if active is not None else "there is no active object with"
            raise SceneError(f"Show Policy (Active Object): {what} no states; make a sampled mesh "
                             "active or choose Most Informative")
        return np.flatnonzero(states.point_object == index)
    chosen = [index for index in (captured_index(scene, o) for o in meshes) if index is not None]
    candidates = np.flatnonzero(np.isin(states.point_object, chosen))
    if candidates.size == 0:
        raise SceneError("Show Policy: none of the selected meshes carries states; select "
                         "meshes that were sampled")
    return candidates


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
        lmdp = session.result
        props = context.scene.lmdp
        candidates = policy_candidates(context, lmdp.scene, lmdp.states, props.policy_subset, meshes)
        self._skipped = skipped_mesh_messages(meshes)
        previous = session.get("policy")
        return {"states": lmdp.states, "dynamics": lmdp.dynamics, "solution": solution, "candidates": candidates,
                "scene": lmdp.scene, "lmdp": lmdp.lmdp,
                "subset": props.policy_subset, "max_points": props.policy_max_points,
                "scale": props.policy_arrow_scale, "probe": previous.probe if previous is not None else None,
                "as_mesh": self.as_mesh}

    def compute(self, inputs, settings, progress):
        states = inputs["states"]
        u = stratum_policy(inputs["dynamics"], inputs["solution"], "all")
        if not states.unknowns.identity:   # glossy points: the u* of one outgoing direction
            u = arrow_geometry.directional_policy(inputs["scene"], states, inputs["dynamics"], u,
                                                  optimal_policy(inputs["lmdp"], inputs["solution"]),
                                                  inputs["candidates"])
        view = arrow_geometry.policy_view(states, u, inputs["subset"], inputs["max_points"], inputs["scale"],
                                          inputs["candidates"], probe=inputs["probe"])
        mesh = arrow_mesh_arrays(view.arrows, inputs["scale"]) if inputs["as_mesh"] else None
        return view, mesh

    def apply(self, context, result):
        view, mesh = result
        for message in self._skipped:
            self.report({'WARNING'}, message)
        session_for(context.scene).store("policy", view, seconds=self.compute_seconds)
        if mesh is not None:
            set_generated_mesh_object(context, "policy", "LMDP Policy", *mesh)
        tag_redraw(context)
        where = " and the object 'LMDP Policy'" if mesh is not None else ""
        if bpy.app.background and mesh is None:
            where = " (drawn in the 3D viewport only: use as_mesh=True for an object that renders)"
        return f"u* arrows: {view.summary()}{where}"


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
        lmdp = session.result
        location = np.array(context.scene.cursor.location if self.use_cursor else self.location, dtype=np.float64)
        scale = self.arrow_scale if self.arrow_scale > 0 else context.scene.lmdp.policy_arrow_scale
        self._inputs = {"states": lmdp.states, "dynamics": lmdp.dynamics, "lmdp": lmdp.lmdp,
                        "solution": solution, "location": location, "scale": scale, "scene": lmdp.scene,
                        "longest": self.arrow_scale <= 0, "next_states": self.next_states,
                        "as_mesh": self.as_mesh, "names": current_names(lmdp.scene),
                        "view": session.get("policy")}
        return self._inputs

    def compute(self, inputs, settings, progress):
        states, dynamics = inputs["states"], inputs["dynamics"]
        u = stratum_policy(dynamics, inputs["solution"], "all")
        U = optimal_policy(inputs["lmdp"], inputs["solution"])
        u = arrow_geometry.directional_policy(inputs["scene"], states, dynamics, u, U)

        def row(i):
            return U.indices[U.indptr[i]:U.indptr[i + 1]], U.data[U.indptr[i]:U.indptr[i + 1]]
        probe = arrow_geometry.probe(states, u, row, inputs["location"], inputs["scale"], inputs["next_states"],
                                     longest=inputs["longest"])
        cols, vals = row(arrow_geometry.probe_unknown(states, probe.state))
        m = states.n_unknowns
        to_lights = float(vals[(cols >= m) & (cols < m + dynamics.n_emitters)].sum())
        mesh = None
        if inputs["as_mesh"]:
            extra = next_state_markers(probe, states) if len(probe.targets) else None
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
            set_generated_mesh_object(context, "probe", "LMDP Probe", *mesh)
        tag_redraw(context)
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


classes = (LMDP_OT_show_policy, LMDP_OT_probe_policy)
register, unregister = bpy.utils.register_classes_factory(classes)
