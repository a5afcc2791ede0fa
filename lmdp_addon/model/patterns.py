"""Ray patterns of the passive-dynamics build (thesis 3.1.2): where each point's rays go.

Every point takes one pattern of a small pool (point index modulo the pool size), so the warps
run once per pattern instead of once per ray while each point's own samples stay a stratified,
unbiased set:

* :class:`DirectionPatterns`: R directions per hemisphere stratum, BRDF·cos distributed within
  the stratum (the stratum rays);
* :class:`LightPatterns`: K points on the emitters, stratified by area (the shadow rays of the
  next-event estimate), drawn by :class:`~lmdp_addon.lights.EmitterSampler`.
"""
import numpy as np

from .hemisphere import square_to_hemisphere, stratum_square_samples


class DirectionPatterns:
    """A pool of ray patterns, one per point modulo the pool size: R directions per stratum.

    Within stratum k the R directions are drawn independently with density proportional to
    BRDF·cos (by rejection from the uniform-solid-angle cell), so each ray carries exactly
    ``w_k / R`` of the stratum's cosine mass ``w_k = ∫_k cos θ dω / π``: the estimate of
    ``p(x'|x)`` is unbiased and every row of P sums to one exactly.

    local        (pool, S*R, 3) float32 local directions (normal along +z), ordered by stratum
    ray_stratum  (S*R,) stratum of each ray of a pattern
    """

    def __init__(self, strata_u, strata_v, rays_per_stratum, rng, pool=64):
        S, R = strata_u * strata_v, int(rays_per_stratum)
        self.pool = pool
        self.ray_stratum = np.repeat(np.arange(S), R)
        stratum = np.tile(self.ray_stratum, pool)
        # Largest cos θ = 1 - max(a², b²) over each cell, (a, b) = 2(u, v) - 1.
        k = np.arange(S)
        a0, a1 = 2.0 * (k // strata_v) / strata_u - 1.0, 2.0 * (k // strata_v + 1) / strata_u - 1.0
        b0, b1 = 2.0 * (k % strata_v) / strata_v - 1.0, 2.0 * (k % strata_v + 1) / strata_v - 1.0
        a_min = np.where((a0 < 0) & (a1 > 0), 0.0, np.minimum(a0 ** 2, a1 ** 2))
        b_min = np.where((b0 < 0) & (b1 > 0), 0.0, np.minimum(b0 ** 2, b1 ** 2))
        cos_max = 1.0 - np.maximum(a_min, b_min)
        local = np.empty((len(stratum), 3))
        todo = np.arange(len(stratum))
        while len(todo):  # rounds of rejection sampling (a few), vectorised over all rays
            u, v = stratum_square_samples(stratum[todo], rng.random(len(todo)), rng.random(len(todo)),
                                          strata_u, strata_v)
            d = square_to_hemisphere(u, v)
            accept = rng.random(len(todo)) * cos_max[stratum[todo]] < d[:, 2]
            local[todo[accept]] = d[accept]
            todo = todo[~accept]
        self.local = local.reshape(pool, S * R, 3).astype(np.float32)

    def directions(self, frames, point_ids):
        """World directions (len(point_ids) * S * R, 3) for the points with these frames."""
        local = self.local[point_ids % self.pool]          # (n, S*R, 3)
        return np.matmul(local, frames).reshape(-1, 3)      # rows of frames are t, b, n

    def cos_theta(self, point_ids):
        """(len(point_ids) * S * R,) float32 cosine to the normal of every ray of these points."""
        return self.local[point_ids % self.pool][..., 2].reshape(-1)


class LightPatterns:
    """A pool of next-event patterns, one per point modulo the pool size: K points on the
    emitters, stratified by area (``EmitterSampler.stratified``), each pattern with its own
    random shift. As with :class:`DirectionPatterns`, every point's K samples are a stratified
    set of uniform area samples, so its estimate stays unbiased.
    """

    def __init__(self, sampler, per_point, rng, pool=256):
        self.sampler = sampler
        self.pool = pool
        sample = sampler.stratified(pool, per_point, rng)
        self.position = sample.position.reshape(pool, per_point, 3)
        self.triangle_index = sample.triangle_index.reshape(pool, per_point)
        self.single = len(sampler.triangles) == 1

    def of_points(self, point_ids):
        """Emitter points ``(n, K, 3)`` and their emitter-triangle indices ``(n, K)``."""
        p = point_ids % self.pool
        return self.position[p], self.triangle_index[p]

    def cos_emitter(self, omega, triangle_index):
        """Cosine at the emitter of connections ``omega (n, K, 3)`` leaving the receivers; 0 where
        they reach the back of a one-sided emitter."""
        s = self.sampler
        if self.single:  # the common single-quad light: no gathers
            signed = -(omega @ s.normals[0])
            return np.abs(signed) if s.two_sided[0] else np.maximum(signed, 0.0)
        signed = -np.einsum("nki,nki->nk", omega, s.normals[triangle_index])
        return np.where(s.two_sided[triangle_index], np.abs(signed), np.maximum(signed, 0.0))
