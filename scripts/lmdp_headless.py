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
``bpy.ops.lmdp.run_pipeline()`` (sample, build, solve, show, bake; or, while that operator does
not exist yet, every stage operator that does), exports ``lmdp.npz`` when ``lmdp.export_npz`` exists, and writes into ``--output``:
``summary.json`` (objects, settings, steps with timings, errors) and ``<name>_lmdp.blend`` (a copy
of the scene with the results). Bakes go to ``--output`` too (``scene.lmdp.output_dir``).
With pictures, Cycles renders (Standard view transform) of ``<name>_z.png`` (z as colours,
``lmdp.show_desirability`` + ``lmdp.view_desirability(target='RENDER')``), ``<name>_policy.png``
(``lmdp.show_policy(as_mesh=True)`` in the lit scene), ``<name>_probe.png`` (``lmdp.probe_policy``)
``<name>_lightmaps.png`` (the baked lightmaps on their objects) and, when matplotlib is
importable, ``<name>_z_legend.png`` (the z picture with its colour bar).
Exit status: 0 on success, 1 when a step fails (its message is printed), 2 for bad arguments.
"""
import argparse
import json
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
CHECKOUT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import lmdp_extension  # noqa: E402  (needs HERE on sys.path, also under `blender --python`)

DEMO_KINDS = {"cornell": "CORNELL_BOX", "narrow_opening": "NARROW_OPENING", "plane_under_sky": "PLANE_UNDER_SKY",
              "parallel_squares": "PARALLEL_SQUARES", "heavy": "HEAVY"}
STAGE_OPERATORS = ("lmdp.sample_states", "lmdp.build_dynamics", "lmdp.solve",
                   "lmdp.show_desirability", "lmdp.bake")


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
    if not common.operator_available("lmdp.add_demo_scene"):
        raise StepError("the built-in demo scenes are not in this build of the extension "
                        "(lmdp.add_demo_scene is not registered: operators/demo_scenes.py)")
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
    if common.operator_available("lmdp.run_pipeline"):
        run_operator(common, "lmdp.run_pipeline", steps, bake=bake)
    else:
        stages = [idname for idname in STAGE_OPERATORS if common.operator_available(idname)
                  and (bake or idname != "lmdp.bake")]
        if not stages:
            raise StepError("this build of the extension has no LMDP pipeline operators yet "
                            "(neither lmdp.run_pipeline nor any stage operator is registered)")
        for idname in stages:
            run_operator(common, idname, steps)
    if common.operator_available("lmdp.export_npz"):
        run_operator(common, "lmdp.export_npz", steps, filepath=os.path.join(output, "lmdp.npz"))


# -- pictures -----------------------------------------------------------------------------------------
#: Render size and samples of the pictures (2 CPU cores: seconds, not minutes).
PICTURE_SIZE = 320
PICTURE_SAMPLES = {"z": 16, "lit": 32}
#: Where the demo probes u* (a point on the floor in front of the boxes), per demo kind.
DEMO_PROBES = {"cornell": (0.12, -0.38, 0.0), "heavy": (0.12, -0.38, 0.0)}
PICTURE_OPERATORS = ("lmdp.show_desirability", "lmdp.view_desirability", "lmdp.show_policy",
                     "lmdp.probe_policy")


def configure_render(scene, samples):
    """Cycles on the CPU at PICTURE_SIZE, Standard view transform, 8-bit PNG; OIDN when the
    samples are few for a lit scene (the colour renders are emission only and need none)."""
    scene.render.engine = 'CYCLES'
    scene.cycles.device = 'CPU'
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = samples > PICTURE_SAMPLES["z"]
    if scene.cycles.use_denoising:
        try:
            scene.cycles.denoiser = 'OPENIMAGEDENOISE'
        except TypeError:  # a build without OIDN: more samples instead
            scene.cycles.use_denoising = False
            scene.cycles.samples = 2 * samples
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.look = 'None'
    scene.render.resolution_x = scene.render.resolution_y = PICTURE_SIZE
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = 'PNG'
    scene.render.image_settings.color_mode = 'RGB'
    scene.render.image_settings.color_depth = '8'


def render_picture(scene, path, samples, steps):
    import bpy
    configure_render(scene, samples)
    scene.render.filepath = path
    start = time.perf_counter()
    print(f"[LMDP] rendering {os.path.basename(path)} ({PICTURE_SIZE}x{PICTURE_SIZE}, {samples} samples)", flush=True)
    bpy.ops.render.render(write_still=True)
    steps.append({"operator": "render.render", "arguments": {"filepath": path}, "status": "FINISHED",
                  "seconds": time.perf_counter() - start})
    return path


def _hide_generated(kind, hidden):
    import bpy
    for obj in bpy.data.objects:
        if obj.get("lmdp_generated") == kind:
            obj.hide_render = hidden


def render_pictures(common, extension, output, name, steps, explicit, demo):
    """The three pictures of the module docstring; returns {kind: path}."""
    import bpy
    missing = [i for i in PICTURE_OPERATORS if not common.operator_available(i)]
    if missing:
        print(f"[LMDP] no pictures: this build has no {', '.join(missing)}", flush=True)
        return {}
    scene = bpy.context.scene
    if scene.camera is None:
        print("[LMDP] no pictures: the scene has no camera", flush=True)
        return {}
    props = scene.lmdp
    if "display_subdivide" not in explicit:
        props.display_subdivide = True  # a faithful picture even on single-quad walls
    pictures = {}
    run_operator(common, "lmdp.show_desirability", steps)
    run_operator(common, "lmdp.view_desirability", steps, target='RENDER')
    try:
        pictures["z"] = render_picture(scene, os.path.join(output, f"{name}_z.png"), PICTURE_SAMPLES["z"], steps)
    finally:
        run_operator(common, "lmdp.view_desirability", steps, target='RENDER', enable=False)
    legend = legend_picture(extension, scene, pictures["z"], os.path.join(output, f"{name}_z_legend.png"))
    if legend:
        pictures["z_legend"] = legend

    if "policy_subset" not in explicit:
        props.policy_subset = 'MOST_INFORMATIVE'
    if "policy_max_points" not in explicit:
        props.policy_max_points = 40
    if "policy_arrow_scale" not in explicit:
        props.policy_arrow_scale = 0.3 * scene_size(extension, scene)
    run_operator(common, "lmdp.show_policy", steps, as_mesh=True)
    _hide_generated("probe", True)
    pictures["policy"] = render_picture(scene, os.path.join(output, f"{name}_policy.png"), PICTURE_SAMPLES["lit"], steps)

    location = DEMO_PROBES.get(demo)
    if location is None:  # a .blend file: probe where the policy is most informative
        view = submodule(extension, "operators.session").peek(scene).get("policy")
        states = submodule(extension, "operators.session").peek(scene).get("states")
        location = tuple(states.points[view.points[0]]) if view is not None and len(view.points) else None
    if location is not None:
        run_operator(common, "lmdp.probe_policy", steps, use_cursor=False, location=location, as_mesh=True,
                     next_states=16)
        _hide_generated("policy", True)
        _hide_generated("probe", False)
        pictures["probe"] = render_picture(scene, os.path.join(output, f"{name}_probe.png"), PICTURE_SAMPLES["lit"], steps)
        _hide_generated("policy", False)

    lightmaps = lightmap_picture(extension, scene, os.path.join(output, f"{name}_lightmaps.png"), steps)
    if lightmaps:
        pictures["lightmaps"] = lightmaps
    return pictures


def lightmap_picture(extension, scene, path, steps):
    """The baked lightmaps shown on their objects (each object's preview material: emission =
    its ``<object>_lmdp_indirect`` image, i.e. E_ind/π as baked, no albedo), rendered like the z
    picture; the materials are restored afterwards. None when nothing was baked."""
    import bpy
    lightmaps = submodule(extension, "operators.adapters.lightmaps")
    materials = submodule(extension, "operators.adapters.materials")
    baked = [(obj, lightmaps.own_image(obj.name)) for obj in scene.objects if obj.type == 'MESH']
    baked = [(obj, image) for obj, image in baked if image is not None]
    if not baked:
        return None
    for obj, image in baked:
        materials.hook_preview(obj, image)
    _hide_generated("policy", True)
    _hide_generated("probe", True)
    try:
        return render_picture(scene, path, PICTURE_SAMPLES["z"], steps)
    finally:
        for obj, _image in baked:
            materials.unhook_preview(obj)
        _hide_generated("policy", False)
        _hide_generated("probe", False)


def scene_size(extension, scene):
    """Bounding-box diagonal of the captured scene over sqrt(3) (1 m for the Cornell box)."""
    arrays = submodule(extension, "operators.session").peek(scene).get("scene")
    return arrays.bounding_diagonal() / 3 ** 0.5 if arrays is not None else 1.0


def legend_picture(extension, scene, z_path, path):
    """The z picture beside its colour bar (matplotlib, when importable; else nothing)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    record = submodule(extension, "operators.session").peek(scene).get("display")
    colormap = submodule(extension, "lmdp_addon.display.colormap")
    import numpy as np
    scale = record.scale
    image = plt.imread(z_path)
    figure, axes = plt.subplots(figsize=(4.6, 3.6), dpi=100, gridspec_kw={"width_ratios": [1.0, 0.05]},
                                ncols=2, constrained_layout=True)
    axes[0].imshow(image)
    axes[0].set_axis_off()
    bar = colormap.colormap_srgb(np.linspace(0, 1, 256), record.colormap)
    ticks = np.linspace(0, 1, 5)
    axes[1].imshow(bar[::-1, None, :], aspect="auto", extent=(0, 1, 0, 1))
    axes[1].yaxis.tick_right()
    axes[1].set_yticks(ticks, scale.tick_labels(5))
    axes[1].set_xticks([])
    label = scale.label.replace("z: ", "z, ")
    axes[1].set_ylabel(label + (" (log)" if scale.log else ""), fontsize=8)
    axes[1].yaxis.set_label_position("right")
    axes[1].tick_params(labelsize=8)
    figure.savefig(path)
    plt.close(figure)
    return path


def session_summary(extension, scene):
    session = submodule(extension, "operators.session").peek(scene)
    if session is None:
        return None
    return {
        "timings": dict(session.timings),
        "status": [f"{stage}: {text}" for stage, text in session.status_lines()],
        "messages": [text for _t, _stage, _level, text in session.messages],
    }


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    try:
        args = parse_arguments(argv)
    except UsageError as error:
        print(f"lmdp_headless.py: error: {error}", file=sys.stderr)
        return 2

    import bpy

    output = os.path.abspath(args.output)
    os.makedirs(output, exist_ok=True)
    summary = {"blend": None, "extension": None, "objects": [], "settings": {}, "steps": [],
               "dry_run": bool(args.dry_run), "error": None}
    cleanup = []
    status = 0
    try:
        extension, origin = load_extension(cleanup)
        summary["extension"] = {"module": extension, "origin": origin}
        common = submodule(extension, "operators.common")
        properties = submodule(extension, "operators.properties")

        if args.demo:
            build_demo(args.demo, common)
            summary["blend"] = f"demo:{args.demo}"
            name = args.demo
        else:
            if args.blend:
                bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend), load_ui=False)
            elif not bpy.data.filepath:
                raise UsageError("no .blend file: pass scene.blend (or run inside `blender scene.blend "
                                 "--background --python ...`), or use --demo cornell")
            summary["blend"] = bpy.data.filepath
            name = os.path.splitext(os.path.basename(bpy.data.filepath))[0]

        scene = bpy.context.scene
        scene.lmdp.output_dir = output
        apply_settings(scene, args.settings)
        if args.demo and not args.objects and any(o.type == 'MESH' for o in bpy.context.selected_objects):
            objects = [o for o in bpy.context.selected_objects if o.type == 'MESH']  # the demo's choice
        else:
            objects = choose_objects(args.objects)
        if not objects:
            raise StepError("no mesh to compute: the scene has no visible mesh that is not an emitter "
                            "(use --objects to choose)")
        select_only(objects)
        summary["objects"] = sorted(obj.name for obj in objects)
        summary["settings"] = properties.settings_from_scene(scene).as_dict()
        print(f"[LMDP] {len(objects)} meshes carry the states: {', '.join(summary['objects'])}", flush=True)

        if not args.dry_run:
            try:
                bake = args.bake
                if bake is None:
                    no_uv = [obj.name for obj in objects if not obj.data.uv_layers]
                    bake = not no_uv
                    if no_uv:
                        print(f"[LMDP] no bake: {', '.join(sorted(no_uv))} ha{'s' if len(no_uv) == 1 else 've'} "
                              "no UV map (add one, or pass --bake to insist)", flush=True)
                summary["bake"] = bake
                run_pipeline(common, output, summary["steps"], bake=bake)
                pictures = args.pictures if args.pictures is not None else bool(args.demo)
                if pictures:
                    explicit = {item.partition("=")[0].strip() for item in args.settings}
                    summary["pictures"] = render_pictures(common, extension, output, name, summary["steps"],
                                                          explicit, args.demo)
            finally:
                summary["session"] = session_summary(extension, bpy.context.scene)
            result_blend = os.path.join(output, f"{name}_lmdp.blend")
            bpy.ops.wm.save_as_mainfile(filepath=result_blend, copy=True)
            summary["result_blend"] = result_blend
    except UsageError as error:
        summary["error"] = str(error)
        print(f"lmdp_headless.py: error: {error}", file=sys.stderr)
        status = 2
    except StepError as error:
        summary["error"] = str(error)
        print(f"lmdp_headless.py: error: {error}", file=sys.stderr)
        status = 1
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
