"""AUTO, the default bake mode: unguided paths where they are quiet, the solved LMDP where it wins.

A bake of S samples per texel runs in parts, each an ordinary bake with its own random streams
(seed ``AUTO_PARTS · seed + part``), and the parts are pooled with fixed weights (their sample
counts), so the result is unbiased whatever is decided between them:

1. *Pilot*: n = S / 32 samples (even, at least 2; below 16 samples no pilot: all unguided) (:func:`pilot_samples`) UNGUIDED with light connections. Its
   relative variance per path, ``Σ n se² / (texels · mean²)`` over every baked texel and
   channel, says how hard the scene is for unguided paths. Below :data:`NOISY` (measured:
   Cornell box 2.4, heavy box 2.9, sun + HDRI 5, glossy box 10-11 per path; light through a
   hatch 77-82) the remaining S − n samples are traced the same way, with no solve.
2. Noisy (and the rest of the bake at least 1 / :data:`SOLVE_SHARE` times the build's rays, or a
   solution given): the LMDP is sampled, built and solved (or the given solution reused) and another n
   samples are traced GUIDED (the fine guide, light connections, the solution's Russian
   roulette and splitting: :mod:`~lmdp_addon.bake.splitting`).
3. The last S − 2n samples go to whichever of the two was more efficient on its pilot,
   1 / (variance per path x cost per path), the cost counted in rays (a GUIDED ray
   :data:`GUIDED_RAY_COST` times an unguided one), its tracer reused. Counts, not clocks: the
   bake stays the same for a seed whatever the machine or thread count.

``AutoChoice`` records what was measured and chosen; the Bake report prints it.
"""
from dataclasses import dataclass, field, replace

import numpy as np

from .results import BakeResult, ObjectBake

#: Random streams of one AUTO bake: part k uses seed ``AUTO_PARTS * seed + k``.
AUTO_PARTS = 4
#: Share of the samples in each pilot (1 / PILOT_SHARE, at least :data:`MIN_PILOT` samples).
PILOT_SHARE = 32
#: Fewest samples per texel of a pilot (two batches: a standard error).
MIN_PILOT = 2
#: Fewest samples per texel of a bake with pilots (each at least :data:`MIN_PILOT`): below, the
#: solve and the parts' own costs outweigh what guiding the rest could gain.
MIN_SAMPLES = 16
#: Relative variance per path of the unguided pilot above which the LMDP is solved.
NOISY = 25.0
#: Time of a GUIDED ray over an UNGUIDED one, both with light connections (the guide's lookups
#: and mixture densities; measured on the narrow opening at 64 and 256 samples: 1.46x the time per
#: path for 1.13x the rays).
GUIDED_RAY_COST = 1.3
#: Largest share of the rest of the bake's rays that the LMDP's build may cost (its rays: points x
#: (strata x rays per stratum + light samples)); a smaller bake stays unguided. GUIDED gained
#: 2-3x on the rest where the pilot was noisy, so a build of half the rest's rays still pays.
SOLVE_SHARE = 0.5


@dataclass
class AutoChoice:
    """What AUTO measured and chose (``BakeResult.auto``)."""

    relative_variance: float               #: of the unguided pilot, per path
    solved: bool = False                   #: the LMDP was solved (or reused) and piloted
    too_small: bool = False                #: noisy, but the rest too small to pay for a solve
    guided_gain: float = float("nan")      #: GUIDED's efficiency over UNGUIDED's on the pilots
    mode: str = "UNGUIDED"                 #: the mode of the remaining samples
    samples: tuple = ()                    #: (mode, samples) of the whole bake
    parts: tuple = ()                      #: (mode, samples, seconds) of each part, in order
    lmdp: object = field(default=None, repr=False)   #: the solution it solved (None: given or none)

    def sentence(self):
        """The Bake report's line."""
        if self.too_small:
            return (f"AUTO: unguided paths were noisy (relative variance {self.relative_variance:.3g} per path), "
                    "but the bake is too small to pay for solving the LMDP: UNGUIDED with light connections "
                    "(more samples or texels, or a solution in the session, let it guide)")
        if not self.solved:
            return (f"AUTO: unguided paths were quiet (relative variance {self.relative_variance:.3g} per path, "
                    f"below {NOISY:g}): no solve, UNGUIDED with light connections")
        return (f"AUTO: unguided paths were noisy (relative variance {self.relative_variance:.3g} per path): "
                f"solved the LMDP; GUIDED was {self.guided_gain:.2f}x as efficient on the pilot, "
                f"{self.mode} traced the rest ({' + '.join(f'{n} {m}' for m, n in self.samples)} samples)")

    def as_dict(self):
        return dict(relative_variance=self.relative_variance, solved=self.solved, guided_gain=self.guided_gain,
                    mode=self.mode, samples=[list(s) for s in self.samples], parts=[list(p) for p in self.parts])


def pilot_samples(samples):
    """Samples per texel of each pilot of an AUTO bake of ``samples`` (0: too few to split): S / 32
    rounded down to an even number, at least :data:`MIN_PILOT`, so that the pilot has two batches
    and a standard error (``driver.batch_count``: 11 samples would be one batch), raised by 2 while
    the rest (S - n, or S - 2n after two pilots) would be a single batch where S is not."""
    from .driver import batch_count
    samples = int(samples)
    if samples < MIN_SAMPLES:
        return 0
    n = max(samples // PILOT_SHARE // 2 * 2, MIN_PILOT)
    while (n + 2 <= (samples - 4) // 2 and batch_count(samples) > 1
           and (batch_count(samples - n) == 1 or batch_count(samples - 2 * n) == 1)):
        n += 2
    return n


def relative_variance(result):
    """Relative variance per path of a bake (``BakeResult``): Σ n se² / (texels · mean²) over
    its objects' texels and channels (0 for a black or empty bake)."""
    var = [np.square(ob.standard_error.astype(np.float64)) * ob.samples for ob in result.objects
           if ob.n_texels and np.all(np.isfinite(ob.standard_error))]
    val = [ob.value.astype(np.float64) for ob in result.objects if ob.n_texels]
    if not var or not val:
        return 0.0
    mean = np.mean(np.concatenate(val))
    return float(np.mean(np.concatenate(var)) / mean ** 2) if mean > 0 else 0.0


def efficiency(result, ray_cost=1.0):
    """1 / (variance per path x cost per path) of a bake, the variance averaged over its texels and
    channels, the cost its rays per path times ``ray_cost`` (a count, not a clock: the choice, and
    so the bake, is the same for a seed on any machine and thread count)."""
    var = np.mean(np.concatenate([np.square(ob.standard_error.astype(np.float64)) * ob.samples
                                  for ob in result.objects if ob.n_texels]))
    paths = sum(ob.n_texels * ob.samples for ob in result.objects)
    rays = sum(ob.stats.total_rays for ob in result.objects)
    return 1.0 / max(var * ray_cost * rays / max(paths, 1), 1e-300)


def worth_solving(pilot, settings, remaining):
    """Whether the LMDP's build (its rays) costs at most :data:`SOLVE_SHARE` of the rays the rest
    of the bake (``remaining`` samples per texel) will trace, at the pilot's rays per path."""
    paths = sum(ob.n_texels * ob.samples for ob in pilot.objects)
    per_path = sum(ob.stats.total_rays for ob in pilot.objects) / max(paths, 1)
    texels = sum(ob.n_texels for ob in pilot.objects)
    build = int(settings.point_count) * (int(settings.strata_u) * int(settings.strata_v) * int(settings.rays_per_stratum)
                                         + int(settings.light_samples))
    return build <= SOLVE_SHARE * per_path * texels * int(remaining)


def part_settings(settings, mode, samples, part):
    """The settings of part ``part`` of an AUTO bake: ``mode``, ``samples``, its own seed."""
    return replace(settings, bake_mode=mode, bake_samples=int(samples), seed=AUTO_PARTS * int(settings.seed) + part)


def pooled(parts, settings, seconds, warnings, info, auto, compose):
    """One :class:`BakeResult` of the ``parts`` (BakeResults of the same objects and texels):
    per texel the mean over all samples, ``Σ n_k v_k / S``, and its standard error
    ``sqrt(Σ n_k² se_k²) / S``; the lightmaps re-dilated by ``compose(ObjectBake) -> image``."""
    objects = []
    S = sum(p.objects[0].samples for p in parts) if parts and parts[0].objects else 0
    for i, first in enumerate(parts[0].objects):
        obs = [p.objects[i] for p in parts]
        value = sum(ob.value.astype(np.float64) * ob.samples for ob in obs) / S
        se2 = sum(np.square(ob.standard_error.astype(np.float64)) * ob.samples ** 2 for ob in obs) / S ** 2
        stats = type(first.stats)()
        for ob in obs:
            stats.add(ob.stats)
        ob = ObjectBake(name=first.name, texels=first.texels, triangles=first.triangles,
                        value=value.astype(np.float32), standard_error=np.sqrt(se2).astype(np.float32),
                        image=None, samples=S, batches=sum(ob.batches for ob in obs), stats=stats,
                        seconds=sum(ob.seconds for ob in obs))
        ob.image = compose(ob)
        objects.append(ob)
    return BakeResult(mode="AUTO", objects=objects, settings=settings.as_dict(), seconds=seconds,
                      warnings=warnings, guide_info=info, auto=auto)
