"""Blender scene -> :class:`~lmdp_addon.scene_arrays.SceneArrays`, the engine's only view of bpy data.

:func:`extract_scene` reads every visible mesh of the view layer from the evaluated depsgraph
(modifiers and geometry nodes applied, instances included, world space), its triangles, the
active render UV map, and one diffuse albedo / emitted radiance per triangle from the material of
its polygon, plus Blender area lights (as one-sided emitting quads) and the world background.
Conventions follow Cycles as measured in docs/cycles_conventions.md:

* Emission shader: radiance = Color x Strength, two-sided. Principled BSDF: Base Color is the
  albedo, Emission Color x Emission Strength the radiance.
* A material whose node tree has no connected Surface renders black: albedo 0. A polygon without
  material uses Cycles' default surface, a Diffuse BSDF of 0.8 grey.
* AREA light of power P (W) x 2^exposure, colour c (x its temperature colour), size a x b and
  object scale (sx, sy): radiance L = P c / (π a sx b sy) (``normalize`` on, the default;
  P c / π when off), emitted towards the light's -Z only. Disk / ellipse: a rectangle of the
  same area, with a warning. Cycles' lights do not occlude; the quad here does.
* World: Background Color x Strength of the shader connected to the World Output.
* Objects in Edit Mode are captured as the user sees them (their edit mesh, modifiers applied).

The result is a :class:`CapturedScene`: a ``SceneArrays`` that also knows which Blender object
each of its objects is (``session_uid``, which survives renames) and a fingerprint of the mesh
and transform of each object that carries states, so that results are never matched to
objects by name (:func:`..session.captured_index`, :func:`..session.changed_since_capture`).

Whatever is approximated (textures by their mean, Mix / Add shaders by weighted sums, non-diffuse
BSDFs as diffuse, unsupported lights skipped) is reported in ``SceneArrays.warnings`` with the
object, material and node names.
"""
import hashlib
from dataclasses import dataclass

import bpy
import numpy as np

from ...lmdp_addon.bsdf import MaterialTable
from ...lmdp_addon.scene_arrays import SceneArrays
from ..common import mode_holding_mesh, skipped_mesh_messages
from .bsdf_params import cycles_glossy_settings, material_lobes
from .materials import NODE_MULTIPLY, slot_materials

#: Cycles' default surface (a polygon without material): Diffuse BSDF, colour 0.8.
DEFAULT_ALBEDO = (0.8, 0.8, 0.8)
#: Object types whose evaluated geometry is a mesh.
GEOMETRY_TYPES = {'MESH', 'CURVE', 'CURVES', 'SURFACE', 'META', 'FONT'}

_BLACK = np.zeros(3)
#: Before Blender 5.0 materials and worlds could switch their node trees off (``use_nodes``).
_NODES_OPTIONAL = bpy.app.version < (5, 0, 0)


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


def _srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


class _MaterialReader:
    """Diffuse albedo and emitted radiance of node materials, with warnings (cached per material)."""

    def __init__(self, warnings):
        self.warnings = warnings
        self._cache = {}
        self._image_means = {}

    def warn(self, message):
        if message not in self.warnings:
            self.warnings.append(message)

    # -- sockets ------------------------------------------------------------------------------
    @staticmethod
    def _source(socket):
        """(node, output socket) feeding ``socket``, through reroutes and muted nodes; or None."""
        links = [link for link in socket.links if not link.is_muted and link.is_valid]
        while links:
            link = links[0]
            node, out = link.from_node, link.from_socket
            if node.type == 'REROUTE':
                links = [l for l in node.inputs[0].links if not l.is_muted and l.is_valid]
                continue
            if node.mute:
                through = [il.from_socket for il in node.internal_links if il.to_socket == out]
                links = [l for s in through for l in s.links if not l.is_muted and l.is_valid]
                continue
            return node, out
        return None

    def image_mean(self, image, equirect=False):
        """Mean linear RGB of ``image`` (rows weighted by solid angle for equirect maps)."""
        key = (image.name, equirect)
        if key not in self._image_means:
            w, h = image.size
            if not image.has_data and w * h == 0:
                self._image_means[key] = None
            else:
                px = np.empty(w * h * image.channels, dtype=np.float32)
                image.pixels.foreach_get(px)
                px = px.reshape(h, w, image.channels)[..., :3].astype(np.float64)
                if px.shape[-1] < 3:
                    px = np.repeat(px[..., :1], 3, axis=-1)
                if not image.is_float and image.colorspace_settings.name == 'sRGB':
                    px = _srgb_to_linear(px)
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

    # -- shaders ------------------------------------------------------------------------------
    def shader(self, socket, owner, depth=0):
        """(albedo (3,), emission (3,)) of the shader feeding ``socket``."""
        source = self._source(socket)
        if source is None:
            return _BLACK, _BLACK
        node, _ = source
        t = node.type
        if depth > 32:
            self.warn(f"{owner}: shader graph too deep at '{node.name}'; treated as black")
            return _BLACK, _BLACK
        if t == 'BSDF_DIFFUSE':
            return self.colour(node, "Color", owner), _BLACK
        if t == 'BSDF_PRINCIPLED':
            base = self.colour(node, "Base Color", owner)
            metallic = self.value(node, "Metallic", owner)
            transmission = self.value(node, "Transmission Weight", owner)
            if transmission > 0:   # metallic and specular: bsdf_params' microfacet lobes
                self.warn(f"{owner}: Principled BSDF '{node.name}' has Transmission {transmission:g}; "
                          "LMDP keeps its diffuse, specular and metallic parts (no transmission)")
            albedo = base * (1.0 - metallic) * (1.0 - transmission)
            strength = self.value(node, "Emission Strength", owner)
            emission = self.colour(node, "Emission Color", owner) * strength if strength else _BLACK
            return albedo, emission
        if t in ('EMISSION', 'BACKGROUND'):
            return _BLACK, self.colour(node, "Color", owner) * self.value(node, "Strength", owner)
        if t == 'MIX_SHADER':
            fac = min(max(self.value(node, "Fac", owner), 0.0), 1.0)
            a1, e1 = self.shader(node.inputs[1], owner, depth + 1)
            a2, e2 = self.shader(node.inputs[2], owner, depth + 1)
            self.warn(f"{owner}: Mix Shader '{node.name}' is approximated by the weighted average "
                      f"of its inputs (factor {fac:g})")
            return (1 - fac) * a1 + fac * a2, (1 - fac) * e1 + fac * e2
        if t == 'ADD_SHADER':
            a1, e1 = self.shader(node.inputs[0], owner, depth + 1)
            a2, e2 = self.shader(node.inputs[1], owner, depth + 1)
            albedo = a1 + a2
            self.warn(f"{owner}: Add Shader '{node.name}' is approximated by the sum of its inputs"
                      + (" (albedo clipped to 1)" if np.any(albedo > 1) else ""))
            return np.minimum(albedo, 1.0), e1 + e2
        if t == 'BSDF_GLOSSY':   # no diffuse part: its reflection is a microfacet lobe (bsdf_params)
            return _BLACK, _BLACK
        if t in ('BSDF_TRANSPARENT', 'HOLDOUT', 'BSDF_REFRACTION'):
            self.warn(f"{owner}: '{node.name}' ({node.bl_label}) cannot be modelled; the surface "
                      "is treated as black (absorbing)")
            return _BLACK, _BLACK
        if "Color" in node.inputs or "Base Color" in node.inputs:
            name = "Base Color" if "Base Color" in node.inputs else "Color"
            self.warn(f"{owner}: '{node.name}' ({node.bl_label}) is treated as a diffuse surface "
                      f"with its {name} as albedo")
            return self.colour(node, name, owner), _BLACK
        self.warn(f"{owner}: shader node '{node.name}' ({node.bl_label}) is not supported; using "
                  f"Cycles' default grey {DEFAULT_ALBEDO[0]:g}")
        return np.array(DEFAULT_ALBEDO), _BLACK

    def material(self, mat):
        """(albedo, emission) of a material (None: Cycles' default surface)."""
        if mat is None:
            return np.array(DEFAULT_ALBEDO), _BLACK
        key = mat.name_full if hasattr(mat, "name_full") else mat.name
        if key not in self._cache:
            owner = f"Material '{mat.name}'"
            tree = mat.node_tree
            output = tree.get_output_node('CYCLES') if tree is not None else None
            if tree is None or (_NODES_OPTIONAL and not mat.use_nodes):
                # Blender < 5.0 without nodes: Cycles shades the viewport colour as a Diffuse BSDF.
                albedo, emission = np.array(mat.diffuse_color[:3], dtype=np.float64), _BLACK
            elif output is None or self._source(output.inputs["Surface"]) is None:
                self.warn(f"{owner} has no shader connected to a Material Output: Cycles renders "
                          "it black, so LMDP uses albedo 0 (no emission)")
                albedo, emission = _BLACK, _BLACK
            else:
                albedo, emission = self.shader(output.inputs["Surface"], owner)
            albedo = np.clip(np.asarray(albedo, dtype=np.float64), 0.0, 1.0)
            emission = np.maximum(np.asarray(emission, dtype=np.float64), 0.0)
            self._cache[key] = (albedo, emission)
        return self._cache[key]

    def world(self, world):
        """(3,) radiance of a uniform world seen by escaping rays."""
        if world is None:
            return _BLACK
        owner = f"World '{world.name}'"
        tree = world.node_tree
        if tree is None or (_NODES_OPTIONAL and not world.use_nodes):
            return np.array(world.color[:3], dtype=np.float64)
        output = tree.get_output_node('CYCLES')
        if output is None:
            return _BLACK
        albedo, emission = self.shader(output.inputs["Surface"], owner)
        return np.maximum(np.asarray(emission, dtype=np.float64), 0.0)


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


def _render_uv(mesh, loops):
    """(T, 3, 2) UVs of the active render UV map, or None when the mesh has no UV map."""
    layer = next((l for l in mesh.uv_layers if l.active_render), None)
    if layer is None:
        layer = mesh.uv_layers.active
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


def _area_light_quad(name, matrix, light, warnings):
    """Corners (4, 3) facing the light's -Z and radiance (3,) of an AREA light, as Cycles sees it."""
    m = np.asarray(matrix, dtype=np.float64)
    axis_u, axis_v, centre = m[:3, 0], m[:3, 1], m[:3, 3]
    size_u = light.size
    size_v = light.size_y if light.shape in ('RECTANGLE', 'ELLIPSE') else light.size
    area = np.linalg.norm(axis_u) * size_u * np.linalg.norm(axis_v) * size_v
    half_u, half_v = size_u / 2.0, size_v / 2.0
    if light.shape in ('DISK', 'ELLIPSE'):
        area *= np.pi / 4.0
        half_u *= np.sqrt(np.pi / 4.0)
        half_v *= np.sqrt(np.pi / 4.0)
        warnings.append(f"Light '{name}': {light.shape.lower()} area light modelled as a "
                        "rectangle of the same area")
    colour = np.array(light.color[:3], dtype=np.float64)
    if getattr(light, "use_temperature", False):
        colour = colour * np.array(light.temperature_color[:3], dtype=np.float64)
    strength = colour * light.energy * 2.0 ** getattr(light, "exposure", 0.0)
    if getattr(light, "normalize", True):
        radiance = strength / (np.pi * area) if area > 0 else np.zeros(3)
    else:
        radiance = strength / np.pi
    if getattr(light, "spread", np.pi) < np.pi - 1e-6:
        warnings.append(f"Light '{name}': spread {np.degrees(light.spread):.0f}° is not "
                        "modelled; the light emits like a diffuse (180°) area light")
    if getattr(light, "use_nodes", False):
        warnings.append(f"Light '{name}': its shader nodes are ignored (emission colour x "
                        "power only)")
    du, dv = axis_u * half_u, axis_v * half_v
    # (p0, p1, p2, p3) with normal (p1 - p0) x (p3 - p0) = v x u = -Z: facing the light's -Z.
    corners = np.array([centre - du - dv, centre - du + dv, centre + du + dv, centre + du - dv])
    return corners, radiance


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
        self.materials = []  # (T,) index into self.lobes per object (-1: Lambertian)
        self.lobes, self.lobe_names, self._lobe_index = [], [], {}
        self.offset = 0

    def material_index(self, key, name, lobes):
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
            uid=-1, fingerprint=None, corner_normals=None, material=None):
        """One object: world vertices (V, 3), triangles (T, 3) into them, per-triangle albedo /
        emission (T, 3) and two-sidedness (T,), UVs (T, 3, 2) or None; the ``session_uid`` and
        :func:`object_fingerprint` of its Blender object (see :class:`CapturedScene`); its
        corner normals (T, 3, 3) world space, or None (flat: the face normals); ``material``
        (T,) its triangles' :meth:`material_index` (None: Lambertian)."""
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
        self.materials.append(np.full(len(tris), -1, np.int32) if material is None
                              else np.asarray(material, np.int32))
        self.offset += len(world)

    def scene_arrays(self, world_radiance, warnings):
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
            triangle_emission_two_sided=two_sided,
            triangle_uv=triangle_uv,
            corner_normals=corner_normals,
            triangle_material=np.concatenate(self.materials) if materials is not None else None,
            materials=materials,
            object_has_uv=np.array(self.has_uv, dtype=bool),
            warnings=warnings,
            object_uids=np.array(self.uids, dtype=np.int64),
            object_fingerprints=list(self.fingerprints),
        )


def _add_light(builder, name, inst, warnings, skipped_lights):
    """An AREA light as a one-sided emitting quad; other lights are listed in ``skipped_lights``."""
    light = inst.object.data
    if light.type != 'AREA':
        skipped_lights.append(f"'{name}' ({light.type.lower()})")
        return
    if light.cycles.is_portal:
        warnings.append(f"Light '{name}' is a portal: ignored")
        return
    corners, radiance = _area_light_quad(name, inst.matrix_world, light, warnings)
    if not np.any(radiance > 0):
        return
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    builder.add(name, False, corners, tris, np.zeros((2, 3)), np.tile(radiance, (2, 1)),
                np.zeros(2, dtype=bool), None)


def _add_mesh(builder, name, inst, fingerprint, reader, warnings):
    """The evaluated mesh of ``inst`` in world space, with its materials and render UV map;
    returns False when it has no faces. ``fingerprint``: the object's :func:`object_fingerprint`
    when it carries states, else None. Objects in Edit Mode are read from their edit mesh
    (``to_mesh``): the evaluated mesh of an object in Edit Mode holds no faces of its own."""
    carries_states = fingerprint is not None
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
        uv = _render_uv(mesh, loops)
        corner_normals = _corner_normals(mesh, matrix, loops)
        if uv is None and carries_states:
            warnings.append(f"Object '{name}' has no UV map")
        material_index = np.empty(len(mesh.polygons), dtype=np.int32)
        mesh.polygons.foreach_get("material_index", material_index)
        slots = slot_materials(obj)          # through the add-on's PREVIEW hook-up
        per_slot = [reader.material(m) for m in slots] or [reader.material(None)]
        slot_of_tri = np.clip(material_index[poly], 0, len(per_slot) - 1)
        albedo_table = np.array([a for a, _ in per_slot])
        emission_table = np.array([e for _, e in per_slot])
        glossy = np.array([builder.material_index(m.name_full if m is not None else None,
                                                  m.name if m is not None else "", material_lobes(reader, m))
                           for m in slots] or [-1], dtype=np.int32)
        builder.add(name, carries_states, world, tris, albedo_table[slot_of_tri],
                    emission_table[slot_of_tri], np.ones(len(tris), dtype=bool), uv,
                    -1 if inst.is_instance else original.session_uid, None if inst.is_instance else fingerprint,
                    corner_normals=corner_normals, material=glossy[slot_of_tri])
        return True
    finally:
        if own_mesh:
            obj.to_mesh_clear()


def extract_scene(context, selected_objects, depsgraph=None):
    """:class:`CapturedScene` of every visible mesh and area light in ``context``'s view layer.

    ``selected_objects``: the objects whose meshes carry LMDP states (originals or evaluated,
    matched by object, not by name); every other visible mesh only occludes and reflects. The
    meshes that :func:`..common.selected_meshes` left out (its ``skipped``) and selected
    objects that turn out to have no faces are named in the warnings. ``depsgraph`` defaults to
    ``context.evaluated_depsgraph_get()``. Hidden objects (eye, monitor or camera icon off, or
    not visible in the view layer) are ignored. Object names of instances are
    "<instancer>/<object>#<n>".
    """
    selected = {o.session_uid: o for o in (getattr(o, "original", o) for o in selected_objects or ())}
    # Before the depsgraph is evaluated: fingerprints update objects in Edit Mode from their edit mesh.
    fingerprints = {uid: object_fingerprint(o) if o.type == 'MESH' else "" for uid, o in selected.items()}
    if depsgraph is None:
        depsgraph = context.evaluated_depsgraph_get()
    view_layer = depsgraph.view_layer
    warnings = skipped_mesh_messages(selected_objects)
    reader = _MaterialReader(warnings)
    builder = _SceneBuilder()
    instance_count = {}
    skipped_lights = []
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
            if _add_mesh(builder, name, inst, fingerprints.get(top.session_uid), reader, warnings):
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
        warnings.append("Only area lights are modelled; skipped " + ", ".join(skipped_lights)
                        + ": use an area light or an emissive mesh instead")
    arrays = builder.scene_arrays(reader.world(depsgraph.scene.world), warnings)
    arrays.warnings.extend(cycles_glossy_settings(depsgraph.scene, arrays))
    return arrays
