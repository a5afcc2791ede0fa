"""Built-in demo scenes as real Blender objects, and Cycles reference bakes that leave no trace.

:func:`build_demo_scene` turns :func:`lmdp_addon.demo_geometry.scene_parts` into mesh objects with
ordinary node materials (Diffuse BSDF walls, Emission shader lights), a UV map named "UVMap", a
camera and Cycles render settings, so Cycles, the user and :func:`operators.adapters.extract.extract_scene`
all see the same scene.

:func:`bake_cycles` runs ``bpy.ops.object.bake`` into a scratch float image and restores
everything it touched (selection, active object, active image nodes, render settings); it is the
reference the engine's bakes and texel mapping are compared with (docs/cycles_conventions.md).
"""
from contextlib import contextmanager

import bpy
import numpy as np
from mathutils import Vector

from ...lmdp_addon import demo_geometry as scene_library

#: Label of each scene kind (used for collection names and the Add menu).
SCENE_LABELS = {
    "CORNELL_BOX": "Cornell Box",
    "NARROW_OPENING": "Narrow Opening",
    "PLANE_UNDER_SKY": "Plane Under Sky",
    "PARALLEL_SQUARES": "Parallel Squares",
    "HEAVY": "Heavy Cornell Box",
    "GLOSSY_BOX": "Glossy Cornell Box",
}
#: Name of the UV map every demo mesh gets.
UV_MAP_NAME = "UVMap"
#: Cycles settings of the demo scenes: samples for renders and bounces matching the engine's
#: default path length (``Settings.max_bounces``).
RENDER_SAMPLES = 128
MAX_BOUNCES = 8


def _split_strength(radiance):
    """(colour, strength) with colour * strength == radiance and max(colour) == 1."""
    radiance = np.asarray(radiance, dtype=np.float64)
    strength = float(radiance.max())
    if strength <= 0.0:
        return (0.0, 0.0, 0.0), 0.0
    return tuple(float(c) for c in radiance / strength), strength


def _materials(part):
    """The node materials of ``part``, one per distinct face colour (:attr:`Part.base_colours`)."""
    if part.principled is None:
        return [_material(part)]
    colours, _ = part.base_colours
    return [_principled_material(part, colour, i) for i, colour in enumerate(colours)]


def _principled_material(part, colour, index):
    """A Principled BSDF material of Base Color ``colour`` with the part's Principled inputs."""
    mat = bpy.data.materials.new(f"LMDP {part.name}" + (f" {index}" if index else ""))
    tree = mat.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    output.location = (300, 0)
    shader = tree.nodes.new("ShaderNodeBsdfPrincipled")
    shader.inputs["Base Color"].default_value = (*(float(c) for c in colour), 1.0)
    p = part.principled
    shader.inputs["Metallic"].default_value = p.get("metallic", 0.0)
    shader.inputs["Roughness"].default_value = p.get("roughness", 0.5)
    shader.inputs["IOR"].default_value = p.get("ior", 1.5)
    shader.inputs["Specular IOR Level"].default_value = p.get("ior_level", 0.5)
    mat.diffuse_color = (*(float(c) for c in colour), 1.0)
    tree.links.new(shader.outputs[0], output.inputs["Surface"])
    return mat


def _material(part):
    """A node material for ``part``: Emission (colour, strength) or Diffuse BSDF (albedo)."""
    mat = bpy.data.materials.new(f"LMDP {part.name}")
    tree = mat.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    output.location = (300, 0)
    if part.is_emitter:
        colour, strength = _split_strength(part.emission)
        shader = tree.nodes.new("ShaderNodeEmission")
        shader.inputs["Color"].default_value = (*colour, 1.0)
        shader.inputs["Strength"].default_value = strength
        mat.diffuse_color = (*colour, 1.0)
    else:
        shader = tree.nodes.new("ShaderNodeBsdfDiffuse")
        shader.inputs["Color"].default_value = (*(float(c) for c in part.albedo), 1.0)
        shader.inputs["Roughness"].default_value = 0.0
        mat.diffuse_color = (*(float(c) for c in part.albedo), 1.0)
    tree.links.new(shader.outputs[0], output.inputs["Surface"])
    return mat


def part_mesh(part, name=None):
    """A new mesh datablock for ``part``: its quads, a "UVMap" UV map, flat shading."""
    mesh = bpy.data.meshes.new(name or part.name)
    mesh.from_pydata(part.vertices.tolist(), [], part.faces.tolist())
    uv_layer = mesh.uv_layers.new(name=UV_MAP_NAME)
    uv_layer.data.foreach_set("uv", part.face_uv.astype(np.float32).ravel())
    if part.face_albedo is not None:   # one material slot per face colour (a checker)
        mesh.polygons.foreach_set("material_index", part.base_colours[1].astype(np.int32))
    mesh.update()
    return mesh


def _world(kind):
    radiance = scene_library.world_radiance(kind)
    world = bpy.data.worlds.new(f"LMDP {SCENE_LABELS[kind]} World")
    tree = world.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputWorld")
    background = tree.nodes.new("ShaderNodeBackground")
    colour, strength = _split_strength(radiance)
    background.inputs["Color"].default_value = (*colour, 1.0)
    background.inputs["Strength"].default_value = strength
    tree.links.new(background.outputs[0], output.inputs["Surface"])
    world.color = colour
    return world


def look_at_rotation(location, target):
    """Euler rotation that points a camera at ``target`` from ``location`` (Y up in the view)."""
    direction = Vector(target) - Vector(location)
    return direction.to_track_quat('-Z', 'Y').to_euler()


def _camera(kind, collection):
    view = scene_library.camera_view(kind)
    data = bpy.data.cameras.new(f"LMDP {SCENE_LABELS[kind]} Camera")
    data.sensor_fit = 'AUTO'
    data.angle = float(view.fov)
    cam = bpy.data.objects.new(data.name, data)
    cam.location = Vector(view.location)
    cam.rotation_euler = look_at_rotation(view.location, view.look_at)
    collection.objects.link(cam)
    return cam


def configure_cycles(scene, samples=RENDER_SAMPLES):
    """Cycles on the CPU, fixed sample count, Standard view transform, engine-matching bounces, no
    indirect clamp."""
    scene.render.engine = 'CYCLES'
    cycles = scene.cycles
    cycles.device = 'CPU'
    cycles.samples = samples
    cycles.preview_samples = min(samples, 32)
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.max_bounces = MAX_BOUNCES
    cycles.diffuse_bounces = MAX_BOUNCES
    cycles.sample_clamp_indirect = 0.0     # unclamped: Cycles' bakes and the add-on's are the same quantity
    cycles.glossy_bounces = MAX_BOUNCES    # glossy surfaces (GLOSSY_BOX): the engine's path length,
    cycles.blur_glossy = 0.0               # Filter Glossy off: the BSDFs unblurred (bsdf_params)
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.look = 'None'
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.resolution_x = 512
    scene.render.resolution_y = 512
    scene.render.resolution_percentage = 100


def build_demo_scene(kind, context):
    """Add the built-in scene ``kind`` to ``context.scene``; return its state-carrying objects.

    Adds a collection "LMDP <label>" holding one mesh object per part (named like the part:
    "Floor", "TallBox", "Light", ...) with a Diffuse BSDF (albedo) or Emission material, a UV map
    "UVMap", and a camera; sets the scene camera, a new world (black, or the uniform sky of
    PLANE_UNDER_SKY) and Cycles render settings (:func:`configure_cycles`). Returns the mesh
    objects that are not emitters, in part order. Raises ``SceneError`` for an unknown kind.
    """
    kind = scene_library.check_kind(kind)
    scene = context.scene
    parts = scene_library.scene_parts(kind)
    collection = bpy.data.collections.new(f"LMDP {SCENE_LABELS[kind]}")
    scene.collection.children.link(collection)
    carriers = []
    for part in parts:
        mesh = part_mesh(part)
        for material in _materials(part):
            mesh.materials.append(material)
        obj = bpy.data.objects.new(part.name, mesh)
        collection.objects.link(obj)
        if not part.is_emitter:
            carriers.append(obj)
    scene.camera = _camera(kind, collection)
    scene.world = _world(kind)
    configure_cycles(scene)
    context.view_layer.update()  # world matrices of the new objects
    return carriers


# -- Cycles reference bakes ---------------------------------------------------------------------

def _scratch_material():
    """Stand-in for objects without a material: Cycles' default surface (Diffuse BSDF, 0.8)."""
    mat = bpy.data.materials.new("LMDP bake scratch")
    tree = mat.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    shader = tree.nodes.new("ShaderNodeBsdfDiffuse")
    shader.inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    tree.links.new(shader.outputs[0], output.inputs["Surface"])
    return mat


#: Cycles settings :func:`bake_cycles` may change, restored afterwards.
_CYCLES_SETTINGS = ("samples", "use_adaptive_sampling", "max_bounces", "diffuse_bounces", "seed", "device",
                    "sample_clamp_indirect")


@contextmanager
def _bake_target(obj, image):
    """``obj``'s materials with an active Image Texture node of ``image`` (Cycles bakes into the
    active node), a stand-in Diffuse material if it has none; all removed afterwards."""
    added_nodes = []     # (node tree, node, previous active node)
    scratch_slot = None
    try:
        if not obj.material_slots or all(slot.material is None for slot in obj.material_slots):
            scratch_slot = _scratch_material()
            obj.data.materials.append(scratch_slot)
        for mat in {slot.material for slot in obj.material_slots if slot.material is not None}:
            tree = mat.node_tree
            node = tree.nodes.new("ShaderNodeTexImage")
            node.image = image
            node.label = "LMDP bake scratch"
            added_nodes.append((tree, node, tree.nodes.active))
            tree.nodes.active = node
        yield
    finally:
        for tree, node, previous in added_nodes:
            tree.nodes.remove(node)
            if previous is not None:
                tree.nodes.active = previous
        if scratch_slot is not None:
            obj.data.materials.pop(index=len(obj.data.materials) - 1)
            bpy.data.materials.remove(scratch_slot)


@contextmanager
def _only_selected(view_layer, obj):
    """``obj`` alone selected and active (selectable even if it was not); restored afterwards."""
    saved_selection = [o for o in view_layer.objects if o.select_get(view_layer=view_layer)]
    saved_active = view_layer.objects.active
    saved_hidden_select = obj.hide_select
    try:
        for o in saved_selection:
            o.select_set(False)
        obj.hide_select = False
        obj.select_set(True)
        view_layer.objects.active = obj
        yield
    finally:
        obj.select_set(False)
        obj.hide_select = saved_hidden_select
        for o in saved_selection:
            o.select_set(True)
        view_layer.objects.active = saved_active


@contextmanager
def _cycles_settings(scene, samples, max_bounces, seed, clamp_indirect):
    """Cycles on the CPU without adaptive sampling, with the given overrides (None: keep);
    the render engine and every setting of :data:`_CYCLES_SETTINGS` restored afterwards."""
    cycles = scene.cycles
    saved_engine = scene.render.engine
    saved = {key: getattr(cycles, key) for key in _CYCLES_SETTINGS}
    try:
        scene.render.engine = 'CYCLES'
        cycles.device = 'CPU'
        cycles.use_adaptive_sampling = False
        if samples is not None:
            cycles.samples = int(samples)
        if max_bounces is not None:
            cycles.max_bounces = int(max_bounces)
            cycles.diffuse_bounces = int(max_bounces)
        if seed is not None:
            cycles.seed = int(seed)
        if clamp_indirect is not None:
            cycles.sample_clamp_indirect = float(clamp_indirect)
        yield
    finally:
        scene.render.engine = saved_engine
        for key, value in saved.items():
            setattr(cycles, key, value)


def bake_cycles(context, obj, bake_type='DIFFUSE', pass_filter=('INDIRECT',), resolution=128,
                samples=None, margin=0, margin_type='EXTEND', uv_map="", fill=0.0,
                normal_space='OBJECT', max_bounces=None, seed=None, clamp_indirect=None):
    """Bake ``obj`` with Cycles into a scratch image and return its pixels (R, R, 4) float32.

    The image is a new float image filled with ``fill`` (uncovered pixels keep it: pass a
    sentinel to find the covered texels; ``use_clear`` is off). Pixel rows start at the bottom.
    ``bake_type``: 'DIFFUSE' (with ``pass_filter`` e.g. ('INDIRECT',)), 'POSITION', 'NORMAL'
    (``normal_space`` 'OBJECT' encodes n/2 + 0.5), ... ``samples`` (default: the scene's) with
    adaptive sampling off; ``max_bounces`` sets Cycles' total and diffuse bounces for the bake;
    ``clamp_indirect`` sets ``sample_clamp_indirect`` (0: off, an unbiased bake; None: the scene's,
    Cycles' default 10 clips the brightest indirect paths).

    Nothing the user had changes: the scratch image nodes, the image and any scratch material are
    removed, and the selection, active object, active node of every material and the render
    settings touched are restored, even when the bake fails.
    """
    scene = context.scene
    view_layer = context.view_layer
    image = bpy.data.images.new(f"LMDP bake {obj.name}", resolution, resolution,
                                alpha=True, float_buffer=True)
    image.pixels.foreach_set(np.full(resolution * resolution * 4, fill, dtype=np.float32))
    kwargs = dict(type=bake_type, margin=int(margin), margin_type=margin_type, use_clear=False,
                  target='IMAGE_TEXTURES', save_mode='INTERNAL', use_selected_to_active=False,
                  uv_layer=uv_map or "")
    if bake_type == 'DIFFUSE':
        kwargs["pass_filter"] = set(pass_filter)
    if bake_type == 'NORMAL':
        kwargs["normal_space"] = normal_space
    try:
        with _bake_target(obj, image), _cycles_settings(scene, samples, max_bounces, seed, clamp_indirect), \
                _only_selected(view_layer, obj), \
                context.temp_override(scene=scene, view_layer=view_layer, active_object=obj, object=obj,
                                      selected_objects=[obj], selected_editable_objects=[obj]):
            result = bpy.ops.object.bake(**kwargs)
            if result != {'FINISHED'}:
                raise RuntimeError(f"Cycles bake of '{obj.name}' did not finish: {result}")
            pixels = np.empty(resolution * resolution * 4, dtype=np.float32)
            image.pixels.foreach_get(pixels)
        return pixels.reshape(resolution, resolution, 4)
    finally:
        bpy.data.images.remove(image)
