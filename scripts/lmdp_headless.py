"""Run LMDP Light Transport on a .blend file without the UI.

With Blender::

    blender --background scene.blend --python scripts/lmdp_headless.py -- --output DIR [options]

With the PyPI bpy module (``make venv``)::

    .venv/bin/python scripts/lmdp_headless.py scene.blend --output DIR [options]
    .venv/bin/python scripts/lmdp_headless.py --demo cornell --output DIR   # built-in scene

It loads the extension (an installed ``bl_ext.*.lmdp_light_transport`` if there is one, otherwise
this checkout through a temporary extension repository), checks every argument before any work,
selects the meshes, runs ``bpy.ops.lmdp.run_pipeline()`` (sample, build, solve, show, bake),
exports ``lmdp.npz`` (``lmdp.export_npz``), and writes into ``--output``: ``summary.json``
(objects, settings, the bake's light paths, steps with timings, ``"error"``, ``"exit_status"``) and ``<name>_lmdp.blend``
(a copy of the scene with the results; the input file is never written). Bakes go to
``--output`` too (``scene.lmdp.output_dir``); the pictures are described in
``scripts/lmdp_pictures.py``, the checks of the arguments in ``scripts/lmdp_headless_checks.py``.
``--help`` lists the options, the default selection and the exit statuses (:data:`EXIT_STATUS`).
"""
import argparse
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
from functools import partial

HERE = os.path.dirname(os.path.abspath(__file__))
CHECKOUT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import lmdp_extension  # noqa: E402  (needs HERE on sys.path, also under `blender --python`)
import lmdp_pictures  # noqa: E402
from lmdp_headless_checks import (  # noqa: E402
    StepError, UsageError, apply_settings, carrier_objects, check_blend_file, check_farm_arguments, check_output,
    connect_farm, select_only, setting_items, submodule)

DEMO_KINDS = {"cornell": "CORNELL_BOX", "narrow_opening": "NARROW_OPENING", "plane_under_sky": "PLANE_UNDER_SKY",
              "parallel_squares": "PARALLEL_SQUARES", "heavy": "HEAVY"}

DESCRIPTION = """\
Run the LMDP pipeline (sample, build, solve, show, bake) on a .blend file, or on a built-in
scene (--demo), and write the results into --output.

Without --objects the states go on every visible mesh that can carry them: meshes without
faces and meshes that emit light on every face are left out, and so, when the run bakes with
auto_lightmap_uvs off, are meshes without a UV map (they still occlude and reflect light; with
it on, the default, the bake gives them the UV map "LMDP Lightmap"); the script names each mesh
it leaves out. --objects is only needed to choose other meshes."""

EXIT_STATUS = """\
exit status:
  0    success: the results are in --output
  1    the pipeline failed (e.g. a scene with no light, a setting an LMDP operator refuses, a
       render or the save failed) or an internal error; summary.json's "error" says what happened
  2    bad arguments: a missing, unreadable or corrupt .blend file, an unusable --output,
       --objects naming what cannot carry states, --set with an unknown key or a bad value,
       --demo with an unknown kind, conflicting options, a --scheduler that cannot be reached or
       whose workers run another engine; nothing was computed, and when --output
       is usable summary.json's "error" names the argument
  130  interrupted (Ctrl+C)
An error ends the run with one line on stderr, "lmdp_headless.py: error: ...", that names the
argument or the step and what to do (for bad arguments it is the only line)."""


class HeadlessParser(argparse.ArgumentParser):
    """argparse whose errors raise :class:`UsageError` (one line, summary.json) instead of exiting."""

    def error(self, message):
        raise UsageError(f"{message} (see --help)")


def script_arguments(argv):
    """The script's own arguments: after ``--`` when present (Blender's convention), else argv[1:]."""
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    if "--python" in argv or "-P" in argv:  # run by the blender binary without Blender's `--`
        raise UsageError("inside Blender, put the script's arguments after `--`: blender scene.blend "
                         "--background --python scripts/lmdp_headless.py -- --output DIR")
    return argv[1:]


def build_parser():
    parser = HeadlessParser(prog="lmdp_headless.py", description=DESCRIPTION, epilog=EXIT_STATUS,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("blend", nargs="?", help="the .blend file (omit inside `blender scene.blend "
                        "--python ...`, where Blender has loaded it already); it is never written")
    parser.add_argument("--output", required=True, help="folder for summary.json, lmdp.npz, bakes "
                        "and the result .blend (created if missing)")
    parser.add_argument("--objects", default=None, help="comma-separated names of the meshes that "
                        "carry the states (default: see above); a name that contains commas is "
                        "matched whole")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="set scene.lmdp.KEY (repeatable), e.g. --set point_count=4096; values "
                        "are checked against the setting's type and range")
    parser.add_argument("--demo", choices=sorted(DEMO_KINDS), help="build a built-in scene instead of "
                        "loading a file")
    parser.add_argument("--dry-run", action="store_true", help="load, select and configure, write "
                        "summary.json, but run no LMDP operator")
    parser.add_argument("--pictures", action=argparse.BooleanOptionalAction, default=None,
                        help="render z, the policy arrows and a probe with the scene camera into "
                        "--output (default: on with --demo, off for a .blend file)")
    parser.add_argument("--bake", action=argparse.BooleanOptionalAction, default=None,
                        help="bake the indirect light of the meshes that carry the states into "
                        "--output (default: on; with --set auto_lightmap_uvs=false a mesh without UV "
                        "map is left out of the default selection, and one named in --objects turns "
                        "the bake off, which the script says; --bake refuses it instead; --no-bake "
                        "also puts states on meshes without UV map)")
    # -- bake farms (lmdp_addon.farm, Dask distributed)
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run the build's ray batches and the bake's work units on the Dask "
                        "cluster of this scheduler (e.g. tcp://host:8786; the results are byte-identical "
                        "to a local run); each worker: PYTHONPATH=/path/to/checkout dask worker "
                        "ADDRESS --nthreads 1")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="start a local Dask cluster of N worker processes for the run instead")
    return parser


# -- the arguments ------------------------------------------------------------------------------
def check_arguments(args):
    """Every check that needs no Blender data: the .blend file, --set's form, conflicts."""
    if args.blend and args.demo:
        raise UsageError("give either a .blend file or --demo, not both")
    if args.blend:
        check_blend_file(args.blend)
    if args.objects is not None and not any(n.strip() for n in args.objects.split(",")):
        raise UsageError(f"--objects {args.objects!r} names no object: give comma-separated "
                         "object names, e.g. --objects Floor,Wall (or leave --objects out)")
    if args.dry_run and (args.bake or args.pictures):
        flag = "--bake" if args.bake else "--pictures"
        raise UsageError(f"--dry-run runs nothing, so {flag} would do nothing: drop one of them")
    setting_items(args.settings)
    check_farm_arguments(args)


def usable_output(argv):
    """--output of a command line that failed to parse, when it names a usable folder (else None)."""
    parser = HeadlessParser(add_help=False)
    parser.add_argument("--output")
    try:
        return check_output(parser.parse_known_args(argv)[0].output)
    except UsageError:
        return None


# -- the extension --------------------------------------------------------------------------------
def load_extension(cleanup):
    """Module name of the enabled extension: installed if present, else this checkout."""
    module = lmdp_extension.find_enabled()
    if module:
        return module, "installed (enabled)"
    module = lmdp_extension.find_installed()
    if module:
        return lmdp_extension.enable(module), "installed"
    repo_dir = tempfile.mkdtemp(prefix="lmdp_repo_")
    cleanup.append(lambda: remove_repo_directory(repo_dir))  # runs last (cleanup runs in reverse)
    module, repo = lmdp_extension.register_checkout(CHECKOUT, repo_dir, repo_module="lmdp_headless_checkout")
    cleanup.append(lambda: lmdp_extension.unregister_checkout(module, repo))
    return module, f"checkout {CHECKOUT}"


def remove_repo_directory(repo_dir):
    """Remove the temporary repository: unlink the checkout symlink first, never follow it."""
    link = os.path.join(repo_dir, lmdp_extension.EXTENSION_ID)
    if os.path.islink(link):
        os.unlink(link)
    shutil.rmtree(repo_dir, ignore_errors=True)


def operator_message(error):
    """The text of a ``bpy.ops`` RuntimeError on one line, without Blender's "Error: " prefix."""
    text = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
    return text[len("Error: "):] if text.startswith("Error: ") else text


# -- scene ----------------------------------------------------------------------------------------
def build_demo(kind, common):
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    try:
        common.call_operator("lmdp.add_demo_scene", kind=DEMO_KINDS[kind])
    except RuntimeError as error:
        raise StepError(f"lmdp.add_demo_scene failed: {operator_message(error)}") from error


def open_scene(args, common, preloaded):
    """Build the demo or open the .blend file; returns (summary's "blend", the results' name).

    ``preloaded``: the file Blender had loaded before the script ran (``blender scene.blend
    --python ...``); naming another one, or --demo, as well is a conflict."""
    import bpy
    if preloaded and (args.demo or (args.blend and not _same_file(preloaded, args.blend))):
        other = f"--demo {args.demo}" if args.demo else f"the arguments name {args.blend}"
        raise UsageError(f"Blender has loaded {preloaded} and {other}: give one scene")
    if args.demo:
        build_demo(args.demo, common)
        return f"demo:{args.demo}", args.demo
    if args.blend:
        try:
            bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend), load_ui=False)
        except RuntimeError as error:
            raise UsageError(f"{args.blend}: Blender cannot open it ({operator_message(error)}): give "
                             "a complete .blend file (a truncated save or a newer Blender's file "
                             "cannot be read)") from None
    elif not bpy.data.filepath:
        raise UsageError("no .blend file: pass scene.blend (or run inside `blender scene.blend "
                         "--background --python ...`), or use --demo cornell")
    return bpy.data.filepath, os.path.splitext(os.path.basename(bpy.data.filepath))[0]


def _same_file(a, b):
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def leave_edit_mode():
    """Switch objects saved in Edit (or another) Mode to Object Mode, so the capture sees their
    edits; returns their names. Only the loaded copy changes, never the input file."""
    import bpy
    view_layer = bpy.context.view_layer
    editing = sorted(obj.name for obj in view_layer.objects if obj.mode != 'OBJECT')
    for name in editing:
        obj = view_layer.objects[name]
        if obj.mode == 'OBJECT':  # left with an earlier one (multi-object editing)
            continue
        view_layer.objects.active = obj
        try:
            bpy.ops.object.mode_set(mode='OBJECT')
        except RuntimeError as error:
            raise StepError(f"{name} is in {obj.mode.replace('_', ' ').title()} Mode and switching "
                            f"to Object Mode failed ({operator_message(error)}): save the file in "
                            "Object Mode") from None
    if editing:
        print(f"[LMDP] {', '.join(editing)}: switched to Object Mode, as Blender does before it "
              "renders (the input file is not changed)", flush=True)
    return editing


# -- running --------------------------------------------------------------------------------------
def run_operator(common, idname, steps, **kwargs):
    start = time.perf_counter()
    step = {"operator": idname, "arguments": {k: str(v) for k, v in kwargs.items()}}
    steps.append(step)
    print(f"[LMDP] running {idname}", flush=True)
    try:
        result = common.call_operator(idname, **kwargs)
    except RuntimeError as error:  # bpy.ops raises with the operator's ERROR report
        message = operator_message(error)
        step.update(status="FAILED", seconds=time.perf_counter() - start, message=message)
        raise StepError(f"{idname} failed: {message}") from error
    step.update(status=sorted(result)[0] if result else "", seconds=time.perf_counter() - start)
    if "FINISHED" not in result:
        raise StepError(f"{idname} returned {sorted(result)}")
    return result


def run_pipeline(common, output, steps, bake=True, show=True):
    run_operator(common, "lmdp.run_pipeline", steps, bake=bake, show=show)
    run_operator(common, "lmdp.export_npz", steps, filepath=os.path.join(output, "lmdp.npz"))


def session_summary(extension, scene):
    session = submodule(extension, "operators.session").peek(scene)
    if session is None:
        return None
    return {
        "timings": dict(session.timings),
        "status": [f"{stage}: {text}" for stage, text in session.status_lines()],
        "messages": [text for _t, _stage, _level, text in session.messages],
    }


def compute(args, common, extension, output, name, summary):
    """Run All (and the pictures), then save the result .blend; fills ``summary``."""
    import bpy
    scene = bpy.context.scene
    try:
        run_pipeline(common, output, summary["steps"], bake=summary["bake"], show=scene.lmdp.run_all_show)
        if args.pictures if args.pictures is not None else bool(args.demo):
            explicit = set(setting_items(args.settings))
            try:
                summary["pictures"] = lmdp_pictures.render_pictures(
                    partial(run_operator, common), extension, output, name, summary["steps"], explicit, args.demo)
            except RuntimeError as error:  # bpy.ops.render.render
                raise StepError(f"rendering the pictures failed: {operator_message(error)}") from error
            except submodule(extension, "lmdp_addon.errors").LMDPError as error:  # e.g. a material hook-up
                raise StepError(f"the pictures failed: {error}") from error
    finally:
        summary["session"] = session_summary(extension, scene)
    result_blend = os.path.join(output, f"{name}_lmdp.blend")
    try:
        bpy.ops.wm.save_as_mainfile(filepath=result_blend, copy=True)
    except RuntimeError as error:
        raise StepError(f"saving {result_blend} failed: {operator_message(error)}") from error
    summary["result_blend"] = result_blend


def run(args, output, summary, cleanup):
    """Everything after the arguments: load, configure, select, compute (unless --dry-run)."""
    import bpy
    preloaded = bpy.data.filepath
    try:
        extension, origin = load_extension(cleanup)
    except Exception as error:  # the add-on's own import or registration error
        raise StepError(f"could not load the LMDP extension: {type(error).__name__}: {error}") from error
    summary["extension"] = {"module": extension, "origin": origin}
    farm = connect_farm(args, extension, cleanup)     # before any work: refused here if unusable
    common = submodule(extension, "operators.common")
    summary["blend"], name = open_scene(args, common, preloaded)
    if os.path.isdir(os.path.join(output, f"{name}_lmdp.blend")):
        raise UsageError(f"--output {output}: {name}_lmdp.blend in it is a folder, and the script "
                         "saves the result .blend there: remove it or give another folder")
    summary["mode_switched"] = leave_edit_mode()
    scene = bpy.context.scene
    if args.pictures and scene.camera is None:
        raise UsageError(f"--pictures: scene '{scene.name}' has no active camera (the pictures are "
                         "taken with it): set one (Scene Properties > Camera), or drop --pictures")
    scene.lmdp.output_dir = output
    apply_settings(scene, args.settings)
    objects, summary["bake"], summary["left_out"] = carrier_objects(args, extension)
    select_only(objects)
    summary["objects"] = sorted(obj.name for obj in objects)
    properties = submodule(extension, "operators.properties")
    summary["settings"] = properties.settings_from_scene(scene).as_dict()
    # The bake's path length: the scene's Cycles Light Paths, or --set light_paths=CUSTOM max_bounces.
    summary["light_paths"] = properties.light_paths_from_scene(scene).as_dict()
    carry = "mesh carries" if len(objects) == 1 else "meshes carry"
    print(f"[LMDP] {len(objects)} {carry} the states: {', '.join(summary['objects'])}", flush=True)
    if not args.dry_run:
        if farm is None:
            compute(args, common, extension, output, name, summary)
            return
        summary["farm"] = {"scheduler": farm.address, "workers": farm.n_workers}
        try:
            with submodule(extension, "lmdp_addon.farm.session").use(farm):
                compute(args, common, extension, output, name, summary)
        finally:
            summary["farm"]["traffic"] = farm.traffic.as_dict()


def write_summary(output, summary):
    """``summary.json`` into ``output``; False (and a line on stderr) if it cannot be written."""
    try:
        with open(os.path.join(output, "summary.json"), "w", encoding="utf-8") as fh:
            json.dump(summary, fh, indent=2, default=str)
        return True
    except OSError as error:
        print(f"lmdp_headless.py: error: cannot write {output}/summary.json ({error.strerror})", file=sys.stderr)
        return False


def main(argv=None):
    """The script: returns its exit status (:data:`EXIT_STATUS`)."""
    argv = list(sys.argv if argv is None else argv)
    summary = {"blend": None, "extension": None, "objects": [], "settings": {}, "steps": [],
               "dry_run": "--dry-run" in argv, "error": None, "exit_status": None}
    output, cleanup, status, message = None, [], 0, None
    try:
        argv = script_arguments(argv)
        args = build_parser().parse_args(argv)
        output = check_output(args.output)
        check_arguments(args)
        run(args, output, summary, cleanup)
    except UsageError as error:
        status, message = 2, str(error)
    except StepError as error:
        status, message = 1, str(error)
    except KeyboardInterrupt:
        status, message = 130, "interrupted (Ctrl+C): the results in --output are incomplete"
    except Exception as error:  # a bug: keep its traceback in the summary
        status, message = 1, f"internal error: {type(error).__name__}: {error}"
        summary["traceback"] = traceback.format_exc()
    finally:
        for action in reversed(cleanup):
            try:
                action()
            except Exception as error:  # cleanup must not hide the result
                print(f"lmdp_headless.py: warning: cleanup failed: {error}", file=sys.stderr)
    summary.update(error=message, exit_status=status)
    if output is None and status == 2:
        output = usable_output(argv)
    written = output is not None and write_summary(output, summary)
    if message:
        where = f" (traceback in {output}/summary.json; please report it)" if "traceback" in summary and written else ""
        print(f"lmdp_headless.py: error: {message}{where}", file=sys.stderr)
        if "traceback" in summary and not written:
            print(summary["traceback"], file=sys.stderr)
    elif not written:
        status = 1
    else:
        print(f"[LMDP] results in {output}", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
