"""The checks of ``scripts/lmdp_headless.py``: its arguments and the meshes it chooses.

Every check raises :class:`UsageError` (exit status 2) with one line that names the argument
and what to do, before any work; :class:`StepError` (exit status 1) is a step that failed.
The .blend file and ``--output`` are checked without Blender data; ``--set`` against the
``scene.lmdp`` property's type and range; ``--objects`` and the default selection against the
add-on's own capture of the scene (``operators.adapters.extract``).
"""
import difflib
import math
import os
import tempfile

#: How a .blend file starts: plain, zstd-compressed (Blender 3.0+), gzip-compressed (older).
BLEND_MAGIC = (b"BLENDER", b"\x28\xb5\x2f\xfd", b"\x1f\x8b")
#: Files of --output with a fixed name (the result .blend is named after the input).
FIXED_OUTPUTS = ("summary.json", "lmdp.npz")
#: scene.lmdp properties that --set refuses, and what to use instead (None: not a setting).
RESERVED_SETTINGS = {"rna_type": None, "name": None, "session_id": None,
                     "output_dir": "the output folder is --output",
                     "run_all_bake": "the script bakes by --bake / --no-bake"}
BOOLEAN_WORDS = {"1": True, "true": True, "yes": True, "on": True,
                 "0": False, "false": False, "no": False, "off": False}


class UsageError(Exception):
    """Bad command line (exit status 2)."""


class StepError(Exception):
    """A step failed (exit status 1)."""


# -- the .blend file and --output --------------------------------------------------------------
def check_blend_file(path):
    """Refuse a .blend argument that is missing, a folder, unreadable, empty or not a .blend."""
    if not os.path.lexists(path):
        raise UsageError(f"{path}: no such file: give the path of a .blend file")
    if os.path.isdir(path):
        raise UsageError(f"{path} is a folder, not a .blend file: give the path of a .blend file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(BLEND_MAGIC[0]))
    except OSError as error:
        raise UsageError(f"{path}: cannot read the file ({error.strerror}): check that it exists "
                         "and that you may read it") from None
    if not head:
        raise UsageError(f"{path} is empty (0 bytes), not a .blend file: give a file saved by Blender")
    if not head.startswith(BLEND_MAGIC):
        raise UsageError(f"{path} is not a .blend file (it does not start like one): give a file "
                         "saved by Blender")


def _blocking_file(path):
    """The nearest existing ancestor of ``path`` when it is a file (nothing can be made inside)."""
    parent = os.path.dirname(path)
    while parent and not os.path.exists(parent) and parent != os.path.dirname(parent):
        parent = os.path.dirname(parent)
    return parent if parent and os.path.exists(parent) and not os.path.isdir(parent) else None


def check_output(path):
    """The absolute --output folder, created and checked writable; :class:`UsageError` if unusable."""
    if path is None or not path.strip():
        raise UsageError("--output is empty: give a folder (it is created if missing)")
    if path.startswith("//"):
        raise UsageError(f"--output {path}: '//' is Blender's prefix for 'next to the .blend file' "
                         "and means nothing on the command line: give a folder relative to the "
                         "current directory, or an absolute one")
    output = os.path.abspath(os.path.expanduser(path))
    if os.path.exists(output) and not os.path.isdir(output):
        raise UsageError(f"--output {path} is a file, not a folder: give a folder (it is created "
                         "if missing)")
    blocking = _blocking_file(output)
    if blocking:
        raise UsageError(f"--output {path}: {blocking} is a file, so no folder can be made inside "
                         "it: give another folder")
    try:
        os.makedirs(output, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".lmdp_write_test_", dir=output)
        os.close(handle)
        os.remove(probe)
    except OSError as error:
        raise UsageError(f"--output {path}: cannot create or write the folder ({error.strerror}): "
                         "give a folder you may write to") from None
    for name in FIXED_OUTPUTS:
        if os.path.isdir(os.path.join(output, name)):
            raise UsageError(f"--output {path}: {name} in it is a folder, and the script writes a "
                             "file of that name: remove it or give another folder")
    return output


def setting_items(items):
    """``--set`` strings as ``{key: text}``; refuses items without '=' and keys given twice."""
    settings = {}
    for item in items:
        key, equals, text = item.partition("=")
        key = key.strip()
        if not equals or not key:
            raise UsageError(f"--set expects KEY=VALUE, got {item!r}")
        if key in settings and settings[key].strip() != text.strip():
            raise UsageError(f"--set {key} is given twice ({settings[key]} and {text}): give it once")
        settings[key] = text
    return settings


def submodule(extension, name):
    import importlib
    return importlib.import_module(f"{extension}.{name}")


# -- bake farms -----------------------------------------------------------------------------------
def check_farm_arguments(args):
    """--scheduler and --workers: one of them at most, a positive number of workers."""
    if args.scheduler is not None and args.workers is not None:
        raise UsageError("give either --scheduler (a running Dask cluster) or --workers (a local one), "
                         "not both")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers {args.workers}: give at least 1 worker process (or leave --workers out)")
    if args.scheduler is not None and not args.scheduler.strip():
        raise UsageError("--scheduler is empty: give the scheduler's address, e.g. tcp://host:8786")


def connect_farm(args, extension, cleanup):
    """The extension's ``lmdp_addon.farm.cluster.Farm`` for --scheduler / --workers (None
    without them), connected and its workers' versions checked; closed by ``cleanup``. An
    unreachable scheduler, a worker with another engine, or no dask is a :class:`UsageError`."""
    if args.scheduler is None and args.workers is None:
        return None
    cluster = submodule(extension, "lmdp_addon.farm.cluster")
    flag = f"--scheduler {args.scheduler}" if args.scheduler is not None else f"--workers {args.workers}"
    try:
        farm = cluster.Farm(scheduler=args.scheduler, workers=args.workers)
    except cluster.FarmError as error:
        raise UsageError(f"{flag}: {error}") from error
    cleanup.append(farm.close)
    print(f"[LMDP] bake farm: {farm.n_workers} workers at {farm.address}", flush=True)
    return farm


# -- settings -------------------------------------------------------------------------------------
def _setting_value(prop, key, text):
    """``text`` as a value of the ``scene.lmdp`` property ``prop``; :class:`UsageError` if it is not one."""
    word = text.strip()
    if prop.type == 'BOOLEAN':
        if word.lower() not in BOOLEAN_WORDS:
            raise UsageError(f"--set {key}={text}: expected true or false (also 1/0, yes/no, on/off)")
        return BOOLEAN_WORDS[word.lower()]
    if prop.type == 'ENUM':
        allowed = [item.identifier for item in prop.enum_items]
        if word.upper() not in allowed:
            raise UsageError(f"--set {key}={text}: expected one of {', '.join(allowed)}")
        return word.upper()
    if prop.type not in ('INT', 'FLOAT') or getattr(prop, "is_array", False):
        raise UsageError(f"--set {key}: this setting cannot be set from the command line")
    try:
        value = int(word) if prop.type == 'INT' else float(word)
    except ValueError:
        kind = "a whole number" if prop.type == 'INT' else "a number"
        raise UsageError(f"--set {key}={text}: expected {kind}") from None
    if not math.isfinite(value):
        raise UsageError(f"--set {key}={text}: expected a finite number")
    low, high = prop.hard_min, prop.hard_max
    stored = value if prop.type == 'INT' else _float32(value)  # Blender keeps floats in single precision
    if not low <= stored <= high:
        bounds = f"{low} to {high}" if prop.type == 'INT' else f"{low:.7g} to {high:.7g}"
        raise UsageError(f"--set {key}={text}: out of range: give a value from {bounds}")
    return value


def _float32(value):
    import numpy as np
    with np.errstate(over="ignore"):
        return float(np.float32(value))


def apply_settings(scene, items):
    """Set ``scene.lmdp`` from ``KEY=VALUE`` strings, converting and range-checking by the
    property's type; anything else is a :class:`UsageError` that names the key."""
    props = scene.lmdp
    rna = props.bl_rna.properties
    known = sorted(p.identifier for p in rna if p.identifier not in RESERVED_SETTINGS)
    for key, text in setting_items(items).items():
        if RESERVED_SETTINGS.get(key):
            raise UsageError(f"--set {key}: {RESERVED_SETTINGS[key]}; drop this --set")
        if key not in known:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise UsageError(f"--set: unknown setting {key!r}{hint}; the settings are: {', '.join(known)}")
        setattr(props, key, _setting_value(rna[key], key, text))


# -- the meshes that carry the states -------------------------------------------------------------
def hidden_reason(obj, view_layer):
    """Why the add-on's capture leaves ``obj`` (in ``view_layer``) out, with what to do; None if
    it is captured."""
    if obj.hide_get(view_layer=view_layer):
        return "is hidden (eye icon): unhide it"
    if obj.hide_viewport:
        return "is disabled in viewports (monitor icon): enable it"
    if obj.hide_render:
        return "is disabled in renders (camera icon): enable it, the LMDP captures what renders"
    if not obj.visible_get(view_layer=view_layer):
        return "is in a hidden collection: show the collection"
    return None


def mesh_facts(extension, meshes):
    """``(problems, has_uv)`` of visible ``meshes`` from the add-on's own capture of the scene
    (evaluated meshes, materials, render UV maps): ``problems[name]`` says why a mesh can carry
    no states (no faces, no face of finite non-zero area, light on every face)."""
    import bpy
    import numpy as np
    extract = submodule(extension, "operators.adapters.extract")
    errors = submodule(extension, "lmdp_addon.errors")
    try:
        scene = extract.extract_scene(bpy.context, meshes)
    except errors.LMDPError as error:
        raise StepError(f"capturing the scene failed: {error}") from None
    index = {name: i for i, name in enumerate(scene.object_names)}
    valid, emits = scene.valid_triangles(), scene.is_emissive()
    problems, has_uv = {}, {}
    for obj in meshes:
        i = index.get(obj.name)
        if i is None:
            problems[obj.name] = "has no faces"
            continue
        has_uv[obj.name] = bool(scene.object_has_uv[i])
        own = scene.triangle_object == i
        if not np.any(valid & own):
            problems[obj.name] = "has no face of finite, non-zero area"
        elif not np.any(valid & own & ~emits):
            problems[obj.name] = "emits light on every face (a light source carries no states)"
    return problems, has_uv


def _split_names(text):
    """--objects as names: split at commas, but commas inside an object's name stay (the longest
    run of comma-separated parts that names an object is taken whole)."""
    import bpy
    parts, names, i = text.split(","), [], 0
    while i < len(parts):
        whole = next((j for j in range(len(parts), i + 1, -1)
                      if bpy.data.objects.get(",".join(parts[i:j]).strip()) is not None), i + 1)
        name = ",".join(parts[i:whole]).strip()
        if name and name not in names:
            names.append(name)
        i = whole
    return names


def named_objects(extension, text):
    """The meshes named by --objects; every name that cannot carry states is a :class:`UsageError`."""
    import bpy
    view_layer = bpy.context.view_layer
    in_layer = {obj.as_pointer() for obj in view_layer.objects}
    chosen, wrong = [], []
    for name in _split_names(text):
        obj = bpy.data.objects.get(name)
        if obj is None:
            close = difflib.get_close_matches(name, [o.name for o in view_layer.objects], n=1)
            wrong.append(f"no object named {name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        elif obj.type != 'MESH':
            wrong.append(f"{name!r} is a {obj.type.lower()}, not a mesh: name meshes (Object > Convert "
                         "> Mesh turns curves and text into one)")
        elif obj.as_pointer() not in in_layer:
            wrong.append(f"{name!r} is not in scene '{view_layer.id_data.name}' (or its collection is "
                         "excluded from the view layer): link it into the scene, or include its collection")
        elif hidden_reason(obj, view_layer):
            wrong.append(f"{name!r} {hidden_reason(obj, view_layer)}")
        else:
            chosen.append(obj)
    problems, has_uv = mesh_facts(extension, chosen) if chosen else ({}, {})
    wrong += [f"{name!r} {why}: leave it out" for name, why in sorted(problems.items())]
    if wrong:
        raise UsageError("--objects: " + "; ".join(wrong))
    return chosen, has_uv


def default_objects(extension, bake, auto_uvs=False):
    """Every visible mesh of the view layer that can carry states and, unless --no-bake, has a
    UV map when any mesh has one (with ``auto_uvs``, scene.lmdp.auto_lightmap_uvs, every mesh
    can be baked: the bake gives those without one the UV map "LMDP Lightmap"); returns
    ``(objects, has_uv, left_out)``, ``left_out[name]`` saying why a mesh was left out (printed,
    one line each)."""
    import bpy
    view_layer = bpy.context.view_layer
    meshes = [obj for obj in view_layer.objects if obj.type == 'MESH']
    hidden = {obj.name: hidden_reason(obj, view_layer) for obj in meshes}
    meshes = [obj for obj in meshes if hidden[obj.name] is None]
    problems, has_uv = mesh_facts(extension, meshes)
    bakeable = {name: uv or auto_uvs for name, uv in has_uv.items()}
    capable = [obj for obj in meshes if obj.name not in problems]
    left_out = {name: why for name, why in hidden.items() if why} | problems
    with_uv = [obj for obj in capable if bakeable[obj.name]]
    if bake is not False and with_uv:
        for obj in capable:
            if not bakeable[obj.name]:
                left_out[obj.name] = ("has no UV map, so it cannot be baked (it still occludes and "
                                      "reflects; add a UV map, --set auto_lightmap_uvs=true gives it one, "
                                      "or --no-bake puts states on it)")
        capable = with_uv
    elif bake and capable:
        names = ", ".join(sorted(obj.name for obj in capable))
        raise UsageError(f"--bake: no mesh has a UV map ({names}): add one (UV > Smart UV Project or "
                         "Lightmap Pack), or pass --no-bake")
    for name, why in sorted(left_out.items()):
        print(f"[LMDP] left out {name}: it {why}", flush=True)
    if not capable:
        reasons = "; ".join(f"{name} {why}" for name, why in sorted(left_out.items())) or "it has no visible mesh"
        raise StepError(f"no mesh can carry the states ({reasons}): add a visible mesh with faces "
                        "that does not emit light")
    return capable, has_uv, left_out


def carrier_objects(args, extension):
    """The meshes that carry the states (--objects, the demo's selection, or :func:`default_objects`)
    and whether to bake them; returns ``(objects, bake, left_out)``."""
    import bpy
    left_out = {}
    auto_uvs = bool(getattr(bpy.context.scene.lmdp, "auto_lightmap_uvs", False))
    demo_choice = [o for o in bpy.context.selected_objects if o.type == 'MESH'] if args.demo else []
    if args.objects is not None:
        objects, has_uv = named_objects(extension, args.objects)
    elif demo_choice:
        objects, has_uv = demo_choice, mesh_facts(extension, demo_choice)[1]
    else:
        objects, has_uv, left_out = default_objects(extension, args.bake, auto_uvs)
    no_uv = sorted(obj.name for obj in objects if not has_uv.get(obj.name))
    if no_uv and auto_uvs and args.bake is not False:
        print(f"[LMDP] {', '.join(no_uv)}: no UV map, the bake gives "
              f"{'it' if len(no_uv) == 1 else 'them'} 'LMDP Lightmap' (auto_lightmap_uvs)", flush=True)
        no_uv = []
    if no_uv and args.bake:
        it = "it" if len(no_uv) == 1 else "them"
        raise UsageError(f"--bake: {', '.join(no_uv)} ha{'s' if len(no_uv) == 1 else 've'} no UV map: "
                         f"add one (UV > Smart UV Project or Lightmap Pack), leave {it} out of "
                         "--objects, or pass --no-bake")
    if no_uv and args.bake is None:
        print(f"[LMDP] no bake: {', '.join(no_uv)} ha{'s' if len(no_uv) == 1 else 've'} no UV map "
              "(add one to bake)", flush=True)
    return objects, args.bake is not False and not no_uv, left_out


def select_only(objects):
    import bpy
    view_layer = bpy.context.view_layer
    for obj in view_layer.objects:
        obj.select_set(False)
    for obj in objects:
        obj.select_set(True)
    view_layer.objects.active = objects[0] if objects else None
