"""The three steps of a bake, shared by ``lmdp.bake`` and ``lmdp.run_pipeline`` (Run All).

* :func:`bake_inputs` (main thread): capture the current scene (``extract_scene``) and run every
  check of the bake once, before any work (``lmdp_addon.bake.checks.check_bake``: UV maps and
  their values, resolution, memory, light, the solution GUIDED / FINAL_GATHER need), objects the
  bake could not tell apart (a linked and a local object of the same name), an output folder that
  can be used, and a material hook-up that would not edit library data. Only the texel checks
  (coverage, overlapping UVs), which rasterise every object and take seconds at 1024² and up, are
  left to the worker, where the progress shows them and Esc cancels them.
  :func:`planned_bake_inputs` does the same for Run All, which captures the scene itself and
  solves it before baking (it runs :func:`check_bake_texels` before it samples).
* :func:`compute_bake` (no bpy; a worker thread in the UI, Esc cancels between objects and work
  units): ``lmdp_addon.bake.driver.bake`` with the plan (its texel checks first, then the bake
  with the texels they rasterised), so nothing is checked or rasterised twice.
* :func:`apply_bake` (main thread, after success only): with ``denoise``, OIDN per UV island
  (:mod:`.adapters.denoise`, laid out by ``lmdp_addon.bake.islands`` in :func:`compute_bake`); the
  lightmaps into images and files (:mod:`.adapters.lightmaps`), the optional material hook-up (:mod:`.adapters.materials`) and
  the session's ``bake`` stage.

The path length comes from the scene's Cycles Light Paths or ``scene.lmdp.max_bounces``
(``scene.lmdp.light_paths``): the operators read ``(settings, light_paths)`` with
``properties.bake_settings_from_scene`` and hand the :class:`~lmdp_addon.settings.LightPaths` to
:func:`bake_inputs`, which refuses a path length of 0; the light paths' clamps reach the engine in
the settings (``clamp_direct`` / ``clamp_indirect``); the result records them (``bake_stats.json``
"light_paths", the report's last words).

Objects are identified by their key, ``name_full`` (the name, or "Floor [library.blend]" for a
linked object), so a linked object never writes into the lightmap of a local namesake.
"""
import copy
from collections import Counter
from dataclasses import dataclass, field

import bpy
import numpy as np

from ..lmdp_addon.bake import connections, driver, reuse
from ..lmdp_addon.bake.checks import check_bake, check_texels, scene_fingerprint
from ..lmdp_addon.bake.content import BakeContent
from ..lmdp_addon.bake.islands import denoise_input
from ..lmdp_addon.errors import SceneError
from ..lmdp_addon.model import pipeline
from .adapters.denoise import denoise_bake
from .adapters.extract import extract_scene
from .adapters.lightmap_uvs import prepare_lightmap_uvs
from .adapters.lightmaps import prepare_output_folder, write_lightmaps
from .adapters.materials import check_hook_up, hook_up as hook_up_materials
from .common import selected_meshes
from .session import session_for

#: The bake modes that read the solved LMDP (the others need none).
SOLUTION_MODES = ("GUIDED", "FINAL_GATHER", "RESIDUAL")
#: AUTO reads it when its pilot asks for it: the session's if usable, else solved during the bake.


@dataclass
class BakeInputs:
    """What :func:`compute_bake` needs, read and checked on the main thread."""

    scene: object                      #: SceneArrays of the current scene
    plan: object                       #: checks.BakePlan: the objects, their texels, the warnings
    lmdp: object = None                #: LMDPResult that guides GUIDED / FINAL_GATHER / RESIDUAL
    solve: bool = False                #: no usable solution: compute_bake samples, builds, solves first
    warnings: list = field(default_factory=list)
    keys: dict = field(default_factory=dict)  #: object name -> key (``name_full``)
    light_paths: object = None         #: the LightPaths the bake follows (None: settings.max_bounces)
    uv_maps: dict = field(default_factory=dict)  #: object name -> the UV map its lightmap is laid out on


@dataclass
class BakedLightmaps:
    """What :func:`compute_bake` hands to :func:`apply_bake`."""

    result: object                     #: the engine's BakeResult
    keys: dict                         #: object name -> key (``name_full``)
    light_paths: object = None         #: the LightPaths of the bake
    solved: object = None              #: the LMDPResult compute_bake solved first (None: reused)
    names: tuple = ()                  #: the meshes that carry its states (every mesh with states)
    denoise: dict = field(default_factory=dict)  #: object name -> islands.DenoiseInput (denoise on)
    uv_maps: dict = field(default_factory=dict)  #: object name -> the UV map its lightmap is laid out on
    connections_off: str = None        #: why no light connections were traced although asked for
    reuse_off: str = None              #: why the texels did not share their first bounces although asked to


def check_light_paths(light_paths):
    """Raise ``SceneError`` when the scene's Cycles Light Paths allow no diffuse bounce (Cycles'
    indirect bake would be black); return the light paths' warnings."""
    if light_paths is None:
        return []
    if light_paths.path_length < 1:
        raise SceneError(f"The scene's Cycles Light Paths allow no indirect diffuse light (Max Bounces "
                         f"{light_paths.max_bounces}, Diffuse {light_paths.diffuse_bounces}): raise them "
                         "(Render Properties > Light Paths), or set the LMDP Bake's Light Paths to Custom")
    return light_paths.warnings()


def _origin(obj):
    return "local" if obj.library is None else f"linked from {obj.library.filepath}"


def check_distinct_names(context, scene, meshes):
    """Raise ``SceneError`` when a selected mesh shares its name with another captured object
    (a linked and a local one): the bake's results are matched to objects by name."""
    counts = Counter(scene.object_names)
    for obj in meshes:
        if counts[obj.name] > 1:
            same = [o for o in context.view_layer.objects if o.name == obj.name]
            where = ", ".join(_origin(o) for o in same) or "twice"
            raise SceneError(f"Two objects named '{obj.name}' are in the scene ({where}): the bake "
                             "cannot tell them apart; rename the local one, or hide one of them")


def object_keys(meshes):
    """{object name: key} of the meshes to bake."""
    return {obj.name: obj.name_full for obj in meshes}


def usable_solution(result, scene, settings):
    """The session's ``LMDPResult`` if it can serve a bake of ``scene`` in ``settings.bake_mode``:
    solved, on this very scene (``checks.scene_fingerprint``: same geometry, materials and
    lights), and in the PHYSICAL cost mode where the mode reads z itself (FINAL_GATHER,
    RESIDUAL); else None."""
    if result is None or result.solution is None or result.scene is None:
        return None
    if settings.bake_mode in ("FINAL_GATHER", "RESIDUAL") and result.solution.cost_mode != "PHYSICAL":
        return None
    if scene_fingerprint(scene) != scene_fingerprint(result.scene):
        return None
    return result


def bake_inputs(context, settings, hook_up="NONE", light_paths=None):
    """Main thread: capture the scene and check the bake (raises ``LMDPError`` before any work).

    GUIDED, FINAL_GATHER and RESIDUAL read the session's ``LMDPResult`` when it is a usable
    solution of this scene (:func:`usable_solution`); otherwise the bake samples, builds and
    solves the selected meshes first (``BakeInputs.solve``: :func:`compute_bake` runs the
    pipeline with ``settings``, :func:`apply_bake` keeps its result in the session), so a first
    bake on a fresh scene just works. ``settings`` carry the path length of ``light_paths``
    (``properties.bake_settings_from_scene``)."""
    path_warnings = check_light_paths(light_paths)
    meshes = selected_meshes(context)
    uv_maps, uv_warnings = prepare_lightmap_uvs(context, meshes, settings, extract_scene)
    scene = extract_scene(context, meshes, uv_maps=uv_maps)
    check_distinct_names(context, scene, meshes)
    names = [obj.name for obj in meshes]
    lmdp, solve = None, False
    if settings.bake_mode in SOLUTION_MODES:
        lmdp = usable_solution(session_for(context.scene).result, scene, settings)
        solve = lmdp is None
    elif settings.bake_mode == "AUTO":     # reused if the pilot asks for it (else solved then)
        lmdp = usable_solution(session_for(context.scene).result, scene, settings)
    if solve:
        solve_scene(scene).check_for_lmdp()
        pipeline.check_build(solve_scene(scene), settings)
    plan = check_bake(scene, names, settings, lmdp, will_solve=solve, rasterise=False)
    prepare_output_folder(settings.output_dir)
    check_hook_up(meshes, hook_up)
    return BakeInputs(scene=scene, plan=plan, lmdp=lmdp, solve=solve,
                      warnings=path_warnings + uv_warnings + list(scene.warnings) + list(plan.warnings),
                      keys=object_keys(meshes), light_paths=light_paths, uv_maps=uv_maps)


def planned_bake_inputs(context, scene, names, settings, hook_up="NONE", light_paths=None, uv_maps=None,
                        uv_warnings=()):
    """Main thread: the bake inputs of Run All, which has captured ``scene`` (the selected meshes
    ``names``, laid out on ``uv_maps``: :func:`.adapters.lightmap_uvs.prepare_lightmap_uvs`, whose
    ``uv_warnings`` it passes on) and will sample, build and solve it before baking (it sets
    ``BakeInputs.lmdp`` to that result). Checks everything the bake can check before the solution
    exists."""
    path_warnings = check_light_paths(light_paths)
    meshes = [obj for obj in selected_meshes(context) if obj.name in set(names)]
    check_distinct_names(context, scene, meshes)
    plan = check_bake(scene, names, settings, will_solve=True, rasterise=False)
    prepare_output_folder(settings.output_dir)
    check_hook_up(meshes, hook_up)
    return BakeInputs(scene=scene, plan=plan, warnings=path_warnings + list(uv_warnings) + list(plan.warnings),
                      keys=object_keys(meshes), light_paths=light_paths, uv_maps=dict(uv_maps or {}))


def check_bake_texels(inputs, progress):
    """No bpy: the texel checks the main thread left out (they rasterise every object; here the
    progress reports them and Esc cancels them). Run All calls this before it samples, so a UV
    problem stops it before the long stages; :func:`compute_bake` needs no call (the driver runs
    them first when they are still due)."""
    check_texels(inputs.scene, inputs.plan, progress)


def solve_scene(scene):
    """The captured ``scene`` with states on every mesh (a shallow copy: the same arrays), for
    the solve a bake runs itself: the light the bake's paths meet on unselected walls is then
    guided and gathered too. The scene fingerprint ignores which meshes carry states, so the
    session's result serves the next bake of any selection in this scene."""
    solved = copy.copy(scene)
    solved.object_carries_states = np.ones(len(scene.object_names), dtype=bool)
    return solved


def compute_bake(inputs, settings, progress):
    """No bpy: the engine bake of the checked plan (``lmdp_addon.bake.driver.bake``); with
    ``inputs.solve`` the texel checks, then ``pipeline.run_all`` (sample, build, solve) first."""
    lmdp, solved = inputs.lmdp, None
    if inputs.solve:
        check_bake_texels(inputs, progress)       # a UV problem stops the bake before the solve
        lmdp = solved = pipeline.run_all(solve_scene(inputs.scene), settings, progress, check=False)
    auto = settings.bake_mode == "AUTO"

    def solve():     # AUTO's pilot asked for the solution: the pipeline of a bake that solves
        return pipeline.run_all(solve_scene(inputs.scene), settings, progress, check=False)
    result = driver.bake(inputs.scene, inputs.plan.names, settings, lmdp=lmdp, progress=progress,
                         precompute_seconds=dict(lmdp.seconds) if lmdp is not None and not auto else None,
                         plan=inputs.plan, solve=solve if auto else None)
    if result.auto is not None and result.auto.lmdp is not None:
        solved = result.auto.lmdp
    result.warnings = list(inputs.warnings) + list(inputs.plan.texel_warnings)
    if inputs.light_paths is not None:
        result.light_paths = inputs.light_paths.as_dict()
    carriers = () if solved is None else tuple(np.asarray(solved.scene.object_names)[
        np.unique(solved.states.point_object)].tolist())
    prepared = {}
    if settings.denoise and result.atlases:
        result.warnings.append("Denoise is not applied to an atlas lightmap yet: bake without Atlas to "
                               "denoise each object's lightmap")
    elif settings.denoise:   # the islands laid out for the denoiser here, off the main thread
        prepared = {ob.name: denoise_input(inputs.scene, ob, settings.multiply_color) for ob in result.objects}
    return BakedLightmaps(result=result, keys=dict(inputs.keys), light_paths=inputs.light_paths, solved=solved,
                          names=carriers, denoise={k: v for k, v in prepared.items() if v is not None},
                          uv_maps=dict(inputs.uv_maps),
                          connections_off=connections.off_reason(inputs.scene, settings),
                          reuse_off=reuse.off_reason(inputs.scene, settings))


def _objects_by_key(keys):
    """{object name: the object whose key it is, or None if it is gone}."""
    by_key = {obj.name_full: obj for obj in bpy.data.objects}
    return {name: by_key.get(key) for name, key in keys.items()}


def apply_bake(context, baked, settings, hook_up="NONE"):
    """Main thread: swap the baked lightmaps in, save files and statistics, hook up materials,
    keep the ``BakeResult`` as the session's ``bake`` stage.

    Returns ``(message, warnings)``. Raises ``LMDPError`` (nothing changed) if the files cannot
    be written or the hook-up would edit library data (checked again: the scene may have
    changed while the bake ran).
    """
    result = baked.result
    warnings = list(result.warnings)
    if baked.solved is not None:
        warnings += list(baked.solved.dynamics.warnings)
    output_dir = prepare_output_folder(settings.output_dir)
    objects = _objects_by_key(baked.keys)
    present = [obj for obj in objects.values() if obj is not None]
    check_hook_up(present, hook_up)
    if baked.denoise:
        denoise_bake(result, baked.denoise, settings.bake_margin)
        warnings.append("Denoised lightmaps blur contact shadows over a few texels (where light falls off "
                        "sharply, e.g. around an object's feet); the path-traced lightmap is kept as the image "
                        "'<lightmap>_raw'")
    images = write_lightmaps(result, output_dir, warnings, baked.keys, output_format=settings.output_format,
                             output_8bit=settings.output_8bit, view_scene=context.scene)
    images = {ob.name: images[result.output_of(ob.name)] for ob in result.objects}   # atlas members share one
    gone = [name for name, obj in objects.items() if obj is None]
    if gone and hook_up != "NONE":
        warnings.append(f"{', '.join(gone)} no longer in the file: lightmap written, not hooked up")
    warnings += hook_up_materials([(objects[n], im) for n, im in images.items()
                                    if objects.get(n) is not None], hook_up, baked.uv_maps)
    session = session_for(context.scene)
    if baked.solved is not None:             # the bake solved the LMDP first: keep it (Run All does)
        session.store_result(baked.solved, baked.names)
    session.store("bake", result, seconds=result.seconds.get("bake"))
    rays = sum(ob.stats.total_rays for ob in result.objects)
    bake_seconds = result.seconds.get("bake", 0.0)
    where = f", saved to {output_dir}" if output_dir else ""
    content = BakeContent.from_settings(settings).label() + (", denoised" if baked.denoise else "")
    message = (f"Baked {len(result.objects)} lightmap(s) ({result.mode}, {content}, {result.n_texels} texels x "
               f"{settings.bake_samples} samples, {rays / 1e6:.2f} M rays) in {bake_seconds:.2f} s{where}")
    if result.auto is not None:
        message += f"; {result.auto.sentence()}"
    if baked.solved is not None:
        message += (f"; sampled, built and solved the LMDP{'' if result.auto is not None else ' first'} "
                    f"({baked.solved.states.n_points} points, {sum(baked.solved.seconds.values()):.2f} s)")
    if baked.light_paths is not None:
        message += f"; {baked.light_paths.summary()}"
    if result.portals.get("used"):
        message += (f"; world portals ({100 * result.portals['probe_visible']:.0f} % of the probe's world samples "
                    f"saw the world, {result.portals['regions']} region(s))")
    elif result.portals.get("off"):
        message += f"; {result.portals['off']}"
    if any(ob.stats.light_vertices for ob in result.objects):
        message += f"; light connections (share {settings.light_share:g})"
    elif baked.connections_off:
        message += f"; {baked.connections_off}"
    shared = sum(ob.stats.shared_hits for ob in result.objects)
    if shared:
        paths = max(sum(ob.stats.paths for ob in result.objects), 1)
        message += (f"; path reuse (tiles of about {settings.path_reuse} x {settings.path_reuse} texels, "
                    f"{shared / paths:.1f} other texels' first hits per path)")
    elif baked.reuse_off:
        message += f"; {baked.reuse_off}"
    return message, warnings
