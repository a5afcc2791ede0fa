"""Hemisphere warps and strata (thesis 3.1.1, Figure 2; Shirley & Chiu 1997).

The unit square is mapped to the unit disk by Shirley–Chiu's concentric map (area preserving up
to the constant π) and the disk to the upper hemisphere by the equal-area (Lambert azimuthal)
lift ``z = 1 - r^2``, ``(x, y) *= sqrt(2 - r^2)``. The composition maps equal areas of the square
to equal solid angles, so a regular ``strata_u x strata_v`` grid on the square gives strata of
solid angle exactly ``2π / S`` each (S = strata_u * strata_v).

Stratum ``k = iu * strata_v + iv`` covers ``u in [iu, iu+1)/strata_u`` and
``v in [iv, iv+1)/strata_v``. Local directions have the surface normal along +z; world
directions use the orthonormal frame of :func:`tangent_frame`.
"""
import functools

import numpy as np

QUARTER_PI = np.pi / 4.0


def concentric_square_to_disk(u, v):
    """Shirley–Chiu concentric map of ``u, v in [0,1]`` to the unit disk; returns ``x, y``."""
    a = 2.0 * np.asarray(u, dtype=np.float64) - 1.0
    b = 2.0 * np.asarray(v, dtype=np.float64) - 1.0
    use_a = np.abs(a) > np.abs(b)
    r = np.where(use_a, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(use_a, QUARTER_PI * (b / a), 2 * QUARTER_PI - QUARTER_PI * (a / b))
    phi = np.where(r == 0, 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


def concentric_disk_to_square(x, y):
    """Inverse of :func:`concentric_square_to_disk`; returns ``u, v in [0,1]``."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    r = np.hypot(x, y)
    phi = np.arctan2(y, x)
    phi = np.where(phi < -QUARTER_PI, phi + 2 * np.pi, phi)  # phi in [-π/4, 7π/4)
    sector = np.floor((phi + QUARTER_PI) / (2 * QUARTER_PI)).astype(np.int64)  # 0..3
    sector = np.clip(sector, 0, 3)
    # Sector 0: a = r, b = phi*r/(π/4); 1: b = r, a = -(phi-π/2)*r/(π/4);
    # 2: a = -r, b = -(phi-π)*r/(π/4); 3: b = -r, a = (phi-3π/2)*r/(π/4).
    t = (phi - sector * 2 * QUARTER_PI) / QUARTER_PI  # in [-1, 1)
    a = np.select([sector == 0, sector == 1, sector == 2, sector == 3], [r, -t * r, -r, t * r])
    b = np.select([sector == 0, sector == 1, sector == 2, sector == 3], [t * r, r, -t * r, -r])
    return np.clip(0.5 * (a + 1.0), 0.0, 1.0), np.clip(0.5 * (b + 1.0), 0.0, 1.0)


def square_to_hemisphere(u, v):
    """Equal-area map of the unit square to the upper hemisphere; returns ``(..., 3)`` unit vectors."""
    x, y = concentric_square_to_disk(u, v)
    r2 = x * x + y * y
    s = np.sqrt(np.maximum(2.0 - r2, 0.0))
    return np.stack([x * s, y * s, 1.0 - r2], axis=-1)


def hemisphere_to_square(d):
    """Inverse of :func:`square_to_hemisphere` for local directions ``d (..., 3)`` with z >= 0."""
    d = np.asarray(d, dtype=np.float64)
    z = np.clip(d[..., 2], 0.0, 1.0)
    s = np.sqrt(1.0 + z)  # sqrt(2 - r^2) with r^2 = 1 - z
    return concentric_disk_to_square(d[..., 0] / s, d[..., 1] / s)


def stratum_of_local_direction(d, strata_u, strata_v):
    """Stratum index of local directions ``d (..., 3)``; -1 below the horizon (z <= 0).

    The inverse of the concentric map with one arctangent of a ratio in [-1, 1] (no ``arctan2``
    and no four-way select; the build and the tracer call it for every shadow ray and vertex):
    for a disk point (x, y) with |x| >= |y|, ``a = sign(x) r`` and ``b = a (4/π) atan(y/x)``;
    otherwise ``b = sign(y) r`` and ``a = b (4/π) atan(x/y)``.
    """
    d = np.asarray(d)
    z = d[..., 2]
    s = np.sqrt(1.0 + np.maximum(z, 0.0))
    x = d[..., 0] / s
    y = d[..., 1] / s
    r = np.sqrt(x * x + y * y)
    xa = np.abs(x) >= np.abs(y)
    num = np.where(xa, y, x)
    den = np.where(xa, x, y)
    t = np.arctan(num / np.where(den != 0, den, 1.0)) * (4.0 / np.pi)
    major = np.where(den >= 0, r, -r)
    a = np.where(xa, major, major * t)
    b = np.where(xa, major * t, major)
    iu = np.clip(((a + 1.0) * 0.5 * strata_u).astype(np.int64), 0, strata_u - 1)
    iv = np.clip(((b + 1.0) * 0.5 * strata_v).astype(np.int64), 0, strata_v - 1)
    return np.where(z > 0, iu * strata_v + iv, -1)


def stratum_square_samples(strata, jitter_u, jitter_v, strata_u, strata_v):
    """Points of the unit square inside stratum ``strata`` at offsets ``jitter in [0,1)``."""
    strata = np.asarray(strata)
    iu = strata // strata_v
    iv = strata % strata_v
    return (iu + jitter_u) / strata_u, (iv + jitter_v) / strata_v


def stratum_centers(strata_u, strata_v):
    """(S, 3) local central direction of each stratum (image of the cell centre)."""
    k = np.arange(strata_u * strata_v)
    u, v = stratum_square_samples(k, 0.5, 0.5, strata_u, strata_v)
    return square_to_hemisphere(u, v)


def stratum_solid_angle(strata_u, strata_v):
    """Solid angle of every stratum, ``2π / S`` steradians (equal-area map)."""
    return 2.0 * np.pi / (strata_u * strata_v)


def stratum_cosine_weights(strata_u, strata_v, resolution=None):
    """Projected solid angle of each stratum over π: ``w_k = ∫_k cos θ dω / π`` (sums to 1).

    This is the passive-dynamics mass a Lambertian BRDF·cos (eq. 3.1) puts into stratum k.
    On the square, ``cos θ = 1 - r^2`` with ``r = max(|2u-1|, |2v-1|)`` (concentric radius) and
    ``dω = 2π du dv``, so ``w_k = 2 ∫∫_cell (1 - max(a², b²)) du dv``; integrated with a fine
    midpoint rule (relative error < 1e-6) and renormalised to sum exactly to 1. Computed once
    per grid and copied out.
    """
    return _stratum_cosine_weights(int(strata_u), int(strata_v), resolution).copy()


@functools.lru_cache(maxsize=32)
def _stratum_cosine_weights(strata_u, strata_v, resolution):
    if resolution is None:
        resolution = max(64, int(np.ceil(2048 / max(strata_u, strata_v))))
    s = (np.arange(resolution) + 0.5) / resolution
    weights = np.empty((strata_u, strata_v))
    for iu in range(strata_u):  # loop over strata (tens), not over rays
        a = 2.0 * (iu + s) / strata_u - 1.0
        for iv in range(strata_v):
            b = 2.0 * (iv + s) / strata_v - 1.0
            m = np.maximum(a[:, None] ** 2, b[None, :] ** 2)
            weights[iu, iv] = np.mean(1.0 - m)
    weights = weights.reshape(-1)
    return weights / weights.sum()


def tangent_frame(n):
    """Orthonormal frame ``(t, b, n)`` for unit normals ``n (..., 3)`` (Duff et al. 2017).

    Deterministic in n: equal normals get equal frames, so strata of coplanar points coincide.
    Returns an array ``(..., 3, 3)`` whose rows are t, b, n.
    """
    n = np.asarray(n, dtype=np.float64)
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t = np.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=-1)
    bt = np.stack([b, sign + ny * ny * a, -ny], axis=-1)
    return np.stack([t, bt, n], axis=-2)


def local_to_world(d_local, frames):
    """Rotate local directions ``(..., 3)`` by frames ``(..., 3, 3)`` (rows t, b, n)."""
    return np.einsum("...i,...ij->...j", d_local, frames)


def world_to_local(d_world, frames):
    """Express world directions in the frames' (t, b, n) coordinates."""
    return np.einsum("...ij,...j->...i", frames, d_world)
