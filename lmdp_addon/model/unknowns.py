"""The LMDP's unknowns: one per Lambertian point, one per (point, outgoing stratum) on glossy points.

The thesis's state is the pair (point x, stratum k) (3.1.1). On a Lambertian point every
stratum has the same row of the passive dynamics (eq. 3.1 does not depend on the outgoing
direction), so its S states collapse into one unknown z(x). On a glossy point (a material with a
microfacet lobe, ``SceneArrays.materials``) the row depends on the outgoing direction: the point
keeps S unknowns z(x, k), the outgoing radiance of x towards the centre of its stratum k
(PHYSICAL mode). :class:`UnknownMap` is the index map every consumer uses: unknowns are ordered
by point, a glossy point's S unknowns adjacent in stratum order. A scene without glossy points
has exactly one unknown per point, index = point; so has a grid of one stratum, where a glossy
point keeps the hemispherical albedo of its BSDF (``bsdf.lambertian_albedo``).
"""
import functools

import numpy as np

from .hemisphere import stratum_of_local_direction


class UnknownMap:
    """Point -> unknowns of the LMDP.

    glossy          (m,) bool: the point carries S directional unknowns (none when S = 1)
    strata_u, strata_v  the Shirley–Chiu grid of the strata (``StateSpace``); S = strata_u * strata_v
    first           (m,) int64 index of each point's first unknown
    count           (m,) int64 1 (Lambertian) or S (glossy)
    n_unknowns      N = Σ count
    point           (N,) int64 the point of each unknown
    stratum         (N,) int64 the outgoing stratum of each unknown (-1: a Lambertian point's)
    """

    def __init__(self, glossy, strata_u, strata_v):
        self.strata_u, self.strata_v = int(strata_u), int(strata_v)
        self.n_strata = self.strata_u * self.strata_v
        # one stratum resolves no direction: glossy points then keep one (Lambertian) unknown
        self.glossy = np.asarray(glossy, dtype=bool).reshape(-1) & (self.n_strata > 1)
        self.count = np.where(self.glossy, self.n_strata, 1).astype(np.int64)
        self.first = (np.cumsum(self.count) - self.count).astype(np.int64)
        self.n_unknowns = int(self.count.sum())
        self.point = np.repeat(np.arange(len(self.glossy), dtype=np.int64), self.count)
        self.stratum = np.where(self.glossy[self.point], np.arange(self.n_unknowns) - self.first[self.point], -1)

    @property
    def n_points(self):
        return len(self.glossy)

    @property
    def identity(self):
        """True when every point has one unknown (no glossy point): unknown index = point index."""
        return self.n_unknowns == self.n_points

    @property
    def n_glossy(self):
        return int(np.count_nonzero(self.glossy))

    @functools.cached_property
    def glossy_points(self):
        """(G,) indices of the glossy points."""
        return np.flatnonzero(self.glossy)

    def columns(self, points, local_out):
        """Unknown of landing on ``points (k,)`` from local directions ``local_out (k, 3)``: the
        direction from the landing point back to where the ray came from (the reversed ray) in
        the point's frame. Lambertian points: their one unknown; glossy points: the unknown of
        the stratum containing that direction (clamped to the horizon, where a grazing ray meets
        a slightly tilted state)."""
        points = np.asarray(points, dtype=np.int64)
        out = self.first[points]
        g = np.flatnonzero(self.glossy[points])
        if len(g):
            d = np.array(local_out[g], dtype=np.float64)
            d[:, 2] = np.maximum(d[:, 2], 1e-7)
            out[g] += np.maximum(stratum_of_local_direction(d, self.strata_u, self.strata_v), 0)
        return out

    def point_values(self, values, weights):
        """(m, C) per-point values of ``values (N, C)``: a Lambertian point's own; a glossy
        point's mean over its strata with ``weights (S,)`` (the strata's cosine masses w_k: the
        radiosity-equivalent B/π of its directional radiance)."""
        values = np.asarray(values, dtype=np.float64)
        if self.identity:
            return values
        out = values[self.first].copy()
        g = self.glossy_points
        if len(g):
            S = self.n_strata
            block = values[self.first[g][:, None] + np.arange(S)[None, :]]      # (G, S, C)
            out[g] = np.einsum("gsc,s->gc", block, np.asarray(weights, dtype=np.float64))
        return out

    def point_log_values(self, log_values, weights):
        """:meth:`point_values` of ``exp(log_values)`` kept in logs (exact where z underflows)."""
        log_values = np.asarray(log_values, dtype=np.float64)
        if self.identity:
            return log_values
        out = log_values[self.first].copy()
        g = self.glossy_points
        if len(g):
            S = self.n_strata
            block = log_values[self.first[g][:, None] + np.arange(S)[None, :]]  # (G, S, C)
            top = np.max(block, axis=1, keepdims=True)
            safe = np.where(np.isfinite(top), top, 0.0)
            with np.errstate(divide="ignore"):
                s = np.log(np.einsum("gsc,s->gc", np.exp(block - safe), np.asarray(weights, dtype=np.float64)))
            out[g] = np.where(np.isfinite(top[:, 0]), s + safe[:, 0], -np.inf)
        return out

    def point_max(self, values):
        """(m,) the largest of each point's unknowns' ``values (N,)`` (e.g. residuals)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if self.identity or len(values) == 0:
            return values
        return np.maximum.reduceat(values, self.first)


def identity_map(n_points, strata_u, strata_v):
    """The map of ``n_points`` Lambertian points (one unknown each)."""
    return UnknownMap(np.zeros(int(n_points), dtype=bool), strata_u, strata_v)
