"""What a lightmap holds (``Settings.bake_content``, ``Settings.multiply_color``), as the
quantities of Cycles' ``bake(type='DIFFUSE', pass_filter=...)``:

* ``INDIRECT`` (pass_filter {'INDIRECT'}): I(x) = E_ind(x)/π, light that bounced at least once
  before reaching x (thesis eq. 2.7 without the emission term of the first hit);
* ``DIRECT_INDIRECT`` ({'DIRECT', 'INDIRECT'}): D(x) + I(x), where the direct term
  D(x) = (1/π) ∫ L_e(h(x, ω), -ω) cos θ dω is estimated at the texel point x0 exactly as at
  every later path vertex: next-event estimation at x0 plus the MIS-weighted emission (and world)
  found by x0's own first ray (the balance heuristic of ``lights.EmitterSampler``);
* ``multiply_color`` (the 'COLOR' filter added): each path's estimate times the diffuse colour ρ
  at x0, the "combined diffuse" lightmap ρ (D + I) or ρ I.
"""
from dataclasses import dataclass

import numpy as np

from ..settings import BAKE_CONTENTS


@dataclass(frozen=True)
class BakeContent:
    """The terms a bake adds up at each texel."""

    direct: bool = False          #: D(x0): NEE at x0 and the emitters / world its first ray meets
    multiply_color: bool = False  #: times ρ(x0)

    @classmethod
    def from_settings(cls, settings):
        content = getattr(settings, "bake_content", "INDIRECT")
        if content not in BAKE_CONTENTS:
            raise ValueError(f"bake_content must be one of {BAKE_CONTENTS}, not {content!r}")
        return cls(direct=content == "DIRECT_INDIRECT",
                   multiply_color=bool(getattr(settings, "multiply_color", False)))

    @property
    def pass_filter(self):
        """Cycles' DIFFUSE ``pass_filter`` of the same quantity."""
        return (("DIRECT", "INDIRECT") if self.direct else ("INDIRECT",)) + (("COLOR",) if self.multiply_color else ())

    def label(self):
        terms = "direct + indirect" if self.direct else "indirect"
        return f"({terms}) x diffuse colour" if self.multiply_color else terms


def times_color(values, albedo):
    """``values (n, 3)`` times the diffuse colour ``albedo (n, 3)`` of their start points, in place."""
    values *= np.asarray(albedo, dtype=np.float32)
    return values
