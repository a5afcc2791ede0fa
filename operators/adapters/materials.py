"""Material hook-up of baked lightmaps (Bake's ``hook_up``) and its removal.

* ``'MULTIPLY'``: in each material used only by this object, an Image Texture node "LMDP
  Lightmap" (the lightmap, default UV map = the render UV map that was baked) and a Mix node
  "LMDP Lightmap Multiply" (Multiply, factor 1) are inserted in front of the Base Color (Principled
  BSDF) or Color (Diffuse BSDF) input; whatever fed that input (a link or its value) feeds the Mix
  node's A input. Nothing else is changed; :func:`unhook_multiply` removes both nodes and
  restores the link or value.
* ``'PREVIEW'``: a material "<object>_lmdp_preview" (Emission shader showing the lightmap) is
  linked to the object's material slots at *object* level (``slot.link = 'OBJECT'``), so the
  mesh's own materials stay assigned to the mesh; :func:`unhook_preview` restores each slot's
  previous link and object material.
"""
import json

import bpy

#: Custom property of preview materials, and of objects whose slots show one (JSON of the slots).
PREVIEW_TAG = "lmdp_preview_material"
PREVIEW_SAVED = "lmdp_preview_saved_slots"
#: Names of the nodes the MULTIPLY hook-up adds.
NODE_IMAGE = "LMDP Lightmap"
NODE_MULTIPLY = "LMDP Lightmap Multiply"

HOOK_UP_ITEMS = (
    ("NONE", "None", "Only write the images (and files)"),
    ("MULTIPLY", "Multiply Base Color",
     "Insert an Image Texture of the lightmap multiplied into the Base Color / Color of the "
     "object's own materials (undo with Remove Bake Hook-up)"),
    ("PREVIEW", "Preview Material",
     "Show the lightmap on the object through an emission material linked to the object's "
     "material slots (the mesh's materials are kept; undo with Remove Bake Hook-up)"),
)


def hook_up(images, mode):
    """Show each lightmap of ``images`` ({object name: image}) in its object's materials the
    ``mode`` way (:data:`HOOK_UP_ITEMS`); returns the warnings."""
    warnings = []
    if mode == "NONE":
        return warnings
    for name, image in images.items():
        obj = bpy.data.objects.get(name)
        if obj is None:
            continue
        if mode == "MULTIPLY":
            warnings += hook_multiply(obj, image)
        elif mode == "PREVIEW":
            hook_preview(obj, image)
    return warnings


def _own_materials(obj):
    return {slot.material for slot in obj.material_slots if slot.material is not None}


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


def _insert_multiply(tree, bsdf, socket, image):
    """Image Texture x whatever fed ``socket`` (a link or its value), into ``socket``."""
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


def hook_multiply(obj, image):
    """Insert the lightmap multiplied into the colour of ``obj``'s own materials; returns warnings."""
    warnings = []
    for mat in _own_materials(obj):
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
        _insert_multiply(tree, *target, image)
    return warnings


def unhook_multiply(obj):
    """Remove the MULTIPLY hook-up from ``obj``'s materials, restoring the colour input."""
    removed = 0
    for mat in _own_materials(obj):
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
