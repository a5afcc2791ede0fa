"""Scene helpers for the add-on tests (import as `from helpers import ...`)."""


def add_material(name, color=(0.8, 0.8, 0.8), emission=0.0):
    """A Diffuse BSDF material, or an Emission material of strength ``emission``."""
    import bpy
    material = bpy.data.materials.new(name)
    tree = material.node_tree if material.node_tree is not None else None
    if tree is None:
        material.use_nodes = True
        tree = material.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    if emission > 0.0:
        shader = tree.nodes.new("ShaderNodeEmission")
        shader.inputs["Strength"].default_value = emission
    else:
        shader = tree.nodes.new("ShaderNodeBsdfDiffuse")
    shader.inputs["Color"].default_value = (*color, 1.0)
    tree.links.new(shader.outputs[0], output.inputs["Surface"])
    return material


def select(objects, active=None):
    """Select exactly ``objects`` (and make ``active`` or the first one active)."""
    import bpy
    view_layer = bpy.context.view_layer
    for obj in view_layer.objects:
        obj.select_set(False)
    for obj in objects:
        obj.select_set(True)
    view_layer.objects.active = active or (objects[0] if objects else None)


def remove_uv_maps(obj):
    """Delete every UV map of ``obj``'s mesh (a mesh the bake must refuse)."""
    while obj.data.uv_layers:
        obj.data.uv_layers.remove(obj.data.uv_layers[0])
    obj.data.update()
