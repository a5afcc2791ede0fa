"""Light sampling: the scene's emissive triangles as area lights, for the build and the bake.

One :class:`EmitterSampler` per scene holds the emitter table both stages sample:

* the build's next-event estimates of the passive dynamics (``dynamics.LightPatterns``) draw
  points on the emitters **proportionally to area** (:meth:`EmitterSampler.sample`,
  :meth:`EmitterSampler.stratified`, float64);
* the bake's tracer draws one emitter triangle **proportionally to area x max-channel radiance**
  and a point on it (:meth:`EmitterSampler.next_event`, float32), uniform on the triangle far
  away and uniform in its solid angle close by, as Cycles chooses (:meth:`EmitterSampler.near`),
  and weights emitters hit by sampled rays for MIS (:meth:`EmitterSampler.emission_hits`).

A connection from a receiver x (normal n_x) to an emitter point y (normal n_y) carries

    G(x, y) = cos θ_x · cos θ_y / |y - x|^2,     cos θ_x = n_x · ω,   cos θ_y = -n_y · ω (front),

with ω the unit direction from x to y. Mesh emission is two-sided (Cycles), so there
``cos θ_y = |n_y · ω|``; one-sided emitters (area lights) emit only along +n_y.
With y drawn with area density ``1 / total_area``, ``G V total_area / π`` is an unbiased
estimate of the form factor from x to the emitters (the Lambertian transition mass towards them).
In the bake, D_e(y) = (1/π) ∫ L_e cos θ dω is estimated per vertex from one light sample and
combined with the emitters the sampled rays hit by the balance heuristic (Veach 1997).
"""
from dataclasses import dataclass

import numpy as np

from .sampling import (GOLDEN, dot, dot3, rows, set_rows, spherical_triangle_sample,
                       spherical_triangle_solid_angle, table_index)
from .transparency import Transparency, reaches

INV_PI = 1.0 / np.pi


@dataclass
class EmitterSample:
    """Points on emitters: ``position (n, 3)`` and the index of each one's triangle among the
    sampler's ``triangles`` (``triangle_index (n,)``)."""

    position: np.ndarray
    triangle_index: np.ndarray


class EmitterSampler:
    """The emissive triangles (non-zero area) of a scene and their sampling tables.

    Build (float64, area-proportional): ``triangles`` (E_t,) scene triangle indices,
    ``emitter_of_triangle`` their emitter group (``SceneArrays.emitter_groups``), ``areas``,
    ``total_area``, ``normals``, ``two_sided``.
    Bake (float32, power-proportional): per emitter triangle its probability ``power_prob``,
    area density ``pdf_area`` (p_A = P(triangle) / area) and radiance; per scene triangle
    ``triangle_pdf_area`` (0: not an emitter), ``triangle_emitter`` (-1: not an emitter).
    """

    def __init__(self, scene):
        self.scene = scene
        tri_emitter, _ = scene.emitter_groups()
        normals, areas = scene.triangle_geometry()
        self.triangles = np.flatnonzero(tri_emitter >= 0)
        self.emitter_of_triangle = tri_emitter[self.triangles]
        self.areas = areas[self.triangles]
        self.total_area = float(self.areas.sum())
        self.cdf = np.cumsum(self.areas)
        self.normals = normals[self.triangles]
        corners = scene.corners()[self.triangles]
        self.v0 = corners[:, 0].copy()
        self.e1 = corners[:, 1] - corners[:, 0]
        self.e2 = corners[:, 2] - corners[:, 0]
        self.two_sided = scene.triangle_emission_two_sided[self.triangles]
        #: Transparent surfaces attenuate shadow rays by 1 - alpha (None: every surface opaque).
        self.transparency = Transparency.of(scene)
        self._power_tables(scene, corners, normals)

    def _power_tables(self, scene, c, normals):
        """The bake's tables: triangles with probability ∝ area x max-channel radiance."""
        em = self.triangles
        T = scene.n_triangles
        self.n_triangles = len(em)
        self.any_two_sided = bool(np.any(self.two_sided))
        self.triangle_emitter = np.full(T, -1, dtype=np.int64)
        self.triangle_emitter[em] = np.arange(len(em))
        self.triangle_pdf_area = np.zeros(T, np.float32)   #: p_A of a point on each scene triangle
        self.triangle_two_sided = scene.triangle_emission_two_sided
        self.triangle_emission32 = scene.triangle_emission.astype(np.float32)
        if len(em) == 0:
            return
        weight = self.areas * scene.triangle_emission[em].max(axis=1)
        cdf = np.cumsum(weight)
        prob = weight / cdf[-1]
        self.power_cdf32 = (cdf / cdf[-1]).astype(np.float32)
        self.power_prob = prob
        self.radiance32 = scene.triangle_emission[em].astype(np.float32)
        self.pdf_area32 = (prob / self.areas).astype(np.float32)
        self.triangle_pdf_area[em] = self.pdf_area32
        # float64 corners and normals for solid-angle sampling (close emitters)
        self.corners64 = c
        self.corner64 = np.ascontiguousarray(c[:, 0])
        self.normal64 = np.ascontiguousarray(normals[em], dtype=np.float64)
        # float32 tables per component (x, y, z) for area sampling and the strategy choice
        normal32, corner32 = self.normal64.astype(np.float32), c[:, 0].astype(np.float32)
        edge1, edge2 = (c[:, 1] - c[:, 0]).astype(np.float32), (c[:, 2] - c[:, 0]).astype(np.float32)
        self.normal32_xyz = tuple(np.ascontiguousarray(normal32[:, i]) for i in range(3))
        self.corner32_xyz = tuple(np.ascontiguousarray(corner32[:, i]) for i in range(3))
        self.edge1_32_xyz = tuple(np.ascontiguousarray(edge1[:, i]) for i in range(3))
        self.edge2_32_xyz = tuple(np.ascontiguousarray(edge2[:, i]) for i in range(3))
        self.plane32 = np.einsum("ij,ij->i", normal32, corner32)
        self.longest2 = np.max(np.stack([np.sum((c[:, 1] - c[:, 0]) ** 2, axis=1),
                                         np.sum((c[:, 2] - c[:, 1]) ** 2, axis=1),
                                         np.sum((c[:, 0] - c[:, 2]) ** 2, axis=1)]),
                               axis=0).astype(np.float32)

    @property
    def empty(self):
        return len(self.triangles) == 0 or self.total_area <= 0

    # ---- the build: points proportional to area ---------------------------------------------------
    def sample(self, u1, u2):
        """Map uniform ``u1, u2 (n,)`` to emitter points (area-proportional, area preserving)."""
        x = np.asarray(u1, dtype=np.float64) * self.total_area
        k = np.minimum(np.searchsorted(self.cdf, x, side="right"), len(self.triangles) - 1)
        start = self.cdf[k] - self.areas[k]
        r1 = np.clip((x - start) / self.areas[k], 0.0, 1.0)
        s = np.sqrt(r1)
        b1, b2 = s * (1.0 - np.asarray(u2)), s * np.asarray(u2)
        if len(self.triangles) == 1:  # the common single-quad light: no gathers
            pos = self.v0[0] + b1[:, None] * self.e1[0] + b2[:, None] * self.e2[0]
        else:
            pos = np.take(self.v0, k, axis=0)
            pos += b1[:, None] * np.take(self.e1, k, axis=0)
            pos += b2[:, None] * np.take(self.e2, k, axis=0)
        return EmitterSample(position=pos, triangle_index=k)

    def stratified(self, n_receivers, per_receiver, rng):
        """``per_receiver`` stratified samples for each of ``n_receivers``, receiver-major.

        Receiver i's samples take ``u1 = (j + ξ_i)/K`` (one per 1/K of the emitter area, in the
        area-CDF order) and ``u2 = frac(j/φ + ξ'_i)``, a randomly shifted rank-1 lattice.
        """
        K = int(per_receiver)
        j = np.tile(np.arange(K, dtype=np.float64), n_receivers)
        shift = rng.random((n_receivers, 2)).repeat(K, axis=0)
        u1 = (j + shift[:, 0]) / K
        u2 = np.mod(j * GOLDEN + shift[:, 1], 1.0)
        return self.sample(u1, u2)

    # ---- the bake: next-event estimation ------------------------------------------------------------
    def near(self, origins, e, n_l=None):
        """Light-sampling strategy per (ray origin ``origins`` float32, (k, 3) or its three (k,)
        components, emitter triangle ``e``), as Cycles chooses it: solid-angle sampling when the
        triangle's longest edge exceeds the origin's distance to its plane (``n_l``: the
        triangles' normals per component, if already gathered). :meth:`next_event` and the MIS
        weight of emitter hits both call this with the same float32 origins, so they always
        agree on the strategy."""
        o = origins if isinstance(origins, tuple) else (origins[:, 0], origins[:, 1], origins[:, 2])
        if n_l is None:
            n_l = tuple(np.take(c, e) for c in self.normal32_xyz)
        d_plane = dot3(o, n_l) - np.take(self.plane32, e)
        return np.take(self.longest2, e) > d_plane * d_plane

    def next_event(self, points, normals, rng, caster, mis=True, lift=None, geometric=None, bsdf=None,
                   mis_hook=None):
        """``(values (k, 3) float32, shadow rays)``: the light-sampling half of the MIS estimate
        of D_e(y) = (1/π) ∫ L_e cos θ dω at surface points y (``mis=False``: the whole of D_e(y)
        by light sampling alone, weight ``q / p_L``; for paths that end at y).

        One point on the emitters (triangle ∝ area x max radiance) with the weight
        ``q / (p_L + q)``: ``p_L`` is the light-sampling density per steradian and
        ``q = cos θ_y / π`` the cosine density. Far from the triangle the point is uniform on it
        (``p_L = p_A r² / cos θ_l``); close to it, uniform in the solid angle Ω it subtends
        (Arvo 1995, ``p_L = P(triangle) / Ω``), as Cycles chooses (:meth:`near`). The
        sampled-ray half (:meth:`emission_hits`) uses ``q / (q + p_L)`` with the same q and
        strategy, so the two weights sum to one for every direction and the combination is
        unbiased whatever density drew the ray (in GUIDED mode q is the cosine part of the
        mixture only: a cheaper, still exact, partition of unity; Veach's balance heuristic when
        sampling is purely cosine). ``caster``: the :class:`~lmdp_addon.raycast.RayCaster` of
        the shadow rays, whose origins are lifted along ``normals`` by ``lift (k,)``, the
        offsets of the points' triangles (``caster.offset(triangles)``; None: ``caster.offset()``),
        and which stop short of the emitter by its own offset (``caster.shadow_distance``).
        ``geometric (k, 3)``: the geometric normals of the lit side where they differ from the
        shading ``normals`` (smooth or custom normals): the origins are lifted along them, the
        cosine q stays the shading one, and directions below the geometric surface give 0 (the
        light the tracer's BSDF sampling absorbs there, see ``tracer``). None: ``normals``.
        ``bsdf``: the glossy points' BSDF (:class:`~lmdp_addon.bsdf.GlossyRows`, None: every
        point is Lambertian): at its ``mask`` points the value is ``L_e f cos / (p_L + p_bsdf)``
        with the BSDF's f cos and sampling density instead of the cosine ones (MIS with the
        density that samples their rays, :meth:`emission_hits` ``pdf_from``).
        """
        k = len(points)
        out = np.zeros((k, 3), np.float32)
        if self.n_triangles == 0 or k == 0:
            return out, 0
        eps = (np.float32(caster.offset()) if lift is None
               else np.asarray(lift, dtype=np.float32).reshape(-1, 1))
        r = rng.random((k, 3), dtype=np.float32)
        r1, r2 = np.ascontiguousarray(r[:, 1]), np.ascontiguousarray(r[:, 2])
        if self.n_triangles == 1:
            e = np.zeros(k, dtype=np.int64)
        else:
            e = table_index(self.power_cdf32, r[:, 0])
        # Direction and distance from the offset origin itself: from the surface point, a shadow
        # ray at a grazing angle would meet the emitter's plane before ``dist`` (close emitters).
        origin = points + eps * (normals if geometric is None else geometric)
        o = tuple(np.ascontiguousarray(origin[:, i]) for i in range(3))
        n_l = tuple(np.take(c, e) for c in self.normal32_xyz)
        near = self.near(o, e, n_l)
        dl, dist, solid_angle = self._connect(origin, o, e, np.flatnonzero(near), r1, r2)
        d = (dl[:, 0], dl[:, 1], dl[:, 2])
        cos_y = dot3((normals[:, 0], normals[:, 1], normals[:, 2]), d)
        cos_l = -dot3(n_l, d)
        if self.any_two_sided:
            cos_l = np.where(np.take(self.two_sided, e), np.abs(cos_l), cos_l)
        valid = (cos_y > 0) & (cos_l > 0) & (dist > 0)
        if geometric is not None:
            valid &= dot3((geometric[:, 0], geometric[:, 1], geometric[:, 2]), d) > 0
        ok = np.flatnonzero(valid)
        if len(ok) == 0:
            return out, 0
        tmax = caster.shadow_distance(np.take(dist, ok), np.take(self.triangles, np.take(e, ok)))
        if self.transparency is None:
            vis, passed = ok[~caster.occluded(rows(origin, ok), rows(dl, ok), tmax)], None
        else:
            T = self.transparency.transmittance(caster, rows(origin, ok), rows(dl, ok), tmax)
            seen = reaches(T)
            vis, passed = ok[seen], T[seen]
        if len(vis) == 0:
            return out, len(ok)
        ev = np.take(e, vis)
        dv = np.take(dist, vis)
        p_light = np.take(self.pdf_area32, ev) * dv * dv / np.take(cos_l, vis)
        solid = np.flatnonzero(np.take(near, vis))
        if len(solid):
            p_light[solid] = (np.take(self.power_prob, np.take(ev, solid))
                              / np.maximum(np.take(solid_angle, np.take(vis, solid)), 1e-300))
        q = np.take(cos_y, vis) * np.float32(INV_PI)
        weight = q / (p_light + q) if mis else q / p_light
        if mis_hook is not None:   # a third strategy for these paths (light tracing): its share
            gv = normals if geometric is None else geometric
            q_g = dot3(tuple(np.take(gv[:, i], vis) for i in range(3)), tuple(np.take(dl[:, i], vis) for i in range(3)))
            weight = weight * mis_hook(vis, ev, p_light, q, q_g * np.float32(INV_PI))
        if passed is not None and passed.ndim == 1:
            weight = weight * passed
        set_rows(out, vis, rows(self.radiance32, ev) * weight[:, None])
        if bsdf is not None:
            g = np.flatnonzero(np.take(bsdf.mask, vis))
            if len(g):
                f_cos, p_bsdf = bsdf.eval_at(np.take(vis, g), rows(dl, np.take(vis, g)))
                denom = np.take(p_light, g) + (p_bsdf if mis else 0.0)
                value = rows(self.radiance32, np.take(ev, g)) * (f_cos / denom[:, None])
                if passed is not None and passed.ndim == 1:
                    value = value * np.take(passed, g)[:, None]
                out[vis[g]] = value
        if passed is not None and passed.ndim == 2:    # tinted transparent surfaces on the way
            out[vis] *= passed
        return out, len(ok)

    def _connect(self, origin, o, e, close, r1, r2):
        """Directions ``dl (k, 3)`` float32, distances ``dist (k,)`` and solid angles (k,) (set
        for ``close`` only) from the lifted ``origin`` (and its components ``o``) to one point of
        emitter triangle ``e`` each: uniform on the triangle (area measure, float32), and for the
        ``close`` ones uniform in its solid angle (float64: the spherical construction loses
        precision in float32) with the distance to the triangle's plane along it."""
        k = len(e)
        sq = np.sqrt(r1)
        b = sq * r2
        a = sq - b
        to = [np.take(c0, e) - oc + a * np.take(c1, e) + b * np.take(c2, e)
              for c0, c1, c2, oc in zip(self.corner32_xyz, self.edge1_32_xyz, self.edge2_32_xyz, o)]
        dist = np.sqrt(to[0] * to[0] + to[1] * to[1] + to[2] * to[2])
        inv = 1.0 / np.where(dist > 0, dist, 1.0)
        dl = np.empty((k, 3), np.float32)
        for i in range(3):
            dl[:, i] = to[i] * inv
        solid_angle = None
        if len(close):
            ec = np.take(e, close)
            oc = rows(origin, close).astype(np.float64)
            dl_close, omega = spherical_triangle_sample(rows(self.corners64, ec) - oc[:, None, :],
                                                        np.take(r1, close), np.take(r2, close))
            nc = rows(self.normal64, ec)
            denom = dot(dl_close, nc)
            t = dot(rows(self.corner64, ec) - oc, nc) / np.where(denom != 0, denom, 1e-300)
            dl[close] = dl_close
            dist[close] = np.where((denom != 0) & (t > 0) & (omega > 0), t, 0.0)
            solid_angle = np.zeros(k)
            solid_angle[close] = omega
        return dl, dist, solid_angle

    def direct_light(self, points, normals, rng, caster, lift=None, geometric=None):
        """``(D_e(y) (k, 3) float32, shadow rays)`` = (1/π) ∫ L_e cos θ dω at surface points y
        with normals ``normals`` (the side that is lit), by light sampling alone: one shadow ray
        each (:meth:`next_event` with ``mis=False``; ``lift``, ``geometric`` as there)."""
        return self.next_event(np.ascontiguousarray(points, dtype=np.float32),
                               np.ascontiguousarray(normals, dtype=np.float32), rng, caster, mis=False,
                               lift=lift, geometric=None if geometric is None
                               else np.ascontiguousarray(geometric, dtype=np.float32))

    def light_density(self, origins, e, dist, cos_l):
        """(k,) the light-sampling density per steradian of :meth:`next_event` from the float32
        ``origins (k, 3)`` (lifted as next_event lifts them) of points on emitter triangles
        ``e`` at distances ``dist`` with cosines ``cos_l`` there: ``p_A r² / cos θ_l`` where
        the point is sampled on the area, ``P(triangle) / Ω`` where in its solid angle
        (:meth:`near`)."""
        p_light = np.take(self.pdf_area32, e) * dist ** 2 / cos_l
        near = np.flatnonzero(self.near(origins, e))
        if len(near):
            omega = spherical_triangle_solid_angle(rows(self.corners64, e[near])
                                                   - rows(origins, near).astype(np.float64)[:, None, :])
            p_light[near] = self.power_prob[e[near]] / np.maximum(omega, 1e-300)
        return p_light

    def emission_hits(self, origins, d, tri, dist, cos_from, hits, face_normals, pdf_from=None, mis_hook=None):
        """BSDF-sampling half of the MIS estimate for the rays ``hits (k,)`` of a wavefront (from
        a vertex y_k, k >= 1) that hit geometry: ``(lit, values)``, the rays among them that hit
        an emitter's emitting side and their ``L_e · q / (q + p_L)`` (k_lit, 3), to be multiplied
        by ``β w`` (``cos_from``: cos θ of the ray at the vertex it left; q = cos θ / π, see
        :meth:`next_event`; ``face_normals (T, 3)`` float32 of the scene). ``pdf_from`` (k,): the
        density that sampled each ray where it is not the cosine one (glossy vertices; NaN:
        cos θ / π), used as q."""
        none = np.zeros(0, dtype=np.int64), np.zeros((0, 3), np.float32)
        if self.n_triangles == 0:
            return none
        ray = hits[self.triangle_pdf_area[tri[hits]] > 0]
        if len(ray) == 0:
            return none
        t = tri[ray]
        cos_l = -dot(rows(face_normals, t), rows(d, ray))
        cos_l = np.where(self.triangle_two_sided[t], np.abs(cos_l), cos_l)
        lit = np.flatnonzero(cos_l > 0)
        ray, t, cos_l = ray[lit], t[lit], cos_l[lit]
        e = self.triangle_emitter[t]
        p_light = self.light_density(rows(origins, ray), e, dist[ray], cos_l)
        q = cos_from[ray] * INV_PI
        if pdf_from is not None:
            p = pdf_from[ray]
            q = np.where(np.isnan(p), q, p).astype(q.dtype, copy=False)
        weight = q / (q + p_light)
        if mis_hook is not None:
            weight = weight * mis_hook(ray, e, p_light, q)
        return ray, rows(self.triangle_emission32, t) * weight[:, None]
