"""The "LMDP" tab of the 3D viewport sidebar (N panel): Sample, Build, Solve, Show, Bake.

Each section is greyed out until the session holds its inputs (states before Build, dynamics
before Solve, a solution before Show), and shows only the operators that are registered, so the
panel works while later modules are missing. Drawing reads the session with ``session.peek`` and
never writes Blender data.
"""
import bpy

from .common import operator_available, selected_meshes
from .jobs import running_job
from .session import format_seconds, peek


def _operator(layout, idname, text=None, icon='NONE', enabled=True):
    """Draw the button of ``idname`` if that operator is registered; returns True if drawn."""
    if not operator_available(idname):
        return False
    row = layout.row()
    row.enabled = enabled
    if text is None:
        row.operator(idname, icon=icon)
    else:
        row.operator(idname, text=text, icon=icon)
    return True


def _has_mesh_selection(context):
    try:
        selected_meshes(context)
    except Exception:
        return False
    return True


def _has(context, stage):
    session = peek(context.scene)
    return session is not None and session.has(stage)


class LMDP_PT_main(bpy.types.Panel):
    bl_idname = "LMDP_PT_main"
    bl_label = "LMDP Light Transport"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "LMDP"

    @classmethod
    def poll(cls, context):
        return getattr(context.scene, "lmdp", None) is not None

    def draw(self, context):
        layout = self.layout
        job = running_job()
        if job is not None:
            label, (stage, fraction, message) = job
            box = layout.box()
            box.label(text=f"Running: {label}", icon='SORTTIME')
            box.label(text=f"{stage} {100.0 * fraction:.0f}% {message}".strip())
            box.label(text="Press Esc to cancel")

        _operator(layout, "lmdp.run_pipeline", text="Run All", icon='PLAY',
                  enabled=job is None and _has_mesh_selection(context))

        box = layout.box()
        meshes = [obj.name for obj in context.selected_objects if obj.type == 'MESH']
        box.label(text=f"Selected meshes: {len(meshes)}", icon='MESH_DATA')
        session = peek(context.scene)
        if session is None or not session.results:
            box.label(text="No results yet: select meshes and Sample")
            return
        column = box.column(align=True)
        for stage, text in session.status_lines():
            column.label(text=f"{stage.replace('_', ' ').capitalize()}: {text}")
        if session.timings:
            column.label(text=f"Total: {format_seconds(sum(session.timings.values()))}")
        if session.last_message:
            box.label(text=session.last_message, icon='INFO')


class _LMDPSection:
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "LMDP"
    bl_parent_id = "LMDP_PT_main"
    #: session stage whose presence marks this section as done (check mark in the header)
    done_stage = ""

    def draw_header(self, context):
        done = bool(self.done_stage) and _has(context, self.done_stage)
        self.layout.label(icon='CHECKMARK' if done else 'BLANK1')

    @staticmethod
    def ready(context):
        """True when this section's inputs exist."""
        return True

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        ready = self.ready(context) and running_job() is None
        layout.active = ready
        self.draw_section(context, layout, context.scene.lmdp, ready)


class LMDP_PT_sample(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_sample"
    bl_label = "Sample"
    done_stage = "states"

    @staticmethod
    def ready(context):
        return _has_mesh_selection(context)

    def draw_section(self, context, layout, props, ready):
        column = layout.column(align=True)
        column.prop(props, "point_count")
        column.prop(props, "strata_u")
        column.prop(props, "strata_v")
        layout.prop(props, "seed")
        _operator(layout, "lmdp.sample_states", icon='STICKY_UVS_DISABLE', enabled=ready)
        if not ready and running_job() is None:
            layout.label(text="Select at least one mesh object", icon='ERROR')


class LMDP_PT_build(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_build"
    bl_label = "Build"
    done_stage = "dynamics"

    @staticmethod
    def ready(context):
        return _has(context, "states")

    def draw_section(self, context, layout, props, ready):
        layout.prop(props, "rays_per_stratum")
        layout.prop(props, "cost_mode")
        row = layout.row()
        row.active = props.cost_mode == 'THESIS'
        row.prop(props, "epsilon")
        layout.prop(props, "memory_budget_gb")
        _operator(layout, "lmdp.build_dynamics", icon='LIGHT', enabled=ready)


class LMDP_PT_solve(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_solve"
    bl_label = "Solve"
    done_stage = "solution"

    @staticmethod
    def ready(context):
        return _has(context, "dynamics")

    def draw_section(self, context, layout, props, ready):
        row = layout.row()
        row.active = props.cost_mode == 'THESIS'
        row.prop(props, "lambda_scale")
        layout.prop(props, "solver")
        row = layout.row(align=True)
        row.prop(props, "tolerance")
        row.label(text=f"{props.tolerance:.1e}")  # the field shows 6 decimals: 1e-8 reads 0.000000
        row = layout.row()
        row.active = props.solver != 'DIRECT'
        row.prop(props, "max_iterations")
        _operator(layout, "lmdp.solve", icon='PLAY', enabled=ready)


class LMDP_PT_show(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_show"
    bl_label = "Show"
    done_stage = "display"

    @staticmethod
    def ready(context):
        return _has(context, "solution")

    def draw_section(self, context, layout, props, ready):
        layout.prop(props, "display_quantity")
        _operator(layout, "lmdp.show_desirability", icon='VPAINT_HLT', enabled=ready)
        layout.separator()
        layout.prop(props, "policy_subset")
        layout.prop(props, "policy_max_points")
        layout.prop(props, "policy_arrow_scale")
        _operator(layout, "lmdp.show_policy", icon='FORWARD', enabled=ready)


class LMDP_PT_bake(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_bake"
    bl_label = "Bake"
    done_stage = "bake"

    @staticmethod
    def ready(context):
        if context.scene.lmdp.bake_mode == 'UNGUIDED':
            return _has_mesh_selection(context)
        return _has(context, "solution")

    def draw_section(self, context, layout, props, ready):
        layout.prop(props, "bake_mode")
        column = layout.column(align=True)
        column.prop(props, "bake_resolution")
        column.prop(props, "bake_samples")
        column.prop(props, "bake_margin")
        row = layout.row()
        row.active = props.bake_mode == 'GUIDED'
        row.prop(props, "guide_fraction")
        layout.prop(props, "max_bounces")
        layout.prop(props, "output_dir")
        _operator(layout, "lmdp.bake", icon='RENDER_STILL', enabled=ready)
        _operator(layout, "lmdp.export_npz", text="Export Matrices (.npz)", icon='EXPORT',
                  enabled=_has(context, "dynamics"))


classes = (
    LMDP_PT_main,
    LMDP_PT_sample,
    LMDP_PT_build,
    LMDP_PT_solve,
    LMDP_PT_show,
    LMDP_PT_bake,
)
register, unregister = bpy.utils.register_classes_factory(classes)
