"""Emitters as area lights: stratified sampling of points on emissive triangles, for the next-event
estimates of the passive dynamics (``dynamics.LightPatterns``).

A connection from a receiver x (normal n_x) to an emitter point y (normal n_y) carries

    G(x, y) = cos θ_x · cos θ_y / |y - x|^2,     cos θ_x = n_x · ω,   cos θ_y = -n_y · ω (front),

with ω the unit direction from x to y. Mesh emission is two-sided (Cycles), so there
``cos θ_y = |n_y · ω|``; one-sided emitters (area lights) emit only along +n_y.
With y drawn with area density ``1 / total_area``, ``G V total_area / π`` is an unbiased
estimate of the form factor from x to the emitters (the Lambertian transition mass towards them).
"""
from dataclasses import dataclass

import numpy as np

from .sampling import GOLDEN


@dataclass
class EmitterSample:
    """Points on emitters: ``position (n, 3)`` and the index of each one's triangle among the
    sampler's ``triangles`` (``triangle_index (n,)``)."""

    position: np.ndarray
    triangle_index: np.ndarray


class EmitterSampler:
    """Samples points on all emissive triangles of a scene proportionally to area."""

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

    @property
    def empty(self):
        return len(self.triangles) == 0 or self.total_area <= 0

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

