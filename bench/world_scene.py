"""The bench's sun + HDRI scene (issue 19): the Cornell box without its lamp, open at the front,
under Blender's bundled ``city.exr`` turned so that the HDRI's sun (about 21 % of the map's light,
48° above the horizon) shines in through the opening.

:func:`build` edits the Blender scene the session loaded (``BlenderSession.load_scene``) and
returns the engine's view of it, extracted by the add-on as a user's bake would be
(``operators.adapters.extract``: the environment map included), converted to this checkout's
``lmdp_addon`` classes (the session's extension is a second import of the same code).
"""
import numpy as np

from .common import ROOT

#: The HDRI, its strength and its turn about z: the sun of city.exr (azimuth -36° in the map)
#: comes from -y, the Cornell box's open side.
HDRI = "city.exr"
STRENGTH = 1.0
TURN_Z_DEGREES = 54.0
#: The Cornell box's emitter (``demo_geometry``), removed: the world lights the scene alone.
LAMP = "Light"
#: The source of this module is part of the reference cache key (``speed_error.geometry_hash``).
SOURCE = ROOT / "bench" / "world_scene.py"


def build(session):
    """Turn the loaded CORNELL_BOX into the sun + HDRI scene; returns its ``SceneArrays``."""
    bpy = session.bpy
    scene = bpy.context.scene
    bpy.data.objects.remove(bpy.data.objects[LAMP])        # the box's ceiling lamp
    world = bpy.data.worlds.new("LMDP bench HDRI")
    tree = world.node_tree
    nodes, links = tree.nodes, tree.links
    background = nodes["Background"]
    background.inputs["Strength"].default_value = STRENGTH
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(bpy.utils.system_resource('DATAFILES', path="studiolights/world")
                                     + "/" + HDRI, check_existing=True)
    coords = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, np.radians(TURN_Z_DEGREES))
    links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    links.new(tex.outputs["Color"], background.inputs["Color"])
    scene.world = world
    # LAMPS MERGE HOOK: add a SUN light here (e.g. from -y, 48° up) once lmdp_addon/lamps.py models sun lights.
    return engine_scene(session)


def engine_scene(session):
    """The add-on's capture of the session's scene (every mesh carries states), as this
    checkout's ``SceneArrays`` with its ``EnvironmentMap``."""
    import importlib

    from lmdp_addon.scene_arrays import SceneArrays
    from lmdp_addon.world import EnvironmentMap
    bpy = session.bpy
    extract = importlib.import_module(f"{session.module}.operators.adapters.extract")
    meshes = [o for o in bpy.context.scene.objects if o.type == 'MESH']
    c = extract.extract_scene(bpy.context, meshes)
    env = c.environment
    return SceneArrays(
        vertices=c.vertices, triangles=c.triangles, triangle_object=c.triangle_object,
        triangle_albedo=c.triangle_albedo, triangle_emission=c.triangle_emission,
        object_names=list(c.object_names), object_carries_states=c.object_carries_states,
        world_radiance=c.world_radiance, triangle_emission_two_sided=c.triangle_emission_two_sided,
        triangle_uv=c.triangle_uv, object_has_uv=c.object_has_uv, corner_normals=c.corner_normals,
        warnings=list(c.warnings),
        environment=None if env is None else EnvironmentMap(env.radiance, rotation=env.rotation,
                                                            interpolation=env.interpolation, name=env.name))
