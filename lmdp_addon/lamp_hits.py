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
#: Ray x lamp pairs tested at once (the (k, L) float64 matrices of :func:`intersect` stay
#: within a few tens of MB whatever the number of lamps).
PAIRS_PER_CHUNK = 1 << 21


def intersect(lamps, origins, d, tmax, escaped):
    """The (ray, lamp) pairs of rays from ``origins (k, 3)`` along unit ``d (k, 3)`` (float64)
    that cross a :attr:`~lmdp_addon.lamps.Lamps.hittable` lamp before ``tmax (k,)`` (the
    closest surface; inf for rays that escape): ``(ray (m,), lamp (m,), t (m,))`` sorted by ray,
    t the distance to the lamp (inf for a sun, hit by the ``escaped (k,)`` rays inside its
    cone). All rays x all hittable lamps, culled by (k, L) matrix products before the exact
    tests run on the candidate pairs."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    tmax = np.asarray(tmax, dtype=np.float64)
    escaped = np.asarray(escaped, bool)
    hit = np.flatnonzero(lamps.hittable)
    step = max(1, PAIRS_PER_CHUNK // max(len(hit), 1))
    if len(o) > step:   # chunks of rays: bounded memory with many lamps
        parts = [intersect(lamps, o[i:i + step], d[i:i + step], tmax[i:i + step], escaped[i:i + step])
                 for i in range(0, len(o), step)]
        return (np.concatenate([r + i for r, i in zip((p[0] for p in parts), range(0, len(o), step))]),
                np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]))
    kind = lamps.kind[hit]
    found = []
    # ---- area lights: the plane, one-sided, inside the rectangle / ellipse ----
    a = hit[kind == AREA]
    if len(a):
        n = lamps.axis[a]
        denom = d @ n.T                                             # (k, A)
        height = (lamps.position[a] * n).sum(axis=1)[None, :] - o @ n.T
        ray, j = np.nonzero((denom < 0) & (height < 0))             # in front, heading to the plane
        lamp = a[j]
        t = height[ray, j] / denom[ray, j]
        rel = o[ray] + t[:, None] * d[ray] - lamps.position[lamp]
        eu, ev = lamps.extent_u[lamp], lamps.extent_v[lamp]
        u = (rel * eu).sum(axis=1) / (eu * eu).sum(axis=1)
        v = (rel * ev).sum(axis=1) / (ev * ev).sum(axis=1)
        ok = ((t > 0) & (t < tmax[ray]) & (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
              & (~lamps.ellipse[lamp] | (u * u + v * v <= 0.25)))
        found.append((ray[ok], lamp[ok], t[ok]))
    # ---- point and spot lamps: spheres, or disks facing the ray's origin ----
    p = hit[(kind != AREA) & (kind != SUN)]
    if len(p):
        c = lamps.position[p]
        r_sq = lamps.radius[p] ** 2
        d_cos = d @ c.T - (o * d).sum(axis=1)[:, None]               # (c - o) · d, (k, P)
        d_sq = np.maximum((o * o).sum(axis=1)[:, None] - 2.0 * (o @ c.T) + (c * c).sum(axis=1)[None, :], 0.0)
        # both shapes need the ray's line within r of the centre, ahead of the origin or from inside
        ray, j = np.nonzero((d_sq - d_cos * d_cos <= r_sq[None, :]) & ((d_cos > 0) | (d_sq <= r_sq[None, :])))
        lamp, dc, dq, rq = p[j], d_cos[ray, j], d_sq[ray, j], r_sq[j]
        # spheres: Cycles' ray_sphere_intersect (the entry from outside, the exit from inside)
        outside = dq > rq
        ts = dc - np.where(outside, 1.0, -1.0) * np.sqrt(np.maximum(rq - np.maximum(dq - dc * dc, 0.0), 0.0))
        # disks: normal N = (o - c) / |o - c|, N · (-d) = d_cos / |o - c|, hit within r of c
        dist_c = np.sqrt(dq)
        td = np.where(dc > 0, dq / np.where(dc > 0, dc, 1.0), 0.0)    # |o - c| / (N · (-d))
        disk_ok = (dc > 0) & (dist_c > 0) & (td * td - 2.0 * td * dc + dq < rq)   # |o + t d - c|² < r²
        t = np.where(lamps.sphere[lamp], ts, np.where(disk_ok, td, np.inf))
        ok = (t > 0) & (t < tmax[ray]) & ~((lamps.kind[lamp] == SPOT) & (dc <= 0))   # spots: one-sided
        found.append((ray[ok], lamp[ok], t[ok]))
    # ---- suns of angle > 0: escaping rays inside the cone ----
    s = hit[kind == SUN]
    if len(s):
        cos_sun = -(d @ lamps.axis[s].T)
        ray, j = np.nonzero(escaped[:, None] & (cos_sun >= np.cos(0.5 * lamps.angle[s])[None, :]))
        found.append((ray, s[j], np.full(len(ray), np.inf)))
    if not found:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    ray, lamp, t = (np.concatenate(x) for x in zip(*found))
    order = np.argsort(ray, kind="stable")
    return ray[order], lamp[order], t[order]


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
    ray, lamp, t = intersect(lamps, o, dd, np.where(np.isfinite(dist), dist, np.inf), escaped)
    if len(ray) == 0:
        return none
    nrm = np.asarray(normals, dtype=np.float64)
    p_l = lamps.pdf(o[ray], nrm[ray], lamp, dd[ray], t)
    if len(lamps) > ALL_LAMPS:
        p_l = p_l * lamps.selection(o[ray], nrm[ray])[np.arange(len(ray)), lamp]
    q = np.asarray(cos_from, dtype=np.float64)[ray] * INV_PI
    if pdf_from is not None:
        pb = np.asarray(pdf_from, dtype=np.float64)[ray]
        q = np.where(np.isnan(pb), q, pb)
    with np.errstate(invalid="ignore"):
        weight = np.where(q > 0, q * q / (q * q + p_l * p_l), 0.0)
    value = lamps.radiance(lamp, o[ray], dd[ray]) * weight[:, None]
    rays, first = np.unique(ray, return_index=True)   # sorted by ray: each ray's lamps together
    out = np.add.reduceat(value, first, axis=0) if len(ray) > len(rays) else value
    return rays, out.astype(np.float32)
