"""RESIDUAL: the solved LMDP as a control variate of the texel's first bounce (unbiased).

For a texel point x the bake estimates ``I(x) = E[f(ω, r)]``, f the path estimate of
:class:`~lmdp_addon.bake.tracer.IndirectTracer` along a cosine-distributed first direction ω
(r: the path's other random numbers). At the first hit y_1 the path's throughput is
``β_1 = ρ(y_1)`` (cosine sampling: ``w_0 = 1``) and it samples the direct light there by
next-event estimation, ``D̂(y_1)``. The control variate is what FINAL_GATHER would return along
the same first direction with the same light sample,

    g(ω, r) = β_1 (D̂(y_1) + ẑ_ind(y_1)),

ẑ_ind the PHYSICAL solution's indirect irradiance/π interpolated at y_1
(:class:`~lmdp_addon.bake.gather.GatherField`, 0 where the gather has no state near, at back
faces and at hits closer than half a state spacing). The estimate of a batch of a texel is

    Î = (1/M) Σ_m g(ω_m, r_m)  +  (1/N) Σ_n [f(ω_n, r_n) − g(ω_n, r_n)],            (control variate, c = 1)

with M = ``CONTROL_RATIO`` x N *control samples* (one closest hit, one shadow ray and a table
lookup each, :meth:`ControlVariate.samples`) and N full paths that also record their own g on
the same random numbers. Both sums are unbiased for their means whatever g is (E[g] is estimated
by its own samples, never read from the solution), so Î is unbiased for I(x); the solution only
decides how much of f's variance is left to the expensive paths: the residual f − g is the
light of the path's bounces after y_1 minus its prediction β_1 ẑ_ind(y_1) (the direct light at
y_1 cancels exactly).

Both sample sets have the same distribution: the same footprint points (the texel point carries
the same weight in both, see :func:`control_footprint`), stratified first directions
(``sampling.stratified_first_uniforms`` over each set) and the tracer's own first vertex and
next-event estimation (``IndirectTracer.trace(..., control_out=..., first_hit_only=True)``).
"""
import numpy as np

from ..sampling import stratified_first_uniforms
from .texels import sample_footprint
from .tracer import TraceStats

#: Control samples per full path (M / N). A control sample costs one closest hit and one shadow
#: ray, a full path several of each; 2 was the most efficient measured (docs/design.md, "RESIDUAL").
CONTROL_RATIO = 2


class ControlVariate:
    """The control variate g at a path's first hit (module docstring) from ``gather``, a
    :class:`~lmdp_addon.bake.gather.GatherField` of the PHYSICAL solution."""

    def __init__(self, gather, ratio=None):
        self.gather = gather
        self.ratio = int(CONTROL_RATIO if ratio is None else ratio)

    def indirect_at(self, tri, bu, bv, pos, gnrm, front, objs, dist):
        """ẑ_ind (k, 3) float32 at first hits (0 where the gather cannot serve the hit:
        no compatible state near, back faces, hits closer than half a state spacing)."""
        z = self.gather.value_at(tri, bu, bv, pos, gnrm, front, objs)
        usable = ~np.isnan(z[:, 0]) & ~self.gather.too_close(dist, objs)
        return np.where(usable[:, None], z, 0.0).astype(np.float32)

    def samples(self, tracer, ts, triangles, per_batch, first_batch, rng):
        """``(Σ g (n_texels, 3) float64, TraceStats)`` over ``ratio x per_batch`` control samples for the
        texels ``ts`` (a ``TexelSet``; ``triangles``: their scene triangles) in one batch;
        ``first_batch``: the bake's batch 0 (it holds the texel point, :func:`control_footprint`).
        Traced in ``ratio`` slices of ``per_batch`` samples per texel (bounded memory)."""
        n_tex = len(ts)
        M = self.ratio * per_batch
        fp = control_footprint(ts, per_batch, self.ratio, rng, first_batch)
        u, _ = stratified_first_uniforms(n_tex, M, rng)
        total = np.zeros((n_tex, 3), np.float64)
        stats = TraceStats()
        tris = np.repeat(triangles, per_batch)
        for c in range(self.ratio):
            cols = slice(c * per_batch, (c + 1) * per_batch)
            k = n_tex * per_batch
            g = np.zeros((k, 3), np.float32)
            _, st = tracer.trace(fp.position[:, cols].reshape(k, 3), fp.normal[:, cols].reshape(k, 3),
                         np.full(k, -1), u[:, cols].reshape(k, 2), np.zeros(k), rng, triangles=tris,
                         control_out=g, first_hit_only=True)
            total += g.reshape(n_tex, per_batch, 3).sum(axis=1, dtype=np.float64)
            stats.add(st)
        return total, stats


def control_footprint(ts, per_batch, ratio, rng, first_batch):
    """The footprint points of ``ratio x per_batch`` control samples per texel
    (``texels.sample_footprint``). In the bake's first batch the paths' sample 0 is the texel
    point (weight 1/N); the control samples give it the same weight with their first ``ratio``
    samples (``ratio`` / M = 1/N), so both sets average g over the same distribution."""
    fp = sample_footprint(ts, ratio * per_batch, rng, include_center=first_batch)
    if first_batch and ratio > 1:
        fp.position[:, 1:ratio] = fp.position[:, :1]
        fp.normal[:, 1:ratio] = fp.normal[:, :1]
        fp.barycentric[:, 1:ratio] = fp.barycentric[:, :1]
    return fp

