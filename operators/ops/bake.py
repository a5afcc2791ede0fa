"""``lmdp.bake``: indirect light of the selected meshes into ``<object>_lmdp_indirect`` images;
``lmdp.remove_bake_hookup`` undoes its material hook-up.

The bake is an ``EngineJob`` of the three steps in :mod:`..bake_steps` (check on the main
thread, engine bake in the worker, lightmaps written back); the images, files and material
hook-up are described in :mod:`..adapters.lightmaps` and :mod:`..adapters.materials`.
"""
import bpy
from bpy.props import EnumProperty

from ..adapters.materials import HOOK_UP_ITEMS, remove_hook_up
from ..bake_steps import apply_bake, bake_inputs, compute_bake
from ..common import report_error, report_warnings, selected_meshes
from ..jobs import EngineJob, ready
from ..properties import bake_settings_from_scene
from ...lmdp_addon.errors import LMDPError


class LMDP_OT_bake(EngineJob, bpy.types.Operator):
    """Bake the indirect diffuse light of the selected meshes into <object>_lmdp_indirect images,
    texel for texel like Cycles' Diffuse / Indirect bake (bake_mode, bake_resolution, bake_samples)"""

    bl_idname = "lmdp.bake"
    bl_label = "Bake Indirect Light"
    # Undo removes the new images and the material hook-up (pixel buffers of re-baked images
    # are not part of Blender's undo; the previous EXR files stay replaced).
    bl_options = {'REGISTER', 'UNDO'}
    stage = ""  # the engine reports one stage per object

    hook_up: EnumProperty(
        name="Hook Up",
        description="Also show the lightmap in the object's material",
        items=HOOK_UP_ITEMS, default='NONE',
    )

    @classmethod
    def poll(cls, context):
        # The modes that read a solution solve the scene first when the session has none for it.
        return ready(cls, context, selection=True)

    def read_settings(self, context):
        # The path length follows the scene's Cycles Light Paths unless scene.lmdp.light_paths is CUSTOM.
        settings, self.light_paths = bake_settings_from_scene(context.scene)
        return settings

    def prepare(self, context):
        return bake_inputs(context, self.settings, self.hook_up, self.light_paths)

    def compute(self, inputs, settings, progress):
        return compute_bake(inputs, settings, progress)

    def apply(self, context, result):
        message, warnings = apply_bake(context, result, self.settings, self.hook_up)
        report_warnings(self, warnings)
        return message


class LMDP_OT_remove_bake_hookup(bpy.types.Operator):
    """Remove what Bake's material hook-up added to the selected objects (the lightmap nodes, or
    the object-level preview material) and restore their materials"""

    bl_idname = "lmdp.remove_bake_hookup"
    bl_label = "Remove Bake Hook-up"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True)

    def execute(self, context):
        try:
            objects = selected_meshes(context)
        except LMDPError as error:
            return report_error(self, error)
        nodes = previews = 0
        left = []
        for obj in objects:
            removed, preview, linked = remove_hook_up(obj)
            nodes, previews, left = nodes + removed, previews + int(preview), left + linked
        if left:
            self.report({'WARNING'}, f"Left library data alone (linked or overridden): "
                                     f"{', '.join(sorted(set(left))[:5])}; make it local to remove its hook-up")
        self.report({'INFO'}, f"Removed the lightmap nodes from {nodes} material(s) and the preview "
                              f"from {previews} object(s)")
        return {'FINISHED'}


classes = (LMDP_OT_bake, LMDP_OT_remove_bake_hookup)
register, unregister = bpy.utils.register_classes_factory(classes)
