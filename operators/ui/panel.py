"""The "LMDP" tab of the 3D viewport sidebar (N panel): Sample, Build, Solve, Show, Bake.

Each section draws its settings and its operator buttons (only the operators that are
registered, so the panel works while later modules are missing); an operator that cannot run
yet (no mesh selected, Solve first ...) is greyed out by its own ``poll``, with the reason as
its tooltip. Under the button, the stage's status: counts, nnz and memory, wall time, residual. Show holds the legend of the latest Show Desirability
(quantity, colour swatches with their values, the states' full range) and the policy tools.
Drawing reads the session with ``session.peek`` and never writes Blender data (the legend's
swatch icons are previews, not data).
"""
import bpy

from ...lmdp_addon.errors import LMDPError
from ..common import MeshSelection, operator_available, selected_meshes
from ..jobs import running_job
from ..properties import light_paths_from_scene
from ..session import format_bytes, format_seconds, peek


#: How the main panel's status lines name the session's stages (default: capitalised).
_STAGE_LABELS = {"lmdp": "LMDP"}


def _operator(layout, idname, text=None, icon='NONE'):
    """Draw the button of ``idname`` if that operator is registered; returns True if drawn."""
    if not operator_available(idname):
        return False
    row = layout.row()
    if text is None:
        row.operator(idname, icon=icon)
    else:
        row.operator(idname, text=text, icon=icon)
    return True


def _has(context, stage):
    session = peek(context.scene)
    return session is not None and session.has(stage)


def _result(context, stage):
    session = peek(context.scene)
    return session.get(stage) if session is not None else None


def _timing(context, stage):
    session = peek(context.scene)
    seconds = session.timings.get(stage) if session is not None else None
    return f", {format_seconds(seconds)}" if seconds is not None else ""


def _status(layout, text, icon='NONE'):
    """A small status line under a section's button."""
    row = layout.row()
    row.scale_y = 0.8
    row.label(text=text, icon=icon)


# -- legend swatches (icons made from the colour maps) -------------------------------------------------

LEGEND_STEPS = 5
_previews = {"collection": None}


def _swatch_icon(colormap, position):
    """icon_id of a solid swatch of ``colormap`` at ``position`` in [0, 1] (0 when unavailable,
    e.g. in background mode)."""
    collection = _previews["collection"]
    if collection is None:
        return 0
    key = f"{colormap}_{position:.3f}"
    preview = collection.get(key)
    if preview is None:
        from ...lmdp_addon.display.colormap import colormap_srgb
        try:
            rgb = colormap_srgb([position], colormap)[0]
            size = 16
            pixels = [float(c) for c in (*rgb, 1.0)] * (size * size)
            preview = collection.new(key)
            preview.icon_size = (size, size)
            preview.icon_pixels_float = pixels
            preview.image_size = (size, size)
            preview.image_pixels_float = pixels
        except Exception:  # no preview support (background mode): text-only legend
            return 0
    return preview.icon_id


def draw_legend(layout, record):
    """The colour legend of the latest Show Desirability: quantity, range, swatches with values
    (top = high), the data's full range when clipped, coarse-mesh hint."""
    box = layout.box()
    scale = record.scale
    box.label(text=scale.label, icon='COLOR')
    if scale.empty:     # nothing to map: say why instead of drawing a made-up range
        box.label(text=scale.describe(), icon='INFO')
        box.label(text=record.summary() + f", {format_seconds(record.seconds)}")
        for message in record.skipped[:3]:
            box.label(text=f"Skipped {message}", icon='ERROR')
        return
    column = box.column(align=True)
    labels = scale.tick_labels(LEGEND_STEPS)
    for i in reversed(range(LEGEND_STEPS)):
        position = i / (LEGEND_STEPS - 1)
        icon = _swatch_icon(record.colormap, position)
        text = labels[i] + ("  (and above)" if i == LEGEND_STEPS - 1 else "  (and below)" if i == 0 else "")
        if icon:
            column.label(text=text, icon_value=icon)
        else:
            column.label(text=text)
    kind = f"log scale, {scale.decades:.1f} decades" if scale.log else "linear scale"
    box.label(text=f"{record.colormap.capitalize()}, {kind}")
    from ...lmdp_addon.display.colormap import format_log10, format_value
    fmt = format_log10 if scale.log else format_value
    box.label(text=f"States: {fmt(scale.data_lo)} .. {fmt(scale.data_hi)}")
    box.label(text=record.summary() + f", {format_seconds(record.seconds)}")
    if record.coarse:
        box.label(text=f"Coarse: {', '.join(record.coarse[:3])}{' ...' if len(record.coarse) > 3 else ''}",
                  icon='INFO')
        box.label(text="Enable Subdivide Coarse Meshes for a faithful picture")
    for message in record.skipped[:3]:
        box.label(text=f"Skipped {message}", icon='ERROR')


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

        if operator_available("lmdp.run_pipeline"):
            props = context.scene.lmdp
            row = layout.row(align=True)
            op = row.operator("lmdp.run_pipeline", text="Run All", icon='PLAY')
            op.show, op.bake = props.run_all_show, props.run_all_bake
            row.prop(props, "run_all_show", toggle=True)
            row.prop(props, "run_all_bake", toggle=True)

        box = layout.box()
        try:
            selection = selected_meshes(context, evaluate=False)
        except LMDPError:
            selection = MeshSelection([])
        faceless = f" ({len(selection.skipped)} without faces, skipped)" if selection.skipped else ""
        box.label(text=f"Selected meshes: {len(selection)}{faceless}", icon='MESH_DATA')
        session = peek(context.scene)
        if session is None or not session.results:
            box.label(text="No results yet: select meshes and Sample")
            return
        column = box.column(align=True)
        for stage, text in session.status_lines():
            column.label(text=f"{_STAGE_LABELS.get(stage, stage.capitalize())}: {text}")
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

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        self.draw_section(context, layout, context.scene.lmdp)


class LMDP_PT_sample(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_sample"
    bl_label = "Sample"
    done_stage = "states"

    def draw_section(self, context, layout, props):
        column = layout.column(align=True)
        column.prop(props, "point_count")
        column.prop(props, "strata_u")
        column.prop(props, "strata_v")
        layout.prop(props, "seed")
        _operator(layout, "lmdp.sample_states", icon='STICKY_UVS_DISABLE')
        states = _result(context, "states")
        if states is not None and hasattr(states, "n_states"):
            glossy = getattr(states, "unknowns", None)
            glossy = (f"; {glossy.n_glossy:,} glossy points: {glossy.n_unknowns:,} unknowns"
                      if glossy is not None and glossy.n_glossy else "")
            _status(layout, f"{states.n_points:,} points x {states.n_strata} strata = "
                            f"{states.n_states:,} states{glossy}{_timing(context, 'states')}")


class LMDP_PT_build(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_build"
    bl_label = "Build"
    done_stage = "dynamics"

    def draw_section(self, context, layout, props):
        layout.prop(props, "rays_per_stratum")
        layout.prop(props, "cost_mode")
        row = layout.row()
        row.active = props.cost_mode == 'THESIS'
        row.prop(props, "epsilon")
        layout.prop(props, "memory_budget_gb")
        _operator(layout, "lmdp.build_dynamics", icon='LIGHT')
        dynamics = _result(context, "dynamics")
        if dynamics is not None and hasattr(dynamics, "P"):
            _status(layout, f"P: {dynamics.P.shape[0]:,} x {dynamics.n_columns:,}, nnz {dynamics.P.nnz:,}, "
                            f"{format_bytes(dynamics.memory_bytes())}{_timing(context, 'dynamics')}")


class LMDP_PT_solve(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_solve"
    bl_label = "Solve"
    done_stage = "solution"

    def draw_section(self, context, layout, props):
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
        _operator(layout, "lmdp.solve", icon='PLAY')
        solution = _result(context, "solution")
        if solution is not None and hasattr(solution, "residual"):
            state = "converged" if solution.converged else "NOT converged"
            _status(layout, f"{solution.solver} {state}, {solution.iterations} iterations{_timing(context, 'solution')}",
                    icon='CHECKMARK' if solution.converged else 'ERROR')
            _status(layout, f"Relative residual {solution.residual:.2e}")
            if solution.n_unreachable:
                _status(layout, f"{solution.n_unreachable:,} states cannot reach a light (z = 0)", icon='INFO')


class LMDP_PT_show(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_show"
    bl_label = "Show"
    done_stage = "display"

    def draw_section(self, context, layout, props):
        layout.label(text="Desirability", icon='VPAINT_HLT')
        layout.prop(props, "display_quantity")
        layout.prop(props, "display_colormap")
        layout.prop(props, "display_subdivide")
        row = layout.row()
        row.active = props.display_subdivide
        row.prop(props, "display_max_level")
        _operator(layout, "lmdp.show_desirability", icon='VPAINT_HLT')
        if operator_available("lmdp.view_desirability"):
            row = layout.row(align=True)
            row.operator("lmdp.view_desirability", text="Viewport", icon='SHADING_SOLID').target = 'VIEWPORT'
            row.operator("lmdp.view_desirability", text="Render", icon='SHADING_RENDERED').target = 'RENDER'
        record = _result(context, "display")
        if record is not None and hasattr(record, "scale"):
            draw_legend(layout, record)

        layout.separator()
        layout.label(text="Optimal Policy", icon='FORWARD')
        layout.prop(props, "policy_subset")
        layout.prop(props, "policy_max_points")
        layout.prop(props, "policy_arrow_scale")
        layout.prop(props, "show_policy_arrows")
        if operator_available("lmdp.show_policy"):
            row = layout.row(align=True)
            row.operator("lmdp.show_policy", icon='FORWARD').as_mesh = False
            row.operator("lmdp.show_policy", text="As Mesh", icon='MESH_DATA').as_mesh = True
        if operator_available("lmdp.probe_policy"):
            row = layout.row(align=True)
            op = row.operator("lmdp.probe_policy", text="Probe 3D Cursor", icon='PIVOT_CURSOR')
            op.use_cursor, op.pick = True, False
            op = row.operator("lmdp.probe_policy", text="Pick", icon='EYEDROPPER')
            op.use_cursor, op.pick = False, True
        view = _result(context, "policy")
        if view is not None and hasattr(view, "summary"):
            _status(layout, view.summary() + _timing(context, "policy"))
        _operator(layout, "lmdp.clear_display", icon='TRASH')


def _light_paths_line(scene):
    """The path length the scene's Cycles Light Paths give the bake, for the Bake section."""
    paths = light_paths_from_scene(scene)
    if paths.source != "SCENE":
        return "Cycles is not available: Max Bounces is used"
    return (f"Cycles: {paths.path_length} bounces (Max {paths.max_bounces}, Diffuse "
            f"{paths.diffuse_bounces}), {paths.clamp_summary()}")


def _lightmap_layout(layout, props):
    """The lightmap layout settings: UV map, automatic UVs, size per object, atlas."""
    column = layout.column(align=True)
    column.prop(props, "lightmap_uv_map")
    column.prop(props, "auto_lightmap_uvs")
    column.prop(props, "atlas")
    layout.prop(props, "resolution_mode")
    if props.resolution_mode == 'DENSITY':
        column = layout.column(align=True)
        column.prop(props, "texel_density")
        column.prop(props, "min_resolution")
        column.prop(props, "max_resolution")
        column.prop(props, "power_of_two")
    _operator(layout, "lmdp.create_lightmap_uvs", icon='UV')


class LMDP_PT_bake(_LMDPSection, bpy.types.Panel):
    bl_idname = "LMDP_PT_bake"
    bl_label = "Bake"
    done_stage = "bake"

    def draw_section(self, context, layout, props):
        layout.prop(props, "bake_mode")
        column = layout.column(align=True)
        column.prop(props, "bake_resolution")
        column.prop(props, "bake_samples")
        column.prop(props, "bake_margin")
        _lightmap_layout(layout, props)
        row = layout.row()
        row.active = props.bake_mode in ('AUTO', 'GUIDED', 'FINAL_GATHER')   # they draw bounces from u*
        row.prop(props, "guide_fraction")
        row = layout.row()
        row.active = props.bake_mode in ('AUTO', 'UNGUIDED', 'GUIDED')   # the path tracers join light vertices
        row.prop(props, "light_share")
        row = layout.row()
        row.active = props.bake_mode in ('AUTO', 'UNGUIDED', 'GUIDED')   # the path tracers share first bounces
        row.prop(props, "path_reuse")
        row = layout.row()
        row.active = props.bake_mode in ('AUTO', 'GUIDED')   # the solution's roulette and splitting
        row.prop(props, "splitting")
        row = layout.row()
        row.active = context.scene.world is not None   # an environment map lights the scene
        row.prop(props, "world_portals")
        layout.prop(props, "light_paths")
        column = layout.column(align=True)
        column.active = props.light_paths == 'CUSTOM'   # SCENE: the scene's Cycles Light Paths decide
        column.prop(props, "max_bounces")
        column.prop(props, "clamp_direct")
        column.prop(props, "clamp_indirect")
        if props.light_paths == 'SCENE':
            _status(layout, _light_paths_line(context.scene), icon='LIGHT')
        layout.prop(props, "bake_content")
        layout.prop(props, "multiply_color")
        layout.prop(props, "denoise")
        layout.prop(props, "output_dir")
        column = layout.column(align=True)
        column.active = bool(props.output_dir)   # files only with an Output Folder
        column.prop(props, "output_format")
        column.prop(props, "output_8bit")
        if not _operator(layout, "lmdp.bake", icon='RENDER_STILL'):
            _status(layout, "The bake operator is not part of this build", icon='INFO')
        _operator(layout, "lmdp.export_npz", text="Export Matrices (.npz)", icon='EXPORT')


classes = (
    LMDP_PT_main,
    LMDP_PT_sample,
    LMDP_PT_build,
    LMDP_PT_solve,
    LMDP_PT_show,
    LMDP_PT_bake,
)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    try:
        import bpy.utils.previews
        _previews["collection"] = bpy.utils.previews.new()
    except Exception:  # previews are optional (the legend then shows text only)
        _previews["collection"] = None


def unregister():
    collection = _previews["collection"]
    _previews["collection"] = None
    if collection is not None:
        bpy.utils.previews.remove(collection)
    _unregister_classes()
