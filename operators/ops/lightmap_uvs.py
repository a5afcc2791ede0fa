"""``lmdp.create_lightmap_uvs``: the UV map "LMDP Lightmap" on the selected meshes, laid out for
their lightmaps (:func:`..adapters.lightmap_uvs.create_lightmap_uvs`); the other UV maps, the
active and the render UV map stay as they were."""
import bpy
from bpy.props import EnumProperty, IntProperty

from ..adapters.extract import extract_scene
from ..adapters.lightmap_uvs import LIGHTMAP_UV, UV_MARGIN_TEXELS, create_lightmap_uvs
from ..common import report_error, report_warnings, selected_meshes
from ..jobs import ready
from ..properties import settings_from_scene
from ...lmdp_addon.bake.resolution import object_resolutions
from ...lmdp_addon.errors import LMDPError

METHOD_ITEMS = (
    ("SMART", "Smart UV Project", "Smart UV Project, then Pack Islands with the margin"),
    ("LIGHTMAP", "Lightmap Pack", "Every face its own island (Lightmap Pack), then Pack Islands with the margin"),
)


class LMDP_OT_create_lightmap_uvs(bpy.types.Operator):
    """Create the UV map 'LMDP Lightmap' on the selected meshes for their lightmaps (Smart UV
    Project or Lightmap Pack, islands packed with a margin in texels); with Atlas on, all of them
    packed together. The other UV maps and the render UV map are not changed"""

    bl_idname = "lmdp.create_lightmap_uvs"
    bl_label = "Create Lightmap UVs"
    bl_options = {'REGISTER', 'UNDO'}

    method: EnumProperty(name="Method", description="How the faces are unwrapped", items=METHOD_ITEMS,
                         default='SMART')
    margin: IntProperty(name="Margin", description="Space between UV islands (texels of the lightmap)",
                        default=UV_MARGIN_TEXELS, min=0, max=64, subtype='PIXEL')

    @classmethod
    def poll(cls, context):
        return ready(cls, context, selection=True)

    def execute(self, context):
        try:
            meshes = selected_meshes(context)
            settings = settings_from_scene(context.scene)
            joint = bool(settings.atlas) and len(meshes) > 1
            if settings.resolution_mode == "DENSITY":
                scene = extract_scene(context, meshes)
                indices = [scene.object_names.index(o.name) for o in meshes if o.name in scene.object_names]
                R = max(object_resolutions(scene, indices, settings, atlas=joint).values(),
                        default=settings.min_resolution)
            else:
                R = int(settings.bake_resolution)
            warnings = create_lightmap_uvs(context, meshes, R, self.margin, self.method, joint=joint)
        except LMDPError as error:
            return report_error(self, error)
        report_warnings(self, warnings)
        self.report({'INFO'}, f"'{LIGHTMAP_UV}' laid out on {len(meshes)} mesh(es) "
                              f"({'packed together' if joint else 'each on its own'}, margin {self.margin} "
                              f"texels of {R} x {R})")
        return {'FINISHED'}


classes = (LMDP_OT_create_lightmap_uvs,)
register, unregister = bpy.utils.register_classes_factory(classes)
