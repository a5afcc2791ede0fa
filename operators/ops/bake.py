"""``lmdp.bake``: indirect light of the selected meshes into ``<object>_lmdp_indirect`` images.

The operator is thin (``jobs.EngineJob``):

* ``prepare`` (:func:`bake_inputs`): captures the current scene (``extract_scene``), checks
  everything that can be wrong *before any work* (``baking.check_bake_inputs``: UV maps, overlapping
  UVs, resolution, light, the solution GUIDED / FINAL_GATHER need, an output folder that can be
  created) and gathers the session's solution;
* ``compute`` (:func:`compute_bake`): ``lmdp_addon.bake.driver.bake`` (no bpy; a worker thread in the
  UI, Esc cancels between work units);
* ``apply`` (:func:`apply_bake`): the scratch buffers computed above are first saved as OpenEXR
  to temporary files (when ``output_dir`` is set), and only when that worked are they swapped in:
  the pixels go into the add-on's own image of each object (``foreach_set``), the files replace
  the previous ones, ``bake_stats.json`` is written, and the optional material hook-up is made.
  A cancelled or failed bake leaves every image and file as it was.

``run_pipeline`` (or any script) can reuse the three pieces: ``bake_inputs(context, settings)``
(``planned_bake_inputs(scene, names, settings)`` before a solve that is still to come),
``compute_bake(inputs, settings, progress)``, ``apply_bake(context, result, settings, hook_up)``.

Images: a float RGBA image of ``bake_resolution``² pixels named ``<object>_lmdp_indirect``,
colour space Non-Color (linear data, shown and saved without any view transform), alpha 1 on the
baked texels and their margin. The image carries the custom property ``lmdp_bake_object`` (the
object's name); re-baking writes only into an image with that tag, so an image of the user that
happens to have the same name is never touched (Blender then names the new one ``.001``).

Material hook-up (``hook_up``):

* ``'MULTIPLY'``: in each material used only by this object, an Image Texture node "LMDP
  Lightmap" (the lightmap, default UV map = the render UV map that was baked) and a Mix node
  "LMDP Lightmap Multiply" (Multiply, factor 1) are inserted in front of the Base Color (Principled
  BSDF) or Color (Diffuse BSDF) input; whatever fed that input (a link or its value) feeds the Mix
  node's A input. Nothing else is changed; ``lmdp.remove_bake_hookup`` removes both nodes and
  restores the link or value.
* ``'PREVIEW'``: a material "<object>_lmdp_preview" (Emission shader showing the lightmap) is
  linked to the object's material slots at *object* level (``slot.link = 'OBJECT'``), so the
  mesh's own materials stay assigned to the mesh; ``lmdp.remove_bake_hookup`` restores each
  slot's previous link and object material.
"""
import json
import os
import tempfile
from dataclasses import dataclass, field

import bpy
from bpy.props import EnumProperty

from ...lmdp_addon.bake import driver as baking
from ...lmdp_addon.errors import LMDPError, SceneError, StageOrderError
from ...lmdp_addon.model.pipeline import LMDPResult
from ..common import report_error, report_warnings, selected_meshes
from ..adapters.extract import extract_scene
from ..jobs import EngineJob
from ..session import session_for

#: Custom property naming the object an image was baked for (marks the add-on's own images).
IMAGE_TAG = "lmdp_bake_object"
#: Custom property of preview materials, and of objects whose slots show one (JSON of the slots).
PREVIEW_TAG = "lmdp_preview_material"
PREVIEW_SAVED = "lmdp_preview_saved_slots"
#: Names of the nodes the MULTIPLY hook-up adds.
NODE_IMAGE = "LMDP Lightmap"
NODE_MULTIPLY = "LMDP Lightmap Multiply"
STATS_FILE = "bake_stats.json"

HOOK_UP_ITEMS = (
    ("NONE", "None", "Only write the images (and files)"),
    ("MULTIPLY", "Multiply Base Color",
     "Insert an Image Texture of the lightmap multiplied into the Base Color / Color of the "
     "object's own materials (undo with Remove Bake Hook-up)"),
    ("PREVIEW", "Preview Material",
     "Show the lightmap on the object through an emission material linked to the object's "
     "material slots (the mesh's materials are kept; undo with Remove Bake Hook-up)"),
)


@dataclass
class BakeInputs:
    """What :func:`compute_bake` needs, read on the main thread."""

    scene: object                      #: SceneArrays of the current scene
    names: list                        #: objects to bake
    lmdp: object = None                #: LMDPResult of the session (GUIDED / FINAL_GATHER)
    precompute_seconds: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    output_dir: str = ""


def session_lmdp(context):
    """The session's solved LMDP as an ``LMDPResult`` (None when nothing is solved)."""
    session = session_for(context.scene)
    if not session.has("solution"):
        return None, {}
    lmdp = LMDPResult(scene=session.require("scene_arrays"), states=session.require("states"),
                      dynamics=session.require("dynamics"), lmdp=session.get("costs"),
                      solution=session.require("solution"))
    seconds = {"sample": session.timings.get("states"), "build": session.timings.get("dynamics"),
               "solve": session.timings.get("solution")}
    return lmdp, {k: v for k, v in seconds.items() if v is not None}


def bake_inputs(context, settings):
    """Main thread: capture the scene and check the bake (raises ``LMDPError`` before any work)."""
    meshes = selected_meshes(context)
    names = [obj.name for obj in meshes]
    if int(settings.bake_resolution) < 1:
        raise SceneError(f"Bake resolution must be at least 1 pixel (got {settings.bake_resolution})")
    scene = extract_scene(context, meshes)
    lmdp, seconds = (None, {})
    if settings.bake_mode != "UNGUIDED":
        lmdp, seconds = session_lmdp(context)
        if lmdp is None:
            raise StageOrderError(f"Solve first (LMDP panel > Solve, or Run All): the "
                                  f"{settings.bake_mode.replace('_', ' ').title()} bake mode is "
                                  "guided by the solved optimal policy; or choose bake mode Unguided")
    warnings = list(scene.warnings) + baking.check_bake_inputs(scene, names, settings, lmdp)
    return _with_output_dir(BakeInputs(scene=scene, names=names, lmdp=lmdp, precompute_seconds=seconds,
                                       warnings=warnings), settings)


def planned_bake_inputs(scene, names, settings):
    """Main thread: the bake inputs of a caller that has captured ``scene`` and will sample, build
    and solve it before baking (Run All); it fills in ``BakeInputs.lmdp`` and the precompute
    times itself. Checks everything the bake can check before the solution exists."""
    warnings = baking.check_bake_inputs(scene, names, settings, will_solve=True)
    return _with_output_dir(BakeInputs(scene=scene, names=names, warnings=warnings), settings)


def _with_output_dir(inputs, settings):
    """``inputs`` with ``settings.output_dir``, created (and checked writable) if set."""
    output_dir = settings.output_dir
    if output_dir:
        try:
            os.makedirs(output_dir, exist_ok=True)
        except OSError as error:
            raise SceneError(f"Cannot create the output folder {output_dir}: {error.strerror}; "
                             "choose another Output Folder or clear it") from error
        if not os.access(output_dir, os.W_OK):
            raise SceneError(f"The output folder {output_dir} is not writable: choose another one")
    inputs.output_dir = output_dir
    return inputs


def compute_bake(inputs, settings, progress):
    """No bpy: the engine bake (``lmdp_addon.bake.driver.bake``)."""
    result = baking.bake(inputs.scene, inputs.names, settings, lmdp=inputs.lmdp, progress=progress,
                         precompute_seconds=inputs.precompute_seconds)
    result.warnings = list(inputs.warnings)
    return result


# -- images ------------------------------------------------------------------------------------

def own_image(object_name):
    """The add-on's image for ``object_name`` (tagged), or None."""
    wanted = object_name + baking.IMAGE_SUFFIX
    tagged = [im for im in bpy.data.images if im.get(IMAGE_TAG) == object_name]
    for im in tagged:
        if im.name == wanted:
            return im
    return tagged[0] if tagged else None


def _new_float_image(name, resolution):
    image = bpy.data.images.new(name, resolution, resolution, alpha=True, float_buffer=True)
    image.colorspace_settings.name = 'Non-Color'
    return image


def _write_pixels(image, rgba):
    image.pixels.foreach_set(rgba.reshape(-1).astype("float32", copy=False))
    image.update()


def apply_bake(context, result, settings, hook_up="NONE"):
    """Main thread: swap the baked lightmaps in, save files and statistics, hook up materials.

    Returns ``(message, warnings)``. Raises ``LMDPError`` (nothing changed) if the files cannot
    be written.
    """
    warnings = list(result.warnings)
    output_dir = settings.output_dir
    scratch, temp_files = [], []
    try:
        # 1. Scratch images hold the new pixels; with an output folder they are saved to
        #    temporary files first, so a failure leaves the previous files and images alone.
        for ob in result.objects:
            im = _new_float_image(f"LMDP scratch {ob.name}", ob.resolution)
            _write_pixels(im, ob.image)
            scratch.append(im)
            if output_dir:
                fd, tmp = tempfile.mkstemp(prefix=".lmdp_", suffix=".exr", dir=output_dir)
                os.close(fd)
                temp_files.append(tmp)
                im.filepath_raw = tmp
                im.file_format = 'OPEN_EXR'
                im.save()
        stats_tmp = None
        if output_dir:
            fd, stats_tmp = tempfile.mkstemp(prefix=".lmdp_", suffix=".json", dir=output_dir)
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                json.dump(result.stats(), fh, indent=2, default=_json_default)
            temp_files.append(stats_tmp)
    except (OSError, RuntimeError) as error:
        for im in scratch:
            bpy.data.images.remove(im)
        for tmp in temp_files:
            if os.path.exists(tmp):
                os.remove(tmp)
        raise SceneError(f"Could not write the lightmaps to {output_dir}: {error}; nothing was "
                         "changed. Check the Output Folder") from error

    # 2. Swap: the add-on's own images get the new pixels, files replace the previous ones.
    images = {}
    for i, ob in enumerate(result.objects):
        image = own_image(ob.name)
        if image is None:
            wanted = ob.image_name
            if wanted in bpy.data.images:
                warnings.append(f"An image named '{wanted}' that LMDP did not create exists: it is "
                                "left alone and the lightmap gets a new name")
            image = _new_float_image(wanted, ob.resolution)
            image[IMAGE_TAG] = ob.name
        if output_dir:
            final = os.path.join(output_dir, ob.image_name + ".exr")
            os.replace(temp_files[i], final)
            if image.packed_file is not None:
                image.unpack(method='REMOVE')
            image.source = 'FILE'
            image.filepath_raw = final
            image.file_format = 'OPEN_EXR'
            image.colorspace_settings.name = 'Non-Color'
            image.reload()
        else:
            fresh = _new_float_image(ob.image_name, ob.resolution)
            _write_pixels(fresh, ob.image)
            fresh.pack()  # generated pixels are otherwise lost when the .blend is saved
            fresh[IMAGE_TAG] = ob.name
            if image.users:
                image.user_remap(fresh)  # nodes that showed the old lightmap show the new one
            name = image.name
            bpy.data.images.remove(image)
            fresh.name = name
            image = fresh
        images[ob.name] = image
    if output_dir:
        os.replace(stats_tmp, os.path.join(output_dir, STATS_FILE))
    for im in scratch:
        bpy.data.images.remove(im)

    # 3. Optional material hook-up.
    if hook_up != "NONE":
        for ob in result.objects:
            obj = bpy.data.objects.get(ob.name)
            if obj is None:
                continue
            if hook_up == "MULTIPLY":
                warnings += hook_multiply(obj, images[ob.name])
            elif hook_up == "PREVIEW":
                hook_preview(obj, images[ob.name])

    rays = sum(ob.stats.total_rays for ob in result.objects)
    bake_seconds = result.seconds.get("bake", 0.0)
    where = f", saved to {output_dir}" if output_dir else ""
    message = (f"Baked {len(result.objects)} lightmap(s) ({result.mode}, {result.n_texels} texels x "
               f"{settings.bake_samples} samples, {rays / 1e6:.2f} M rays) in {bake_seconds:.2f} s{where}")
    return message, warnings


def _json_default(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)


# -- material hook-up ------------------------------------------------------------------------------

def _colour_input(tree):
    """(node, input socket) of the BSDF whose colour the lightmap multiplies, or None."""
    output = tree.get_output_node('CYCLES') if tree is not None else None
    if output is None or not output.inputs["Surface"].links:
        return None
    node = output.inputs["Surface"].links[0].from_node
    if node.type == 'BSDF_PRINCIPLED':
        return node, node.inputs["Base Color"]
    if node.type == 'BSDF_DIFFUSE':
        return node, node.inputs["Color"]
    return None


def hook_multiply(obj, image):
    """Insert the lightmap multiplied into the colour of ``obj``'s own materials; returns warnings."""
    warnings = []
    for mat in {slot.material for slot in obj.material_slots if slot.material is not None}:
        users = [o.name for o in bpy.data.objects
                 if o != obj and any(s.material == mat for s in o.material_slots)]
        if users:
            warnings.append(f"Material '{mat.name}' is shared with {', '.join(users[:3])}: not hooked "
                            "up (a lightmap belongs to one object); use the Preview hook-up instead")
            continue
        tree = mat.node_tree
        if tree is None:
            continue
        if NODE_MULTIPLY in tree.nodes:
            tree.nodes[NODE_IMAGE].image = image
            continue
        target = _colour_input(tree)
        if target is None:
            warnings.append(f"Material '{mat.name}' has no Principled or Diffuse BSDF at its output: "
                            "not hooked up")
            continue
        bsdf, socket = target
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.name = tex.label = NODE_IMAGE
        tex.image = image
        tex.interpolation = 'Linear'
        tex.location = (bsdf.location.x - 520, bsdf.location.y - 260)
        mix = tree.nodes.new("ShaderNodeMix")
        mix.name = mix.label = NODE_MULTIPLY
        mix.data_type = 'RGBA'
        mix.blend_type = 'MULTIPLY'
        mix.inputs["Factor"].default_value = 1.0
        mix.location = (bsdf.location.x - 240, bsdf.location.y - 120)
        a, b, result = _mix_colour_sockets(mix)
        if socket.links:
            tree.links.new(socket.links[0].from_socket, a)
        else:
            a.default_value = socket.default_value
        tree.links.new(tex.outputs["Color"], b)
        tree.links.new(result, socket)
    return warnings


def _mix_colour_sockets(mix):
    """The colour A, B inputs and Result output of a Mix node (data_type 'RGBA')."""
    a, b = [s for s in mix.inputs if s.type == 'RGBA'][:2]
    result = next(s for s in mix.outputs if s.type == 'RGBA')
    return a, b, result


def unhook_multiply(obj):
    """Remove the MULTIPLY hook-up from ``obj``'s materials, restoring the colour input."""
    removed = 0
    for mat in {slot.material for slot in obj.material_slots if slot.material is not None}:
        tree = mat.node_tree
        if tree is None or NODE_MULTIPLY not in tree.nodes:
            continue
        mix = tree.nodes[NODE_MULTIPLY]
        a, _, result = _mix_colour_sockets(mix)
        targets = [link.to_socket for link in result.links]
        source = a.links[0].from_socket if a.links else None
        for socket in targets:
            if source is not None:
                tree.links.new(source, socket)
            else:
                for link in list(socket.links):
                    tree.links.remove(link)
                socket.default_value = a.default_value
        tree.nodes.remove(mix)
        if NODE_IMAGE in tree.nodes:
            tree.nodes.remove(tree.nodes[NODE_IMAGE])
        removed += 1
    return removed


def preview_material(obj, image):
    """The tagged preview material of ``obj`` (Emission = lightmap), created on first use."""
    name = f"{obj.name}_lmdp_preview"
    mat = next((m for m in bpy.data.materials if m.get(PREVIEW_TAG) == obj.name), None)
    if mat is None:
        mat = bpy.data.materials.new(name)
        mat[PREVIEW_TAG] = obj.name
        tree = mat.node_tree
        if tree is None:
            mat.use_nodes = True
            tree = mat.node_tree
        tree.nodes.clear()
        out = tree.nodes.new("ShaderNodeOutputMaterial")
        out.location = (300, 0)
        emission = tree.nodes.new("ShaderNodeEmission")
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.name = tex.label = NODE_IMAGE
        tex.location = (-300, 0)
        tree.links.new(tex.outputs["Color"], emission.inputs["Color"])
        tree.links.new(emission.outputs[0], out.inputs["Surface"])
    mat.node_tree.nodes[NODE_IMAGE].image = image
    return mat


def hook_preview(obj, image):
    """Show the preview material on every slot of ``obj`` at object level (mesh data untouched)."""
    mat = preview_material(obj, image)
    if PREVIEW_SAVED not in obj:
        added = False
        if not obj.material_slots:
            obj.data.materials.append(None)
            added = True
        saved = [{"link": s.link, "material": s.material.name if (s.link == 'OBJECT' and s.material) else None}
                 for s in obj.material_slots]
        obj[PREVIEW_SAVED] = json.dumps({"slots": saved, "added_slot": added})
    for slot in obj.material_slots:
        slot.link = 'OBJECT'
        slot.material = mat


def unhook_preview(obj):
    """Restore the slots saved by :func:`hook_preview`; returns True if there was a preview."""
    if PREVIEW_SAVED not in obj:
        return False
    saved = json.loads(obj[PREVIEW_SAVED])
    for slot, old in zip(obj.material_slots, saved["slots"]):
        slot.link = 'OBJECT'
        slot.material = bpy.data.materials.get(old["material"]) if old["material"] else None
        slot.link = old["link"]
    if saved.get("added_slot") and len(obj.data.materials) == 1 and obj.data.materials[0] is None:
        obj.data.materials.pop(index=0)
    del obj[PREVIEW_SAVED]
    return True


# -- operators -------------------------------------------------------------------------------------

class LMDP_OT_bake(EngineJob, bpy.types.Operator):
    """Bake the indirect diffuse light of the selected meshes into <object>_lmdp_indirect images,
    texel for texel like Cycles' Diffuse / Indirect bake (bake_mode, bake_resolution, bake_samples)"""

    bl_idname = "lmdp.bake"
    bl_label = "Bake Indirect Light"
    # Undo removes the new images and the material hook-up (pixel buffers of re-baked images
    # are not part of Blender's undo; the previous EXR files stay replaced).
    bl_options = {'REGISTER', 'UNDO'}
    stage = ""  # compute reports one stage per object

    hook_up: EnumProperty(
        name="Hook Up",
        description="Also show the lightmap in the object's material",
        items=HOOK_UP_ITEMS, default='NONE',
    )

    def prepare(self, context):
        return bake_inputs(context, self.settings)

    def compute(self, inputs, settings, progress):
        return compute_bake(inputs, settings, progress)

    def apply(self, context, result):
        message, warnings = apply_bake(context, result, self.settings, self.hook_up)
        session_for(context.scene).store("bake", result, seconds=result.seconds.get("bake"),
                                         settings=self.settings)
        report_warnings(self, warnings)
        return message


class LMDP_OT_remove_bake_hookup(bpy.types.Operator):
    """Remove what Bake's material hook-up added to the selected objects (the lightmap nodes, or
    the object-level preview material) and restore their materials"""

    bl_idname = "lmdp.remove_bake_hookup"
    bl_label = "Remove Bake Hook-up"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        try:
            objects = selected_meshes(context)
        except LMDPError as error:
            return report_error(self, error)
        nodes = previews = 0
        for obj in objects:
            nodes += unhook_multiply(obj)
            previews += int(unhook_preview(obj))
        self.report({'INFO'}, f"Removed the lightmap nodes from {nodes} material(s) and the preview "
                              f"from {previews} object(s)")
        return {'FINISHED'}


classes = (LMDP_OT_bake, LMDP_OT_remove_bake_hookup)
register, unregister = bpy.utils.register_classes_factory(classes)
