"""Operators that show the solution's desirability on the meshes, and the shading presets.

* ``lmdp.show_desirability``: z (or J, or the residual: ``scene.lmdp.display_quantity``) of the
  states, interpolated to the vertices of every selected mesh (``lmdp_addon.display.vertex_field``) and
  written as point attributes; with ``scene.lmdp.display_subdivide`` also at the resolution of the
  states through the non-destructive "LMDP Display" modifier (:mod:`..adapters.display_data`).
* ``lmdp.view_desirability``: one-click presets that make the colours visible: the 3D viewport
  in Solid shading with Attribute colours and flat lighting, or the render override material.
* ``lmdp.clear_display``: removes everything the display operators wrote.

The policy's arrows and probe are in :mod:`.policy`. Operators are thin (``jobs.EngineJob``):
``prepare`` reads Blender data into arrays, ``compute`` calls the engine, ``apply`` writes
Blender data and the session's ``display`` stage.
"""
import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty

from ...lmdp_addon.display import vertex_field
from ...lmdp_addon.errors import SceneError
from ...lmdp_addon.model.solvers import state_residuals
from ..adapters.display_data import show_field
from ..adapters.display_objects import clear_all
from ..adapters.display_targets import DisplayRecord, check_targets, display_targets, read_targets
from ..adapters.viewport import set_render_override, shade_viewports, tag_redraw
from ..common import report_error, selected_meshes
from ..jobs import EngineJob, ready
from ..session import format_seconds, peek, session_for

#: log10 of the smallest normal float32: attributes cannot hold smaller z.
FLOAT32_LOG10_MIN = float(np.log10(np.finfo(np.float32).tiny))


def shown_state_objects(states, dynamics):
    """The object of each state for the interpolation, -1 for buried states (inside or pressed
    against other geometry: ``locator.buried_points``): they get no light and colour no vertex,
    or the floor beside a box would darken towards it."""
    locator = dynamics.locator
    shown = locator.targets if locator is not None else None
    return states.point_object if shown is None else np.where(shown, states.point_object, -1)


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
        lmdp = session.result
        props = context.scene.lmdp
        targets, skipped = display_targets(context, lmdp.scene, lmdp.states)
        if not targets:
            raise SceneError("Nothing to show z on: " + "; ".join(skipped))
        # apply() needs these too (the jobs protocol hands it only compute's result).
        self._inputs = {"targets": read_targets(targets, lmdp.scene, lmdp.states, props, session.get("display")),
                        "skipped": skipped, "states": lmdp.states, "solution": solution, "lmdp": lmdp.lmdp,
                        "quantity": props.display_quantity, "colormap": props.display_colormap,
                        "state_objects": shown_state_objects(lmdp.states, lmdp.dynamics)}
        return self._inputs

    def compute(self, inputs, settings, progress):
        states, solution = inputs["states"], inputs["solution"]
        residuals = state_residuals(inputs["lmdp"], solution) if inputs["quantity"] == "RESIDUAL" else None
        sq = vertex_field.state_quantity(solution, inputs["quantity"], residuals, states)
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
                               states_id=id(inputs["states"]), seconds=self.compute_seconds)
        check_targets(inputs["targets"])  # every object as read, before anything is written
        for target, (fields, weights) in zip(inputs["targets"], results):
            obj = target["object"]
            record.weights[obj.session_uid] = (target["key"], weights)
            nodes = show_field(obj, fields, target["level"], target["lattice"])
            if target["lattice"] is None and target["level"] > 0:
                record.coarse.append(obj.name)
            record.objects[obj.name] = {"vertices": len(target["points"]),
                                        "level": target["level"] if nodes else 0, "nodes": nodes}
        session_for(context.scene).store("display", record, seconds=self.compute_seconds)
        self._report(record, sq, results)
        if self.shade_viewport:
            shade_viewports(context)
        tag_redraw(context)
        return f"Showed {record.summary()} in {format_seconds(self.compute_seconds)}: {sq.scale.describe()}"

    def _report(self, record, sq, results):
        underflow = sum(int(np.count_nonzero(np.isfinite(f[0].log10_z) & (f[0].log10_z < FLOAT32_LOG10_MIN)))
                        for f, _ in results)
        if underflow:
            self.report({'INFO'}, f"z is below float32's range on {underflow:,} vertices (THESIS mode with "
                                  f"λ = {sq.lambda_:.4g}): lmdp_z holds 0 there; lmdp_log10_z and the colours "
                                  "hold the exact values")
        for message in record.skipped:
            self.report({'WARNING'}, f"Skipped {message}")
        if record.coarse:
            self.report({'INFO'}, f"{len(record.coarse)} meshes have faces larger than the spacing of their "
                                  f"states ({', '.join(record.coarse[:4])}{' ...' if len(record.coarse) > 4 else ''}): "
                                  "their vertex colours are a coarse summary; turn on Subdivide Coarse "
                                  "Meshes (display_subdivide) for a faithful picture")


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
            counts = clear_all(context)
            session = peek(context.scene)
            if session is not None:
                session.invalidate_from("display")
                session.invalidate_from("policy")
            tag_redraw(context)
        except Exception as error:
            return report_error(self, error)
        self.report({'INFO'}, f"Removed LMDP colours from {counts['attributes']} meshes, "
                              f"{counts['modifiers']} LMDP Display modifiers, {counts['objects']} arrow objects")
        return {'FINISHED'}


classes = (
    LMDP_OT_show_desirability,
    LMDP_OT_view_desirability,
    LMDP_OT_clear_display,
)
register, unregister = bpy.utils.register_classes_factory(classes)
