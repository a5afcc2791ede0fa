"""Material hook-up of baked lightmaps (Bake's ``hook_up``) and its removal.

* ``'MULTIPLY'``: in each material the object renders with, an Image Texture node "LMDP
  Lightmap" (the lightmap, read through a UV Map node "LMDP Lightmap UV" naming the UV map that
  was baked, ``lightmap_uvs.chosen_uv_name``, unless that is the render UV map) and a Mix node "LMDP Lightmap Multiply" (Multiply,
  factor 1) are inserted in front of the Base Color (Principled BSDF) or Color (Diffuse BSDF)
  input; whatever fed that input (a link or its value) feeds the Mix node's A input. Nothing else
  is changed; :func:`unhook_multiply` removes the nodes and restores the link or value. A material
  that other objects use too is hooked up only when all its users show the same image through a
  UV map of the same name: the members of an atlas, whose shared image holds each object's
  texels in its own region of "LMDP Lightmap", so one material selects every object's lightmap
  through that object's own UV map. Other shared materials are left alone (one warning names
  them all and their users).
* ``'PREVIEW'``: a material "<object>_lmdp_preview" (Emission shader showing the lightmap) is
  linked to the object's material slots at *object* level (``slot.link = 'OBJECT'``), so the
  mesh's own materials stay assigned to the mesh; :func:`unhook_preview` restores each slot's
  previous link and object material.

The materials an object renders with are read through the preview (:func:`render_materials`),
so the two hook-ups can be stacked in any order and removed together. Only local data is ever
edited: :func:`check_hook_up` refuses, before the bake, a hook-up that would edit linked library
data or a library override (Blender would not save the edit, or would reset it on reload).
"""
import json

import bpy

from ...lmdp_addon.errors import SceneError
from .gltf_lightmap import emissive_copy, hook_gltf, unhook_gltf
from .lightmap_uvs import chosen_uv_name

#: Custom property of preview materials, and of objects whose slots show one (JSON of the slots).
PREVIEW_TAG = "lmdp_preview_material"
PREVIEW_SAVED = "lmdp_preview_saved_slots"
#: Names of the nodes the MULTIPLY hook-up adds.
NODE_IMAGE = "LMDP Lightmap"
NODE_MULTIPLY = "LMDP Lightmap Multiply"
NODE_UV = "LMDP Lightmap UV"

HOOK_UP_ITEMS = (
    ("NONE", "None", "Only write the images (and files)"),
    ("MULTIPLY", "Multiply Base Color",
     "Insert an Image Texture of the lightmap multiplied into the Base Color / Color of the "
     "object's own materials (undo with Remove Bake Hook-up)"),
    ("PREVIEW", "Preview Material",
     "Show the lightmap on the object through an emission material linked to the object's "
     "material slots (the mesh's materials are kept; undo with Remove Bake Hook-up)"),
    ("GLTF_EMISSIVE", "glTF Emissive (Preview)",
     "The Preview hook-up showing an 8-bit sRGB copy of the lightmap scaled to its brightest texel, "
     "so the glTF exporter writes it as an emissive texture with that strength that viewers show "
     "right (bake Direct + Indirect times the diffuse colour for the whole baked look)"),
    ("GLTF", "glTF Occlusion",
     "Wire the lightmap into the glTF exporter's Occlusion (a 'glTF Material Output' group) of the "
     "object's own materials, on the baked UV map: exported as occlusionTexture (red channel, "
     "clipped at 1); Cycles and the bake do not see it (undo with Remove Bake Hook-up)"),
)


# ---- Library data ---------------------------------------------------------------------------------

def is_local(id_data):
    """True for a data-block of this file that is neither linked nor a library override."""
    return id_data.library is None and getattr(id_data, "override_library", None) is None


def _origin(id_data):
    """'linked from <library>' or 'a library override of <library>' for a non-local data-block."""
    if id_data.library is not None:
        return f"linked from {id_data.library.filepath}"
    reference = id_data.override_library.reference
    library = reference.library.filepath if reference is not None and reference.library else "a library"
    return f"a library override of {library}"


def check_hook_up(objects, mode):
    """Before any work: raise ``SceneError`` naming the object or material when the ``mode``
    hook-up of ``objects`` would edit data that is not local."""
    users = None
    for obj in objects:
        if mode in ("PREVIEW", "GLTF_EMISSIVE"):
            if not is_local(obj):
                raise SceneError(f"'{obj.name}' is {_origin(obj)}: the Preview hook-up would edit "
                                 "library data, which Blender does not keep. Make the object local "
                                 "(Object > Relations > Make Local) or bake with Hook Up: None")
            if not obj.material_slots and not is_local(obj.data):
                raise SceneError(f"The mesh of '{obj.name}' is {_origin(obj.data)} and has no "
                                 "material slot for the Preview hook-up: make the mesh local or bake "
                                 "with Hook Up: None")
        elif mode in ("MULTIPLY", "GLTF"):
            users = users if users is not None else material_users()
            edited = _multiply_targets(obj, [], users)[0] if mode == "MULTIPLY" else _own_materials(obj, [], users)
            for mat in edited:
                if not is_local(mat):
                    raise SceneError(
                        f"Material '{mat.name}' of '{obj.name}' is {_origin(mat)}: the {mode.title()} "
                        "hook-up would edit library data, which Blender does not keep. Make the "
                        "material local (Object > Relations > Make Local > Selected Objects, Data "
                        "and Materials) or bake with Hook Up: Preview or None")


def hook_up(targets, mode, uv_maps=None):
    """Show each lightmap of ``targets`` ([(object, image)]) in its object's materials the
    ``mode`` way (:data:`HOOK_UP_ITEMS`), read through the UV map ``uv_maps[object name]`` (None
    or absent: the render UV map); returns the warnings. Run :func:`check_hook_up` first."""
    warnings = []
    baked_on = dict(uv_maps or {})   # object name -> the UV map its lightmap is laid out on
    users = material_users() if mode in ("MULTIPLY", "GLTF") else None
    uv_maps = {obj.name: _pinned_uv_map(obj, baked_on.get(obj.name)) for obj, _ in targets}
    shown = {obj.name_full: (image, uv_maps.get(obj.name)) for obj, image in targets}
    shared = {}
    for obj, image in targets:
        if mode == "MULTIPLY":
            warnings += hook_multiply(obj, image, users, uv_maps.get(obj.name), shown, shared)
        elif mode == "PREVIEW":
            hook_preview(obj, image, uv_map=baked_on.get(obj.name))
        elif mode == "GLTF_EMISSIVE":
            hook_preview(obj, *emissive_copy(image), uv_map=baked_on.get(obj.name))
        elif mode == "GLTF":
            hook_gltf(obj, image, _own_materials(obj, warnings, users), warnings, uv_maps.get(obj.name))
    if shared:
        warnings.append("Shared materials not hooked up (their users do not show one atlas image through "
                        "the same UV map; bake them with Atlas on, or use the Preview hook-up): "
                        + "; ".join(f"'{m}' (used by {', '.join(sorted(u))})" for m, u in sorted(shared.items())))
    return warnings


def _own_materials(obj, warnings, users):
    """The materials ``obj`` renders with that no other object uses (``users``:
    :func:`material_users`); appends a warning for each shared one."""
    own = []
    for mat in render_materials(obj):
        others = [name for name in users.get(mat, ()) if name != obj.name_full]
        if others:
            warnings.append(f"Material '{mat.name}' is shared with {', '.join(others[:3])}: not hooked "
                            "up (a lightmap belongs to one object)")
        elif mat.node_tree is not None:
            own.append(mat)
    return own


def _pinned_uv_map(obj, uv_map):
    """``uv_map``, or None when it is the render UV map of ``obj``'s mesh (the Image Texture reads
    that one without a UV Map node)."""
    layers = getattr(obj.data, "uv_layers", None)
    render = next((l.name for l in layers if l.active_render), None) if layers is not None else None
    return None if not uv_map or uv_map == render else uv_map


# ---- What an object renders with ----------------------------------------------------------------------

def _material_by_full_name(name):
    if not name:
        return None
    return next((m for m in bpy.data.materials if m.name_full == name), None)


def _saved_slots(obj):
    return json.loads(obj[PREVIEW_SAVED]) if PREVIEW_SAVED in obj else None


def _is_preview(mat):
    return mat is not None and PREVIEW_TAG in mat


def _underlying_material(obj, index, saved):
    """The material slot ``index`` of ``obj`` shows when no preview covers it."""
    slots = saved["slots"] if saved else []
    if index < len(slots) and slots[index]["link"] == 'OBJECT':
        return _material_by_full_name(slots[index]["material"])
    materials = obj.data.materials if obj.data is not None else ()
    return materials[index] if index < len(materials) else None


def material_users():
    """{material: full names of the objects that render with it} over the whole file."""
    users = {}
    for obj in bpy.data.objects:
        for mat in render_materials(obj):
            users.setdefault(mat, []).append(obj.name_full)
    return users


def slot_materials(obj):
    """The material of each of ``obj``'s slots as it renders without LMDP's preview (the one the
    preview covers, or None); ``obj`` may be an evaluated object (its original holds the record
    of what the preview covered)."""
    source = getattr(obj, "original", obj)
    saved = _saved_slots(source)
    materials = []
    for index, slot in enumerate(obj.material_slots):
        mat = slot.material
        if _is_preview(mat):
            mat = _underlying_material(source, index, saved)
        materials.append(None if _is_preview(mat) else mat)
    return materials


def render_materials(obj):
    """The materials ``obj`` renders with, the ones under LMDP's preview material included."""
    materials = []
    for mat in slot_materials(obj):
        if mat is not None and mat not in materials:
            materials.append(mat)
    return materials


# ---- MULTIPLY -----------------------------------------------------------------------------------------

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


def _mix_colour_sockets(mix):
    """The colour A, B inputs and Result output of a Mix node (data_type 'RGBA')."""
    a, b = [s for s in mix.inputs if s.type == 'RGBA'][:2]
    result = next(s for s in mix.outputs if s.type == 'RGBA')
    return a, b, result


def _image_node(tree, image, location):
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.name = tex.label = NODE_IMAGE
    tex.image = image
    tex.interpolation = 'Linear'
    tex.location = location
    return tex


def _read_through_uv_map(tree, tex, uv_map):
    """The image node ``tex`` reads UV map ``uv_map`` (a UV Map node "LMDP Lightmap UV"), or the
    render UV map when ``uv_map`` is None."""
    node = tree.nodes.get(NODE_UV)
    if not uv_map:
        if node is not None:
            tree.nodes.remove(node)
        return
    if node is None or node.type != 'UVMAP':
        node = tree.nodes.new("ShaderNodeUVMap")
        node.name = node.label = NODE_UV
        node.location = (tex.location.x - 220, tex.location.y)
    node.uv_map = uv_map
    tree.links.new(node.outputs["UV"], tex.inputs["Vector"])


def _insert_multiply(tree, bsdf, socket, image, uv_map=None):
    """Image Texture x whatever fed ``socket`` (a link or its value), into ``socket``. An "LMDP
    Lightmap" node left over from a hook-up whose Mix node was deleted is reused."""
    tex = tree.nodes.get(NODE_IMAGE)
    if tex is None or tex.type != 'TEX_IMAGE':
        tex = _image_node(tree, image, (bsdf.location.x - 520, bsdf.location.y - 260))
    tex.image = image
    _read_through_uv_map(tree, tex, uv_map)
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


def _update_multiply(tree, image, uv_map=None):
    """Point an existing MULTIPLY hook-up at ``image`` (its image node remade if it was deleted)."""
    mix = tree.nodes[NODE_MULTIPLY]
    tex = tree.nodes.get(NODE_IMAGE)
    if tex is None:
        tex = _image_node(tree, image, (mix.location.x - 280, mix.location.y - 140))
        tree.links.new(tex.outputs["Color"], _mix_colour_sockets(mix)[1])
    tex.image = image
    _read_through_uv_map(tree, tex, uv_map)


def _multiply_targets(obj, warnings, users, shown=None, shared=None):
    """(materials of ``obj`` the MULTIPLY hook-up edits, their (node, socket) or None if already
    hooked up); appends why the others are skipped to ``warnings``. ``users``: :func:`material_users`.
    ``shown``: {object key: (image, UV map)} of the hook-up: a material other objects use is edited
    only when every user shows the same (image, UV map) as ``obj``; the others are added to
    ``shared`` {material name: its users} (or named in ``warnings`` without ``shared``)."""
    materials, inputs = [], []
    shown = shown or {}
    for mat in render_materials(obj):
        others = [name for name in users.get(mat, ()) if name != obj.name_full]
        mine = shown.get(obj.name_full)
        if others and not (mine is not None and all(shown.get(o) == mine for o in others)):
            if shared is not None:
                shared[mat.name] = set(users.get(mat, ()))
            else:
                warnings.append(f"Material '{mat.name}' is shared with {', '.join(others)}: not hooked up")
            continue
        tree = mat.node_tree
        if tree is None:
            continue
        target = None if NODE_MULTIPLY in tree.nodes else _colour_input(tree)
        if target is None and NODE_MULTIPLY not in tree.nodes:
            warnings.append(f"Material '{mat.name}' has no Principled or Diffuse BSDF at its output: "
                            "not hooked up")
            continue
        materials.append(mat)
        inputs.append(target)
    return materials, inputs


def hook_multiply(obj, image, users=None, uv_map=None, shown=None, shared=None):
    """Insert the lightmap multiplied into the colour of ``obj``'s materials, read through
    ``uv_map``; returns warnings. ``users``: :func:`material_users` (computed if not given);
    ``shown``, ``shared``: see :func:`_multiply_targets`."""
    warnings = []
    users = users if users is not None else material_users()
    for mat, target in zip(*_multiply_targets(obj, warnings, users, shown, shared)):
        if target is None:
            _update_multiply(mat.node_tree, image, uv_map)
        else:
            _insert_multiply(mat.node_tree, *target, image, uv_map)
    return warnings


def unhook_multiply(obj):
    """Remove the MULTIPLY hook-up from ``obj``'s local materials, restoring the colour input;
    returns (materials restored, names of the non-local materials left alone)."""
    removed, left = 0, []
    for mat in render_materials(obj):
        tree = mat.node_tree
        if tree is None or NODE_MULTIPLY not in tree.nodes:
            continue
        if not is_local(mat):
            left.append(mat.name)
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
        for name in (NODE_IMAGE, NODE_UV):
            if name in tree.nodes:
                tree.nodes.remove(tree.nodes[name])
        removed += 1
    return removed, left


# ---- PREVIEW ------------------------------------------------------------------------------------------

def _build_preview_tree(mat, image):
    tree = mat.node_tree
    if tree is None:
        mat.use_nodes = True
        tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.location = (300, 0)
    emission = tree.nodes.new("ShaderNodeEmission")
    tex = _image_node(tree, image, (-300, 0))
    tree.links.new(tex.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs[0], out.inputs["Surface"])


#: The UV Map node of the preview material: the lightmap is read through its own UV map.
NODE_PREVIEW_UV = "LMDP Lightmap UV"


def preview_material(obj, image, strength=1.0, uv_map=None):
    """The tagged preview material of ``obj`` (Emission = lightmap x ``strength``), created on
    first use (and its nodes rebuilt if its image node was deleted); it reads the lightmap
    through the UV map ``uv_map`` (None: the lightmap's map, ``lightmap_uvs.chosen_uv_name``:
    "LMDP Lightmap" where the mesh has it, else its render map)."""
    mat = next((m for m in bpy.data.materials if m.get(PREVIEW_TAG) == obj.name and is_local(m)), None)
    if mat is None:
        mat = bpy.data.materials.new(f"{obj.name}_lmdp_preview")
        mat[PREVIEW_TAG] = obj.name
    if mat.node_tree is None or mat.node_tree.nodes.get(NODE_IMAGE) is None:
        _build_preview_tree(mat, image)
    mat.node_tree.nodes[NODE_IMAGE].image = image
    uv_map = uv_map or (chosen_uv_name(obj.data) if getattr(obj.data, "uv_layers", None) is not None else None)
    if uv_map:
        tree = mat.node_tree
        node = tree.nodes.get(NODE_PREVIEW_UV)
        if node is None:
            node = tree.nodes.new("ShaderNodeUVMap")
            node.name = node.label = NODE_PREVIEW_UV
            node.location = (-500, 0)
            tree.links.new(node.outputs["UV"], tree.nodes[NODE_IMAGE].inputs["Vector"])
        node.uv_map = uv_map
    for node in mat.node_tree.nodes:
        if node.type == 'EMISSION':
            node.inputs["Strength"].default_value = float(strength)
    return mat


def _slot_state(slot):
    """A slot's link and its object-level material (kept even while the slot shows the mesh's)."""
    link = slot.link
    slot.link = 'OBJECT'
    material = slot.material
    slot.link = link
    return {"link": link, "material": material.name_full if material is not None else None}


def hook_preview(obj, image, strength=1.0, uv_map=None):
    """Show the preview material on every slot of ``obj`` at object level (mesh data untouched,
    except for one empty slot added to a mesh that has none). The slots' previous state is kept
    on the object, extended with any slot added since an earlier preview."""
    mat = preview_material(obj, image, strength, uv_map)
    saved = _saved_slots(obj)
    if saved is None:
        added = False
        if not obj.material_slots:
            obj.data.materials.append(None)
            added = True
        saved = {"slots": [], "added_slot": added}
    slots = list(obj.material_slots)
    saved["slots"] += [_slot_state(s) for s in slots[len(saved["slots"]):]]
    obj[PREVIEW_SAVED] = json.dumps(saved)
    for slot in slots:
        slot.link = 'OBJECT'
        slot.material = mat


def unhook_preview(obj):
    """Restore the slots saved by :func:`hook_preview`; returns True if there was a preview.
    A slot added later that shows the preview is emptied and linked to the mesh again."""
    saved = _saved_slots(obj)
    if saved is None:
        return False
    for index, slot in enumerate(obj.material_slots):
        if index < len(saved["slots"]):
            old = saved["slots"][index]
            slot.link = 'OBJECT'
            slot.material = _material_by_full_name(old["material"])
            slot.link = old["link"]
        elif slot.link == 'OBJECT' and _is_preview(slot.material):
            slot.material = None
            slot.link = 'DATA'
    if saved.get("added_slot") and len(obj.data.materials) == 1 and obj.data.materials[0] is None:
        obj.data.materials.pop(index=0)
    del obj[PREVIEW_SAVED]
    return True


def remove_hook_up(obj):
    """Remove both hook-ups from ``obj`` (the preview first: it hides the materials MULTIPLY
    hooked up). Returns (materials restored, whether a preview was removed, names of the
    non-local data left alone)."""
    left = []
    if is_local(obj):
        preview = unhook_preview(obj)
    else:
        preview = False
        if PREVIEW_SAVED in obj:
            left.append(obj.name_full)
    removed, linked = unhook_multiply(obj)
    removed += unhook_gltf([mat for mat in render_materials(obj) if is_local(mat)])
    return removed, preview, left + linked
