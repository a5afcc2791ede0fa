"""Run LMDP Light Transport on a .blend file without the UI.

With Blender::

    blender --background scene.blend --python scripts/lmdp_headless.py -- --output DIR [options]

With the PyPI bpy module (``make venv``)::

    .venv/bin/python scripts/lmdp_headless.py scene.blend --output DIR [options]
    .venv/bin/python scripts/lmdp_headless.py --demo cornell --output DIR   # built-in scene

Options: ``--objects A,B`` (meshes that carry the states; default: every visible mesh that is not
an emitter), ``--set key=value`` (any ``scene.lmdp`` setting, repeatable), ``--dry-run`` (load,
select and configure, write ``summary.json``, run nothing), ``--bake`` / ``--no-bake`` (bake the
lightmaps; by default when every mesh has a UV map), ``--pictures`` / ``--no-pictures``
(render the solution with the scene camera; on by default with ``--demo``).

It loads the extension (an installed ``bl_ext.*.lmdp_light_transport`` if there is one, otherwise
this checkout through a temporary extension repository), selects the meshes, runs
``bpy.ops.lmdp.run_pipeline()`` (sample, build, solve, show, bake), exports ``lmdp.npz``
(``lmdp.export_npz``), and writes into ``--output``: ``summary.json`` (objects, settings, steps
with timings, errors) and ``<name>_lmdp.blend`` (a copy of the scene with the results). Bakes go
to ``--output`` too (``scene.lmdp.output_dir``); the pictures are described in
``scripts/lmdp_pictures.py``.
Exit status: 0 on success, 1 when a step fails (its message is printed), 2 for bad arguments.
"""
import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from functools import partial

HERE = os.path.dirname(os.path.abspath(__file__))
CHECKOUT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import lmdp_extension  # noqa: E402  (needs HERE on sys.path, also under `blender --python`)
import lmdp_pictures  # noqa: E402

DEMO_KINDS = {"cornell": "CORNELL_BOX", "narrow_opening": "NARROW_OPENING", "plane_under_sky": "PLANE_UNDER_SKY",
              "parallel_squares": "PARALLEL_SQUARES", "heavy": "HEAVY"}


class UsageError(Exception):
    """Bad command line (exit status 2)."""


class StepError(Exception):
    """A step failed (exit status 1)."""


def script_arguments(argv):
    """The script's own arguments: after ``--`` when present (Blender's convention), else argv[1:]."""
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return argv[1:]


def build_parser():
    parser = argparse.ArgumentParser(
        prog="lmdp_headless.py",
        description="Run the LMDP pipeline (sample, build, solve, show, bake) on a .blend file.")
    parser.add_argument("blend", nargs="?", help="the .blend file (omit inside `blender scene.blend "
                        "--python ...`, where Blender has loaded it already)")
    parser.add_argument("--output", required=True, help="folder for summary.json, lmdp.npz, bakes "
                        "and the result .blend (created if missing)")
    parser.add_argument("--objects", default="", help="comma-separated names of the meshes that carry "
                        "the states (default: every visible mesh that is not an emitter)")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="set scene.lmdp.KEY (repeatable), e.g. --set point_count=4096")
    parser.add_argument("--demo", choices=sorted(DEMO_KINDS), help="build a built-in scene instead of "
                        "loading a file")
    parser.add_argument("--dry-run", action="store_true", help="load, select and configure, write "
                        "summary.json, but run no LMDP operator")
    parser.add_argument("--pictures", action=argparse.BooleanOptionalAction, default=None,
                        help="render z, the policy arrows and a probe with the scene camera into "
                        "--output (default: on with --demo, off for a .blend file)")
    parser.add_argument("--bake", action=argparse.BooleanOptionalAction, default=None,
                        help="bake the indirect light of the meshes into --output (default: on when "
                        "every mesh that carries states has a UV map; --bake insists and fails otherwise)")
    return parser


def parse_arguments(argv):
    args = build_parser().parse_args(script_arguments(argv))
    if args.blend and args.demo:
        raise UsageError("give either a .blend file or --demo, not both")
    if args.blend and not os.path.isfile(args.blend):
        raise UsageError(f"no such .blend file: {args.blend}")
    for item in args.settings:
        if "=" not in item:
            raise UsageError(f"--set expects KEY=VALUE, got {item!r}")
    return args


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


def submodule(extension, name):
    import importlib
    return importlib.import_module(f"{extension}.{name}")


# -- scene ----------------------------------------------------------------------------------------
def build_demo(kind, common):
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    try:
        common.call_operator("lmdp.add_demo_scene", kind=DEMO_KINDS[kind])
    except RuntimeError as error:
        raise StepError(f"lmdp.add_demo_scene failed: {error}") from error


def _rgb_positive(socket):
    value = socket.default_value
    try:
        return any(float(c) > 0.0 for c in tuple(value)[:3])
    except TypeError:
        return float(value) > 0.0


def is_emitter(obj):
    """True when a material of ``obj`` emits light (Emission shader or Principled emission)."""
    for slot in obj.material_slots:
        material = slot.material
        if material is None or not material.node_tree:
            continue
        for node in material.node_tree.nodes:
            if node.type == 'EMISSION':
                strength, color = node.inputs.get("Strength"), node.inputs.get("Color")
            elif node.type == 'BSDF_PRINCIPLED':
                strength, color = node.inputs.get("Emission Strength"), node.inputs.get("Emission Color")
            else:
                continue
            if strength is None or color is None:
                continue
            lit_strength = strength.is_linked or float(strength.default_value) > 0.0
            lit_color = color.is_linked or _rgb_positive(color)
            if lit_strength and lit_color:
                return True
    return False


def choose_objects(names_arg):
    """The mesh objects that carry the states (see --objects)."""
    import bpy
    view_layer = bpy.context.view_layer
    if names_arg:
        chosen = []
        for name in (n.strip() for n in names_arg.split(",") if n.strip()):
            obj = bpy.data.objects.get(name)
            if obj is None:
                raise UsageError(f"--objects: no object named {name!r} in the scene")
            if obj.type != 'MESH':
                raise UsageError(f"--objects: {name!r} is a {obj.type.lower()}, not a mesh")
            if obj.name not in view_layer.objects or not obj.visible_get():
                raise UsageError(f"--objects: {name!r} is hidden or not in the view layer: unhide it")
            chosen.append(obj)
        return chosen
    return [obj for obj in view_layer.objects
            if obj.type == 'MESH' and obj.visible_get() and not is_emitter(obj)]


def select_only(objects):
    import bpy
    view_layer = bpy.context.view_layer
    for obj in view_layer.objects:
        obj.select_set(False)
    for obj in objects:
        obj.select_set(True)
    view_layer.objects.active = objects[0] if objects else None


def apply_settings(scene, items):
    """Set ``scene.lmdp`` from ``KEY=VALUE`` strings, converting by the property's type."""
    props = scene.lmdp
    rna = props.bl_rna.properties
    for item in items:
        key, _, text = item.partition("=")
        key = key.strip()
        if key not in rna or key in ("rna_type", "name", "session_id"):
            known = ", ".join(sorted(p.identifier for p in rna if p.identifier not in ("rna_type", "name", "session_id")))
            raise UsageError(f"--set: unknown setting {key!r}; the settings are: {known}")
        prop = rna[key]
        try:
            if prop.type == 'INT':
                value = int(text)
            elif prop.type == 'FLOAT':
                value = float(text)
            elif prop.type == 'BOOLEAN':
                value = text.strip().lower() in ("1", "true", "yes", "on")
            elif prop.type == 'ENUM':
                value = text.strip().upper()
                allowed = [e.identifier for e in prop.enum_items]
                if value not in allowed:
                    raise ValueError(f"expected one of {', '.join(allowed)}")
            else:
                value = text
            setattr(props, key, value)
        except (ValueError, TypeError) as error:
            raise UsageError(f"--set {key}={text}: {error}") from error


# -- running ----------------------------------------------------------------------------------------
def run_operator(common, idname, steps, **kwargs):
    start = time.perf_counter()
    step = {"operator": idname, "arguments": {k: str(v) for k, v in kwargs.items()}}
    steps.append(step)
    print(f"[LMDP] running {idname}", flush=True)
    try:
        result = common.call_operator(idname, **kwargs)
    except RuntimeError as error:  # bpy.ops raises with the operator's ERROR report
        step.update(status="FAILED", seconds=time.perf_counter() - start, message=str(error))
        raise StepError(f"{idname} failed: {error}") from error
    step.update(status=sorted(result)[0] if result else "", seconds=time.perf_counter() - start)
    if "FINISHED" not in result:
        raise StepError(f"{idname} returned {sorted(result)}")
    return result


def run_pipeline(common, output, steps, bake=True):
    run_operator(common, "lmdp.run_pipeline", steps, bake=bake)
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


def open_scene(args, common):
    """Build the demo or open the .blend file; returns (summary's "blend", the results' name)."""
    import bpy
    if args.demo:
        build_demo(args.demo, common)
        return f"demo:{args.demo}", args.demo
    if args.blend:
        bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend), load_ui=False)
    elif not bpy.data.filepath:
        raise UsageError("no .blend file: pass scene.blend (or run inside `blender scene.blend "
                         "--background --python ...`), or use --demo cornell")
    return bpy.data.filepath, os.path.splitext(os.path.basename(bpy.data.filepath))[0]


def carrier_objects(args):
    """The meshes that carry the states: the demo's selection, or :func:`choose_objects`."""
    import bpy
    if args.demo and not args.objects and any(o.type == 'MESH' for o in bpy.context.selected_objects):
        objects = [o for o in bpy.context.selected_objects if o.type == 'MESH']  # the demo's choice
    else:
        objects = choose_objects(args.objects)
    if not objects:
        raise StepError("no mesh to compute: the scene has no visible mesh that is not an emitter "
                        "(use --objects to choose)")
    return objects


def wants_bake(args, objects):
    """--bake / --no-bake, or by default: bake when every mesh has a UV map (else say why not)."""
    if args.bake is not None:
        return args.bake
    no_uv = [obj.name for obj in objects if not obj.data.uv_layers]
    if no_uv:
        print(f"[LMDP] no bake: {', '.join(sorted(no_uv))} ha{'s' if len(no_uv) == 1 else 've'} "
              "no UV map (add one, or pass --bake to insist)", flush=True)
    return not no_uv


def compute(args, common, extension, output, name, objects, summary):
    """Run All (and the pictures), then save the result .blend; fills ``summary``."""
    import bpy
    try:
        summary["bake"] = wants_bake(args, objects)
        run_pipeline(common, output, summary["steps"], bake=summary["bake"])
        if args.pictures if args.pictures is not None else bool(args.demo):
            explicit = {item.partition("=")[0].strip() for item in args.settings}
            summary["pictures"] = lmdp_pictures.render_pictures(
                partial(run_operator, common), extension, output, name, summary["steps"], explicit, args.demo)
    finally:
        summary["session"] = session_summary(extension, bpy.context.scene)
    result_blend = os.path.join(output, f"{name}_lmdp.blend")
    bpy.ops.wm.save_as_mainfile(filepath=result_blend, copy=True)
    summary["result_blend"] = result_blend


def run(args, output, summary, cleanup):
    """Everything after the arguments: load, configure, select, compute (unless --dry-run)."""
    import bpy
    extension, origin = load_extension(cleanup)
    summary["extension"] = {"module": extension, "origin": origin}
    common = submodule(extension, "operators.common")
    summary["blend"], name = open_scene(args, common)
    scene = bpy.context.scene
    scene.lmdp.output_dir = output
    apply_settings(scene, args.settings)
    objects = carrier_objects(args)
    select_only(objects)
    summary["objects"] = sorted(obj.name for obj in objects)
    summary["settings"] = submodule(extension, "operators.properties").settings_from_scene(scene).as_dict()
    print(f"[LMDP] {len(objects)} meshes carry the states: {', '.join(summary['objects'])}", flush=True)
    if not args.dry_run:
        compute(args, common, extension, output, name, objects, summary)


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    try:
        args = parse_arguments(argv)
    except UsageError as error:
        print(f"lmdp_headless.py: error: {error}", file=sys.stderr)
        return 2
    output = os.path.abspath(args.output)
    os.makedirs(output, exist_ok=True)
    summary = {"blend": None, "extension": None, "objects": [], "settings": {}, "steps": [],
               "dry_run": bool(args.dry_run), "error": None}
    cleanup = []
    status = 0
    try:
        run(args, output, summary, cleanup)
    except (UsageError, StepError) as error:
        summary["error"] = str(error)
        print(f"lmdp_headless.py: error: {error}", file=sys.stderr)
        status = 2 if isinstance(error, UsageError) else 1
    finally:
        with open(os.path.join(output, "summary.json"), "w", encoding="utf-8") as fh:
            json.dump(summary, fh, indent=2, default=str)
        for action in reversed(cleanup):
            try:
                action()
            except Exception as error:  # cleanup must not hide the result
                print(f"lmdp_headless.py: warning: cleanup failed: {error}", file=sys.stderr)
    if status == 0:
        print(f"[LMDP] results in {output}", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
