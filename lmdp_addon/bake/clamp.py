"""Cycles' sample clamp (Render Properties > Light Paths > Clamping), applied per light contribution.

Cycles clamps every contribution a path adds to the film, one at a time
(``kernel/film/light_passes.h`` ``film_clamp_light``): a contribution is the path's throughput
times the light found (a light sample after its MIS weight, or the MIS-weighted emission / world
a sampled ray meets), and with ``S = |c_r| + |c_g| + |c_b|``

    c ← c · T / S   where S > T,   T = 3 · sample_clamp_direct    (light reaching x0 directly)
                                   T = 3 · sample_clamp_indirect  (after one bounce or more)

(``scene/integrator.cpp`` stores the limits times 3; 0 turns a limit off). The "bounce" of a
contribution is the number of surface vertices the light met after the start point x0: a light
sample at y_k has bounce k (x0 = y_0), the emission or world found by the ray leaving y_{k-1} has
bounce k - 1 (Cycles' ``path.bounce - 1``). In a bake the throughput starts at 1 at x0 and its
BSDF weight (the diffuse colour ρ(x0) for a cosine-sampled diffuse surface) joins it, so the
clamp sees ρ(x0) times the light even when the DIFFUSE pass is divided by the colour afterwards
(pass_filter without 'COLOR'): the engine's values carry no ρ(x0), hence ``weight``.

A clamp is biased by design: the clamped mean is below the true one wherever a contribution
exceeds its limit, and it depends on the distribution of the per-sample contributions, i.e. on
the sampling strategies (docs/design.md, "Sample clamp").
"""
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError

#: Cycles keeps each limit times 3 (the sum of the three channels is compared).
CHANNELS = 3.0


@dataclass(frozen=True)
class SampleClamp:
    """Cycles' two clamp limits (0: off), as ``sample_clamp_direct`` / ``sample_clamp_indirect``."""

    direct: float = 0.0     #: light reaching the start point x0 directly (bounce 0)
    indirect: float = 0.0   #: light after one bounce or more

    @classmethod
    def from_settings(cls, settings):
        """The clamp of ``settings.clamp_direct`` / ``clamp_indirect`` (negative values: 0)."""
        return cls(max(float(getattr(settings, "clamp_direct", 0.0)), 0.0),
                   max(float(getattr(settings, "clamp_indirect", 0.0)), 0.0))

    @property
    def active(self):
        return self.direct > 0 or self.indirect > 0

    def limit(self, bounce):
        """T of contributions of ``bounce`` (0: direct), ``inf`` when that limit is off."""
        value = self.direct if bounce == 0 else self.indirect
        return CHANNELS * value if value > 0 else np.inf


def clamp_light(light, limit, weight=None):
    """``light (k, 3)`` with every row whose ``Σ_c |weight_c light_c|`` exceeds ``limit`` scaled
    down to it (Cycles' ``film_clamp_light``); ``weight (k, 3)``: the throughput the engine's
    values leave out (ρ(x0)), None for 1. Returns ``(clamped (k, 3), number of rows clamped)``;
    ``light`` itself is returned when no row is over the limit."""
    if not np.isfinite(limit) or len(light) == 0:
        return light, 0
    seen = light if weight is None else light * weight
    total = np.abs(seen).sum(axis=1)
    over = total > limit
    count = int(np.count_nonzero(over))
    if count == 0:
        return light, 0
    scale = np.where(over, np.float32(limit) / np.where(over, total, 1.0), 1.0).astype(light.dtype)
    return light * scale[:, None], count


def clamp_warnings(scene, settings):
    """The ways a clamped bake of ``scene`` with ``settings`` cannot follow Cycles' clamp, one
    message each (none without a clamp): the clamp is a function of each sample, so it matches
    Cycles' only where it sees the samples Cycles would draw (GUIDED: through the ratio of Cycles'
    throughput to the path's, ``tracer._to_cycles``)."""
    clamp = SampleClamp.from_settings(settings)
    if not clamp.active:
        return []
    what = " and ".join(f"{kind} clamp {value:g}" for kind, value in
                        (("direct", clamp.direct), ("indirect", clamp.indirect)) if value > 0)
    out = []
    mode = getattr(settings, "bake_mode", "UNGUIDED")
    if mode == "FINAL_GATHER":
        out.append(f"The sample clamp ({what}) applies to Final Gather's light samples only: the light beyond "
                   "the first bounce comes from the solution as an expected value and is not clamped, so the "
                   "lightmap is brighter than Cycles' clamped bake where Cycles clips those paths "
                   "(Unguided, Guided or Residual clamp as Cycles does)")
    lamps = len(scene.lamps)
    kinds = [name for name, present in (
        ("emissive meshes", bool(np.any(scene.is_emissive()))),
        (f"{lamps} lights" if lamps > 1 else "the light", lamps > 0),
        ("the world", getattr(scene, "environment", None) is not None
         or bool(np.any(np.asarray(scene.world_radiance) > 0)))) if present]
    if len(kinds) > 1 or lamps > 1:
        out.append(f"The sample clamp ({what}) sees the light samples of {' and '.join(kinds)} apart "
                   + ("(one of every light) " if lamps > 1 else "")
                   + "where Cycles draws one sample among all its lights and divides it by that light's "
                   "probability: with several lights the clamped lightmap can differ from Cycles' clamped bake "
                   "(by a few per cent; one light agrees)")
    return out


def check_clamp(settings):
    """Raise :class:`~lmdp_addon.errors.SceneError` naming the setting when a clamp limit is
    negative or not a number (0 is off, as in Cycles)."""
    for name, label in (("clamp_direct", "Clamp Direct"), ("clamp_indirect", "Clamp Indirect")):
        value = float(getattr(settings, name, 0.0))
        if not np.isfinite(value) or value < 0:
            raise SceneError(f"{label} must be 0 (off) or a positive radiance (got {value!r}): set LMDP > Bake > "
                             f"{label} (Light Paths Custom) or the scene's Render Properties > Light Paths > "
                             "Clamping")
