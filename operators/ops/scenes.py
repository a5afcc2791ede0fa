"""Add > LMDP Demo Scene: the built-in test scenes as ordinary Blender objects (lmdp.add_demo_scene)."""
import bpy
from bpy.props import EnumProperty

from ...lmdp_addon.errors import LMDPError
from ...lmdp_addon.demo_geometry import SCENE_KINDS
from ..adapters.demo_scenes import SCENE_LABELS, build_demo_scene

_DESCRIPTIONS = {
    "CORNELL_BOX": "The Cornell box at 1 m scale: red and green walls, two boxes, a ceiling light",
    "NARROW_OPENING": "Two rooms joined by a small hatch; the light is in the other room",
    "PLANE_UNDER_SKY": "A diffuse plane under a uniform sky (analytic answer: albedo x sky radiance)",
    "PARALLEL_SQUARES": "A plane under a parallel square emitter (analytic form factor)",
    "HEAVY": "The Cornell box with bumpy, finely subdivided surfaces (about 250k triangles)",
    "GLOSSY_BOX": "The Cornell box with a glossy checkered floor and a metallic sphere (Principled BSDFs)",
}


class LMDP_OT_add_demo_scene(bpy.types.Operator):
    """Add one of LMDP's built-in test scenes (meshes with Diffuse / Emission materials, UV maps,
    a camera, world and Cycles settings) and select the meshes that carry LMDP states"""

    bl_idname = "lmdp.add_demo_scene"
    bl_label = "LMDP Demo Scene"
    bl_options = {'REGISTER', 'UNDO'}

    kind: EnumProperty(
        name="Scene",
        description="Which built-in scene to add",
        items=[(k, SCENE_LABELS[k], _DESCRIPTIONS[k]) for k in SCENE_KINDS],
        default="CORNELL_BOX",
    )

    @classmethod
    def poll(cls, context):
        return context.scene is not None and (context.mode == 'OBJECT' or context.mode is None)

    def execute(self, context):
        try:
            carriers = build_demo_scene(self.kind, context)
        except LMDPError as error:
            self.report({'ERROR'}, str(error))
            return {'CANCELLED'}
        view_layer = context.view_layer
        for obj in view_layer.objects:
            obj.select_set(False)
        for obj in carriers:
            obj.select_set(True)
        if carriers:
            view_layer.objects.active = carriers[0]
        self.report({'INFO'}, f"Added {SCENE_LABELS[self.kind]}: {len(carriers)} meshes selected "
                              "(they carry the LMDP states)")
        return {'FINISHED'}


def draw_add_menu(self, context):
    self.layout.operator_menu_enum(LMDP_OT_add_demo_scene.bl_idname, "kind",
                                   text="LMDP Demo Scene", icon='LIGHT_AREA')


classes = (LMDP_OT_add_demo_scene,)

_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.types.VIEW3D_MT_add.append(draw_add_menu)


def unregister():
    bpy.types.VIEW3D_MT_add.remove(draw_add_menu)
    _unregister_classes()
