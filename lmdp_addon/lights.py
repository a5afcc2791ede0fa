"""Emitters as area lights: stratified sampling of points on emissive triangles and the
geometry term of a connection (next-event estimation), shared by the dynamics and the tracer.

A connection from a receiver x (normal n_x) to an emitter point y (normal n_y) carries

    G(x, y) = cos θ_x · cos θ_y / |y - x|^2,     cos θ_x = n_x · ω,   cos θ_y = -n_y · ω (front),

with ω the unit direction from x to y. Mesh emission is two-sided (Cycles), so there
``cos θ_y = |n_y · ω|``; one-sided emitters (area lights) emit only along +n_y.
With y drawn with area density ``pdf_area``, ``G V / (π pdf_area)`` is an unbiased estimate of
the form factor from x to the emitters (the Lambertian transition mass towards them) and
``L_e G V / pdf_area`` one of the irradiance they cause.
"""
from dataclasses import dataclass

import numpy as np

from .states import GOLDEN


@dataclass
class EmitterSample:
    """Points on emitters: ``position (n, 3)`` and, gathered on demand, ``normal (n, 3)``,
    ``triangle (n,)`` (scene triangle), ``emitter (n,)`` (emitter group), ``radiance (n, 3)``,
    ``two_sided (n,)``; ``pdf_area`` is the (uniform) area density, 1 / total emitter area."""

    position: np.ndarray
    triangle_index: np.ndarray
    sampler: "EmitterSampler"
    pdf_area: float

    @property
    def normal(self):
        return np.take(self.sampler.normals, self.triangle_index, axis=0)

    @property
    def triangle(self):
        return self.sampler.triangles[self.triangle_index]

    @property
    def emitter(self):
        return self.sampler.emitter_of_triangle[self.triangle_index]

    @property
    def radiance(self):
        return self.sampler.radiance[self.triangle_index]

    @property
    def two_sided(self):
        return self.sampler.two_sided[self.triangle_index]


class EmitterSampler:
    """Samples points on all emissive triangles of a scene proportionally to area."""

    def __init__(self, scene):
        self.scene = scene
        tri_emitter, self.emitter_radiance = scene.emitter_groups()
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
        self.radiance = scene.triangle_emission[self.triangles].astype(np.float64)
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
        return EmitterSample(position=pos, triangle_index=k, sampler=self,
                             pdf_area=1.0 / self.total_area)

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


def connection(points, normals, sample):
    """Unit directions, distances and the geometry term G of receiver -> emitter connections.

    Returns ``(omega (n, 3), distance (n,), cos_receiver (n,), G (n,))``; G is 0 where the
    emitter point is below the receiver's horizon or the receiver sees the back of a one-sided
    emitter.
    """
    d = sample.position - points
    dist2 = np.einsum("ij,ij->i", d, d)
    dist = np.sqrt(np.maximum(dist2, 1e-300))
    omega = d / dist[:, None]
    cos_x = np.einsum("ij,ij->i", normals, omega)
    sampler = sample.sampler
    if len(sampler.triangles) == 1:
        cos_y_signed = -(omega @ sampler.normals[0])
        two_sided = bool(sampler.two_sided[0])
    else:
        cos_y_signed = -np.einsum("ij,ij->i", sample.normal, omega)
        two_sided = sample.two_sided
    cos_y = np.where(two_sided, np.abs(cos_y_signed), np.maximum(cos_y_signed, 0.0))
    G = np.where(cos_x > 0, cos_x * cos_y / np.maximum(dist2, 1e-300), 0.0)
    return omega, dist, cos_x, G
