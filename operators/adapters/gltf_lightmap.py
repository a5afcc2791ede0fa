"""The ``'GLTF'`` hook-up: the lightmap wired where Blender's glTF exporter keeps it, as the
material's occlusion texture, without changing how Blender or LMDP see the material.

In each material the object renders with and no other object uses, three nodes are added and
connected to nothing Cycles evaluates: an Image Texture "LMDP glTF Lightmap" (the lightmap, read
through a UV Map node "LMDP glTF UV" naming the baked UV map), a Separate Color "LMDP glTF Split"
and a group node "LMDP glTF Output" of the node group "glTF Material Output" (the group the
exporter reads glTF-only inputs from; created with its Occlusion input when the file has none),
the lightmap's red channel in its Occlusion input. The exporter writes that as
``occlusionTexture`` with the ``texCoord`` of the UV map (``TEXCOORD_1`` when the lightmap has its
own second UV map), the image as an 8-bit PNG of the linear values, clipped at 1.

A material whose own "glTF Material Output" already has its Occlusion linked is left alone
(with a warning). :func:`unhook_gltf` removes the three nodes (the group stays: other materials
or the user may use it).

The ``'GLTF_EMISSIVE'`` hook-up is the Preview one (``materials.hook_preview``: an emission
material on the object's slots, which the capture sees through) showing :func:`emissive_copy`:
an 8-bit sRGB image "<lightmap>_gltf" of the lightmap divided by S = its brightest value (at
least 1), with emission strength S. The exporter writes it as ``emissiveTexture`` over a black
base colour, with ``KHR_materials_emissive_strength`` S when S > 1: a viewer that decodes the
texture as sRGB (as glTF says) and multiplies by S shows the baked radiance, to 8 bits.
"""
import bpy
import numpy as np

NODE_IMAGE = "LMDP glTF Lightmap"
NODE_UV = "LMDP glTF UV"
NODE_SPLIT = "LMDP glTF Split"
NODE_OUTPUT = "LMDP glTF Output"
NODES = (NODE_IMAGE, NODE_UV, NODE_SPLIT, NODE_OUTPUT)
#: The node group Blender's glTF exporter reads glTF-only material inputs from.
GLTF_GROUP = "glTF Material Output"


#: Custom property of the 8-bit emissive copy of a lightmap (the lightmap image's name).
EMISSIVE_TAG = "lmdp_gltf_emissive_of"
EMISSIVE_SUFFIX = "_gltf"


def srgb_encode(linear):
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    v = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def emissive_copy(image):
    """``(copy, S)``: the add-on's 8-bit sRGB copy of the float lightmap ``image`` (made or
    refreshed, packed, fake user) holding ``srgb(value / S)``, S = the brightest value, at
    least 1."""
    w, h = image.size
    px = np.empty(w * h * image.channels, np.float32)
    image.pixels.foreach_get(px)
    rgb = px.reshape(h, w, image.channels)[..., :3].astype(np.float64)
    scale = max(1.0, float(rgb.max(initial=0.0)))
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = np.rint(srgb_encode(rgb / scale) * 255.0) / 255.0
    copy = next((im for im in bpy.data.images if im.get(EMISSIVE_TAG) == image.name and im.library is None), None)
    if copy is not None and tuple(copy.size) != (w, h):
        bpy.data.images.remove(copy)
        copy = None
    if copy is None:
        copy = bpy.data.images.new(image.name + EMISSIVE_SUFFIX, w, h, alpha=True, float_buffer=False)
        copy[EMISSIVE_TAG] = image.name
    copy.colorspace_settings.name = 'sRGB'
    copy.pixels.foreach_set(rgba.reshape(-1))
    copy.update()
    copy.pack()
    copy.use_fake_user = True
    return copy, scale


def baked_uv_map(obj):
    """Name of the UV map the lightmap of ``obj`` is laid out on (the active render UV map)."""
    layers = obj.data.uv_layers
    active = next((uv for uv in layers if uv.active_render), None)
    return active.name if active is not None else (layers[0].name if len(layers) else "")


def gltf_output_group():
    """The file's "glTF Material Output" node group with an Occlusion input (made if missing)."""
    group = bpy.data.node_groups.get(GLTF_GROUP)
    if group is None:
        group = bpy.data.node_groups.new(GLTF_GROUP, "ShaderNodeTree")
    if not any(item.item_type == 'SOCKET' and item.in_out == 'INPUT' and item.name == "Occlusion"
               for item in group.interface.items_tree):
        socket = group.interface.new_socket("Occlusion", in_out='INPUT', socket_type='NodeSocketFloat')
        socket.default_value, socket.min_value, socket.max_value = 1.0, 0.0, 1.0
    return group


def _users_occlusion(tree):
    """A group node of the user's (not the add-on's) that feeds glTF Occlusion already."""
    return next((n for n in tree.nodes if n.type == 'GROUP' and n.name != NODE_OUTPUT and n.node_tree is not None
                 and n.node_tree.name == GLTF_GROUP and "Occlusion" in n.inputs and n.inputs["Occlusion"].links),
                None)


def hook_gltf(obj, image, materials, warnings, uv_map=None):
    """Wire ``image`` into the glTF occlusion of each of ``materials`` (``obj``'s own, unshared
    materials), read through ``uv_map`` (None: the render UV map, :func:`baked_uv_map`); appends
    to ``warnings`` why one was left alone."""
    uv_map = uv_map or baked_uv_map(obj)
    for mat in materials:
        tree = mat.node_tree
        if tree is None:
            continue
        theirs = _users_occlusion(tree)
        if theirs is not None:
            warnings.append(f"Material '{mat.name}' already sends an occlusion texture to glTF ('{theirs.name}'): "
                            "the lightmap is not wired into it")
            continue
        nodes = {name: tree.nodes.get(name) for name in NODES}
        x, y = -900.0, -700.0
        if nodes[NODE_UV] is None:
            nodes[NODE_UV] = tree.nodes.new("ShaderNodeUVMap")
        if nodes[NODE_IMAGE] is None:
            nodes[NODE_IMAGE] = tree.nodes.new("ShaderNodeTexImage")
        if nodes[NODE_SPLIT] is None:
            nodes[NODE_SPLIT] = tree.nodes.new("ShaderNodeSeparateColor")
        if nodes[NODE_OUTPUT] is None:
            nodes[NODE_OUTPUT] = tree.nodes.new("ShaderNodeGroup")
        for k, name in enumerate(NODES):
            node = nodes[name]
            node.name = node.label = name
            node.location = (x + 260 * k, y)
        nodes[NODE_UV].uv_map = uv_map
        nodes[NODE_IMAGE].image = image
        nodes[NODE_IMAGE].interpolation = 'Linear'
        nodes[NODE_OUTPUT].node_tree = gltf_output_group()
        tree.links.new(nodes[NODE_UV].outputs["UV"], nodes[NODE_IMAGE].inputs["Vector"])
        tree.links.new(nodes[NODE_IMAGE].outputs["Color"], nodes[NODE_SPLIT].inputs["Color"])
        tree.links.new(nodes[NODE_SPLIT].outputs[0], nodes[NODE_OUTPUT].inputs["Occlusion"])
    return warnings


def unhook_gltf(materials):
    """Remove the add-on's glTF nodes from ``materials`` (local ones); returns how many had them."""
    removed = 0
    for mat in materials:
        tree = mat.node_tree
        if tree is None or NODE_OUTPUT not in tree.nodes:
            continue
        for name in NODES:
            if name in tree.nodes:
                tree.nodes.remove(tree.nodes[name])
        removed += 1
    return removed
