"""Lamps: Blender's point, spot, sun and area lights as arrays, and their next-event estimation.

Conventions are Cycles' (``scene/light.cpp``, ``kernel/light/{point,spot,distant}.h``), with
``strength`` = colour x power x 2^exposure (W; W/m² for a sun):

* **point / spot** of radius r: emitted radiance ``L = strength / (π · 4π r²)`` (``normalize``
  on, the default; ``strength / π`` off). With ``use_soft_falloff`` off the lamp is a sphere
  (sampled uniformly in the cone it subtends); on (Blender's default) it is a disk of radius r
  facing the receiver (``disk_light_sample``). r = 0 is a delta lamp of intensity
  ``I = strength / (4π)`` W/sr: D(y) = I cos θ_y / (π d²).
* **spot**: the point lamp times Cycles' cone mask ``smoothstep((cos ψ - cos(size/2)) /
  ((1 - cos(size/2)) · blend))``, ψ the angle between the lamp's -Z axis and the direction from
  the lamp's sampled point to the receiver.
* **area** light (rectangle or ellipse, edges ``extent_u``, ``extent_v``, area A; A = π |u| |v| / 4
  for an ellipse): radiance ``L = strength / (π A)`` (``normalize`` off: ``strength / π``)
  towards the light's -Z only, times Cycles' spread attenuation
  ``max((tan(s/2) - tan α) / (tan(s/2) - s/2), 0)`` (α the angle to the light's -Z, s the
  spread; 1 at s = 180°). Sampled uniformly on its area, a rectangle seen from closer than its
  diagonal uniformly in its solid angle. Unlike an emissive quad it occludes
  nothing, as in Cycles.
* **sun** of angular diameter 2θ: radiance ``L = strength / (π sin²θ)`` over the cone of
  half-angle θ about the direction to the sun (irradiance ``strength`` at normal incidence);
  θ = 0 is parallel light, D(y) = strength cos θ_y / π.

Next-event estimation (:meth:`Lamps.next_event`) draws one sample of every lamp at every point
(up to :data:`ALL_LAMPS` lamps; with more, one lamp per point chosen by :meth:`Lamps.choose`
and divided by its probability), so a vertex's estimate of the lamps' direct light

    D_lamps(y) = Σ_l (1/π) ∫_l L_l(ω) max(n_y · ω, 0) dω

is unbiased. Lamps with a body (a radius, an area, a sun's angle) and Cycles' Multiple
Importance on (``mis``, :attr:`Lamps.hittable`) are hit by BSDF-sampled rays as well, as
Cycles' ``lights_intersect`` / ``integrate_distant_lights`` find them (``lamp_hits``); there the
two estimates are combined by the power heuristic (Veach 1997, Cycles' ``power_heuristic``): the
light sample is weighted ``p_L² / (p_L² + q²)`` (``next_event(mis=True)``), the hit
``q² / (q² + p_L²)``, with ``p_L`` the
solid-angle density of :meth:`Lamps.connect` times the lamp's selection probability
(:meth:`Lamps.pdf`, :meth:`Lamps.selection`) and q the density of the BSDF ray. Lamps are not
geometry: they occlude nothing and a ray that crosses one goes on (Cycles counts the crossing as
a transparent bounce, ``shade_light.h``).

In the LMDP (thesis 3.1.2-3.1.3) every lamp is a terminal state whose desirability z_T is its
``emission`` (the radiance of a lamp with a body; the intensity W/sr of a delta point / spot;
the irradiance W/m² of a parallel sun), reached only through light samples
(:meth:`Lamps.transitions`) whose transition mass is ``D_l(y) / z_T`` = the lamp's
cosine-weighted solid angle / π (per m² for delta point lamps, times d²): mass x z_T is the
lamp's direct light / π, eq. 3.1's transition into an emitter. The build's stratum rays pass
through lamps as the bake's do (a lamp adds its light and hides nothing), so the light samples
alone carry each lamp's whole D_l: exact in expectation, and the rays' columns are Cycles'.
"""
from dataclasses import dataclass, field

import numpy as np

from .sampling import spherical_triangle_sample, spherical_triangle_solid_angle
from .transparency import reaches

INV_PI = 1.0 / np.pi
POINT, SPOT, SUN, AREA = 0, 1, 2, 3
KIND_NAMES = ("point", "spot", "sun", "area")
#: Shadow rays end this fraction short of a lamp's sampled point (lamps are not geometry).
SHADOW_SHORTEN = 1e-5
#: Length of a shadow ray towards a sun (float32 embree; nothing in a scene is this far).
SUN_DISTANCE = 1e30
#: Up to this many lamps every vertex samples each of them; with more, each vertex samples one
#: lamp (:meth:`Lamps.choose`), so a scene of many lights costs one shadow ray per vertex.
ALL_LAMPS = 4
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _sin_sqr_to_one_minus_cos(s_sq):
    """1 - cos θ from sin² θ without cancellation (Cycles' ``sin_sqr_to_one_minus_cos``)."""
    s_sq = np.clip(s_sq, 0.0, 1.0)
    return s_sq / (1.0 + np.sqrt(1.0 - s_sq))


def _frame(n):
    """Two unit vectors (k, 3) perpendicular to unit ``n (k, 3)`` and to each other."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, s


def _uniform_cone(axis, one_minus_cos, u, frame=None):
    """Directions (k, 3) uniform in the cones about unit ``axis (k, 3)`` with ``1 - cos θ_max``
    (``frame``: :func:`_frame` of ``axis``, if known)."""
    cos_t = 1.0 - u[:, 0] * one_minus_cos
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    phi = 2.0 * np.pi * u[:, 1]
    t, s = _frame(axis) if frame is None else frame
    return (t * (sin_t * np.cos(phi))[:, None] + s * (sin_t * np.sin(phi))[:, None]
            + axis * cos_t[:, None])


def _cosine_hemisphere(n, u):
    """Cosine-distributed directions (k, 3) about unit ``n (k, 3)``."""
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    t, s = _frame(n)
    z = np.sqrt(np.maximum(1.0 - u[:, 0], 0.0))
    return t * (r * np.cos(phi))[:, None] + s * (r * np.sin(phi))[:, None] + n * z[:, None]


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass
class Lamps:
    """Point, spot and sun lamps of a scene (L of them), world space.

    names        L names (the light objects)
    kind         (L,) int8 :data:`POINT`, :data:`SPOT`, :data:`SUN` or :data:`AREA`
    position     (L, 3) float64 metres: centre of a point / spot / area lamp (unused for suns)
    axis         (L, 3) unit: a spot's cone axis, the direction a sun's light travels and the
                 side an area light emits to (all the light's -Z); unused for point lamps
    extent_u, extent_v (L, 3) metres: an area light's edges (its scaled size along the light's
                 X and Y; zero elsewhere)
    ellipse      (L,) bool: a disk / ellipse area light (else a square / rectangle)
    spread       (L,) radians: an area light's spread (π: a diffuse emitter)
    radius       (L,) metres: a point / spot lamp's radius (0: delta lamp)
    angle        (L,) radians: a sun's angular diameter (0: parallel light)
    sphere       (L,) bool: a lamp with a radius is a sphere (``use_soft_falloff`` off) or a
                 disk facing the receiver (on, Blender's default)
    spot_size    (L,) radians: full cone angle of a spot (π elsewhere)
    spot_blend   (L,) 0..1: a spot's blend
    strength     (L, 3) colour x power x 2^exposure: W (point, spot), W/m² (sun)
    normalize    (L,) bool: Cycles' ``normalize`` (power spread over the lamp's area)
    cast_shadow  (L,) bool: ``use_shadow``
    mis          (L,) bool: Cycles' Multiple Importance (``light.cycles.
                 use_multiple_importance_sampling``): BSDF rays hit the lamp if it has a body
                 (:attr:`hittable`); it changes only the noise, so it is not in :meth:`arrays`
    """

    names: list = field(default_factory=list)
    kind: np.ndarray = None
    position: np.ndarray = None
    axis: np.ndarray = None
    radius: np.ndarray = None
    angle: np.ndarray = None
    sphere: np.ndarray = None
    spot_size: np.ndarray = None
    spot_blend: np.ndarray = None
    strength: np.ndarray = None
    normalize: np.ndarray = None
    cast_shadow: np.ndarray = None
    extent_u: np.ndarray = None
    extent_v: np.ndarray = None
    ellipse: np.ndarray = None
    spread: np.ndarray = None
    mis: np.ndarray = None

    def __post_init__(self):
        L = len(self.names)
        self.names = list(self.names)

        def column(value, default, dtype, shape=()):
            if value is None:
                return np.full((L,) + shape, default, dtype=dtype)
            return np.ascontiguousarray(value, dtype=dtype).reshape((L,) + shape)

        self.kind = column(self.kind, POINT, np.int8)
        self.position = column(self.position, 0.0, np.float64, (3,))
        axis = column(self.axis, 0.0, np.float64, (3,))
        if self.axis is None:
            axis[:, 2] = -1.0
        norm = np.linalg.norm(axis, axis=1, keepdims=True)
        self.axis = np.where(norm > 0, axis / np.where(norm > 0, norm, 1.0), [0.0, 0.0, -1.0])
        self.radius = np.maximum(column(self.radius, 0.0, np.float64), 0.0)
        self.angle = np.clip(column(self.angle, 0.0, np.float64), 0.0, np.pi)
        self.sphere = column(self.sphere, False, bool)
        self.spot_size = np.clip(column(self.spot_size, np.pi, np.float64), 1e-6, np.pi)
        self.spot_blend = np.clip(column(self.spot_blend, 0.0, np.float64), 0.0, 1.0)
        self.strength = np.maximum(column(self.strength, 0.0, np.float64, (3,)), 0.0)
        self.normalize = column(self.normalize, True, bool)
        self.cast_shadow = column(self.cast_shadow, True, bool)
        self.extent_u = column(self.extent_u, 0.0, np.float64, (3,))
        self.extent_v = column(self.extent_v, 0.0, np.float64, (3,))
        self.ellipse = column(self.ellipse, False, bool)
        self.spread = np.clip(column(self.spread, np.pi, np.float64), 1e-4, np.pi)
        self.area = (np.linalg.norm(self.extent_u, axis=1) * np.linalg.norm(self.extent_v, axis=1)
                     * np.where(self.ellipse, np.pi / 4.0, 1.0))
        half = 0.5 * self.spread
        self.tan_half_spread = np.where(self.spread >= np.pi, np.inf, np.tan(np.minimum(half, 1.5)))
        self.normalize_spread = np.where(half > 0.05, 1.0 / (self.tan_half_spread - half), 3.0 / half ** 3)
        self.emission = self._emission()
        self.spot_cos_half = np.cos(0.5 * self.spot_size)
        with np.errstate(divide="ignore"):
            self.spot_smooth = 1.0 / ((1.0 - self.spot_cos_half) * self.spot_blend)
        self.mis = column(self.mis, True, bool)
        #: (L,) bool: lamps BSDF rays hit (Cycles' ``SHADER_USE_MIS``: a point / spot lamp of
        #: radius > 0, an area light, a sun of angle > 0; with ``mis`` on)
        body = np.where(self.kind == SUN, self.angle > 0,
                        np.where(self.kind == AREA, self.area > 0, self.radius > 0))
        self.hittable = self.mis & body

    def __len__(self):
        return len(self.names)

    @property
    def empty(self):
        return len(self.names) == 0

    def arrays(self):
        """Every array that defines the lamps (for fingerprints)."""
        return (self.kind, self.position, self.axis, self.radius, self.angle, self.sphere, self.spot_size,
                self.spot_blend, self.strength, self.normalize, self.cast_shadow, self.extent_u, self.extent_v,
                self.ellipse, self.spread)

    def _emission(self):
        """(L, 3) z_T of each lamp: Cycles' ``strength x eval_fac`` (module docstring)."""
        r = self.radius
        area = np.where(self.kind == SUN,
                        np.where(self.angle > 0, np.pi * np.sin(0.5 * self.angle) ** 2, 1.0),
                        np.where(r > 0, 4.0 * np.pi * r * r, 4.0))
        area = np.where(self.kind == AREA, self.area, area)
        with np.errstate(divide="ignore"):
            scale = np.where(self.normalize, np.where(area > 0, 1.0 / np.where(area > 0, area, 1.0), 0.0), 1.0)
        scale = np.where(self.kind == SUN, scale, scale * INV_PI)
        return self.strength * scale[:, None]

    def is_delta(self):
        """(L,) bool: lamps reached along a single direction (one sample is exact)."""
        return np.where(self.kind == SUN, self.angle <= 0, (self.radius <= 0) & (self.kind != AREA))

    def power_density(self, scene_area):
        """Sum over the lamps of their power per unit area (Rec.709 luminance, W/m²): a sun's
        strength, a point / spot lamp's power spread over the scene's ``scene_area`` (m²); the
        lamps' share of the thesis's default λ."""
        if self.empty:
            return 0.0
        lum = self.strength @ np.array([0.2126, 0.7152, 0.0722])
        per = np.where(self.kind == SUN, lum, lum / max(float(scene_area), 1e-12))
        per = np.where(self.kind == AREA, np.pi * (self.emission @ np.array([0.2126, 0.7152, 0.0722])), per)
        return float(per.sum())

    # ---- sampling ---------------------------------------------------------------------------------
    def connect(self, origins, normals, lamp, u):
        """One sample of lamp ``lamp (k,)`` from each of ``origins (k, 3)`` (float64, normals
        ``(k, 3)``) with uniforms ``u (k, 2)``: ``(direction (k, 3) unit, distance (k,),
        weight (k,))`` such that ``emission[lamp] · weight · cos θ / π`` estimates the lamp's
        D(y) = (1/π) ∫ L cos θ dω (weight: 1/pdf per steradian, 1/d² for delta lamps, the
        spot's cone mask included; 0 where the sample carries nothing)."""
        k = len(lamp)
        o = np.asarray(origins, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        d = np.zeros((k, 3))
        dist = np.zeros(k)
        weight = np.zeros(k)
        kind = self.kind[lamp]
        sun = kind == SUN
        area = kind == AREA
        # ---- suns: parallel light or a uniform cone about the direction to the sun ----
        s = np.flatnonzero(sun)
        if len(s):
            ls = lamp[s]
            to_sun = -self.axis[ls]
            half = 0.5 * self.angle[ls]
            omc = 2.0 * np.sin(0.5 * half) ** 2
            cone = half > 0
            t_all, s_all = _frame(-self.axis)                    # per lamp, then per sample
            frame = (t_all[ls], s_all[ls])
            d[s] = np.where(cone[:, None], _uniform_cone(to_sun, np.where(cone, omc, 0.0), u[s], frame), to_sun)
            dist[s] = SUN_DISTANCE
            weight[s] = np.where(cone, 2.0 * np.pi * omc, 1.0)
        # ---- area lights: uniform on the rectangle / ellipse, one-sided, the spread's attenuation ----
        a = np.flatnonzero(area)
        if len(a):
            d[a], dist[a], weight[a] = self._connect_area(o[a], lamp[a], u[a])
        # ---- point and spot lamps ----
        p = np.flatnonzero(~sun & ~area)
        if len(p):
            lp = lamp[p]
            c = self.position[lp]
            r = self.radius[lp]
            to_c = c - o[p]
            dc = np.linalg.norm(to_c, axis=1)
            axis_c = to_c / np.where(dc > 0, dc, 1.0)[:, None]
            dp = np.zeros((len(p), 3))
            tp = np.zeros(len(p))
            wp = np.zeros(len(p))
            delta = r <= 0
            outside = dc > r
            sph = self.sphere[lp] & ~delta
            # delta lamps: the centre, weight 1/d²
            i = np.flatnonzero(delta & (dc > 0))
            dp[i], tp[i], wp[i] = axis_c[i], dc[i], 1.0 / dc[i] ** 2
            # spheres seen from outside: uniform in the subtended cone, the law of cosines for t
            i = np.flatnonzero(sph & outside)
            if len(i):
                omc = _sin_sqr_to_one_minus_cos((r[i] / dc[i]) ** 2)
                di = _uniform_cone(axis_c[i], omc, u[p[i]])
                cos_t = np.einsum("ij,ij->i", di, axis_c[i])
                tp[i] = dc[i] * cos_t - np.sqrt(np.maximum(r[i] ** 2 - dc[i] ** 2 + (dc[i] * cos_t) ** 2, 0.0))
                dp[i], wp[i] = di, 2.0 * np.pi * omc
            # inside a sphere: cosine directions, the whole hemisphere is the lamp
            i = np.flatnonzero(sph & ~outside)
            if len(i):
                n = np.asarray(normals, dtype=np.float64)[p[i]]
                di = _cosine_hemisphere(n, u[p[i]])
                cos_n = np.einsum("ij,ij->i", di, n)
                cos_t = -np.einsum("ij,ij->i", di, -axis_c[i])
                tp[i] = dc[i] * cos_t + np.sqrt(np.maximum(r[i] ** 2 - dc[i] ** 2 + (dc[i] * cos_t) ** 2, 0.0))
                dp[i], wp[i] = di, np.where(cos_n > 0, np.pi / np.maximum(cos_n, 1e-12), 0.0)
            # soft falloff: a disk of radius r about the centre facing the receiver
            i = np.flatnonzero(~sph & ~delta & (dc > 0))
            if len(i):
                light_n = -axis_c[i]                       # from the lamp to the receiver
                t1, t2 = _frame(light_n)
                rad = r[i] * np.sqrt(u[p[i], 0])
                phi = 2.0 * np.pi * u[p[i], 1]
                q = c[i] + t1 * (rad * np.cos(phi))[:, None] + t2 * (rad * np.sin(phi))[:, None]
                v = q - o[p[i]]
                t = np.linalg.norm(v, axis=1)
                di = v / t[:, None]
                cos_l = np.abs(np.einsum("ij,ij->i", light_n, -di))
                dp[i], tp[i], wp[i] = di, t, np.pi * r[i] ** 2 * cos_l / t ** 2
            # spots: the cone mask of the direction from the lamp's point to the receiver
            sp = np.flatnonzero(kind[p] == SPOT)
            if len(sp):
                ls = lp[sp]
                cos_psi = np.einsum("ij,ij->i", -dp[sp], self.axis[ls])
                x = (cos_psi - self.spot_cos_half[ls])
                smooth = self.spot_smooth[ls]
                mask = np.where(np.isinf(smooth), (x > 0).astype(np.float64),
                                _smoothstep(x * np.where(np.isinf(smooth), 0.0, smooth)))
                mask = np.where(sph[sp] & ~outside[sp], 1.0, mask)   # inside the sphere: unmasked
                wp[sp] *= mask
            d[p], dist[p], weight[p] = dp, tp, np.where(np.isfinite(wp), wp, 0.0)
        return d, dist, weight

    def _connect_area(self, o, lamp, u):
        """:meth:`connect` for area lights: a point uniform on the shape, weight
        ``A cos θ_l / t²`` x the spread attenuation (0 behind the light); rectangles seen from
        closer than their diagonal uniformly in their solid angle Ω instead (two spherical
        triangles, Arvo 1995; weight Ω x the attenuation), as Cycles samples them."""
        half = 0.5 * (np.linalg.norm(self.extent_u[lamp], axis=1) ** 2
                      + np.linalg.norm(self.extent_v[lamp], axis=1) ** 2)
        d_plane = np.einsum("ij,ij->i", o - self.position[lamp], self.axis[lamp])
        solid = np.flatnonzero(~self.ellipse[lamp] & (2.0 * half > d_plane * d_plane) & (d_plane > 0))
        di, t, w = self._connect_area_points(o, lamp, u)
        if len(solid):
            di[solid], t[solid], w[solid] = self._connect_area_solid(o[solid], lamp[solid], u[solid])
        return di, t, w

    def _spread_attenuation(self, cos_l, lamp):
        """Cycles' soft-box attenuation of area lights (1 for a spread of 180°)."""
        tan_a = np.sqrt(np.maximum(1.0 - cos_l * cos_l, 0.0)) / np.maximum(cos_l, 1e-300)
        tan_h = self.tan_half_spread[lamp]
        return np.where(np.isinf(tan_h), 1.0,
                        np.maximum((np.where(np.isinf(tan_h), 0.0, tan_h) - tan_a) * self.normalize_spread[lamp], 0.0))

    def _connect_area_solid(self, o, lamp, u):
        """Directions uniform in the solid angle of rectangle lamps (origins in front of them)."""
        c = self.position[lamp]
        eu, ev = 0.5 * self.extent_u[lamp], 0.5 * self.extent_v[lamp]
        p00, p10, p11, p01 = c - eu - ev - o, c + eu - ev - o, c + eu + ev - o, c - eu + ev - o
        t1 = np.stack([p00, p10, p11], axis=1)
        t2 = np.stack([p00, p11, p01], axis=1)
        o1, o2 = spherical_triangle_solid_angle(t1), spherical_triangle_solid_angle(t2)
        omega = o1 + o2
        f1 = o1 / np.where(omega > 0, omega, 1.0)
        first = u[:, 0] < f1
        u1 = np.where(first, u[:, 0] / np.where(f1 > 0, f1, 1.0), (u[:, 0] - f1) / np.where(f1 < 1, 1.0 - f1, 1.0))
        di, _ = spherical_triangle_sample(np.where(first[:, None, None], t1, t2), np.clip(u1, 0.0, 1.0), u[:, 1])
        n = self.axis[lamp]
        cos_l = -np.einsum("ij,ij->i", di, n)
        t = np.einsum("ij,ij->i", c - o, n) / np.where(cos_l != 0, -cos_l, -1.0)
        ok = (cos_l > 0) & (t > 0) & (omega > 0)
        w = np.where(ok, omega * self._spread_attenuation(np.where(ok, cos_l, 1.0), lamp), 0.0)
        return di, np.where(ok, t, 0.0), w

    def _connect_area_points(self, o, lamp, u):
        """Points uniform on the area lamps' rectangles / ellipses."""
        x, y = u[:, 0] - 0.5, u[:, 1] - 0.5
        ell = np.flatnonzero(self.ellipse[lamp])
        if len(ell):   # concentric map of the square to the unit disk, halved: the ellipse's (u, v)
            a, b = 2.0 * x[ell], 2.0 * y[ell]
            use_a = np.abs(a) > np.abs(b)
            r = np.where(use_a, a, b)
            phi = np.where(use_a, np.pi / 4 * b / np.where(a != 0, a, 1.0),
                           np.pi / 2 - np.pi / 4 * a / np.where(b != 0, b, 1.0))
            x[ell], y[ell] = 0.5 * r * np.cos(phi), 0.5 * r * np.sin(phi)
        q = self.position[lamp] + x[:, None] * self.extent_u[lamp] + y[:, None] * self.extent_v[lamp]
        v = q - o
        t = np.linalg.norm(v, axis=1)
        di = v / np.where(t > 0, t, 1.0)[:, None]
        cos_l = -np.einsum("ij,ij->i", di, self.axis[lamp])
        front = (cos_l > 0) & (t > 0)
        cos_l = np.where(front, cos_l, 1.0)
        atten = self._spread_attenuation(cos_l, lamp)
        w = np.where(front, self.area[lamp] * cos_l / np.where(t > 0, t, 1.0) ** 2 * atten, 0.0)
        return di, t, w

    # ---- densities and radiance of a direction (MIS with BSDF rays) -----------------------------
    def pdf(self, origins, normals, lamp, d, t):
        """Solid-angle density (k,) with which :meth:`connect` draws the direction ``d (k, 3)``
        (unit, float64) from ``origins (k, 3)`` (normals ``(k, 3)``) to lamp ``lamp (k,)``, the
        lamp's surface ``t (k,)`` away along it (unused for suns); the selection probability
        is not included (:meth:`selection`). Delta lamps give inf; the caller makes sure ``d``
        reaches the lamp."""
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        k = len(lamp)
        out = np.full(k, np.inf)
        kind = self.kind[lamp]
        # suns: uniform in the cone of half-angle θ = angle / 2
        s = np.flatnonzero((kind == SUN) & (self.angle[lamp] > 0))
        if len(s):
            out[s] = 1.0 / (2.0 * np.pi * 2.0 * np.sin(0.25 * self.angle[lamp[s]]) ** 2)
        # area lights: uniform on the shape (t² / (A cos θ_l)) or, rectangles close by, in Ω
        a = np.flatnonzero(kind == AREA)
        if len(a):
            la, oa = lamp[a], o[a]
            cos_l = -np.einsum("ij,ij->i", d[a], self.axis[la])
            with np.errstate(divide="ignore", invalid="ignore"):
                out[a] = np.where(cos_l > 0, t[a] ** 2 / (self.area[la] * cos_l), np.inf)
            half = 0.5 * (np.linalg.norm(self.extent_u[la], axis=1) ** 2 + np.linalg.norm(self.extent_v[la], axis=1) ** 2)
            d_plane = np.einsum("ij,ij->i", oa - self.position[la], self.axis[la])
            solid = np.flatnonzero(~self.ellipse[la] & (2.0 * half > d_plane * d_plane) & (d_plane > 0))
            if len(solid):
                ls, c = la[solid], self.position[la[solid]] - oa[solid]
                eu, ev = 0.5 * self.extent_u[ls], 0.5 * self.extent_v[ls]
                p00, p10, p11, p01 = c - eu - ev, c + eu - ev, c + eu + ev, c - eu + ev
                omega = (spherical_triangle_solid_angle(np.stack([p00, p10, p11], axis=1))
                         + spherical_triangle_solid_angle(np.stack([p00, p11, p01], axis=1)))
                out[a[solid]] = np.where(omega > 0, 1.0 / np.where(omega > 0, omega, 1.0), np.inf)
        # point and spot lamps of radius r: spheres (a cone outside, cosine inside) or disks
        p = np.flatnonzero((kind != SUN) & (kind != AREA) & (self.radius[lamp] > 0))
        if len(p):
            lp = lamp[p]
            r = self.radius[lp]
            to_c = self.position[lp] - o[p]
            dc = np.sqrt(np.einsum("ij,ij->i", to_c, to_c))
            sph = self.sphere[lp]
            pdf = np.empty(len(p))
            i = np.flatnonzero(sph & (dc > r))           # outside a sphere: uniform in its cone
            pdf[i] = 1.0 / (2.0 * np.pi * _sin_sqr_to_one_minus_cos((r[i] / dc[i]) ** 2))
            i = np.flatnonzero(sph & (dc <= r))          # inside: cosine about the normal
            if len(i):
                cos_n = np.einsum("ij,ij->i", d[p[i]], np.asarray(normals, dtype=np.float64)[p[i]])
                pdf[i] = np.maximum(cos_n, 0.0) * INV_PI
            i = np.flatnonzero(~sph)                     # a disk facing the receiver: t² / (π r² cos θ_l)
            if len(i):
                cos_l = np.abs(np.einsum("ij,ij->i", to_c[i], d[p[i]])) / np.maximum(dc[i], 1e-300)
                with np.errstate(divide="ignore"):
                    pdf[i] = np.where(cos_l > 0, t[p[i]] ** 2 / (np.pi * r[i] ** 2 * np.where(cos_l > 0, cos_l, 1.0)),
                                      np.inf)
            out[p] = pdf
        return out

    def radiance(self, lamp, origins, d):
        """Radiance (k, 3) that lamp ``lamp (k,)`` sends along ``d (k, 3)`` (unit, from the
        receivers ``origins (k, 3)`` towards the lamp): :attr:`emission` x a spot's cone mask
        (not inside its sphere) x an area light's spread attenuation, the integrand whose
        :meth:`connect` weight is ``mask / pdf``."""
        d = np.asarray(d, dtype=np.float64)
        factor = np.ones(len(lamp))
        kind = self.kind[lamp]
        a = np.flatnonzero(kind == AREA)
        if len(a):
            cos_l = -np.einsum("ij,ij->i", d[a], self.axis[lamp[a]])
            factor[a] = np.where(cos_l > 0, self._spread_attenuation(np.where(cos_l > 0, cos_l, 1.0), lamp[a]), 0.0)
        sp = np.flatnonzero(kind == SPOT)
        if len(sp):
            ls = lamp[sp]
            x = -np.einsum("ij,ij->i", d[sp], self.axis[ls]) - self.spot_cos_half[ls]
            smooth = self.spot_smooth[ls]
            mask = np.where(np.isinf(smooth), (x > 0).astype(np.float64),
                            _smoothstep(x * np.where(np.isinf(smooth), 0.0, smooth)))
            dc = np.linalg.norm(self.position[ls] - np.asarray(origins, dtype=np.float64)[sp], axis=1)
            factor[sp] = np.where(self.sphere[ls] & (dc <= self.radius[ls]), 1.0, mask)
        return self.emission[lamp] * factor[:, None]

    def next_event(self, points, normals, rng, caster, lift=None, geometric=None, transparency=None, bsdf=None,
                   mis=False):
        """``(values (k, 3) float32, shadow rays)``: the lamps' direct light D(y) = (1/π) ∫ L
        cos θ dω at surface points y (one sample of every lamp, light sampling alone), or with
        ``mis`` its light-sampling half: samples of :attr:`hittable` lamps weighted
        ``p_L² / (p_L² + q²)`` (p_L = :meth:`pdf` x the selection probability, q = cos θ / π, the
        BSDF density at the points of ``bsdf``), the half that ``lamp_hits.emission_hits``
        completes for rays sampled at the same points. ``caster``, ``lift`` and ``geometric`` as
        :meth:`~lmdp_addon.lights.EmitterSampler.next_event`: shadow rays leave the points
        lifted along ``geometric`` (default ``normals``) by ``lift (k,)``, directions below the
        geometric surface give 0; ``transparency`` (:class:`~lmdp_addon.transparency.Transparency`
        or None) lets shadow rays through cut-outs with ∏ (1 − alpha); at the points of ``bsdf``
        (:class:`~lmdp_addon.bsdf.GlossyRows`, or None) the BSDF's f cos replaces cos θ / π. No
        random numbers are drawn without lamps."""
        k = len(points)
        out = np.zeros((k, 3), np.float32)
        L = len(self.names)
        if L == 0 or k == 0:
            return out, 0
        eps = (np.float32(caster.offset()) if lift is None
               else np.asarray(lift, dtype=np.float32).reshape(-1, 1))
        lifted = (points + eps * (normals if geometric is None else geometric)).astype(np.float64)
        nrm = np.asarray(normals, dtype=np.float64)
        prob = None
        if L <= ALL_LAMPS:
            owner = np.repeat(np.arange(k), L)
            lamp = np.tile(np.arange(L), k)
            u = rng.random((k * L, 2))
            d, dist, weight = self.connect(lifted[owner], nrm[owner], lamp, u)
        else:
            owner = np.arange(k)
            lamp, prob = self.choose(lifted, nrm, rng.random(k))
            u = rng.random((k, 2))
            d, dist, weight = self.connect(lifted, nrm, lamp, u)
            weight = weight / prob
        cos = np.einsum("ij,ij->i", nrm[owner], d)
        valid = (cos > 0) & (weight > 0) & (dist > 0)
        if geometric is not None:
            valid &= np.einsum("ij,ij->i", np.asarray(geometric, dtype=np.float64)[owner], d) > 0
        ok = np.flatnonzero(valid)
        passed, rays = self._visible(caster, lifted[owner[ok]], d[ok], dist[ok], lamp[ok], transparency)
        seen = reaches(passed)
        ok, passed = ok[seen], passed[seen]
        value = self.emission[lamp[ok]] * (weight[ok] * cos[ok] * INV_PI)[:, None]
        q = cos[ok] * INV_PI      # the density of the BSDF rays that may hit the lamp
        if bsdf is not None:     # glossy points: f cos of their BSDF and its density
            g = np.flatnonzero(bsdf.mask[owner[ok]])
            if len(g):
                f_cos, p_bsdf = bsdf.eval_at(owner[ok[g]], d[ok[g]].astype(np.float32))
                value[g] = self.emission[lamp[ok[g]]] * (weight[ok[g], None] * np.asarray(f_cos, np.float64))
                q[g] = p_bsdf
        if mis:
            h = np.flatnonzero(self.hittable[lamp[ok]])
            if len(h):
                oh = ok[h]
                p_l = self.pdf(lifted[owner[oh]], nrm[owner[oh]], lamp[oh], d[oh], dist[oh])
                if prob is not None:
                    p_l = p_l * prob[oh]
                value[h] *= (p_l * p_l / (p_l * p_l + q[h] * q[h]))[:, None]
        value = value * (passed if passed.ndim == 2 else passed[:, None])
        for ch in range(3):
            out[:, ch] = np.bincount(owner[ok], weights=value[:, ch], minlength=k)
        return out, rays

    direct_light = next_event

    def choose(self, origins, normals, u):
        """One lamp per point for scenes of many lamps: ``(lamp (k,), probability (k,))`` drawn
        with ``u (k,)`` from :meth:`selection`."""
        k, L = len(origins), len(self.names)
        p = self.selection(origins, normals)
        cdf = np.cumsum(p, axis=1)
        lamp = np.minimum((cdf < (u * cdf[:, -1])[:, None]).sum(axis=1), L - 1)
        return lamp, p[np.arange(k), lamp]

    def selection(self, origins, normals):
        """(k, L) probability of each lamp being the one sampled at ``origins (k, 3)`` with
        normals ``(k, 3)`` in scenes of more than :data:`ALL_LAMPS` lamps: the mixture
        ``½ e_l / Σ e + ½ / L``, e_l the luminance each lamp would give without shadows if it
        were concentrated at its centre (its direction, for a sun). The uniform half keeps every
        lamp's probability above 1/(2L), so the estimate stays unbiased where the centre
        estimate is 0 but part of a lamp shines."""
        L = len(self.names)
        lum = self.emission @ LUMINANCE
        to_c = self.position[None, :, :] - origins[:, None, :]
        d2 = np.maximum(np.einsum("kli,kli->kl", to_c, to_c), 1e-12)
        w = to_c / np.sqrt(d2)[..., None]
        cos_x = np.maximum(np.einsum("kli,ki->kl", w, normals), 0.0)
        body = np.where(self.radius > 0, np.pi * self.radius ** 2, 1.0)
        body = np.where(self.kind == AREA, self.area, body)
        cos_l = np.where(self.kind == AREA, np.maximum(-np.einsum("kli,li->kl", w, self.axis), 0.0), 1.0)
        spot = self.kind == SPOT
        if np.any(spot):
            cos_psi = -np.einsum("kli,li->kl", w, self.axis)
            cos_l = np.where(spot, (cos_psi > self.spot_cos_half - 1e-3).astype(np.float64), cos_l)
        est = lum * body * cos_x * cos_l / d2
        sun = self.kind == SUN
        if np.any(sun):
            cos_sun = np.maximum(-normals @ self.axis.T, 0.0)
            est = np.where(sun, lum * np.where(self.angle > 0, np.pi * np.sin(0.5 * self.angle) ** 2, 1.0) * cos_sun,
                           est)
        total = est.sum(axis=1, keepdims=True)
        return 0.5 / L + 0.5 * np.where(total > 0, est / np.where(total > 0, total, 1.0), 1.0 / L)

    def _visible(self, caster, origins, d, dist, lamp, transparency=None):
        """The fraction of each shadow ray's light that reaches its lamp, (k,) float64 (1 or 0
        through opaque geometry; ∏ (1 − alpha) through ``transparency``'s cut-outs, (k, 3) when
        they are tinted; lamps without ``use_shadow`` are never blocked), and the number of rays
        traced."""
        shadow = np.flatnonzero(self.cast_shadow[lamp])
        if len(shadow) == 0:
            return np.ones(len(lamp)), 0
        tmax = np.minimum(dist[shadow] * (1.0 - SHADOW_SHORTEN), SUN_DISTANCE).astype(np.float32)
        o, ds = origins[shadow].astype(np.float32), d[shadow].astype(np.float32)
        if transparency is None:
            passed = (~caster.occluded(o, ds, tmax)).astype(np.float64)
        else:
            passed = np.asarray(transparency.transmittance(caster, o, ds, tmax), dtype=np.float64)
        out = np.ones((len(lamp),) + passed.shape[1:])
        out[shadow] = passed
        return out, len(shadow)

    def transitions(self, origins, frames, samples, rng, caster, transparency=None):
        """The build's transitions into the lamp terminals (thesis eq. 3.1) from the lifted
        state points ``origins (n, 3)`` with frames ``(n, 3, 3)`` (rows t, b, n):
        ``(owner (k,), lamp (k,), local directions (k, 3), mass (k,))`` of every unblocked light
        sample, with ``mass x emission[lamp]`` = the sample's share of the lamp's D(x).
        Delta lamps take one sample per point, the others ``samples`` (stratified in the first
        uniform; fewer, ``samples / (L // ALL_LAMPS)``, in scenes of many lamps)."""
        n, L = len(origins), len(self.names)
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
        if L == 0 or n == 0:
            return none
        per = np.where(self.is_delta(), 1, max(int(samples) // max(L // ALL_LAMPS, 1), 1))
        lamp_of = np.repeat(np.arange(L), per)                 # one pattern of sum(per) samples
        j = np.concatenate([np.arange(c) for c in per])
        K = len(lamp_of)
        owner = np.repeat(np.arange(n), K)
        lamp = np.tile(lamp_of, n)
        count = np.tile(per[lamp_of], n).astype(np.float64)
        u = rng.random((n * K, 2))
        u[:, 0] = (np.tile(j, n) + u[:, 0]) / count
        normals = frames[:, 2]
        d, dist, weight = self.connect(origins[owner], normals[owner], lamp, u)
        local = np.einsum("kij,kj->ki", frames[owner], d)
        valid = np.flatnonzero((local[:, 2] > 0) & (weight > 0) & (dist > 0))
        passed, _ = self._visible(caster, origins[owner[valid]], d[valid], dist[valid], lamp[valid], transparency)
        if passed.ndim == 2:     # tinted cut-outs: the LMDP's transitions carry the luminance
            passed = passed @ np.array([0.2126, 0.7152, 0.0722])
        ok, passed = valid[passed > 0], passed[passed > 0]
        mass = weight[ok] * local[ok, 2] * INV_PI / count[ok] * passed
        return owner[ok], lamp[ok], local[ok], mass
