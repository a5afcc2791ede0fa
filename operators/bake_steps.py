"""The three steps of a bake, shared by ``lmdp.bake`` and ``lmdp.run_pipeline`` (Run All).

* :func:`bake_inputs` (main thread): capture the current scene (``extract_scene``) and run every
  check of the bake once, before any work (``lmdp_addon.bake.checks.check_bake``: UV maps,
  overlapping UVs, resolution, light, the solution GUIDED / FINAL_GATHER need), and an output
  folder that can be created; the resulting ``BakePlan`` carries the texels it rasterised.
  :func:`planned_bake_inputs` does the same for Run All, which captures the scene itself and
  solves it before baking.
* :func:`compute_bake` (no bpy; a worker thread in the UI, Esc cancels between work units):
  ``lmdp_addon.bake.driver.bake`` with the plan, so nothing is checked or rasterised twice.
* :func:`apply_bake` (main thread, after success only): the lightmaps into images and files
  (:mod:`.adapters.lightmaps`), the optional material hook-up (:mod:`.adapters.materials`) and
  the session's ``bake`` stage.
"""
from dataclasses import dataclass, field

from ..lmdp_addon.bake import driver
from ..lmdp_addon.bake.checks import check_bake
from .adapters.extract import extract_scene
from .adapters.lightmaps import prepare_output_folder, write_lightmaps
from .adapters.materials import hook_up as hook_up_materials
from .common import selected_meshes
from .session import session_for

#: poll message of a GUIDED / FINAL_GATHER bake without a solution.
SOLVE_FIRST = ("Solve first (LMDP panel > Solve, or Run All): the {mode} bake mode is guided by "
               "the solved optimal policy; or choose bake mode Unguided")


@dataclass
class BakeInputs:
    """What :func:`compute_bake` needs, read and checked on the main thread."""

    scene: object                      #: SceneArrays of the current scene
    plan: object                       #: checks.BakePlan: the objects, their texels, the warnings
    lmdp: object = None                #: LMDPResult that guides GUIDED / FINAL_GATHER
    warnings: list = field(default_factory=list)


def bake_inputs(context, settings):
    """Main thread: capture the scene and check the bake (raises ``LMDPError`` before any work).

    GUIDED and FINAL_GATHER are guided by the session's ``LMDPResult`` as it is."""
    meshes = selected_meshes(context)
    scene = extract_scene(context, meshes)
    lmdp = session_for(context.scene).result if settings.bake_mode != "UNGUIDED" else None
    plan = check_bake(scene, [obj.name for obj in meshes], settings, lmdp)
    prepare_output_folder(settings.output_dir)
    return BakeInputs(scene=scene, plan=plan, lmdp=lmdp, warnings=list(scene.warnings) + list(plan.warnings))


def planned_bake_inputs(scene, names, settings):
    """Main thread: the bake inputs of Run All, which has captured ``scene`` and will sample,
    build and solve it before baking (it sets ``BakeInputs.lmdp`` to that result). Checks
    everything the bake can check before the solution exists."""
    plan = check_bake(scene, names, settings, will_solve=True)
    prepare_output_folder(settings.output_dir)
    return BakeInputs(scene=scene, plan=plan, warnings=list(plan.warnings))


def compute_bake(inputs, settings, progress):
    """No bpy: the engine bake of the checked plan (``lmdp_addon.bake.driver.bake``)."""
    lmdp = inputs.lmdp
    result = driver.bake(inputs.scene, inputs.plan.names, settings, lmdp=lmdp, progress=progress,
                         precompute_seconds=dict(lmdp.seconds) if lmdp is not None else None,
                         plan=inputs.plan)
    result.warnings = list(inputs.warnings)
    return result


def apply_bake(context, result, settings, hook_up="NONE"):
    """Main thread: swap the baked lightmaps in, save files and statistics, hook up materials,
    keep ``result`` as the session's ``bake`` stage.

    Returns ``(message, warnings)``. Raises ``LMDPError`` (nothing changed) if the files cannot
    be written.
    """
    warnings = list(result.warnings)
    output_dir = settings.output_dir
    images = write_lightmaps(result, output_dir, warnings)
    warnings += hook_up_materials(images, hook_up)
    session_for(context.scene).store("bake", result, seconds=result.seconds.get("bake"))
    rays = sum(ob.stats.total_rays for ob in result.objects)
    bake_seconds = result.seconds.get("bake", 0.0)
    where = f", saved to {output_dir}" if output_dir else ""
    message = (f"Baked {len(result.objects)} lightmap(s) ({result.mode}, {result.n_texels} texels x "
               f"{settings.bake_samples} samples, {rays / 1e6:.2f} M rays) in {bake_seconds:.2f} s{where}")
    return message, warnings
