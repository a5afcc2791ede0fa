"""Blender scene -> :class:`~lmdp_addon.scene_arrays.SceneArrays`, the engine's only view of bpy data.

:func:`extract_scene` reads every visible mesh of the view layer from the evaluated depsgraph
(modifiers and geometry nodes applied, instances included, world space), its triangles, the
lightmap's UV map (``scene.lmdp.lightmap_uv_map``, :mod:`.lightmap_uvs`), and the diffuse albedo,
alpha and emitted radiance of the material of its polygon (:mod:`.shading`: constant per
triangle, or an expression of image textures, colour attributes and colour nodes evaluated at
each point, ``SceneArrays.surface``), plus Blender's lights (point, spot, sun and area lights as
lamps) and the world background.
Conventions follow Cycles as measured in docs/cycles_conventions.md:

* Emission shader: radiance = Color x Strength, two-sided. Principled BSDF: Base Color is the
  albedo, Emission Color x Emission Strength the radiance.
* A material whose node tree has no connected Surface renders black: albedo 0. A polygon without
  material uses Cycles' default surface, a Diffuse BSDF of 0.8 grey.
* Lights (POINT, SPOT, SUN, AREA): :class:`~lmdp_addon.lamps.Lamps` (their conventions are in
  ``lamps.py``) with power P (W; W/m² for a sun) x 2^exposure x colour c (x its temperature
  colour, x the Emission node's Color x Strength when it uses nodes); an AREA light of size
  a x b and object scale (sx, sy) has radiance L = P c / (π a sx b sy) (``normalize`` on, the
  default; P c / π when off; x π/4 in the area of a disk / ellipse), emitted towards its -Z.
  Lamps occlude nothing, as Cycles' lights.
* World: Background Color x Strength of the shader connected to the World Output, an
  Environment Texture (HDRI) as an environment map, other world trees rendered into one
  (``world_capture``).
* Objects in Edit Mode are captured as the user sees them (their edit mesh, modifiers applied).

The result is a :class:`CapturedScene`: a ``SceneArrays`` that also knows which Blender object
each of its objects is (``session_uid``, which survives renames) and a fingerprint of the mesh
and transform of each object that carries states, so that results are never matched to
objects by name (:func:`..session.captured_index`, :func:`..session.changed_since_capture`).

Whatever is approximated (nodes LMDP cannot evaluate, emission textures averaged per triangle,
non-diffuse BSDFs as diffuse, unsupported lights skipped) is reported in ``SceneArrays.warnings`` with the
object, material and node names.
"""
import hashlib
from dataclasses import dataclass

import bpy
import numpy as np

from ...lmdp_addon import textures
from ...lmdp_addon.bsdf import MaterialTable
from ...lmdp_addon.lamps import AREA, POINT, SPOT, SUN, Lamps
from ...lmdp_addon.scene_arrays import SceneArrays
from ..common import mode_holding_mesh, skipped_mesh_messages
from . import shading
from .bsdf_params import cycles_glossy_settings, material_lobes
from .lightmap_uvs import chosen_uv_name
from .materials import NODE_MULTIPLY, slot_materials
from .world_capture import WorldReader, socket_source, srgb_to_linear

#: Cycles' default surface (a polygon without material): Diffuse BSDF, colour 0.8.
DEFAULT_ALBEDO = (0.8, 0.8, 0.8)
#: Object types whose evaluated geometry is a mesh.
GEOMETRY_TYPES = {'MESH', 'CURVE', 'CURVES', 'SURFACE', 'META', 'FONT'}



@dataclass
class CapturedScene(SceneArrays):
    """A ``SceneArrays`` captured from Blender, with the identity of its objects.

    object_uids          (O,) int64 ``session_uid`` of each object's Blender object (-1 for
                         instances, which have no object of their own)
    object_fingerprints  O x (str or None): :func:`object_fingerprint` of the mesh objects that
                         carry states ("" for other types), None for the others
    """

    object_uids: np.ndarray = None
    object_fingerprints: list = None


def object_fingerprint(obj):
    """Digest of what the states on the mesh object ``obj`` were sampled on: its mesh's vertex
    positions and faces and its world matrix (changes of modifier settings are not seen). An
    object in Edit Mode is first updated from its edit mesh (``update_from_editmode``, which
    changes nothing the user sees)."""
    mesh = obj.data
    if mesh.is_editmode:
        obj.update_from_editmode()
    co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    corners = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", corners)
    starts = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    digest = hashlib.blake2b(digest_size=16)
    for array in (co, corners, starts, np.array(obj.matrix_world, dtype=np.float32)):
        digest.update(array.tobytes())
    return digest.hexdigest()


class _MaterialReader:
    """The world's radiance and the constant values of node inputs (the microfacet lobes'
    parameters, ``bsdf_params``), with warnings; meshes read their colour, alpha and emission
    with :class:`.shading.ShadingReader`."""

    def __init__(self, warnings):
        self.warnings = warnings
        self._image_means = {}

    def warn(self, message):
        if message not in self.warnings:
            self.warnings.append(message)

    # -- sockets ------------------------------------------------------------------------------
    _source = staticmethod(socket_source)

    def image_mean(self, image, equirect=False):
        """Mean linear RGB of ``image`` (rows weighted by solid angle for equirect maps)."""
        key = (image.name, equirect)
        if key not in self._image_means:
            table = shading.IMAGE_CACHE.table(image)
            if table is None:
                self._image_means[key] = None
            else:
                h, w = table.pixels.shape[:2]
                px = table.pixels[..., :3].astype(np.float64)
                if table.srgb:
                    px = srgb_to_linear(px)
                if equirect:
                    lat = (np.arange(h) + 0.5) / h * np.pi - np.pi / 2
                    weight = np.cos(lat)[:, None]
                    mean = (px * weight[..., None]).sum(axis=(0, 1)) / (weight.sum() * w)
                else:
                    mean = px.mean(axis=(0, 1))
                self._image_means[key] = mean
        return self._image_means[key]

    def colour(self, node, name, owner):
        """Linear RGB (3,) of colour input ``name`` of ``node``; texture -> mean, else default."""
        return self._socket_colour(node, node.inputs[name], name, owner)

    def _socket_colour(self, node, socket, name, owner):
        """:meth:`colour` of the input ``socket`` (called ``name``) of ``node``."""
        default = np.array(socket.default_value[:3], dtype=np.float64)
        source = self._source(socket)
        if source is None:
            return default
        src, _ = source
        if src.type == 'MIX' and src.name == NODE_MULTIPLY:
            # The add-on's own MULTIPLY hook-up: the surface is what its A input holds.
            a = next(s for s in src.inputs if s.type == 'RGBA')
            return self._socket_colour(src, a, "A", owner)
        if src.type in ('TEX_IMAGE', 'TEX_ENVIRONMENT') and src.image is not None:
            equirect = src.type == 'TEX_ENVIRONMENT' and src.projection == 'EQUIRECTANGULAR'
            mean = self.image_mean(src.image, equirect)
            if mean is not None:
                self.warn(f"{owner}: '{node.name}' {name} uses the mean colour of image "
                          f"'{src.image.name}' ({mean[0]:.3f}, {mean[1]:.3f}, {mean[2]:.3f}); "
                          "LMDP surfaces are uniform per material")
                return mean
            self.warn(f"{owner}: image '{src.image.name}' feeding '{node.name}' {name} has no "
                      "pixels; using the socket's default value")
            return default
        self.warn(f"{owner}: '{node.name}' {name} is driven by node '{src.name}', which LMDP "
                  "cannot evaluate; using the socket's default value "
                  f"({default[0]:.3f}, {default[1]:.3f}, {default[2]:.3f})")
        return default

    def value(self, node, name, owner):
        socket = node.inputs[name]
        default = float(socket.default_value)
        source = self._source(socket)
        if source is not None:
            self.warn(f"{owner}: '{node.name}' {name} is driven by node '{source[0].name}', which "
                      f"LMDP cannot evaluate; using the socket's default value {default:g}")
        return default

    def world(self, world):
        """``(world_radiance (3,), environment or None)`` of the world seen by escaping rays
        (:class:`.world_capture.WorldReader`: uniform, an HDRI map, or a render of the world)."""
        return WorldReader(self.warnings).capture(world)


# -- geometry ---------------------------------------------------------------------------------

def _mesh_arrays(mesh, matrix):
    """World-space vertices (V, 3), triangles (T, 3), loops (T, 3), polygon index (T,)."""
    n_verts = len(mesh.vertices)
    co = np.empty(n_verts * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3).astype(np.float64)
    m = np.asarray(matrix, dtype=np.float64)
    world = co @ m[:3, :3].T + m[:3, 3]
    tris = mesh.loop_triangles
    n = len(tris)
    verts = np.empty(n * 3, dtype=np.int32)
    loops = np.empty(n * 3, dtype=np.int32)
    poly = np.empty(n, dtype=np.int32)
    tris.foreach_get("vertices", verts)
    tris.foreach_get("loops", loops)
    tris.foreach_get("polygon_index", poly)
    return world, verts.reshape(-1, 3).astype(np.int64), loops.reshape(-1, 3), poly


def _render_uv(mesh, loops, name=None):
    """(T, 3, 2) UVs of the UV map ``name`` (the lightmap's, :func:`.lightmap_uvs.chosen_uv_name`),
    or None when the mesh has no such map."""
    layer = mesh.uv_layers.get(name) if name else None
    if layer is None or len(loops) == 0:
        return None
    uv = np.empty(len(mesh.loops) * 2, dtype=np.float32)
    layer.data.foreach_get("uv", uv)
    return uv.reshape(-1, 2)[loops]


def _corner_normals(mesh, matrix, loops):
    """(T, 3, 3) float32 world-space unit normals of the triangles' corners as Cycles shades
    them: ``mesh.corner_normals`` (Blender 4.1+: flat faces give their face normal, smooth
    faces the vertex normals, custom split normals and "Smooth by Angle" their results),
    transformed by the inverse transpose of ``matrix``; None when the mesh has none."""
    normals = getattr(mesh, "corner_normals", None)
    if normals is None or len(loops) == 0 or len(normals) != len(mesh.loops):
        return None
    flat = np.empty(len(mesh.loops) * 3, dtype=np.float32)
    normals.foreach_get("vector", flat)
    m = np.asarray(matrix, dtype=np.float64)[:3, :3]
    try:
        inverse_transpose = np.linalg.inv(m).T
    except np.linalg.LinAlgError:
        return None
    world = flat.reshape(-1, 3).astype(np.float64) @ inverse_transpose.T
    with np.errstate(invalid="ignore", divide="ignore"):
        world /= np.linalg.norm(world, axis=1, keepdims=True)
    return world[loops].astype(np.float32)


def _light_strength(name, light, warnings):
    """Cycles' light strength (3,): colour (x its temperature colour) x power x 2^exposure,
    times the Emission node's Color x Strength when the light uses nodes (``_light_nodes``)."""
    colour = np.array(light.color[:3], dtype=np.float64)
    if getattr(light, "use_temperature", False):
        colour = colour * np.array(light.temperature_color[:3], dtype=np.float64)
    strength = colour * light.energy * 2.0 ** getattr(light, "exposure", 0.0)
    if getattr(light, "use_nodes", False) and light.node_tree is not None:
        strength = strength * _light_nodes(name, light.node_tree, warnings)
    return strength


def _linked_source(socket):
    """The node feeding ``socket`` (through reroutes), or None."""
    links = [link for link in socket.links if not link.is_muted and link.is_valid]
    while links:
        node = links[0].from_node
        if node.type != 'REROUTE':
            return node
        links = [link for link in node.inputs[0].links if not link.is_muted and link.is_valid]
    return None


def _blackbody_rgb(temperature):
    """Blender's blackbody colour (3,) of ``temperature`` K (the colour a light's own
    temperature takes, read from a temporary light)."""
    probe = bpy.data.lights.new("LMDP blackbody probe", 'POINT')
    try:
        probe.use_temperature = True
        probe.temperature = float(temperature)
        return np.array(probe.temperature_color[:3], dtype=np.float64)
    finally:
        bpy.data.lights.remove(probe)


def _light_nodes(name, tree, warnings):
    """(3,) factor of a light's node tree: the Emission node's Color x Strength feeding the
    active Light Output (a Blackbody node into Color is evaluated; other links are warned
    about and their socket's value used)."""
    outputs = [n for n in tree.nodes if n.type == 'OUTPUT_LIGHT']
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    if any(n.type == 'TEX_IES' for n in tree.nodes):
        warnings.append(f"Light '{name}': its IES texture is not modelled; the light emits evenly")
    node = _linked_source(output.inputs["Surface"]) if output is not None else None
    if node is None:
        return np.zeros(3)
    if node.type != 'EMISSION':
        warnings.append(f"Light '{name}': shader node '{node.name}' ({node.type.lower()}) is not "
                        "modelled; the light's colour and power are used as they are")
        return np.ones(3)
    strength_socket = node.inputs["Strength"]
    strength = float(strength_socket.default_value)
    if _linked_source(strength_socket) is not None:
        warnings.append(f"Light '{name}': the Emission Strength is driven by a node LMDP cannot "
                        f"evaluate; using {strength:g}")
    colour_socket = node.inputs["Color"]
    colour = np.array(colour_socket.default_value[:3], dtype=np.float64)
    source = _linked_source(colour_socket)
    if source is not None and source.type == 'BLACKBODY' and _linked_source(source.inputs[0]) is None:
        colour = _blackbody_rgb(source.inputs[0].default_value)
    elif source is not None:
        warnings.append(f"Light '{name}': the Emission Color is driven by node '{source.name}', which "
                        "LMDP cannot evaluate; using the socket's colour")
    return colour * strength


def _lamp_record(name, matrix, light, warnings):
    """The :class:`~lmdp_addon.lamps.Lamps` columns (a dict) of a POINT, SPOT, SUN or AREA light."""
    m = np.asarray(matrix, dtype=np.float64)
    axis = -m[:3, 2]
    record = dict(name=name, kind={'POINT': POINT, 'SPOT': SPOT, 'SUN': SUN, 'AREA': AREA}[light.type],
                  position=m[:3, 3], axis=axis / max(np.linalg.norm(axis), 1e-300),
                  strength=_light_strength(name, light, warnings),
                  normalize=bool(getattr(light, "normalize", True)), cast_shadow=bool(light.use_shadow),
                  mis=bool(getattr(getattr(light.original, "cycles", None), "use_multiple_importance_sampling",
                                   True)))
    if np.any(record["strength"] < 0):
        warnings.append(f"Light '{name}': negative power or colour is not modelled; those channels emit "
                        "nothing")
    if light.type == 'AREA':
        # Cycles' axes: the light's X and Y scaled by the object (normal: its -Z)
        size_u = light.size
        size_v = light.size_y if light.shape in ('RECTANGLE', 'ELLIPSE') else light.size
        record.update(extent_u=m[:3, 0] * size_u, extent_v=m[:3, 1] * size_v,
                      ellipse=light.shape in ('DISK', 'ELLIPSE'), spread=float(light.spread))
        if light.spread < 1e-4:
            warnings.append(f"Light '{name}': spread 0 (a parallel beam) is not modelled; LMDP uses a "
                            "spread of 0.006°")
        return record
    if light.type == 'SUN':
        record["angle"] = float(light.angle)
        return record
    record["radius"] = float(light.shadow_soft_size)
    record["sphere"] = not bool(getattr(light, "use_soft_falloff", True))
    if light.type == 'SPOT':
        record["spot_size"] = float(light.spot_size)
        record["spot_blend"] = float(light.spot_blend)
        scale = np.linalg.norm(m[:3, :3], axis=0)
        if np.ptp(scale) > 1e-4 * scale.max():
            warnings.append(f"Light '{name}': a non-uniformly scaled spot's cone is elliptic in Cycles; "
                            "LMDP keeps it round (apply the scale to the light)")
        if getattr(light, "use_square", False):
            warnings.append(f"Light '{name}': the square spot shape only changes the viewport")
    return record


def _lamps(records):
    """:class:`~lmdp_addon.lamps.Lamps` of the lamp records (``_lamp_record``)."""
    if not records:
        return Lamps()
    columns = {key: [r.get(key, default) for r in records]
               for key, default in (("kind", POINT), ("position", (0.0, 0.0, 0.0)), ("axis", (0.0, 0.0, -1.0)),
                                    ("radius", 0.0), ("angle", 0.0), ("sphere", False), ("spot_size", np.pi),
                                    ("spot_blend", 0.0), ("strength", (0.0, 0.0, 0.0)), ("normalize", True),
                                    ("cast_shadow", True), ("extent_u", (0.0, 0.0, 0.0)),
                                    ("extent_v", (0.0, 0.0, 0.0)), ("ellipse", False), ("spread", np.pi),
                                    ("mis", True))}
    return Lamps(names=[r["name"] for r in records], **columns)


def _is_hidden(obj, view_layer):
    return (obj.hide_get(view_layer=view_layer) or obj.hide_viewport or obj.hide_render
            or not obj.visible_get(view_layer=view_layer))


class _SceneBuilder:
    """Collects the objects' world triangles, materials and UVs into one :class:`SceneArrays`."""

    def __init__(self):
        self.names, self.carries, self.has_uv = [], [], []
        self.uids, self.fingerprints = [], []
        self.parts = []  # (vertices, triangles, albedo, emission, two_sided, uv) per object
        self.normals = []  # (T, 3, 3) corner normals per object (NaN: the face normal)
        self.surfaces = []  # (material (T,), {uv index: (T, 3, 2)}, {attribute index: (T, 3, 4)})
        self.materials, self._material_index = [], {}
        self.lobe_of = []  # (T,) index into self.lobes per object (-1: Lambertian)
        self.lobes, self.lobe_names, self._lobe_index = [], [], {}
        self.offset = 0
        self.lamps = []   # point, spot and sun lights (``_lamp_record``)

    def material_index(self, key, shading):
        """Scene-wide index of the textured / transparent material ``key``."""
        if key not in self._material_index:
            self._material_index[key] = len(self.materials)
            self.materials.append(shading)
        return self._material_index[key]

    def lobe_index(self, key, name, lobes):
        """Index of the microfacet lobes ``lobes`` of material ``key`` in the scene's
        ``MaterialTable`` (-1: none, a Lambertian material)."""
        if not lobes:
            return -1
        if key not in self._lobe_index:
            self._lobe_index[key] = len(self.lobes)
            self.lobes.append(lobes)
            self.lobe_names.append(name)
        return self._lobe_index[key]

    def add(self, name, carries_states, world, tris, albedo, emission, two_sided, uv,
            uid=-1, fingerprint=None, corner_normals=None, surface=None, lobes=None):
        """One object: world vertices (V, 3), triangles (T, 3) into them, per-triangle albedo /
        emission (T, 3) and two-sidedness (T,), UVs (T, 3, 2) or None; the ``session_uid`` and
        :func:`object_fingerprint` of its Blender object (see :class:`CapturedScene`); its
        corner normals (T, 3, 3) world space, or None (flat: the face normals); ``surface``:
        ``(material (T,) int32, {uv map: (T, 3, 2)}, {attribute: (T, 3, 4)})`` of its textured
        materials (:meth:`material_index`; -1: constant), or None; ``lobes`` (T,) its
        triangles' :meth:`lobe_index` (None: Lambertian)."""
        self.names.append(name)
        self.uids.append(uid)
        self.fingerprints.append(fingerprint)
        self.carries.append(carries_states)
        self.has_uv.append(uv is not None)
        self.parts.append((world, tris + self.offset, np.full(len(tris), len(self.names) - 1, dtype=np.int32),
                           albedo, emission, two_sided,
                           uv if uv is not None else np.zeros((len(tris), 3, 2), np.float32)))
        self.normals.append(corner_normals if corner_normals is not None
                            else np.full((len(tris), 3, 3), np.nan, np.float32))
        self.surfaces.append(surface if surface is not None
                             else (np.full(len(tris), -1, np.int32), {}, {}))
        self.lobe_of.append(np.full(len(tris), -1, np.int32) if lobes is None
                            else np.asarray(lobes, np.int32))
        self.offset += len(world)

    def surface(self, reader, transparent_max_bounces):
        """The scene's :class:`~lmdp_addon.textures.SurfaceTextures`, or None (all constant)."""
        if not self.materials:
            return None
        sizes = [len(s[0]) for s in self.surfaces]

        def column(which, index, shape):
            return np.concatenate([s[which].get(index, np.zeros((n,) + shape, np.float32))
                                   for s, n in zip(self.surfaces, sizes)])

        return textures.SurfaceTextures(
            images=list(reader.images),
            uv_maps=[column(1, i, (3, 2)) for i in range(len(reader.uv_names))],
            attributes=[column(2, i, (3, 4)) for i in range(len(reader.attribute_names))],
            materials=list(self.materials),
            triangle_material=np.concatenate([s[0] for s in self.surfaces]),
            transparent_max_bounces=transparent_max_bounces)

    def scene_arrays(self, world_radiance, warnings, environment=None, surface=None):
        if self.parts:
            vertices, triangles, triangle_object, albedo, emission, two_sided, triangle_uv = \
                (np.concatenate(column) for column in zip(*self.parts))
        else:
            vertices = np.zeros((0, 3))
            triangles = np.zeros((0, 3), dtype=np.int64)
            triangle_object = np.zeros(0, dtype=np.int32)
            albedo = emission = np.zeros((0, 3))
            two_sided = np.zeros(0, dtype=bool)
            triangle_uv = np.zeros((0, 3, 2), dtype=np.float32)
        corner_normals = np.concatenate(self.normals) if self.normals else None
        if corner_normals is not None and not np.any(np.isfinite(corner_normals)):
            corner_normals = None
        if surface is not None:
            # Textured triangles: their mean albedo (the value at a point is ``surface``'s) and
            # the mean of a textured emission (the engine's emitters are uniform per triangle).
            albedo, emission = albedo.copy(), emission.copy()
            for which, target in (("albedo", albedo), ("emission", emission)):
                tris = np.flatnonzero(surface._flags[which][surface.triangle_material])
                if len(tris):
                    target[tris] = surface.triangle_means(which, tris, albedo)
        materials = MaterialTable.from_lobes(self.lobes, self.lobe_names) if self.lobes else None
        return CapturedScene(
            vertices=vertices,
            triangles=triangles,
            triangle_object=triangle_object,
            triangle_albedo=albedo,
            triangle_emission=emission,
            object_names=self.names,
            object_carries_states=np.array(self.carries, dtype=bool),
            world_radiance=world_radiance,
            environment=environment,
            triangle_emission_two_sided=two_sided,
            triangle_uv=triangle_uv,
            corner_normals=corner_normals,
            triangle_material=np.concatenate(self.lobe_of) if materials is not None else None,
            materials=materials,
            object_has_uv=np.array(self.has_uv, dtype=bool),
            warnings=warnings,
            object_uids=np.array(self.uids, dtype=np.int64),
            object_fingerprints=list(self.fingerprints),
            lamps=_lamps(self.lamps),
            surface=surface,
        )


def _add_light(builder, name, inst, warnings, skipped_lights):
    """A POINT, SPOT, SUN or AREA light of the scene as a lamp (:class:`~lmdp_addon.lamps.Lamps`);
    lights the bake cannot use are named in ``skipped_lights`` or warned about."""
    obj = inst.object
    light = obj.data
    if light.type not in ('AREA', 'POINT', 'SPOT', 'SUN'):
        skipped_lights.append(f"'{name}' ({light.type.lower()})")
        return
    if light.type == 'AREA' and light.original.cycles.is_portal:
        warnings.append(f"Light '{name}' is a portal: ignored")
        return
    if not getattr(obj.original, "visible_diffuse", True):
        warnings.append(f"Light '{name}' is invisible to diffuse rays (Object > Visibility): it lights "
                        "nothing the bake sees, and is left out")
        return
    _unsupported_light_features(name, obj.original, light, warnings)   # the user's settings
    record = _lamp_record(name, inst.matrix_world, light, warnings)
    numbers = [np.asarray(v, dtype=np.float64) for k, v in record.items() if k not in ("name", "kind")]
    if not all(np.all(np.isfinite(v)) for v in numbers):
        warnings.append(f"Light '{name}' has a non-finite transform, size or power (Inf or NaN): it is "
                        "left out; fix its transform or settings")
        return
    size = np.linalg.norm(record["extent_u"]) * np.linalg.norm(record["extent_v"]) if light.type == 'AREA' else 1.0
    if np.any(record["strength"] > 0) and size > 0:   # a light of power or size 0 lights nothing
        builder.lamps.append(record)


def _unsupported_light_features(name, obj, light, warnings):
    """One warning per light feature that changes a Cycles bake and is not modelled."""
    linking = getattr(obj, "light_linking", None)
    if linking is not None and (linking.receiver_collection is not None or linking.blocker_collection is not None):
        warnings.append(f"Light '{name}': light linking is not modelled; it lights and is shadowed by "
                        "every object")
    if getattr(obj, "lightgroup", ""):
        warnings.append(f"Light '{name}': light group '{obj.lightgroup}' is not modelled; the bake holds "
                        "every light")
    if not getattr(obj, "visible_glossy", True):
        warnings.append(f"Light '{name}': Visibility > Glossy off is not modelled; glossy surfaces reflect "
                        "it in the bake")
    bounces = light.original.cycles.max_bounces   # add-on properties: read the user's own
    if bounces < 1024:
        warnings.append(f"Light '{name}': its Max Bounces ({bounces}) is not modelled; it lights every "
                        "bounce of the bake")


def _shadow_flag_warning(name, obj, warnings):
    """A warning for a mesh whose Object > Visibility > Shadow is off: in Cycles it casts no
    shadows, here it does."""
    if not getattr(obj.original, "visible_shadow", True):
        warnings.append(f"Object '{name}': Visibility > Ray Visibility > Shadow off is not modelled; "
                        "it casts shadows in the bake")


def _add_mesh(builder, name, inst, fingerprint, reader, warnings, uv_choice=("", None),
              colour_bakes=None, lobe_reader=None):
    """The evaluated mesh of ``inst`` in world space, with its materials and lightmap UV map
    (``uv_choice``: (``scene.lmdp.lightmap_uv_map``, {object name: UV map} that overrides it));
    returns False when it has no faces. ``fingerprint``: the object's :func:`object_fingerprint`
    when it carries states, else None. Objects in Edit Mode are read from their edit mesh
    (``to_mesh``): the evaluated mesh of an object in Edit Mode holds no faces of its own.
    ``lobe_reader``: the :class:`_MaterialReader` that reads the materials' microfacet lobes
    (``bsdf_params.material_lobes``)."""
    carries_states = fingerprint is not None
    colour_bakes = colour_bakes or {}
    lobe_reader = lobe_reader if lobe_reader is not None else _MaterialReader(warnings)
    obj = inst.object
    original = obj.original
    editing = original.type == 'MESH' and original.data.is_editmode
    own_mesh = obj.type != 'MESH' or editing
    mesh = obj.to_mesh() if own_mesh else obj.data
    try:
        if mesh is None or len(mesh.polygons) == 0:
            return False
        matrix = inst.matrix_world
        world, tris, loops, poly = _mesh_arrays(mesh, matrix)
        if len(tris) == 0:
            return False
        if np.linalg.det(np.asarray(matrix, dtype=np.float64)[:3, :3]) < 0:
            # Mirrored objects: Cycles keeps their normals as displayed, so flip the winding.
            tris = tris[:, [0, 2, 1]]
            loops = loops[:, [0, 2, 1]]
        uv = _render_uv(mesh, loops, (uv_choice[1] or {}).get(name) or chosen_uv_name(mesh, uv_choice[0]))
        corner_normals = _corner_normals(mesh, matrix, loops)
        if uv is None and carries_states:
            warnings.append(f"Object '{name}' has no UV map")
        material_index = np.empty(len(mesh.polygons), dtype=np.int32)
        mesh.polygons.foreach_get("material_index", material_index)
        slots = slot_materials(obj)          # through the add-on's PREVIEW hook-up
        slots = slots or [None]
        per_slot = [reader.material(m) for m in slots]
        slot_of_tri = np.clip(material_index[poly], 0, len(per_slot) - 1)
        albedo_table = np.array([a if isinstance(a, np.ndarray) else np.zeros(3) for a, _, _ in per_slot])
        emission_table = np.array([e if isinstance(e, np.ndarray) else np.zeros(3) for _, e, _ in per_slot])
        surface = _mesh_surface(builder, reader, name, mesh, loops, tris_vertices(mesh, poly, loops),
                                slots, per_slot, slot_of_tri, fallback=colour_bakes.get(original.session_uid))
        glossy = np.array([builder.lobe_index(m.name_full if m is not None else None,
                                              m.name if m is not None else "", material_lobes(lobe_reader, m))
                           for m in slots] or [-1], dtype=np.int32)
        builder.add(name, carries_states, world, tris, albedo_table[slot_of_tri],
                    emission_table[slot_of_tri], np.ones(len(tris), dtype=bool), uv,
                    -1 if inst.is_instance else original.session_uid, None if inst.is_instance else fingerprint,
                    corner_normals=corner_normals, surface=surface, lobes=glossy[slot_of_tri])
        return True
    finally:
        if own_mesh:
            obj.to_mesh_clear()


def tris_vertices(mesh, poly, loops):
    """(T, 3) vertex index of each triangle corner ``loops`` (for point-domain attributes)."""
    vertex_of_loop = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", vertex_of_loop)
    return vertex_of_loop[loops]


def _colour_bakes(context, reader, warnings):
    """``{session_uid: (table, material names)}``: Cycles' own DIFFUSE COLOR bake
    (:data:`.shading.COLOUR_BAKES`) of every visible mesh object whose materials hold nodes LMDP
    cannot evaluate, and the materials (``name_full``) whose albedo it stands for. Objects that
    cannot be baked (no UV map, not in Object Mode, linked) keep the socket values, with the
    reader's warnings."""
    out = {}
    view_layer = context.view_layer
    for obj in list(view_layer.objects):
        if obj is None or obj.type != 'MESH' or _is_hidden(obj, view_layer):   # None: just removed
            continue
        materials = [m for m in slot_materials(obj) if m is not None]
        for m in materials:
            reader.material(m)
        need = {m.name_full for m in materials if reader.unsupported.get(m.name_full)}
        editable = (obj.library is None and obj.data.library is None
                    and all(m.library is None and m.override_library is None for m in materials))
        if not need or not editable or obj.mode != 'OBJECT' or not obj.data.uv_layers or context.mode != 'OBJECT':
            continue
        uv = next((l.name for l in obj.data.uv_layers if l.active_render), obj.data.uv_layers[0].name)
        key = (obj.session_uid, object_fingerprint(obj), uv,
               tuple(shading.tree_digest(m.node_tree).hexdigest() if m.node_tree else "" for m in materials))
        # Under the PREVIEW hook-up Cycles would bake the preview's colour: only a kept bake serves.
        previewed = slot_materials(obj) != [slot.material for slot in obj.material_slots]
        try:
            table = shading.COLOUR_BAKES.table(context, obj, key, bake=not previewed)
        except (RuntimeError, ReferenceError) as exc:
            warnings.append(f"Object '{obj.name}': Cycles' diffuse colour bake failed ({exc}); its "
                            "materials' unsupported nodes read as their socket values")
            continue
        if table is None:
            warnings.append(f"Object '{obj.name}' shows LMDP's lightmap preview, so Cycles cannot bake the "
                            "colour of its materials' unsupported nodes (they read as their socket values): "
                            "remove the hook-up (LMDP > Remove Bake Hook-up) and run again")
            continue
        out[obj.session_uid] = (table, need)
    return out


def _mesh_surface(builder, reader, name, mesh, loops, verts, slots, per_slot, slot_of_tri, fallback=None):
    """The ``surface`` argument of :meth:`_SceneBuilder.add` for a mesh whose material slots
    ``slots`` read as ``per_slot`` (:meth:`.shading.ShadingReader.material`), or None.
    ``fallback``: ``(table, material names)`` of the object's Cycles colour bake
    (:func:`_colour_bakes`): those materials take their albedo from it."""
    index = np.full(len(per_slot), -1, np.int32)
    uv_wanted, attr_wanted = set(), set()
    for s, (mat, (albedo, emission, alpha)) in enumerate(zip(slots, per_slot)):
        key = mat.name_full if mat is not None else ""
        if fallback is not None and key in fallback[1]:
            nodes = ", ".join(sorted({f"'{n}'" for n, _ in reader.unsupported[key]}))
            message = (f"Material '{mat.name}': {nodes} cannot be evaluated by LMDP; on '{name}' its diffuse "
                       f"colour is Cycles' own DIFFUSE COLOR bake ({shading.COLOUR_BAKE_RESOLUTION}² texels on "
                       "the render UV map, interpolated between them)")
            if message not in reader.warnings:
                reader.warnings.append(message)
            baked = textures.ImageTexture(reader.add_table(fallback[0]), reader._uv_index(None), "LINEAR", "EXTEND")
            albedo = baked if alpha is None else textures.quotient(baked, alpha)   # the bake holds alpha x albedo
            key = (key, name)
        else:
            reader.flush(mat)
        exprs = [x for x in (albedo, emission, alpha) if x is not None and not isinstance(x, np.ndarray)]
        if not exprs:
            continue
        index[s] = builder.material_index(key, textures.MaterialShading(
            albedo=None if isinstance(albedo, np.ndarray) else albedo, alpha=alpha,
            emission=None if isinstance(emission, np.ndarray) else emission,
            tint=reader.tints.get(mat.name_full) if mat is not None else None))
        for x in exprs:
            found = textures.references(x)
            uv_wanted |= {(i, mat) for i in found["uv"]}
            attr_wanted |= {(i, mat) for i in found["attribute"]}
    if np.all(index < 0):
        return None
    uvs, attrs = {}, {}
    for i, mat in sorted(uv_wanted, key=lambda x: x[0]):
        if i not in uvs:
            uvs[i] = shading.uv_corners(mesh, loops, reader.uv_names[i])
        if uvs[i] is None:
            reader.warnings.append(f"Object '{name}' has no UV map '{reader.uv_names[i] or 'render'}' that "
                                   f"material '{mat.name if mat else ''}' reads: its textures read UV (0, 0)")
    for i, mat in sorted(attr_wanted, key=lambda x: x[0]):
        if i not in attrs:
            attrs[i] = shading.attribute_corners(mesh, loops, verts, reader.attribute_names[i])
        if attrs[i] is None:
            reader.warnings.append(f"Object '{name}' has no colour attribute "
                                   f"'{reader.attribute_names[i] or 'render'}' that material "
                                   f"'{mat.name if mat else ''}' reads: it reads black")
    return (index[slot_of_tri], {i: a for i, a in uvs.items() if a is not None},
            {i: a for i, a in attrs.items() if a is not None})


def extract_scene(context, selected_objects, depsgraph=None, uv_maps=None):
    """:class:`CapturedScene` of every visible mesh and light in ``context``'s view layer.

    ``selected_objects``: the objects whose meshes carry LMDP states (originals or evaluated,
    matched by object, not by name); every other visible mesh only occludes and reflects. The
    meshes that :func:`..common.selected_meshes` left out (its ``skipped``) and selected
    objects that turn out to have no faces are named in the warnings. ``depsgraph`` defaults to
    ``context.evaluated_depsgraph_get()``. Hidden objects (eye, monitor or camera icon off, or
    not visible in the view layer) are ignored. Object names of instances are
    "<instancer>/<object>#<n>". The UV map of a mesh is the lightmap's (``uv_maps``: {object
    name: UV map name}, else :func:`.lightmap_uvs.chosen_uv_name` of ``scene.lmdp.lightmap_uv_map``).
    """
    selected = {o.session_uid: o for o in (getattr(o, "original", o) for o in selected_objects or ())}
    # Before the depsgraph is evaluated: fingerprints update objects in Edit Mode from their edit mesh.
    fingerprints = {uid: object_fingerprint(o) if o.type == 'MESH' else "" for uid, o in selected.items()}
    warnings = skipped_mesh_messages(selected_objects)
    reader = shading.ShadingReader(warnings)
    # Cycles' colour bakes change the depsgraph: they run before it is evaluated (not at all
    # when the caller hands one in).
    colour_bakes = _colour_bakes(context, reader, warnings) if depsgraph is None else {}
    if depsgraph is None:
        depsgraph = context.evaluated_depsgraph_get()
    view_layer = depsgraph.view_layer
    world_reader = _MaterialReader(warnings)
    builder = _SceneBuilder()
    instance_count = {}
    skipped_lights = []
    uv_choice = (getattr(getattr(depsgraph.scene, "lmdp", None), "lightmap_uv_map", ""), uv_maps)
    captured = set()
    for inst in depsgraph.object_instances:
        obj = inst.object
        top = (inst.parent if inst.is_instance and inst.parent is not None else obj).original
        if _is_hidden(top, view_layer):
            continue
        if inst.is_instance:
            key = (top.name, obj.original.name)
            instance_count[key] = instance_count.get(key, -1) + 1
            name = f"{top.name}/{obj.original.name}#{instance_count[key]}"
        else:
            name = obj.original.name
        if obj.type == 'LIGHT':
            _add_light(builder, name, inst, warnings, skipped_lights)
        elif obj.type in GEOMETRY_TYPES:
            _shadow_flag_warning(name, obj, warnings)
            if _add_mesh(builder, name, inst, fingerprints.get(top.session_uid), reader, warnings, uv_choice,
                         colour_bakes, world_reader):
                captured.add(top.session_uid)
            if not inst.is_instance and mode_holding_mesh(obj.original) == "Sculpt Mode with Dynamic Topology":
                warnings.append(f"Object '{name}' is in Sculpt Mode with Dynamic Topology, whose strokes "
                                "reach its mesh only when you leave it: LMDP captured the mesh as it was "
                                "before; switch to Object Mode to capture them")
    empty = sorted(obj.name for uid, obj in selected.items()
                   if uid not in captured and obj.type in GEOMETRY_TYPES and not _is_hidden(obj, view_layer))
    if empty:
        warnings.append(f"The selected {', '.join(repr(n) for n in empty)} produced no faces (after "
                        "modifiers): they carry no LMDP states")
    if skipped_lights:
        warnings.append("Light types LMDP does not model were skipped: " + ", ".join(skipped_lights))
    cycles = getattr(depsgraph.scene, "cycles", None)
    surface = builder.surface(reader, getattr(cycles, "transparent_max_bounces", 8))
    world_radiance, environment = world_reader.world(depsgraph.scene.world)
    arrays = builder.scene_arrays(world_radiance, warnings, environment, surface)
    arrays.warnings.extend(cycles_glossy_settings(depsgraph.scene, arrays))
    return arrays
