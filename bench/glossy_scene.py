"""The bench's textured glossy scene (issues 18 and 20): ``GLOSSY_BOX`` (the Cornell box with a
glossy Principled floor, roughness 0.2, and a metallic sphere) whose floor colour is an Image
Texture: a 256² float image of the 8 x 8 checker of ``demo_geometry.CHECKER_COLOURS`` shaded by a
smooth gradient, read with Linear interpolation on the floor's UV map, so every path vertex on
the floor reads the texture at its hit.

:func:`build` edits the Blender scene the session loaded (``BlenderSession.load_scene``) and
returns the engine's view of it, extracted by the add-on as a user's bake would be
(``world_scene.engine_scene``: textures, lobes and lamps included).
"""
import numpy as np

from .common import ROOT

#: The floor, its texture size and the gradient that shades the checker along u.
FLOOR = "Floor"
SIZE = 256
GRADIENT = (0.55, 1.0)
#: The source of this module is part of the reference cache key (``speed_error.geometry_hash``).
SOURCE = ROOT / "bench" / "glossy_scene.py"


def texture_pixels(size=SIZE):
    """(size, size, 4) float32 RGBA, row 0 at the bottom: the checker times the gradient in u."""
    from lmdp_addon.demo_geometry import CHECKER_COLOURS
    u = (np.arange(size) + 0.5) / size
    i = np.floor(u * 8).astype(int)
    checker = np.asarray(CHECKER_COLOURS, dtype=np.float32)[(i[None, :] + i[:, None]) % 2]
    shade = GRADIENT[0] + (GRADIENT[1] - GRADIENT[0]) * u[None, :, None]
    rgba = np.ones((size, size, 4), np.float32)
    rgba[..., :3] = checker * shade
    return rgba


def build(session):
    """Give the loaded GLOSSY_BOX's floor one Principled material with the texture; returns the
    scene's ``SceneArrays``."""
    from . import world_scene
    bpy = session.bpy
    floor = bpy.data.objects[FLOOR]
    old = next(m for m in floor.data.materials if m is not None)
    mat = old.copy()
    mat.name = "LMDP bench textured floor"
    tree = mat.node_tree
    principled = next(n for n in tree.nodes if n.type == 'BSDF_PRINCIPLED')
    image = bpy.data.images.new("LMDP bench floor texture", SIZE, SIZE, alpha=True, float_buffer=True)
    image.colorspace_settings.name = 'Linear Rec.709'
    image.pixels.foreach_set(texture_pixels().ravel())
    image.pack()
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image, tex.interpolation, tex.extension = image, 'Linear', 'REPEAT'
    uv = tree.nodes.new("ShaderNodeUVMap")
    uv.uv_map = floor.data.uv_layers[0].name
    tree.links.new(uv.outputs["UV"], tex.inputs["Vector"])
    tree.links.new(tex.outputs["Color"], principled.inputs["Base Color"])
    floor.data.materials.clear()
    floor.data.materials.append(mat)
    floor.data.polygons.foreach_set("material_index", np.zeros(len(floor.data.polygons), np.int32))
    floor.data.update()
    return world_scene.engine_scene(session)
