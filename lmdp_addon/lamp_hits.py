"""BSDF-sampled rays that hit Blender's lamps: the sampled-ray half of the lamps' MIS estimate.

Cycles intersects every ray with its lights that use Multiple Importance (``SHADER_USE_MIS``,
:attr:`~lmdp_addon.lamps.Lamps.hittable`) before the surfaces the ray reaches
(``kernel/light/light.h`` ``lights_intersect``, ``point.h``, ``spot.h``, ``area.h``,
``util/math_intersect.h``):

* **area light** (rectangle / ellipse): one-sided, hit only from the side it emits to
  (``d · axis < 0``), inside ``|u|, |v| <= ½`` of its edges (``u² + v² <= ¼`` for an ellipse);
* **sphere** (point / spot, ``use_soft_falloff`` off): the ray's first crossing of the sphere
  from outside, its exit from inside (``ray_sphere_intersect``);
* **soft falloff** (Blender's default): the disk of radius r about the centre facing the ray's
  origin (``ray_disk_intersect``);
* a **spot** is hit only by rays heading towards its centre (``d · (o - c) < 0``);
* a **sun** of angle > 0 is hit by the rays that escape the scene within its cone
  (``integrate_distant_lights``).

A ray collects the radiance :meth:`~lmdp_addon.lamps.Lamps.radiance` of every lamp it crosses
before its closest surface hit and goes on (Cycles treats a light as a transparent surface,
``shade_light.h``), weighted by the power heuristic ``q² / (q² + p_L²)`` against the lamp's light
sample (:meth:`~lmdp_addon.lamps.Lamps.next_event` with ``mis``): q the density that drew the ray,
p_L the lamp's solid-angle density (:meth:`~lmdp_addon.lamps.Lamps.pdf`) times its selection
probability (1 with up to ``ALL_LAMPS`` lamps, every one sampled; else
:meth:`~lmdp_addon.lamps.Lamps.selection`). The two halves sum to the lamp's D(y) (Veach 1997).
"""
import numpy as np

from .lamps import ALL_LAMPS, AREA, SPOT, SUN

INV_PI = 1.0 / np.pi


def intersect(lamps, origins, d, tmax, escaped):
    """Distances (k, H) from ``origins (k, 3)`` along unit ``d (k, 3)`` (float64) to each of the
    H :attr:`~lmdp_addon.lamps.Lamps.hittable` lamps (their indices: the second value), inf where
    the ray misses it or meets it beyond ``tmax (k,)`` (the closest surface; inf for rays that
    escape); suns are hit (distance inf) by the ``escaped (k,)`` rays inside their cone."""
    hit = np.flatnonzero(lamps.hittable)
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    tmax = np.asarray(tmax, dtype=np.float64)[:, None]
    t = np.full((len(o), len(hit)), np.inf)
    kind = lamps.kind[hit]
    c = lamps.position[hit]
    # ---- area lights: the plane, one-sided, inside the rectangle / ellipse ----
    a = np.flatnonzero(kind == AREA)
    if len(a):
        la = hit[a]
        n = lamps.axis[la]
        denom = d @ n.T
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = ((c[a] * n).sum(axis=1)[None, :] - o @ n.T) / denom
        rel = o[:, None, :] + np.where(np.isfinite(ta), ta, 0.0)[..., None] * d[:, None, :] - c[a][None]
        eu, ev = lamps.extent_u[la], lamps.extent_v[la]
        u = np.einsum("kli,li->kl", rel, eu / (eu * eu).sum(axis=1, keepdims=True))
        v = np.einsum("kli,li->kl", rel, ev / (ev * ev).sum(axis=1, keepdims=True))
        inside = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5) & (~lamps.ellipse[la] | (u * u + v * v <= 0.25))
        ok = (denom < 0) & (ta > 0) & (ta < tmax) & inside
        t[:, a] = np.where(ok, ta, np.inf)
    # ---- point and spot lamps: spheres, or disks facing the ray's origin ----
    p = np.flatnonzero((kind != AREA) & (kind != SUN))
    if len(p):
        lp = hit[p]
        r = lamps.radius[lp][None, :]
        to_c = c[p][None, :, :] - o[:, None, :]                    # (k, P, 3)
        d_sq = np.einsum("kli,kli->kl", to_c, to_c)
        d_cos = np.einsum("kli,ki->kl", to_c, d)
        # spheres: Cycles' ray_sphere_intersect (the entry from outside, the exit from inside)
        sin_sq = np.maximum(d_sq - d_cos * d_cos, 0.0)
        outside = d_sq > r * r
        ts = d_cos - np.where(outside, 1.0, -1.0) * np.sqrt(np.maximum(r * r - sin_sq, 0.0))
        sphere_ok = ~(outside & (d_cos < 0)) & (sin_sq <= r * r)
        # disks: normal (o - c) / |o - c|, hit where the ray meets them within r of the centre
        dist_c = np.sqrt(d_sq)
        with np.errstate(divide="ignore", invalid="ignore"):
            cos_angle = d_cos / dist_c                            # N · (-d), N = (o - c) / |o - c|
            td = dist_c / cos_angle
        q = d[:, None, :] * np.where(np.isfinite(td), td, 0.0)[..., None] - to_c
        disk_ok = (cos_angle > 0) & (np.einsum("kli,kli->kl", q, q) < r * r)
        tp = np.where(lamps.sphere[lp][None, :], np.where(sphere_ok, ts, np.inf), np.where(disk_ok, td, np.inf))
        spot = (kind[p] == SPOT)[None, :]
        tp = np.where(spot & (d_cos <= 0), np.inf, tp)            # spots: one-sided (spot.h)
        t[:, p] = np.where((tp > 0) & (tp < tmax), tp, np.inf)
    # ---- suns of angle > 0: escaping rays inside the cone (distance inf, flagged apart) ----
    s = np.flatnonzero(kind == SUN)
    sun_hit = np.zeros((len(o), len(hit)), bool)
    if len(s):
        ls = hit[s]
        cos_sun = -(d @ lamps.axis[ls].T)
        sun_hit[:, s] = np.asarray(escaped, bool)[:, None] & (cos_sun >= np.cos(0.5 * lamps.angle[ls])[None, :])
    return t, hit, sun_hit


def emission_hits(lamps, origins, normals, d, dist, escaped, cos_from, pdf_from=None):
    """BSDF-sampling half of the lamps' MIS estimate for the rays of a wavefront sampled at
    vertices ``origins (k, 3)`` (the lifted ray origins, as :meth:`~lmdp_addon.lamps.Lamps.
    next_event` lifts them; shading ``normals (k, 3)``) in directions ``d (k, 3)``, their
    closest surface ``dist (k,)`` away (inf: escaped, ``escaped (k,)``): ``(rays, values)``,
    the rays that cross a hittable lamp and ``Σ_l L_l(d) q² / (q² + p_L²)`` (m, 3) float32 over the
    lamps they cross, to be multiplied by ``β w``. q = ``cos_from / π`` (cos θ of the ray at its
    vertex), or ``pdf_from`` where it is not NaN (the BSDF density at glossy vertices), as
    :meth:`~lmdp_addon.lights.EmitterSampler.emission_hits`."""
    none = np.zeros(0, dtype=np.int64), np.zeros((0, 3), np.float32)
    if len(d) == 0 or not np.any(lamps.hittable):
        return none
    o = np.asarray(origins, dtype=np.float32).astype(np.float64)
    dd = np.asarray(d, dtype=np.float32).astype(np.float64)
    dd = dd / np.linalg.norm(dd, axis=1, keepdims=True)
    t, hit, sun_hit = intersect(lamps, o, dd, np.where(np.isfinite(dist), dist, np.inf), escaped)
    ray, col = np.nonzero(np.isfinite(t) | sun_hit)
    if len(ray) == 0:
        return none
    lamp = hit[col]
    nrm = np.asarray(normals, dtype=np.float64)
    p_l = lamps.pdf(o[ray], nrm[ray], lamp, dd[ray], t[ray, col])
    if len(lamps) > ALL_LAMPS:
        p_l = p_l * lamps.selection(o[ray], nrm[ray])[np.arange(len(ray)), lamp]
    q = np.asarray(cos_from, dtype=np.float64)[ray] * INV_PI
    if pdf_from is not None:
        pb = np.asarray(pdf_from, dtype=np.float64)[ray]
        q = np.where(np.isnan(pb), q, pb)
    with np.errstate(invalid="ignore"):
        weight = np.where(q > 0, q * q / (q * q + p_l * p_l), 0.0)
    value = lamps.radiance(lamp, o[ray], dd[ray]) * weight[:, None]
    rays, inverse = np.unique(ray, return_inverse=True)
    out = np.zeros((len(rays), 3))
    np.add.at(out, inverse, value)
    return rays, out.astype(np.float32)
