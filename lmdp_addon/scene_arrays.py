"""Scene arrays: the whole scene as flat triangle arrays, the engine's only view of Blender data.

The Blender layer (``operators/adapters/extract.py``) fills a :class:`SceneArrays` from the evaluated
depsgraph; tests and benchmarks build them directly (see :mod:`lmdp_addon.demo_geometry`).
"""
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from .errors import SceneError
from .lamps import Lamps

#: Guards the nesting count of ``SceneArrays.held`` (the build's threads share a scene).
_HOLD_LOCK = threading.Lock()

#: Largest vertex coordinate (metres, absolute) a usable triangle may have. The ray tracer
#: works in float32 and embree's ray-triangle test forms products of three coordinates, which
#: overflow float32 beyond about 7e12; only corrupt or runaway geometry gets near this.
MAX_COORDINATE = 1e12

#: Rec.709 / sRGB-linear luminance weights.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb):
    """Rec.709 luminance of ``rgb (..., 3)`` linear values."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE


@dataclass
class SceneArrays:
    """All geometry of a scene in world space.

    vertices            (V, 3) float64, world metres
    triangles           (T, 3) int64 indices into ``vertices``
    triangle_object     (T,)   int32 index into ``object_names``
    triangle_albedo     (T, 3) float32 diffuse reflectance (linear RGB, 0..1)
    triangle_emission   (T, 3) float32 emitted radiance, W / (sr m^2) per channel
    triangle_emission_two_sided (T,) bool: mesh emission is two-sided (Cycles), area lights are not
    triangle_uv         (T, 3, 2) float32 UV of each corner (active render UV map), or None
    object_names        list of O object names
    object_carries_states (O,) bool: selected meshes carry LMDP states; others only occlude
    object_has_uv       (O,) bool
    corner_normals      (T, 3, 3) float32 unit shading normal of each corner (world space, as
                        Cycles sees them: smooth, flat, custom split normals, "Smooth by Angle"),
                        or None: every triangle is flat (its face normal). Corners that equal
                        the face normal (flat faces) are flat: :meth:`smooth_triangles`
    triangle_material   (T,) int32 index into ``materials`` of each triangle's microfacet lobes
                        (Principled specular / metallic, Glossy BSDF; -1: Lambertian), or None
    materials           :class:`~lmdp_addon.bsdf.MaterialTable` of those lobes, or None: every
                        surface is Lambertian (``triangle_albedo``)
    world_radiance      (3,) float32 radiance of a uniform world seen by escaping rays; with an
                        ``environment``, its mean radiance over the sphere
    environment         :class:`~lmdp_addon.world.EnvironmentMap` of a world that is not uniform
                        (an HDRI), or None: escaping rays see ``world_radiance``
    lamps               :class:`~lmdp_addon.lamps.Lamps`: point, spot, sun and area lights (default
                        none)
    surface             :class:`~lmdp_addon.textures.SurfaceTextures` of the textured and
                        transparent materials (colour and alpha at a point), or None: every
                        material is uniform and opaque. ``triangle_albedo`` is then each
                        triangle's mean albedo; :meth:`albedo_at` the value at a point
    warnings            messages for the user gathered during extraction, and one per object
                        with triangles that are left out (:meth:`usable_triangles`)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    triangle_object: np.ndarray
    triangle_albedo: np.ndarray
    triangle_emission: np.ndarray
    object_names: list
    object_carries_states: np.ndarray
    world_radiance: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    triangle_emission_two_sided: np.ndarray = None
    triangle_uv: np.ndarray = None
    object_has_uv: np.ndarray = None
    warnings: list = field(default_factory=list)
    corner_normals: np.ndarray = None
    environment: object = None
    lamps: Lamps = None
    surface: object = None
    triangle_material: np.ndarray = None
    materials: object = None
    _held: dict = field(default=None, init=False, repr=False, compare=False)
    _hold_depth: int = field(default=0, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        t = len(self.triangles)
        self.triangle_object = np.ascontiguousarray(self.triangle_object, dtype=np.int32).reshape(t)
        self.triangle_albedo = np.ascontiguousarray(self.triangle_albedo, dtype=np.float32).reshape(t, 3)
        self.triangle_emission = np.ascontiguousarray(self.triangle_emission, dtype=np.float32).reshape(t, 3)
        self.object_names = list(self.object_names)
        self.object_carries_states = np.asarray(self.object_carries_states, dtype=bool).reshape(len(self.object_names))
        self.world_radiance = np.asarray(self.world_radiance, dtype=np.float32).reshape(3)
        if self.triangle_emission_two_sided is None:
            self.triangle_emission_two_sided = np.ones(t, dtype=bool)
        self.triangle_emission_two_sided = np.asarray(self.triangle_emission_two_sided, dtype=bool).reshape(t)
        if self.triangle_uv is not None:
            self.triangle_uv = np.ascontiguousarray(self.triangle_uv, dtype=np.float32).reshape(t, 3, 2)
        if self.corner_normals is not None:
            self.corner_normals = np.ascontiguousarray(self.corner_normals, dtype=np.float32).reshape(t, 3, 3)
        if self.triangle_material is not None:
            self.triangle_material = np.ascontiguousarray(self.triangle_material, dtype=np.int32).reshape(t)
        if self.object_has_uv is None:
            self.object_has_uv = np.zeros(len(self.object_names), dtype=bool)
            if self.triangle_uv is not None:
                self.object_has_uv[np.unique(self.triangle_object)] = True
        self.object_has_uv = np.asarray(self.object_has_uv, dtype=bool).reshape(len(self.object_names))
        if t and (self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices)):
            raise SceneError("Scene arrays are inconsistent: a triangle indexes a missing vertex")
        if t and (self.triangle_object.min() < 0 or self.triangle_object.max() >= len(self.object_names)):
            raise SceneError("Scene arrays are inconsistent: a triangle names a missing object")
        if self.lamps is None:
            self.lamps = Lamps()
        self.warnings = list(self.warnings)
        for message in self._unusable_warnings():
            if message not in self.warnings:
                self.warnings.append(message)

    def _unusable_warnings(self):
        """One message per object with triangles that :meth:`usable_triangles` leaves out."""
        left_out = ~self.usable_triangles()
        if not left_out.any():
            return []
        counts = np.bincount(self.triangle_object[left_out], minlength=len(self.object_names))
        return [f"Object '{self.object_names[o]}': {counts[o]} triangle{'s' if counts[o] > 1 else ''} "
                f"with non-finite or huge vertex coordinates (Inf, NaN or beyond ±{MAX_COORDINATE:g} m) "
                f"left out of the scene (no states, shadows or light from {'it' if counts[o] == 1 else 'them'}): "
                "fix the mesh, e.g. delete the stray vertices"
                for o in np.flatnonzero(counts)]

    # -- derived geometry ---------------------------------------------------------------------
    @contextmanager
    def held(self):
        """Within this block the derived geometry (corners, normals and areas, emitter groups) is
        computed once and then reused: the build and the bake ask for it from several places,
        and each computation walks every triangle. The arrays must not change inside the block; outside it nothing is kept."""
        with _HOLD_LOCK:
            if self._hold_depth == 0:
                self._held = {}
            self._hold_depth += 1
        try:
            yield self
        finally:
            with _HOLD_LOCK:
                self._hold_depth -= 1
                if self._hold_depth == 0:
                    self._held = None

    def _derived(self, name, compute):
        held = self._held
        if held is None:
            return compute()
        if name not in held:
            value = compute()
            for array in value if isinstance(value, tuple) else (value,):
                array.flags.writeable = False   # shared by every caller in the block
            held[name] = value
        return held[name]

    @property
    def n_triangles(self):
        return len(self.triangles)

    def corners(self):
        """(T, 3, 3) float64 corner positions."""
        return self._derived("corners", lambda: self.vertices[self.triangles])

    def usable_triangles(self):
        """(T,) bool: triangles whose corners are finite and within ±:data:`MAX_COORDINATE`.
        The others are left out of everything (area 0: no states, no BVH, no emission, no scene
        bounds) and named in :attr:`warnings`."""
        return self._derived("usable", self._usable)

    def _usable(self):
        with np.errstate(invalid="ignore"):
            ok = np.all(np.abs(self.vertices) <= MAX_COORDINATE, axis=1)   # False for Inf, NaN
        return np.all(ok[self.triangles], axis=1) if len(self.triangles) else np.zeros(0, bool)

    def triangle_geometry(self):
        """Face normals (T, 3) (unit, zero for degenerate triangles) and areas (T,) in m^2.

        Triangles that are not :meth:`usable_triangles` get area 0 and a zero normal.
        """
        return self._derived("geometry", self._triangle_geometry)

    def _triangle_geometry(self):
        c = self.corners()
        with np.errstate(invalid="ignore", over="ignore"):     # the unusable triangles: Inf, NaN
            cross = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
            norm = np.linalg.norm(cross, axis=1)
        finite = np.isfinite(norm) & self.usable_triangles()
        area = np.where(finite, 0.5 * norm, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            normal = np.where((area > 0)[:, None], cross / np.where(norm > 0, norm, 1.0)[:, None], 0.0)
        return normal, area

    def smooth_triangles(self):
        """(T,) bool: triangles whose shading normal varies or differs from the face normal
        (:attr:`corner_normals` set, finite, and some corner more than ~0.08° off the face
        normal). The others shade with their face normal, exactly as without corner normals."""
        return self._derived("smooth", self._smooth_triangles)

    def _smooth_triangles(self):
        t = self.n_triangles
        if self.corner_normals is None or t == 0:
            return np.zeros(t, dtype=bool)
        face = self.triangle_geometry()[0]
        cn = self.corner_normals.astype(np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.isfinite(cn), axis=(1, 2)) & np.any(face != 0, axis=1)
            cos = np.einsum("tkj,tj->tk", cn, face)
        return ok & np.any(cos < 1.0 - 1e-6, axis=1)

    def glossy_triangles(self):
        """(T,) bool: triangles whose material has a microfacet lobe (``materials``)."""
        if self.triangle_material is None or self.materials is None:
            return np.zeros(self.n_triangles, dtype=bool)
        glossy = np.append(self.materials.glossy, False)        # index -1: Lambertian
        return glossy[np.where(self.triangle_material >= 0, self.triangle_material, -1)]

    def has_glossy(self):
        """True when some triangle has a microfacet lobe."""
        return bool(np.any(self.glossy_triangles()))

    def has_smooth_normals(self):
        """True when some triangle shades with interpolated corner normals."""
        return bool(np.any(self.smooth_triangles()))

    def shading_normals(self, tri, bu, bv, side=None):
        """(k, 3) float32 unit shading normals at barycentrics ``(bu, bv)`` (weights
        ``1 - bu - bv, bu, bv`` of corners 0, 1, 2, embree's convention) of triangles ``tri``:
        the interpolated, normalised corner normal on :meth:`smooth_triangles` (Cycles'
        ``triangle_smooth_normal``; the face normal where the interpolation vanishes), the face
        normal elsewhere. ``side (k,)`` bool: False flips the normal (the back side was hit;
        Cycles flips N with Ng there)."""
        tri = np.asarray(tri, dtype=np.int64)
        face = self.triangle_geometry()[0]
        out = face[tri].astype(np.float32)
        smooth = np.flatnonzero(self.smooth_triangles()[tri])
        if len(smooth):
            t = tri[smooth]
            u = np.asarray(bu, dtype=np.float64)[smooth]
            v = np.asarray(bv, dtype=np.float64)[smooth]
            cn = self.corner_normals[t].astype(np.float64)
            n = (1.0 - u - v)[:, None] * cn[:, 0] + u[:, None] * cn[:, 1] + v[:, None] * cn[:, 2]
            norm = np.linalg.norm(n, axis=1)
            good = norm > 1e-12
            n = np.where(good[:, None], n / np.where(good, norm, 1.0)[:, None], face[t])
            out[smooth] = n.astype(np.float32)
        if side is not None:
            out = np.where(np.asarray(side, dtype=bool)[:, None], out, -out)
        return out

    def albedo_at(self, tri, bu, bv):
        """(k, 3) float32 diffuse albedo in [0, 1] at barycentrics ``(bu, bv)`` of triangles
        ``tri`` (embree's convention): the textured value (:attr:`surface`) or the triangle's."""
        if self.surface is None or not self.surface.has_albedo:
            return np.clip(np.take(self.triangle_albedo, np.asarray(tri, dtype=np.int64), axis=0), 0.0, 1.0)
        return self.surface.albedo(tri, bu, bv, self.triangle_albedo)

    def valid_triangles(self):
        """Boolean mask of usable triangles (:meth:`usable_triangles`) with non-zero area."""
        return self.triangle_geometry()[1] > 0

    def bounding_diagonal(self):
        """Length of the diagonal of the bounding box of the corners of the usable triangles
        (metres, >= 1e-6; 1 without any)."""
        v = self.vertices[np.unique(self.triangles[self.usable_triangles()])]
        if len(v) == 0:
            return 1.0
        return max(float(np.linalg.norm(v.max(0) - v.min(0))), 1e-6)

    def is_emissive(self):
        """(T,) bool: triangles that emit light (any channel > 0)."""
        return np.any(self.triangle_emission > 0, axis=1)

    def emitter_groups(self):
        """Group emissive triangles into emitters (one terminal state each).

        Triangles of the same object with the same emitted radiance and sidedness form one
        emitter (uniform emission). Returns ``triangle_emitter (T,) int32`` (-1 for non-emissive
        triangles) and ``emitter_radiance (E, 3) float64``.
        """
        return self._derived("emitter_groups", self._emitter_groups)

    def _emitter_groups(self):
        tri_emitter = np.full(self.n_triangles, -1, dtype=np.int32)
        emissive = np.flatnonzero(self.is_emissive() & self.valid_triangles())
        if len(emissive) == 0:
            return tri_emitter, np.zeros((0, 3))
        key = np.column_stack([
            self.triangle_object[emissive].astype(np.float64),
            self.triangle_emission[emissive].astype(np.float64),
            self.triangle_emission_two_sided[emissive].astype(np.float64),
        ])
        uniq, inverse = np.unique(key, axis=0, return_inverse=True)
        tri_emitter[emissive] = inverse.reshape(-1).astype(np.int32)
        return tri_emitter, uniq[:, 1:4].copy()

    def emitter_names(self):
        """Human-readable name of each emitter group (its object's name)."""
        tri_emitter, radiance = self.emitter_groups()
        names = []
        for e in range(len(radiance)):
            obj = self.triangle_object[np.flatnonzero(tri_emitter == e)[0]]
            names.append(self.object_names[obj])
        return names

    def state_triangles(self):
        """(T,) bool: triangles that carry states: on selected objects, valid, not emissive."""
        return (self.object_carries_states[self.triangle_object]
                & self.valid_triangles() & ~self.is_emissive())

    def total_emitted_power_density(self):
        """Sum over emitters of their exitance π·L (luminance, W/m^2): the thesis's default λ."""
        _, radiance = self.emitter_groups()
        total = float(np.pi * luminance(radiance).sum()) if len(radiance) else 0.0
        if np.any(self.world_radiance > 0):
            total += float(np.pi * luminance(self.world_radiance))
        return total + self.lamps.power_density(self.triangle_geometry()[1].sum())

    def has_light(self):
        """True when some emitter, lamp or a non-black world can light the scene."""
        return bool(np.any(self.is_emissive() & self.valid_triangles()) or np.any(self.world_radiance > 0)
                    or np.any(self.lamps.emission > 0))

    def check_for_lmdp(self):
        """Raise :class:`SceneError` (user message) when no LMDP can be built from this scene."""
        if not np.any(self.object_carries_states):
            raise SceneError("Select at least one mesh object: the selected meshes carry the LMDP states")
        if not np.any(self.state_triangles()):
            names = ", ".join(n for n, s in zip(self.object_names, self.object_carries_states) if s)
            raise SceneError(
                f"The selected meshes ({names}) have no surface that can carry states: "
                "they are empty, degenerate or entirely emissive")
        if not self.has_light():
            raise SceneError(
                "The scene has no light the LMDP can use: add an emissive material (Emission shader "
                "or Principled emission), a light, or a non-black world colour")
