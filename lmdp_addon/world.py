"""The world seen by escaping rays: an equirectangular environment map and its importance sampling.

A world that is not uniform (an HDRI in an Environment Texture node, or any world tree rendered
into an equirectangular table by the Blender layer) is an :class:`EnvironmentMap`:
``radiance (H, W, 3)`` float32 W / (sr m²) per channel, in Cycles' equirectangular convention
(``direction_to_equirectangular``, kernel/geom/... "Equirectangular coordinates"):

    u = (π - atan2(d_y, d_x)) / 2π,     v = 1 - acos(d_z) / π,                       (1)

for the *map* direction ``d = R ω`` of a world direction ω (``R``: the Mapping node's rotation,
identity without one). Row 0 of the table is the bottom of the image (v ∈ [0, 1/H)), as Blender
stores pixels, so +x looks at the image's centre column, +z at its top row. Radiance between
pixel centres is bilinear (Cycles' default ``Linear`` interpolation, periodic in u and v) or the
nearest pixel (``Closest``).

Importance sampling (pbrt's ``PiecewiseConstant2D``, Cycles' background map): pixel (i, j) is
chosen with probability ∝ ``m_ij · sin θ_i`` (θ_i at the row's centre, m_ij the mean over the
pixel of the interpolated max-channel radiance, so every direction with radiance can be drawn),
and a point uniform in it. With θ = π (1 - v), φ = π - 2π u, ``dω = 2π² sin θ du dv``, so the density per
steradian is exact:

    p(ω) = P(i, j) · W H / (2π² sin θ(ω)).                                            (2)

The bake combines these samples with the rays its BSDF sampling sends to the world by the
balance heuristic (``bake/tracer``, as Cycles' world MIS does); the build sends escaping rays to
a world terminal per direction bin (:func:`bin_of_direction`: an equal-area grid of
:data:`WORLD_BINS_Z` x :data:`WORLD_BINS_PHI` bins in cos θ and φ of the world frame), whose
desirability is the map's mean radiance over the bin (:meth:`EnvironmentMap.bin_radiance`).
"""
from dataclasses import dataclass, field

import numpy as np

from .transparency import reaches

TWO_PI_SQUARED = 2.0 * np.pi * np.pi
LUMINANCE32 = np.array([0.2126, 0.7152, 0.0722], np.float32)
#: Equal-area world bins of the LMDP's directional world terminal: bands of equal cos θ times
#: sectors of equal φ (each 4π / (Z Φ) sr).
WORLD_BINS_Z = 4
WORLD_BINS_PHI = 8
INTERPOLATIONS = ("LINEAR", "CLOSEST")


@dataclass
class EnvironmentMap:
    """An equirectangular world (module docstring, eq. 1).

    radiance       (H, W, 3) float32 radiance (W / sr m²), row 0 at the bottom (v = 0)
    rotation       (3, 3) float64: the map direction of a world direction ω is ``rotation @ ω``
    interpolation  'LINEAR' (bilinear, Cycles' default) or 'CLOSEST'
    name           what the map came from (for messages): "World 'X' / image 'city.exr'"
    """

    radiance: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    interpolation: str = "LINEAR"
    name: str = ""

    def __post_init__(self):
        self.radiance = np.ascontiguousarray(np.nan_to_num(np.asarray(self.radiance, dtype=np.float32),
                                                           nan=0.0, posinf=0.0, neginf=0.0))
        if self.radiance.ndim != 3 or self.radiance.shape[2] != 3 or min(self.radiance.shape[:2]) < 1:
            raise ValueError(f"environment radiance must be (H, W, 3), not {self.radiance.shape}")
        self.radiance = np.maximum(self.radiance, 0.0)
        self.rotation = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, not {self.interpolation!r}")
        H, W = self.radiance.shape[:2]
        self.height, self.width = H, W
        # pixel weights ∝ max-channel radiance · sin θ at the row centre (eq. 2)
        theta = np.pi * (1.0 - (np.arange(H) + 0.5) / H)
        self.row_sin = np.sin(theta)
        weight = _pixel_means(self.radiance.max(axis=2).astype(np.float64), self.interpolation) \
            * self.row_sin[:, None]
        total = weight.sum()
        self.lit = bool(total > 0)
        self.pixel_prob = (weight / total).ravel() if self.lit else np.zeros(H * W)
        self.cdf = np.cumsum(self.pixel_prob)
        if self.lit:
            self.cdf /= self.cdf[-1]

    # ---- values ----------------------------------------------------------------------------------
    def mean_radiance(self):
        """(3,) float64 mean radiance over the sphere, (1/4π) ∫ L dω (rows weighted by the solid
        angle of their band, exactly: ``2π/W (cos θ_top - cos θ_bottom)`` per pixel)."""
        H = self.height
        edges = np.cos(np.pi * (1.0 - np.arange(H + 1) / H))        # cos θ at the row edges, bottom first
        band = np.abs(np.diff(edges))                               # ∫ sin θ dθ of each row
        return (self.radiance.astype(np.float64) * band[:, None, None]).sum(axis=(0, 1)) / (2.0 * self.width)

    def fingerprint_arrays(self):
        """The arrays that define this world (for scene fingerprints)."""
        return (self.radiance, self.rotation, np.frombuffer(self.interpolation.encode(), np.uint8))

    def map_uv(self, directions):
        """``(u, v)`` (k,) float64 of world ``directions (k, 3)`` (eq. 1; float64: the pixel of
        a direction drawn by :meth:`sample` is the pixel it was drawn in, so the two halves of
        the MIS estimate see the same pdf)."""
        d = np.asarray(directions, dtype=np.float64) @ self.rotation.T
        norm = np.sqrt(np.einsum("ij,ij->i", d, d))
        z = np.clip(d[:, 2] / np.where(norm > 0, norm, 1.0), -1.0, 1.0)
        u = (np.pi - np.arctan2(d[:, 1], d[:, 0])) * (0.5 / np.pi)
        v = 1.0 - np.arccos(z) * (1.0 / np.pi)
        return u, v

    def radiance_at(self, directions):
        """(k, 3) float32 radiance seen along world ``directions (k, 3)``."""
        u, v = self.map_uv(directions)
        return self._lookup(u, v)

    def _lookup(self, u, v):
        """(k, 3) float32 radiance at map coordinates ``u, v`` (k,): the pixel (CLOSEST) or the
        bilinear blend of the four pixel centres about it (LINEAR; rows and columns wrap), read
        from the flattened map by row-major pixel numbers."""
        H, W = self.height, self.width
        flat = self.radiance.reshape(H * W, 3)
        if self.interpolation == "CLOSEST":
            j = np.floor(u * W).astype(np.int64) % W
            i = np.clip(np.floor(v * H).astype(np.int64), 0, H - 1)
            return np.take(flat, i * W + j, axis=0)
        x = u * W - 0.5
        y = v * H - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0).astype(np.float32)[:, None], (y - y0).astype(np.float32)[:, None]
        j0, i0 = x0.astype(np.int64) % W, y0.astype(np.int64) % H
        j1, i1 = j0 + 1, i0 + 1
        j1[j1 == W] = 0
        i1[i1 == H] = 0
        r0, r1 = i0 * W, i1 * W
        a, b = np.take(flat, r0 + j0, axis=0), np.take(flat, r0 + j1, axis=0)
        c, e = np.take(flat, r1 + j0, axis=0), np.take(flat, r1 + j1, axis=0)
        top = a + fx * (b - a)
        return top + fy * ((c + fx * (e - c)) - top)

    # ---- importance sampling ---------------------------------------------------------------------
    def pdf(self, directions, regions=None):
        """(k,) float32 density per steradian with which :meth:`sample` draws world
        ``directions (k, 3)`` (eq. 2; 0 where the map is black; ``regions`` ignored, as in
        :meth:`sample`)."""
        u, v = self.map_uv(directions)
        return self._pdf_uv(u, v)

    def _pdf_uv(self, u, v, pixel=None):
        H, W = self.height, self.width
        pixel = self.pixel_of_uv(u, v) if pixel is None else pixel
        sin_theta = np.sin(np.pi * (1.0 - v))
        p = self.pixel_prob[pixel] * (W * H / TWO_PI_SQUARED) / np.maximum(sin_theta, 1e-20)
        return np.where(sin_theta > 0, p, 0.0).astype(np.float32)

    def sample(self, r, regions=None):
        """Directions by the map's radiance: ``r (k, 3)`` uniforms in [0, 1) -> ``(directions
        (k, 3) float32 world space, pdf (k,) float32 per steradian, radiance (k, 3) float32)``
        (eq. 2; an all-black map gives pdf 0). ``regions`` is ignored: the same density
        everywhere (``bake.portals.PortalSampler`` takes it)."""
        r = np.asarray(r)
        k = len(r)
        if not self.lit or k == 0:
            return np.zeros((k, 3), np.float32), np.zeros(k, np.float32), np.zeros((k, 3), np.float32)
        # the pixels by the CDF, the uniforms searched in increasing order (the same pixels; the
        # binary searches then share their cache lines: 3x faster on a 1024 x 512 map)
        order = np.argsort(r[:, 0])
        pixel = np.empty(k, np.int64)
        pixel[order] = np.minimum(np.searchsorted(self.cdf, r[order, 0], side="right"), self.height * self.width - 1)
        d, p, L, _ = self.pixel_directions(pixel, r[:, 1], r[:, 2])
        return d, p, L

    def pixel_directions(self, pixel, r1, r2):
        """``(directions (k, 3) float32, pdf (k,) float32, radiance (k, 3) float32, pixel)``:
        points uniform in the map's pixels ``pixel (k,)`` (row-major numbers; ``r1, r2`` (k,)
        uniforms across and up the pixel) as world directions, with the density eq. 2 and the
        radiance there."""
        H, W = self.height, self.width
        i, j = pixel // W, pixel % W
        u = (j + r1) / W
        v = (i + r2) / H
        theta = np.pi * (1.0 - v)
        phi = np.pi - 2.0 * np.pi * u
        s = np.sin(theta)
        d_map = np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=1)
        d = (d_map @ self.rotation).astype(np.float32)     # R^-1 = R^T: back to the world frame
        p = np.where(s > 0, self.pixel_prob[pixel] * (W * H / TWO_PI_SQUARED) / np.maximum(s, 1e-20), 0.0)
        return d, p.astype(np.float32), self._lookup(u, v), pixel

    def pixel_of_uv(self, u, v):
        """(k,) int64 row-major pixel number of map coordinates ``u, v`` (k,) (the pixel whose
        density :meth:`pdf` reads)."""
        H, W = self.height, self.width
        j = np.minimum(np.floor(u * W).astype(np.int64), W - 1) % W
        i = np.clip(np.floor(v * H).astype(np.int64), 0, H - 1)
        return i * W + j

    # ---- the LMDP's directional world terminal -----------------------------------------------------
    def bin_radiance(self, per_side=16):
        """(B, 3) float64 mean radiance of the map over each world bin (:func:`bin_of_direction`),
        from a ``per_side`` x ``per_side`` grid of equal-area points in each bin."""
        Z, F = WORLD_BINS_Z, WORLD_BINS_PHI
        s = (np.arange(per_side) + 0.5) / per_side
        iz, ip, a, b = np.meshgrid(np.arange(Z), np.arange(F), s, s, indexing="ij")
        z = 1.0 - 2.0 * (iz + a) / Z
        phi = 2.0 * np.pi * (ip + b) / F
        rho = np.sqrt(np.maximum(1.0 - z * z, 0.0))
        d = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=-1).reshape(-1, 3)
        values = self.radiance_at(d).astype(np.float64).reshape(Z * F, per_side * per_side, 3)
        return values.mean(axis=1)


def _pixel_means(values, interpolation):
    """(H, W) mean of the interpolated ``values (H, W)`` over each pixel: the pixels themselves
    for 'CLOSEST'; for 'LINEAR' the separable filter (1/8, 3/4, 1/8) (the integral of the
    bilinear tents over a pixel; periodic in u and v as the lookup), so that the sampling
    density is positive wherever the bilinear radiance is."""
    if interpolation == "CLOSEST":
        return values
    out = 0.75 * values + 0.125 * (np.roll(values, 1, axis=1) + np.roll(values, -1, axis=1))
    return 0.75 * out + 0.125 * (np.roll(out, 1, axis=0) + np.roll(out, -1, axis=0))


def world_bin_count(environment):
    """Number of world terminals of the LMDP: 1 for a uniform world (``environment`` None)."""
    return 1 if environment is None else WORLD_BINS_Z * WORLD_BINS_PHI


def bin_of_direction(directions):
    """(k,) int64 equal-area world bin of unit world ``directions (k, 3)``: band
    ``floor((1 - z) Z / 2)`` of cos θ, sector ``floor(φ Φ / 2π)`` of φ = atan2(y, x) in [0, 2π)."""
    d = np.asarray(directions)
    Z, F = WORLD_BINS_Z, WORLD_BINS_PHI
    band = np.clip(np.floor((1.0 - d[:, 2]) * (Z / 2.0)).astype(np.int64), 0, Z - 1)
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi)
    sector = np.clip(np.floor(phi * (F / (2.0 * np.pi))).astype(np.int64), 0, F - 1)
    return band * F + sector


# ---- the bake: next-event estimation of the world and the escaping rays' MIS weight ------------------

def next_event(environment, points, normals, rng, caster, lift, geometric=None, mis=True, transparency=None,
               bsdf=None, regions=None, record=None):
    """``(values (k, 3) float32, shadow rays)``: the world-sampling half of the MIS estimate of
    the world's direct light D_w(y) = (1/π) ∫ L_env(ω) cos θ V(y, ω) dω at surface points
    ``points (k, 3)`` with (shading) ``normals`` of the lit side: one direction by
    :meth:`EnvironmentMap.sample` and a shadow ray to infinity from the point lifted by
    ``lift (k,)`` along ``geometric`` (the geometric normals; None: ``normals``), weighted
    ``L q / (p + q)`` with ``q = cos θ / π`` (balance heuristic, Veach 1997; the escaping
    rays' half is :func:`escape_weight`) or ``L q / p`` with ``mis=False`` (the whole of D_w
    by world sampling, for paths that end at y). Directions below the geometric surface give 0,
    as the tracer's BSDF sampling absorbs them; ``transparency`` (or None) lets the shadow rays
    through cut-outs with ∏ (1 − alpha); at the points of ``bsdf`` (``bsdf.GlossyRows``, or None)
    the value is ``L f cos / (p + p_bsdf)`` with their BSDF's f cos and density.
    ``environment``: the :class:`EnvironmentMap`, or a sampler of its light with the same
    ``sample`` / ``pdf`` / ``radiance_at`` whose density depends on the points' ``regions`` (k,)
    (``bake.portals.PortalSampler``). ``record(rows, directions, values)``: receives the rows
    whose sample was above the surface, their directions and the world-sampling estimate alone
    ``L cos / (π p)`` of each, 0 where occluded (``bake.portals.PortalProbe``)."""
    k = len(points)
    out = np.zeros((k, 3), np.float32)
    if k == 0 or not environment.lit:
        return out, 0
    d, p, L = environment.sample(rng.random((k, 3)), regions)
    cos = np.einsum("ij,ij->i", normals, d)
    g = normals if geometric is None else geometric
    valid = (cos > 0) & (p > 0)
    if geometric is not None:
        valid &= np.einsum("ij,ij->i", geometric, d) > 0
    ok = np.flatnonzero(valid)
    if len(ok) == 0:
        return out, 0
    if record is not None:
        seen_value = np.zeros(len(ok), np.float32)
    origin = points[ok] + np.asarray(lift, dtype=np.float32)[ok, None] * g[ok]
    if transparency is None:
        blocked = caster.occluded(origin, d[ok], np.full(len(ok), np.inf, np.float32))
        vis, passed = ok[~blocked], None
    else:
        T = transparency.transmittance(caster, origin, d[ok], np.full(len(ok), np.inf, np.float32))
        seen = reaches(T)
        vis, passed = ok[seen], T[seen]
    q = cos[vis] * np.float32(1.0 / np.pi)
    if record is not None:
        at = np.searchsorted(ok, vis)
        seen_value[at] = (L[vis] @ LUMINANCE32) * (q / p[vis])
        if passed is not None:
            seen_value[at] *= passed @ LUMINANCE32 if passed.ndim == 2 else passed
        record(ok, d[ok], seen_value)
    weight = q / (p[vis] + q) if mis else q / p[vis]
    out[vis] = L[vis] * weight[:, None].astype(np.float32)
    if bsdf is not None:
        g = np.flatnonzero(bsdf.mask[vis])
        if len(g):
            f_cos, p_bsdf = bsdf.eval_at(vis[g], d[vis[g]].astype(np.float32))
            denom = p[vis[g]] + (p_bsdf if mis else 0.0)
            out[vis[g]] = L[vis[g]] * (f_cos / denom[:, None]).astype(np.float32)
    if passed is not None:
        out[vis] *= passed if passed.ndim == 2 else passed[:, None]
    return out, len(ok)


def escape_weight(environment, directions, cos_from, pdf_from=None, regions=None):
    """(k, 3) float32 ``L_env(ω) q / (q + p(ω))`` of rays escaping along ``directions (k, 3)``
    from a vertex where their cosine was ``cos_from (k,)`` (q = cos θ / π): the BSDF-sampling
    half of the MIS estimate of :func:`next_event`, to be multiplied by the rays' ``β w``.
    ``pdf_from`` (k,): the density that sampled each ray where it is not the cosine one (glossy
    vertices; NaN: cos θ / π), used as q. ``regions`` (k,): the regions of the vertices the
    rays left, for a sampler whose density depends on them (:func:`next_event`)."""
    q = np.asarray(cos_from, dtype=np.float32) * np.float32(1.0 / np.pi)
    if pdf_from is not None:
        q = np.where(np.isnan(pdf_from), q, pdf_from).astype(np.float32)
    p = environment.pdf(directions, regions)
    w = np.where(q > 0, q / np.maximum(q + p, np.float32(1e-30)), np.float32(0.0))
    return environment.radiance_at(directions) * w[:, None].astype(np.float32)
