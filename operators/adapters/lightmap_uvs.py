"""The UV map a lightmap is laid out on, and the add-on's own lightmap UV map "LMDP Lightmap".

Which map (:func:`chosen_uv_name`): ``scene.lmdp.lightmap_uv_map`` when it names a map of the
mesh; else, with that setting empty, the dedicated "LMDP Lightmap" map where the mesh has one,
else its active render UV map. The bake (``extract_scene``) reads that map, Cycles' bake of the
same texels takes it as ``uv_layer``, and the MULTIPLY hook-up reads the lightmap through it.

:func:`create_lightmap_uvs` makes "LMDP Lightmap" with Blender's own unwrapping: Smart UV Project
(no margin) followed by Pack Islands with ``margin`` texels of the lightmap between islands
(``margin_method='FRACTION'``, which keeps that fraction of the unit square on every side of an
island: margin / 2R; islands packed by their bounding boxes, ``shape_method='AABB'``: Blender's
exact-shape packing with a FRACTION margin took 40-70 s for three cubes), or Lightmap Pack (every face its
own island) when asked or when Smart UV Project's charts overlap. The other UV maps, which one is
active and which one renders are put back as they were, so the materials' Image Textures (which
read the render map unless a UV Map node names another) look up exactly what they did. Only on a
mesh that had no UV map at all does "LMDP Lightmap" become the render map (a mesh's only map
always is); a warning then names the materials whose Image Textures now read it. Several
objects given together with ``joint`` are packed into one unit square (multi-object Edit Mode),
the layout of an atlas.

:func:`prepare_lightmap_uvs` is the bake's step (option ``auto_lightmap_uvs``): it captures the
scene, asks the engine which maps cannot hold a lightmap (``checks.lightmap_uv_problems``: missing,
outside [0, 1], overlapping texels, islands smaller than texels, objects of an atlas sharing
texels) and creates "LMDP Lightmap" on those objects.
"""
import math
from contextlib import contextmanager

import bpy

from ...lmdp_addon.bake.checks import check_bake_memory, lightmap_uv_problems
from ...lmdp_addon.bake.resolution import object_resolutions
from ...lmdp_addon.errors import SceneError

#: Name of the UV map the add-on creates for lightmaps.
LIGHTMAP_UV = "LMDP Lightmap"
#: Default space between islands of "LMDP Lightmap" (texels of the lightmap).
UV_MARGIN_TEXELS = 2
#: Smart UV Project's angle limit (degrees), Blender's default.
SMART_ANGLE_LIMIT = 66.0
UNWRAP_METHODS = ("SMART", "LIGHTMAP")
#: Largest lightmap side at which :func:`prepare_lightmap_uvs` looks for bad maps on the main
#: thread (it rasterises each object once; the bake's own texel checks, in the worker, use the
#: full size and still refuse what only shows there).
DETECT_RESOLUTION = 256


def chosen_uv_name(mesh, setting=""):
    """Name of the UV map of ``mesh`` the lightmap is laid out on (module docstring), or None
    when it has none (or lacks the map ``setting`` names)."""
    layers = mesh.uv_layers
    if setting:
        return setting if layers.get(setting) is not None else None
    if layers.get(LIGHTMAP_UV) is not None:
        return LIGHTMAP_UV
    layer = next((l for l in layers if l.active_render), None) or layers.active
    return layer.name if layer is not None else None


def _check_editable(objects):
    for obj in objects:
        if obj.type != 'MESH':
            raise SceneError(f"'{obj.name}' is not a mesh: lightmap UVs are made for meshes only")
        for data, what in ((obj, "object"), (obj.data, "mesh")):
            if data.library is not None or getattr(data, "override_library", None) is not None:
                raise SceneError(f"The {what} of '{obj.name}' is linked library data: Blender would not keep "
                                 "a new UV map on it. Make it local (Object > Relations > Make Local) or "
                                 "give it a UV map in its library file")


def _check_own_meshes(objects):
    """An atlas lays every object out in its own region of one UV map: objects that share one
    mesh share its UVs and cannot be apart."""
    by_mesh = {}
    for obj in objects:
        by_mesh.setdefault(obj.data.name_full, []).append(obj.name)
    shared = [names for names in by_mesh.values() if len(names) > 1]
    if shared:
        raise SceneError(f"{'; '.join(', '.join(n) for n in shared)} share one mesh, so their UVs are one and the "
                         "same and an atlas cannot give each its own region: make them single users (Object > "
                         "Relations > Make Single User > Object & Data) or bake without Atlas")


@contextmanager
def _editing(context, objects):
    """Edit Mode on ``objects`` (all faces selected), the selection, active object and mode put back after."""
    view_layer = context.view_layer
    selected = [o for o in view_layer.objects if o.select_get()]
    active = view_layer.objects.active
    mode = active.mode if active is not None else 'OBJECT'
    if mode != 'OBJECT':
        bpy.ops.object.mode_set(mode='OBJECT')
    try:
        for o in selected:
            o.select_set(False)
        for o in objects:
            o.select_set(True)
        view_layer.objects.active = objects[0]
        bpy.ops.object.mode_set(mode='EDIT')
        bpy.ops.mesh.reveal()
        bpy.ops.mesh.select_all(action='SELECT')
        yield
    finally:
        if context.object is not None and context.object.mode != 'OBJECT':
            bpy.ops.object.mode_set(mode='OBJECT')
        for o in view_layer.objects:
            o.select_set(False)
        for o in selected:
            o.select_set(True)
        view_layer.objects.active = active
        if active is not None and mode != 'OBJECT' and active.mode != mode:
            try:
                bpy.ops.object.mode_set(mode=mode)
            except RuntimeError:
                pass


def _implicit_texture_materials(obj):
    """Materials of ``obj`` with an Image Texture whose Vector input is not linked (it reads the
    render UV map)."""
    found = []
    for slot in obj.material_slots:
        mat = slot.material
        tree = mat.node_tree if mat is not None else None
        if tree is None:
            continue
        if any(n.type == 'TEX_IMAGE' and not n.inputs["Vector"].is_linked for n in tree.nodes):
            found.append(mat.name)
    return found


def create_lightmap_uvs(context, objects, resolution, margin=UV_MARGIN_TEXELS, method="SMART", joint=False):
    """Create (or lay out again) "LMDP Lightmap" on the meshes of ``objects`` (module docstring);
    ``resolution``: the lightmap side R the ``margin`` (texels) is measured in. ``joint``: pack
    all objects into one unit square (an atlas), else each on its own. Returns the warnings.
    Raises ``SceneError`` for objects Blender would not keep the map on (linked data)."""
    objects = list(dict.fromkeys(objects))
    if method not in UNWRAP_METHODS:
        raise SceneError(f"Unknown unwrap method {method!r}: use one of {', '.join(UNWRAP_METHODS)}")
    if not objects:
        return []
    _check_editable(objects)
    if joint:
        _check_own_meshes(objects)
    warnings = []
    saved = {}
    for obj in objects:
        mesh = obj.data
        if mesh in saved:
            continue
        layers = mesh.uv_layers
        had_none = len(layers) == 0
        saved[mesh] = (layers.active_index, [l.name for l in layers if l.active_render], had_none)
        if layers.get(LIGHTMAP_UV) is None:
            layers.new(name=LIGHTMAP_UV, do_init=False)
        layers.active = layers[LIGHTMAP_UV]
        if had_none:
            implicit = _implicit_texture_materials(obj)
            if implicit:
                warnings.append(f"'{obj.name}' had no UV map, so '{LIGHTMAP_UV}' is its only and render UV map: "
                                f"the Image Textures of {', '.join(implicit)} now read it")
    fraction = 0.5 * float(margin) / max(int(resolution), 1)   # Pack Islands puts it on every side of an island
    try:
        for group in ([objects] if joint else [[o] for o in objects]):
            with _editing(context, group):
                if method == "LIGHTMAP":
                    bpy.ops.uv.lightmap_pack(PREF_CONTEXT='ALL_FACES', PREF_PACK_IN_ONE=True,
                                             PREF_NEW_UVLAYER=False, PREF_MARGIN_DIV=max(fraction * 10.0, 0.001))
                else:
                    bpy.ops.uv.smart_project(angle_limit=math.radians(SMART_ANGLE_LIMIT), island_margin=0.0,
                                             area_weight=0.0, correct_aspect=True, scale_to_bounds=False)
                bpy.ops.uv.select_all(action='SELECT')
                bpy.ops.uv.pack_islands(rotate=True, shape_method='AABB', margin_method='FRACTION', margin=fraction)
    finally:
        for mesh, (active_index, render, had_none) in saved.items():
            layers = mesh.uv_layers
            if not had_none:
                layers.active_index = active_index
                for layer in layers:
                    layer.active_render = layer.name in render
    return warnings


def prepare_lightmap_uvs(context, meshes, settings, extract_scene):
    """Before a bake (main thread): ``({object name: UV map to bake on}, warnings)`` for the
    ``meshes`` to bake. With ``settings.auto_lightmap_uvs`` the objects whose chosen map cannot
    hold their lightmap (``checks.lightmap_uv_problems``) get "LMDP Lightmap"
    (:func:`create_lightmap_uvs`; with ``settings.atlas`` all of them, packed jointly) and bake on
    it; without, the problems are left to the bake's checks. ``extract_scene`` is
    ``extract.extract_scene`` (passed in: that module imports this one)."""
    uv_maps = {obj.name: chosen_uv_name(obj.data, settings.lightmap_uv_map) for obj in meshes}
    if not settings.auto_lightmap_uvs or not meshes:
        return uv_maps, []
    scene = extract_scene(context, meshes, uv_maps=uv_maps)
    names = [obj.name for obj in meshes if obj.name in scene.object_names]
    indices = [scene.object_names.index(n) for n in names]
    atlas = bool(settings.atlas) and len(names) > 1
    resolutions = object_resolutions(scene, indices, settings, atlas=atlas)
    check_bake_memory(scene, names, indices, settings, resolutions)   # an oversized bake stops before any work
    detect = {i: min(int(r), DETECT_RESOLUTION) for i, r in resolutions.items()}
    problems = lightmap_uv_problems(scene, names, indices, detect, atlas=atlas)
    if not problems:
        return uv_maps, []
    by_name = {obj.name: obj for obj in meshes}
    for n in problems:
        if uv_maps.get(n) is None and len(by_name[n].data.uv_layers):
            problems[n] = f"it has no UV map named '{settings.lightmap_uv_map}'"
    targets = names if atlas else [n for n in names if n in problems]
    R = {n: resolutions[i] for n, i in zip(names, indices)}
    warnings = []
    if atlas:
        warnings += _create_checked(context, [by_name[n] for n in targets], max(R.values()), True, extract_scene)
    else:
        for n in targets:
            warnings += _create_checked(context, [by_name[n]], R[n], False, extract_scene)
    for n in targets:
        uv_maps[n] = LIGHTMAP_UV
    reasons = "; ".join(f"{n} ({problems[n]})" for n in sorted(problems))
    warnings.insert(0, f"Created the UV map '{LIGHTMAP_UV}' for the lightmap of {', '.join(sorted(targets))}: "
                       f"{reasons}. The other UV maps and the render UV map are unchanged")
    return uv_maps, warnings


def _create_checked(context, objects, resolution, joint, extract_scene):
    """:func:`create_lightmap_uvs` by Smart UV Project, again by Lightmap Pack if the result
    still overlaps (a chart folded over itself); returns the warnings."""
    warnings = create_lightmap_uvs(context, objects, resolution, joint=joint)
    uv_maps = {obj.name: LIGHTMAP_UV for obj in objects}
    scene = extract_scene(context, objects, uv_maps=uv_maps)
    names = [o.name for o in objects if o.name in scene.object_names]
    indices = [scene.object_names.index(n) for n in names]
    if lightmap_uv_problems(scene, names, indices, {i: min(int(resolution), DETECT_RESOLUTION) for i in indices},
                            atlas=joint):
        warnings = create_lightmap_uvs(context, objects, resolution, method="LIGHTMAP", joint=joint)
    return warnings
