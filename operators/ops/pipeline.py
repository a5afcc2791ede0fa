"""Operators of the LMDP stages: sample states, build dynamics, solve, Run All, export.

Each operator is thin (``jobs.EngineJob``): ``prepare`` reads Blender data and runs the stage's
checks, ``compute`` calls the stage's :mod:`lmdp_addon.model.pipeline` function (no bpy; the
checks are not run again there), ``apply`` stores the result in the scene's session, whose
``LMDPResult`` the next stage reads. The scene is captured (``SceneArrays``) when the states
are sampled; later stages work on that snapshot, so edit the scene and sample again to see the
change.
"""
import os
from dataclasses import replace

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from ...lmdp_addon.errors import SceneError
from ...lmdp_addon.model import pipeline
from ...lmdp_addon.model.export import export_npz
from ..adapters.extract import extract_scene
from ..adapters.lightmap_uvs import prepare_lightmap_uvs
from ..adapters.lightmaps import resolve_output_folder
from ..adapters.materials import HOOK_UP_ITEMS
from ..bake_steps import apply_bake, check_bake_texels, compute_bake, planned_bake_inputs
from ..common import report_error, report_warnings, selected_meshes
from ..jobs import EngineJob, ready
from ..properties import BLEND_RELATIVE_PATH, bake_settings_from_scene
from ..session import format_bytes, session_for


def capture_scene(context, uv_maps=None):
    """SceneArrays of the current scene with the selected meshes carrying the states (their
    lightmap UV maps ``uv_maps``, see ``extract_scene``)."""
    meshes = selected_meshes(context)
    scene = extract_scene(context, meshes, uv_maps=uv_maps)
    scene.check_for_lmdp()
    return scene, [obj.name for obj in meshes]


class LMDP_OT_sample_states(EngineJob, bpy.types.Operator):
    """Sample surface points on the selected meshes and split their hemispheres into strata
    (the LMDP states, thesis 3.1.1)"""

    bl_idname = "lmdp.sample_states"
    bl_label = "Sample States"
    bl_options = {'REGISTER'}
    stage = ""  # run_sample reports the "sample" stage

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True)

    def prepare(self, context):
        return capture_scene(context)

    def compute(self, inputs, settings, progress):
        scene, names = inputs
        states, _ = pipeline.run_sample(scene, settings, progress)
        return scene, names, states

    def apply(self, context, result):
        scene, names, states = result
        session = session_for(context.scene)
        session.store("scene", scene)
        session.object_names = tuple(names)
        session.store("states", states, seconds=self.compute_seconds)
        report_warnings(self, scene.warnings)
        return f"Sampled {states.summary()} on {', '.join(names)}"


class LMDP_OT_build_dynamics(EngineJob, bpy.types.Operator):
    """Cast rays through every stratum of every state to build the sparse passive dynamics P
    (thesis 3.1.2)"""

    bl_idname = "lmdp.build_dynamics"
    bl_label = "Build Dynamics"
    bl_options = {'REGISTER'}
    stage = ""  # run_build reports the "build" stage

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True, stage="states")

    def prepare(self, context):
        selected_meshes(context)
        session = session_for(context.scene)
        states = session.require("states")
        scene = session.require("scene")
        pipeline.check_build(scene, self.settings, states)
        return scene, states

    def compute(self, inputs, settings, progress):
        scene, states = inputs
        dynamics, _ = pipeline.run_build(scene, states, settings, progress, check=False)
        return dynamics

    def apply(self, context, dynamics):
        session_for(context.scene).store("dynamics", dynamics, seconds=self.compute_seconds)
        report_warnings(self, dynamics.warnings)
        rate = dynamics.rays / max(self.compute_seconds, 1e-9)
        return (f"Built {dynamics.summary()} in {self.compute_seconds:.2f} s "
                f"({rate / 1e6:.2f} Mrays/s, {format_bytes(dynamics.memory_bytes())})")


class LMDP_OT_solve(EngineJob, bpy.types.Operator):
    """Solve the first-exit LMDP for the desirability z (thesis eq. 2.22) and derive the
    optimal policy u* and the cost-to-go J"""

    bl_idname = "lmdp.solve"
    bl_label = "Solve"
    bl_options = {'REGISTER'}
    stage = ""  # run_solve reports the "solve" stage

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True, stage="dynamics")

    def prepare(self, context):
        selected_meshes(context)
        session = session_for(context.scene)
        dynamics = session.require("dynamics")
        return session.require("scene"), session.require("states"), dynamics

    def compute(self, inputs, settings, progress):
        lmdp, solution, _ = pipeline.run_solve(*inputs, settings, progress)
        return lmdp, solution

    def apply(self, context, result):
        lmdp, solution = result
        session = session_for(context.scene)
        session.store("lmdp", lmdp)
        session.store("solution", solution, seconds=self.compute_seconds)
        report_solution(self, solution)
        return solution.summary() + (f", λ = {lmdp.lambda_:.4g}" if lmdp.cost_mode == "THESIS" else "")


def report_solution(operator, solution):
    """Warn when the solver did not converge or states cannot reach a light."""
    if not solution.converged:
        operator.report({'WARNING'}, f"The {solution.solver} solver did not converge: {solution.message}")
    if solution.n_unreachable:
        operator.report({'WARNING'}, f"{solution.n_unreachable} states cannot reach any light (z = 0, J = inf); "
                                     "they keep the passive dynamics as their policy")


class LMDP_OT_run_pipeline(EngineJob, bpy.types.Operator):
    """Run every LMDP stage on the selected meshes: sample, build, solve, show the desirability,
    bake the indirect light"""

    bl_idname = "lmdp.run_pipeline"
    bl_label = "Run All"
    bl_options = {'REGISTER', 'UNDO'}  # Show and Bake write Blender data (see lmdp.bake)
    stage = ""  # run_all and the bake report their own stages

    show: BoolProperty(
        name="Show Desirability",
        description="After solving, colour the selected meshes by z (lmdp.show_desirability)",
        default=True,
    )
    bake: BoolProperty(
        name="Bake",
        description="After solving, bake the indirect light of the selected meshes (lmdp.bake; "
                    "needs a UV map on each)",
        default=True,
    )
    hook_up: EnumProperty(
        name="Hook Up",
        description="Bake: also show the lightmap in the object's material",
        items=HOOK_UP_ITEMS, default='NONE',
    )

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True)

    def read_settings(self, context):
        # The bake's path length follows the scene's Cycles Light Paths unless light_paths is CUSTOM.
        settings, self.light_paths = bake_settings_from_scene(context.scene)
        return settings

    def prepare(self, context):
        uv_maps, uv_warnings = (prepare_lightmap_uvs(context, selected_meshes(context), self.settings, extract_scene)
                                if self.bake else (None, []))
        scene, names = capture_scene(context, uv_maps)
        pipeline.check_build(scene, self.settings)
        # Every bake check runs now, before any work (a mesh without UV map is reported here),
        # except the texel checks, which rasterise every object: the worker runs them first.
        bake = (planned_bake_inputs(context, scene, names, self.settings, self.hook_up, self.light_paths,
                                    uv_maps, uv_warnings)
                if self.bake else None)
        return scene, names, bake

    def compute(self, inputs, settings, progress):
        scene, names, bake = inputs
        if bake is not None:
            check_bake_texels(bake, progress)
        result = pipeline.run_all(scene, settings, progress, check=False)
        baked = compute_bake(replace(bake, lmdp=result), settings, progress) if bake is not None else None
        return names, result, baked

    def apply(self, context, result):
        names, r, baked = result
        session = session_for(context.scene)
        session.store_result(r, names)
        report_warnings(self, list(r.scene.warnings) + list(r.dynamics.warnings))
        if not r.solution.converged:
            self.report({'WARNING'}, f"The {r.solution.solver} solver did not converge: {r.solution.message}")
        message = f"LMDP solved on {', '.join(names)} in {sum(r.seconds.values()):.2f} s: {r.solution.summary()}"
        if baked is not None:
            bake_message, warnings = apply_bake(context, baked, self.settings, self.hook_up)
            report_warnings(self, warnings)
            message += f"; {bake_message}"
        if self.show:
            # The display operator reads the session just stored; it reports its own skips.
            if 'FINISHED' not in bpy.ops.lmdp.show_desirability('EXEC_DEFAULT'):
                self.report({'WARNING'}, "Show Desirability did not finish (see its message)")
        return message


class LMDP_OT_export_npz(bpy.types.Operator, ExportHelper):
    """Write the states, passive dynamics, state costs, desirability and optimal policy to a
    NumPy .npz file (reload with numpy/scipy only)"""

    bl_idname = "lmdp.export_npz"
    bl_label = "Export LMDP (.npz)"
    bl_options = {'REGISTER'}

    filename_ext = ".npz"
    filter_glob: StringProperty(default="*.npz", options={'HIDDEN'})
    filepath: StringProperty(
        name="File Path",
        description="Where to write the .npz file ('//' is next to the saved .blend file; empty: "
                    "lmdp.npz in the Output Folder)",
        subtype='FILE_PATH', default="", options=BLEND_RELATIVE_PATH)

    @classmethod
    def poll(cls, context):
        return ready(cls, context, stage="solution")

    def execute(self, context):
        try:
            session = session_for(context.scene)
            solution = session.require("solution")
            path = export_path(self.filepath, context.scene.lmdp.output_dir)
            export_npz(path, session.require("states"), session.require("dynamics"), session.require("lmdp"),
                       solution, extra={"objects": list(session.object_names), "blend": bpy.data.filepath})
        except Exception as error:
            return report_error(self, error)
        self.report({'INFO'}, f"Exported the LMDP to {path}")
        return {'FINISHED'}


def export_path(filepath, output_dir):
    """The absolute .npz path of Export: ``filepath`` (``//`` next to the saved .blend, ``~``
    home, otherwise relative to the working folder; a folder gets ``lmdp.npz``), or ``lmdp.npz``
    in the Output Folder when it is empty. Raises ``SceneError`` for ``//`` in an unsaved file,
    no path at all, or a folder that does not exist."""
    if not filepath:
        folder = resolve_output_folder(output_dir)
        if not folder:
            raise SceneError("Set a file path (filepath=...) or an Output Folder to export to")
        path = os.path.join(folder, "lmdp.npz")
    else:
        path = resolve_output_folder(filepath, "file path") if filepath.startswith("//") else filepath
        path = os.path.abspath(os.path.expanduser(path))
        if os.path.isdir(path) or filepath.endswith(("/", os.sep)):
            path = os.path.join(path, "lmdp.npz")
    if not path.lower().endswith(".npz"):
        path += ".npz"
    folder = os.path.dirname(path)
    if not os.path.isdir(folder):
        what = "is a file, not a folder" if os.path.exists(folder) else "does not exist"
        raise SceneError(f"The folder {folder} {what}: create it or pick another file path")
    return path


classes = (
    LMDP_OT_sample_states,
    LMDP_OT_build_dynamics,
    LMDP_OT_solve,
    LMDP_OT_run_pipeline,
    LMDP_OT_export_npz,
)

register, unregister = bpy.utils.register_classes_factory(classes)
