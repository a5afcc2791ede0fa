"""Rays through transparent surfaces (alpha < 1, ``textures.MaterialShading.alpha``), as Cycles
traces them.

* **Path and build rays** (:meth:`Transparency.intersect`): at a hit on a surface of alpha a the
  ray stops with probability a and passes on unchanged with probability 1 - a (Cycles picks the
  transparent closure with its weight 1 - a, whose sample weight is then 1), so the estimate of
  what the ray finds is unbiased. A ray that would pass more than ``max_bounces`` times
  (Cycles' ``transparent_max_bounces``) is absorbed. The returned distance is measured from the
  original origin, so light-sampling densities (MIS) of an emitter seen through a surface stay
  those of the whole segment.
* **Shadow rays** (:meth:`Transparency.transmittance`): the product of ``1 - a`` over the
  transparent surfaces crossed, 0 at an opaque one or beyond ``max_bounces`` surfaces (Cycles'
  transparent shadows).

Each layer re-traces only the rays that passed (a loop over layers, not over rays). A ray
continues from the hit point rebuilt on the hit triangle and pushed to its far side by the
triangle's ray offset (``raycast``), so it cannot find the same surface again.
"""
import numpy as np

from .sampling import rows

#: ``tri`` of a ray absorbed after more than ``max_bounces`` transparent surfaces.
ABSORBED = -2


def reaches(transmitted):
    """(k,) bool: the shadow rays whose transmittance (:meth:`Transparency.transmittance`,
    (k,) or (k, 3) when tinted) lets some light through."""
    t = np.asarray(transmitted)
    return (t.max(axis=1) if t.ndim == 2 else t) > 0


class Transparency:
    """The transparent triangles of a scene and the ray loops through them."""

    def __init__(self, scene, max_bounces=8):
        self.scene = scene
        self.surface = scene.surface
        self.mask = self.surface.transparent_triangles()
        self.max_bounces = int(max_bounces)
        corners = scene.corners()
        self.c0 = corners[:, 0].astype(np.float32)
        self.e1 = (corners[:, 1] - corners[:, 0]).astype(np.float32)
        self.e2 = (corners[:, 2] - corners[:, 0]).astype(np.float32)
        self.normals = scene.triangle_geometry()[0].astype(np.float32)

    @classmethod
    def of(cls, scene):
        """A :class:`Transparency` for ``scene``, or None when no material has an alpha."""
        surface = getattr(scene, "surface", None)
        if surface is None or not surface.has_alpha:
            return None
        return cls(scene, getattr(surface, "transparent_max_bounces", 8))

    def _far_side(self, caster, tri, bu, bv, d):
        """Points of the hits ``(tri, bu, bv)`` pushed through their surfaces along ``d``."""
        pos = rows(self.c0, tri) + bu[:, None] * rows(self.e1, tri) + bv[:, None] * rows(self.e2, tri)
        n = rows(self.normals, tri)
        side = np.where(np.einsum("ij,ij->i", n, d) > 0, 1.0, -1.0).astype(np.float32)
        lift = caster.offset(tri).astype(np.float32)
        return pos + (side * lift)[:, None] * n

    def intersect(self, caster, origin, d, rng):
        """Closest hits that stop the rays ``origin (k, 3)``, ``d (k, 3)``: ``(tri, dist, bu,
        bv, extra_rays, weight)`` as :meth:`RayCaster.intersect` with barycentrics (``tri`` -1:
        the ray escaped, :data:`ABSORBED`: absorbed), ``dist`` from ``origin``; ``extra_rays``
        the rays traced beyond the first; ``weight (k, 3)`` the product of the tints of the
        surfaces passed (None when no surface is tinted)."""
        origin = np.asarray(origin, dtype=np.float32)
        d = np.asarray(d, dtype=np.float32)
        tri, dist, bu, bv = caster.intersect(origin, d, barycentrics=True)
        tri, dist, bu, bv = tri.copy(), dist.copy(), bu.copy(), bv.copy()
        weight = np.ones((len(tri), 3), np.float32) if self.surface.has_tint else None
        extra = 0
        live = np.arange(len(tri))
        for layer in range(self.max_bounces + 1):
            t = tri[live]
            at = live[(t >= 0) & self.mask[np.maximum(t, 0)]]
            if len(at) == 0:
                break
            alpha = self.surface.alpha(tri[at], bu[at], bv[at])
            passed = at[rng.random(len(at), dtype=np.float32) >= alpha]
            if len(passed) == 0:
                break
            if layer == self.max_bounces:
                tri[passed] = ABSORBED
                dist[passed] = np.inf
                break
            if weight is not None:
                weight[passed] *= self.surface.tint(tri[passed], bu[passed], bv[passed])
            start = self._far_side(caster, tri[passed], bu[passed], bv[passed], d[passed])
            t2, d2, u2, v2 = caster.intersect(start, d[passed], barycentrics=True)
            extra += len(passed)
            dist[passed] = np.where(t2 >= 0, dist[passed] + d2, np.float32(np.inf))
            tri[passed], bu[passed], bv[passed] = t2, u2, v2
            live = passed
        return tri, dist, bu, bv, extra, weight

    def transmittance(self, caster, origin, d, tmax):
        """(k,) float32 fraction of light that reaches ``origin + tmax d`` from along the
        segments (1: unoccluded, 0: blocked; in between: ∏ (1 - alpha) of the transparent
        surfaces crossed); (k, 3) with tinted surfaces: ∏ (1 - alpha) tint, Cycles'
        transparent weight."""
        origin = np.asarray(origin, dtype=np.float32)
        d = np.asarray(d, dtype=np.float32)
        left = np.asarray(tmax, dtype=np.float32).copy()
        tinted = self.surface.has_tint
        T = np.ones((len(origin), 3) if tinted else len(origin), np.float32)
        live = np.flatnonzero(caster.occluded(origin, d, left))   # the unoccluded need no more
        o = origin[live]
        for layer in range(self.max_bounces + 1):
            if len(live) == 0:
                break
            tri, dist, bu, bv = caster.intersect(o, d[live], barycentrics=True)
            hit = (tri >= 0) & (dist < left[live])
            see_through = hit & self.mask[np.maximum(tri, 0)]
            T[live[hit & ~see_through]] = 0.0
            k = np.flatnonzero(see_through)
            if layer == self.max_bounces:
                T[live[k]] = 0.0
                break
            if len(k) == 0:
                break
            passes = 1.0 - self.surface.alpha(tri[k], bu[k], bv[k])
            if tinted:
                T[live[k]] *= passes[:, None] * self.surface.tint(tri[k], bu[k], bv[k])
                k = k[T[live[k]].max(axis=1) > 0]
            else:
                T[live[k]] *= passes
                k = k[T[live[k]] > 0]
            o = self._far_side(caster, tri[k], bu[k], bv[k], d[live[k]])
            left[live[k]] -= dist[k]
            live = live[k]
        return T
