"""AUTO, the default bake mode: unguided paths where they are quiet, the solved LMDP where it wins.

A bake of S samples per texel (S >= :data:`MIN_SAMPLES`; fewer: UNGUIDED) first measures, on
every k-th of its texels, :func:`pilot_paths` paths (4096 to 8192, :func:`pilot_samples` per
texel), on random streams of their own (seed ``PILOT_STREAMS · seed + k``).
The pilots only decide; the bake itself is then an ordinary UNGUIDED or GUIDED bake of all S
samples with the user's seed (the same bytes as that mode's bake), so the decision cannot bias it:

1. *Unguided pilot*, with light connections: its relative variance per path (:func:`relative_variance`:
   ``n se² / mean²`` of each pilot texel, the largest :data:`CLIPPED` of them clipped to the rest's
   largest, averaged) says how hard the scene is for unguided paths (measured over 40 seeds at
   4096 / 8192 pilot paths: Cornell box 2.4-3.2 / 2.6-3.0, heavy box 3.0-3.8 / 3.1-3.7, glossy box
   2.5-3.7 / 2.5-3.3, sun + HDRI 5.0-6.3 / 5.3-6.1, light through a hatch 23-55 / 32-53). Below
   :data:`MODERATE`: UNGUIDED, no solve.
2. Noisy (at or above :data:`NOISY`), and the bake large enough that the LMDP's build costs at
   most :data:`SOLVE_SHARE` of its rays (:func:`worth_solving`), or a solution given: the LMDP is
   sampled, built and solved (or the given solution reused) and, below :data:`SURE`, a *guided
   pilot* runs GUIDED (the fine guide, light connections, the solution's Russian roulette and
   splitting: :mod:`~lmdp_addon.bake.splitting`).
   Moderately noisy (from :data:`MODERATE` to :data:`NOISY`), the same with the smaller share
   :data:`MODERATE_SOLVE_SHARE` (the gain to expect is smaller), and the guided pilot runs
   GUIDED *without* splitting: where unguided paths are only moderately noisy, the copies cost
   more than they save (measured on the sun + HDRI scene: variance per sample 0.68x UNGUIDED's
   without splitting, 0.88x with it, at 1.25x and 1.44x the time); it guides the bake if it
   gained at least :data:`MODERATE_GAIN` on the pilots.
3. At or above :data:`SURE`, GUIDED bakes the lightmaps without a guided pilot. Below, GUIDED
   bakes them if it was more efficient on the pilots, 1 / (variance per path x cost per path),
   the cost counted in rays (a GUIDED ray :data:`GUIDED_RAY_COST` times an
   unguided one): counts, not clocks, so a bake is the same for a seed on any machine and thread
   count. Otherwise UNGUIDED.

``AutoChoice`` records what was measured and chosen; the Bake report prints it.
"""
from dataclasses import dataclass, field

import numpy as np

#: Random streams of the pilots: pilot k uses seed ``PILOT_STREAMS * seed + k`` (k = 1, 2).
PILOT_STREAMS = 4
#: Paths of a pilot: 1/:data:`PILOT_SHARE` of the bake's, at least :data:`PILOT_MIN_PATHS` and at
#: most :data:`PILOT_PATHS` (:func:`pilot_paths`: a 16-sample bake at 128² pilots 4096 paths, 64
#: samples 8192; a pilot's paths cost about twice a bake's, one thread on small arrays, so at 8192 it
#: was 10-16 % of a 16-sample bake of the glossy box and the sun + HDRI scene; relative variance
#: per path over 12 seeds at 4096 / 8192 paths: narrow opening 53-121 / 74-103, Cornell 2.7-3.7 /
#: 3.0-3.7, sun + HDRI 5.9-7.7 / 5.9-6.6) ...
PILOT_PATHS = 8192
PILOT_MIN_PATHS = 4096
PILOT_SHARE = 64
#: ... its fewest samples per texel (batches: each texel's standard error) ...
PILOT_SAMPLES = 4
#: ... and its texels (all baked objects together; every k-th texel of each): where the bake has
#: fewer, more samples each (at most a quarter of the bake's), so that both pilots measure
#: enough paths to compare.
PILOT_TEXELS = PILOT_PATHS // PILOT_SAMPLES
#: Fewest samples per texel of a bake that runs pilots (below, UNGUIDED).
MIN_SAMPLES = 16
#: Share of the pilot's texels whose relative variance is clipped (:func:`relative_variance`): the
#: mean over all texels was carried by a few spiky ones where guiding cannot help (the glossy box's
#: highlights: 3.6-37 over 40 seeds at 8192 paths, 3 of them above :data:`NOISY`'s former 25, where
#: the clipped mean read 2.5-3.3), while a hatch keeps a large clipped mean (32-53, the mean 69-225).
CLIPPED = 0.01
#: Relative variance per path of the unguided pilot from which a bake large enough for
#: :data:`MODERATE_SOLVE_SHARE` solves the LMDP and pilots GUIDED without splitting (the quiet
#: Cornell, heavy and glossy boxes measured up to 3.8, where GUIDED gained nothing over UNGUIDED with
#: light connections; the sun + HDRI scene 5.0-6.3) ...
MODERATE = 4.5
#: ... from which the LMDP is solved and GUIDED piloted with splitting ...
NOISY = 12.0
#: ... and at or above which GUIDED bakes without a guided pilot (light through a hatch, 23-55: GUIDED
#: won every guided pilot there, 1.25-3.5x).
SURE = 20.0
#: Rays of the fine guide's table per path of a bake at or above :data:`SURE` (``Settings.
#: guide_table_rays``; GUIDED's own default is ``fine_guide.FINE_RAYS_PER_PATH`` = 0.5): light
#: through a hatch pays for a finer table sooner (narrow opening, 128², eight seeds: G = 16 in
#: place of 8 at 16 and 32 samples, 1.12x and 1.14x the efficiency, at 4 samples G = 8 in place
#: of 4, 1.54x; the Cornell box's GUIDED bake at 16 samples: 0.91x).
SURE_TABLE_RAYS = 2.0
#: Time of a GUIDED ray over an UNGUIDED one, both with light connections (the guide's lookups
#: and mixture densities; measured on the narrow opening at 64 and 256 samples: 1.46x the time per
#: path for 1.13x the rays).
GUIDED_RAY_COST = 1.3
#: Largest share of the bake's rays that the LMDP's build may cost (its rays: points x (strata x
#: rays per stratum + light samples)); a smaller bake stays unguided. GUIDED gained 2-3x where
#: the pilot was noisy, so a build of half the bake's rays still pays.
SOLVE_SHARE = 0.5
#: The same share where unguided paths are only moderately noisy: GUIDED without splitting gained
#: 1.1-1.25x there (sun + HDRI), and lost 0.75x on the glossy box, where the solve and the guided
#: pilot cost 0.3-0.5 s, a quarter of a 64-sample bake at 128 px: they must stay a few per cent.
MODERATE_SOLVE_SHARE = 0.02
#: Least gain of GUIDED without splitting on the pilots for which a moderately noisy bake is
#: guided (its pilot gains scatter: 1.09-1.39 on the sun + HDRI scene, 0.21-1.06 on the glossy box).
MODERATE_GAIN = 1.1


def pilot_paths(bake_paths):
    """Paths of the pilots of a bake of ``bake_paths`` paths (texels x samples): a
    :data:`PILOT_SHARE`-th of them, from :data:`PILOT_MIN_PATHS` to :data:`PILOT_PATHS`."""
    return int(min(PILOT_PATHS, max(PILOT_MIN_PATHS, int(bake_paths) // PILOT_SHARE)))


def pilot_samples(pilot_texels, samples, paths=PILOT_PATHS):
    """Samples per texel of the pilots at ``pilot_texels`` texels of a bake of ``samples``:
    ``paths`` paths, at least :data:`PILOT_SAMPLES`, at most a quarter of the bake's, a
    multiple of 4 (four batches)."""
    want = -(-int(paths) // max(int(pilot_texels), 1))
    n = max(PILOT_SAMPLES, min(want, int(samples) // 4))
    return -(-n // 4) * 4


@dataclass
class AutoChoice:
    """What AUTO measured and chose (``BakeResult.auto``)."""

    relative_variance: float               #: of the unguided pilot, per path
    solved: bool = False                   #: the LMDP was solved (or reused) and piloted
    moderate: bool = False                 #: moderately noisy: GUIDED piloted without splitting
    too_small: bool = False                #: (moderately) noisy, but the bake too small to pay for a solve
    no_solution: bool = False              #: (moderately) noisy, but no solution given and no solve to call
    sure: bool = False                     #: so noisy that GUIDED baked without a guided pilot
    guided_gain: float = float("nan")      #: GUIDED's efficiency over UNGUIDED's on the pilots
    mode: str = "UNGUIDED"                 #: the mode that baked the lightmaps
    samples: tuple = ()                    #: (mode, samples) of the bake
    lmdp: object = field(default=None, repr=False)   #: the solution it solved (None: given or none)

    def sentence(self):
        """The Bake report's line."""
        how = "moderately noisy" if self.relative_variance < NOISY else "noisy"
        if self.too_small:
            return (f"AUTO: unguided paths were {how} (relative variance {self.relative_variance:.3g} per path), "
                    "but the bake is too small to pay for solving the LMDP: UNGUIDED with light connections "
                    "(more samples or texels, or a solution in the session, let it guide)")
        if self.no_solution:
            return (f"AUTO: unguided paths were {how} (relative variance {self.relative_variance:.3g} per path), "
                    "but no LMDP solution was given to guide them: UNGUIDED with light connections")
        if not self.solved:
            return (f"AUTO: unguided paths were quiet (relative variance {self.relative_variance:.3g} per path, "
                    f"below {MODERATE:g}): no solve, UNGUIDED with light connections")
        if self.sure:
            return (f"AUTO: unguided paths were very noisy (relative variance {self.relative_variance:.3g} per path, "
                    f"above {SURE:g}): solved the LMDP: GUIDED")
        guided = "GUIDED without splitting" if self.moderate else "GUIDED"
        mode = guided if self.mode == "GUIDED" else self.mode
        return (f"AUTO: unguided paths were {'moderately ' if self.moderate else ''}noisy (relative variance "
                f"{self.relative_variance:.3g} per path): solved the LMDP; {guided} was {self.guided_gain:.2f}x "
                f"as efficient on the pilots: {mode}")

    def as_dict(self):
        return dict(relative_variance=self.relative_variance, solved=self.solved, guided_gain=self.guided_gain,
                    mode=self.mode, samples=[list(s) for s in self.samples], too_small=self.too_small,
                    sure=self.sure, moderate=self.moderate, no_solution=self.no_solution)


def _texel_variances(objects):
    """(texels,) n se² of every texel of a pilot (its ``ObjectBake`` s), averaged over the
    channels: the variance per path of each texel's estimate."""
    var = [(np.square(ob.standard_error.astype(np.float64)) * ob.samples).mean(axis=1) for ob in objects
           if ob.n_texels and np.all(np.isfinite(ob.standard_error))]
    return np.concatenate(var) if var else np.zeros(0)


def _clipped_mean(values):
    """The mean of ``values`` with the largest :data:`CLIPPED` of them set to the largest of the
    rest (a winsorised mean)."""
    if len(values) == 0:
        return 0.0
    return float(np.mean(np.minimum(values, np.quantile(values, 1.0 - CLIPPED))))


def relative_variance(objects):
    """Relative variance per path of a pilot (its ``ObjectBake`` s): the clipped mean
    (:data:`CLIPPED`) over their texels of ``n se² / mean²``, the mean over all texels and
    channels (0 for a black or empty pilot)."""
    var = _texel_variances(objects)
    val = [ob.value.astype(np.float64) for ob in objects if ob.n_texels]
    if len(var) == 0 or not val:
        return 0.0
    mean = np.mean(np.concatenate(val))
    return float(_clipped_mean(var) / mean ** 2) if mean > 0 else 0.0


def efficiency(objects, ray_cost=1.0):
    """1 / (variance per path x cost per path) of a pilot (its ``ObjectBake`` s), the variance
    the clipped mean over their texels (as :func:`relative_variance`), the cost their rays per
    path times ``ray_cost`` (a count, not a clock: the choice, and so the bake, is the same for a
    seed on any machine)."""
    var = _clipped_mean(_texel_variances(objects))
    paths = sum(ob.n_texels * ob.samples for ob in objects)
    rays = sum(ob.stats.total_rays for ob in objects)
    return 1.0 / max(var * ray_cost * rays / max(paths, 1), 1e-300)


def worth_solving(rays_per_path, texels, settings, samples, share=None):
    """Whether the LMDP's build (points x (strata x rays per stratum + light samples) rays) costs
    at most ``share`` (None: :data:`SOLVE_SHARE`) of the rays of a bake of ``texels`` x
    ``samples`` paths of ``rays_per_path`` rays (the unguided pilot's)."""
    share = SOLVE_SHARE if share is None else share
    build = int(settings.point_count) * (int(settings.strata_u) * int(settings.strata_v) * int(settings.rays_per_stratum)
                                         + int(settings.light_samples))
    return build <= share * rays_per_path * texels * int(samples)
