"""One-click ways to see the desirability colours: the 3D viewports' shading preset and the
view layer's render override; and redrawing the viewports after a display changed."""
import bpy

from .display_objects import render_material
from .display_data import marked

#: Scene custom property holding the name of the override the render preset replaced.
PREVIOUS_OVERRIDE_KEY = "lmdp_previous_override"


def apply_shading_preset(shading):
    """Solid shading, colours from the active colour attribute, flat lighting (the colours are
    the colour map, unshaded)."""
    shading.type = 'SOLID'
    shading.color_type = 'VERTEX'  # shown as "Attribute" in the Shading popover
    shading.light = 'FLAT'


def reset_shading(shading):
    shading.color_type = 'MATERIAL'
    shading.light = 'STUDIO'


def view3d_spaces(context):
    """Every 3D viewport space of every window (none in background mode)."""
    spaces = []
    for window in getattr(context.window_manager, "windows", ()):
        screen = window.screen
        for area in (screen.areas if screen is not None else ()):
            if area.type == 'VIEW_3D':
                spaces.extend(space for space in area.spaces if space.type == 'VIEW_3D')
    return spaces


def shade_viewports(context, enable=True):
    """Apply (or undo) the preset in every 3D viewport; returns how many were changed."""
    spaces = view3d_spaces(context)
    for space in spaces:
        (apply_shading_preset if enable else reset_shading)(space.shading)
    return len(spaces)


def set_render_override(context, enable=True):
    """Make the view layer render the desirability colours (material override "LMDP
    Desirability"), or restore the override it had before. Object materials are not touched."""
    view_layer = context.view_layer
    scene = context.scene
    if enable:
        material = render_material()
        if view_layer.material_override is not material:
            previous = view_layer.material_override
            scene[PREVIOUS_OVERRIDE_KEY] = previous.name if previous is not None else ""
            view_layer.material_override = material
        return material
    current = view_layer.material_override
    if marked(current, "render_material"):
        previous = scene.get(PREVIOUS_OVERRIDE_KEY, "")
        view_layer.material_override = bpy.data.materials.get(previous) if previous else None
    if PREVIOUS_OVERRIDE_KEY in scene:
        del scene[PREVIOUS_OVERRIDE_KEY]
    return None


def tag_redraw(context):
    """Redraw every 3D viewport (the policy overlay, new colours)."""
    for window in getattr(context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type == 'VIEW_3D':
                area.tag_redraw()
