"""Objects and materials the display operators create: the arrow objects "LMDP Policy" /
"LMDP Probe" (custom property ``lmdp_generated``) in the collection "LMDP" with the emissive
material "LMDP Arrows", the render override material "LMDP Desirability", and
:func:`clear_all`, which removes everything the add-on's display wrote.
"""
import bpy
import numpy as np

from .display_data import (COLOR_ATTRIBUTE, DISPLAY_FLAG, MARK, display_modifier, marked,
                           mesh_from_triangles, remove_display_modifier, remove_point_attributes,
                           socket_by_id)

ARROWS_FLAG = "lmdp_arrows"
COLLECTION = "LMDP"
ARROW_MATERIAL = "LMDP Arrows"
RENDER_MATERIAL = "LMDP Desirability"
ARROW_COLOR_ATTRIBUTE = "lmdp_arrow_color"
#: Grey of surfaces without a displayed field in the render override (sRGB 0.5).
NEUTRAL_GREY = 0.214


# -- generated objects and materials ----------------------------------------------------------------------

def _collection(context):
    for collection in bpy.data.collections:
        if marked(collection, "collection"):
            if collection.name not in context.scene.collection.children and \
                    collection not in context.scene.collection.children_recursive:
                context.scene.collection.children.link(collection)
            return collection
    collection = bpy.data.collections.new(COLLECTION)
    collection[MARK] = "collection"
    context.scene.collection.children.link(collection)
    return collection


def generated_object(kind):
    """The add-on's object of ``kind`` ('policy', 'probe') or None."""
    for obj in bpy.data.objects:
        if marked(obj, kind):
            return obj
    return None


def set_generated_mesh_object(context, kind, name, vertices, triangles, colors, probability):
    """Create or replace the object of ``kind`` (named ``name`` when created) with a mesh of
    ``vertices``/``triangles`` carrying ``lmdp_arrow_color`` and ``lmdp_probability`` point
    attributes and the emissive "LMDP Arrows" material. Returns the object."""
    mesh = mesh_from_triangles(name, vertices, triangles)
    color = mesh.attributes.new(ARROW_COLOR_ATTRIBUTE, 'FLOAT_COLOR', 'POINT')
    color.data.foreach_set("color", np.ascontiguousarray(colors, dtype=np.float32).ravel())
    prob = mesh.attributes.new("lmdp_probability", 'FLOAT', 'POINT')
    prob.data.foreach_set("value", np.ascontiguousarray(probability, dtype=np.float32).ravel())
    mesh.color_attributes.active_color_name = ARROW_COLOR_ATTRIBUTE
    mesh.color_attributes.default_color_name = ARROW_COLOR_ATTRIBUTE
    mesh.materials.append(arrow_material())
    obj = generated_object(kind)
    if obj is None:
        obj = bpy.data.objects.new(name, mesh)
        obj[MARK] = kind
        obj[ARROWS_FLAG] = 1.0
        _collection(context).objects.link(obj)
    else:
        old = obj.data
        obj.data = mesh
        if old is not None and old.users == 0:
            bpy.data.meshes.remove(old)
        if not obj.users_collection:
            _collection(context).objects.link(obj)
    return obj


def remove_generated_object(kind):
    obj = generated_object(kind)
    if obj is None:
        return False
    mesh = obj.data
    bpy.data.objects.remove(obj)
    if mesh is not None and mesh.users == 0:
        bpy.data.meshes.remove(mesh)
    return True


def _material(name, kind):
    for material in bpy.data.materials:
        if marked(material, kind):
            return material, False
    material = bpy.data.materials.new(name)
    material[MARK] = kind
    return material, True


def _attribute_color(tree, name, location):
    node = tree.nodes.new("ShaderNodeAttribute")
    node.attribute_type = 'GEOMETRY'
    node.attribute_name = name
    node.location = location
    return node


def arrow_material():
    """"LMDP Arrows": emission of the arrows' ``lmdp_arrow_color`` (scene-linear, strength 1, so
    the Standard view transform shows the colour map), with a little diffuse shading for shape."""
    material, new = _material(ARROW_MATERIAL, "arrow_material")
    if not new:
        return material
    tree = material.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.location = (600, 0)
    color = _attribute_color(tree, ARROW_COLOR_ATTRIBUTE, (-400, 0))
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.location = (0, 100)
    diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.location = (0, -100)
    add = tree.nodes.new("ShaderNodeMixShader")
    add.location = (300, 0)
    add.inputs["Fac"].default_value = 0.2
    tree.links.new(color.outputs["Color"], emission.inputs["Color"])
    tree.links.new(color.outputs["Color"], diffuse.inputs["Color"])
    tree.links.new(emission.outputs[0], add.inputs[1])
    tree.links.new(diffuse.outputs[0], add.inputs[2])
    tree.links.new(add.outputs[0], out.inputs["Surface"])
    material.diffuse_color = (1.0, 0.6, 0.1, 1.0)
    return material


def render_material():
    """"LMDP Desirability": the render override that shows the field (see module docstring).

    Emission (strength 1) of ``lmdp_z_color`` on objects flagged ``lmdp_display``, of
    ``lmdp_arrow_color`` on the arrow objects, and a neutral grey elsewhere (lights included).
    """
    material, new = _material(RENDER_MATERIAL, "render_material")
    if not new:
        return material
    tree = material.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.location = (900, 0)
    field = _attribute_color(tree, COLOR_ATTRIBUTE, (-300, 200))
    arrows = _attribute_color(tree, ARROW_COLOR_ATTRIBUTE, (-300, -100))
    flag = tree.nodes.new("ShaderNodeAttribute")
    flag.attribute_type = 'OBJECT'
    flag.attribute_name = DISPLAY_FLAG
    flag.location = (-300, 450)
    is_arrow = tree.nodes.new("ShaderNodeAttribute")
    is_arrow.attribute_type = 'OBJECT'
    is_arrow.attribute_name = ARROWS_FLAG
    is_arrow.location = (-300, -350)
    first = tree.nodes.new("ShaderNodeMix")
    first.data_type = 'RGBA'
    first.location = (100, 250)
    socket_by_id(first.inputs, "A_Color").default_value = (NEUTRAL_GREY, NEUTRAL_GREY, NEUTRAL_GREY, 1.0)
    tree.links.new(flag.outputs["Fac"], socket_by_id(first.inputs, "Factor_Float"))
    tree.links.new(field.outputs["Color"], socket_by_id(first.inputs, "B_Color"))
    second = tree.nodes.new("ShaderNodeMix")
    second.data_type = 'RGBA'
    second.location = (350, 0)
    tree.links.new(is_arrow.outputs["Fac"], socket_by_id(second.inputs, "Factor_Float"))
    tree.links.new(socket_by_id(first.outputs, "Result_Color"), socket_by_id(second.inputs, "A_Color"))
    tree.links.new(arrows.outputs["Color"], socket_by_id(second.inputs, "B_Color"))
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.location = (600, 0)
    tree.links.new(socket_by_id(second.outputs, "Result_Color"), emission.inputs["Color"])
    tree.links.new(emission.outputs[0], out.inputs["Surface"])
    return material


def clear_all(context):
    """Remove everything the add-on wrote into the file; returns a short summary."""
    counts = {"attributes": 0, "modifiers": 0, "objects": 0}
    for obj in bpy.data.objects:
        if obj.type == 'MESH' and obj.library is None and obj.data is not None and obj.data.library is None:
            if display_modifier(obj) is not None:
                remove_display_modifier(obj)
                counts["modifiers"] += 1
        if DISPLAY_FLAG in obj.keys() and obj.library is None:
            del obj[DISPLAY_FLAG]
    for mesh in bpy.data.meshes:
        if mesh.library is None and remove_point_attributes(mesh):
            counts["attributes"] += 1
    for kind in ("policy", "probe"):
        if remove_generated_object(kind):
            counts["objects"] += 1
    for view_layer in context.scene.view_layers:
        if marked(view_layer.material_override, "render_material"):
            view_layer.material_override = None
    for obj in list(bpy.data.objects):  # orphaned field objects (their modifier was deleted)
        if marked(obj, "display_field") and obj.users == 0:
            bpy.data.objects.remove(obj)
    return counts
