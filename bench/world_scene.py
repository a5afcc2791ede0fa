"""The bench's sun + HDRI scene (issue 19): the Cornell box without its lamp, open at the front,
under Blender's bundled ``city.exr`` turned so that the HDRI's sun (about 21 % of the map's light,
48° above the horizon) shines in through the opening, and a sun lamp (2 W/m², 2°) from the same
side.

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
#: A sun lamp from -y (through the opening), its elevation, strength (W/m²) and angular diameter.
SUN_ELEVATION_DEGREES = 48.0
SUN_STRENGTH = 2.0
SUN_ANGLE_DEGREES = 2.0
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
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", 'SUN'))
    sun.data.energy, sun.data.angle = SUN_STRENGTH, np.radians(SUN_ANGLE_DEGREES)
    sun.rotation_euler = (np.radians(90.0 - SUN_ELEVATION_DEGREES), 0.0, 0.0)   # shines along -Z: from -y
    scene.collection.objects.link(sun)
    bpy.context.view_layer.update()
    return engine_scene(session)


def engine_scene(session):
    """The add-on's capture of the session's scene (every mesh carries states), as this
    checkout's ``SceneArrays`` (its ``EnvironmentMap``, ``Lamps`` and other parts converted
    field by field: :func:`local_copy`)."""
    import dataclasses
    import importlib

    from lmdp_addon.scene_arrays import SceneArrays
    bpy = session.bpy
    extract = importlib.import_module(f"{session.module}.operators.adapters.extract")
    meshes = [o for o in bpy.context.scene.objects if o.type == 'MESH']
    c = extract.extract_scene(bpy.context, meshes)
    return SceneArrays(**{f.name: local_copy(getattr(c, f.name)) for f in dataclasses.fields(SceneArrays)
                          if f.init and hasattr(c, f.name)})


def local_copy(value):
    """``value`` with every dataclass of the session's extension (``<module>.lmdp_addon.X.C``)
    rebuilt as this checkout's ``lmdp_addon.X.C`` from its init fields; lists and tuples
    element by element; anything else as it is."""
    import dataclasses
    import importlib

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        module = type(value).__module__
        if ".lmdp_addon" in module:
            module = "lmdp_addon" + module.split(".lmdp_addon", 1)[1]
        cls = getattr(importlib.import_module(module), type(value).__name__)
        return cls(**{f.name: local_copy(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init})
    if isinstance(value, (list, tuple)):
        return type(value)(local_copy(v) for v in value)
    return value
