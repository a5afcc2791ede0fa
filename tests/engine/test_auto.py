"""AUTO, the default bake mode (lmdp_addon.bake.auto, ``driver._bake_auto``): pilots of
PILOT_SAMPLES samples on about PILOT_TEXELS texels (none below 16 samples), on their own seeds,
only to decide; quiet (relative variance per path below NOISY) the bake is UNGUIDED with no
solve; noisy the LMDP solved (the ``solve`` callback, or the given ``lmdp``), a GUIDED pilot (none
at or above SURE: GUIDED), and the bake in the more efficient mode: the same bytes as that mode's
own bake.

The tests: the quiet Cornell floor never solves and is UNGUIDED's bake; the narrow opening's
RoomAFloor (lit only through a hatch) solves once, is GUIDED's bake and keeps plain UNGUIDED's
mean; a small bake does not solve; no solution and no callback stays unguided; a given solution
is reused; determinism and threads; the clock; the stats entry; fewer than 16 samples.
"""
import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from bake_scenes import K
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import auto, fine_guide
from lmdp_addon.bake import driver as baking
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings


@pytest.fixture(autouse=True)
def any_size(monkeypatch):
    """These bakes are far smaller than a solve pays for (``auto.worth_solving``): let them solve
    anyway (:func:`test_a_small_bake_stays_unguided` keeps the rule)."""
    monkeypatch.setattr(auto, "SOLVE_SHARE", float("inf"))
    monkeypatch.setattr(auto, "SURE", float("inf"))   # the guided pilot runs (one test lowers SURE)


def settings(**kw):
    """AUTO settings of a small bake (``kw`` overrides)."""
    base = dict(bake_mode="AUTO", bake_resolution=32, bake_samples=32, bake_margin=2)
    base.update(kw)
    return Settings(**base)


def never():
    raise AssertionError("solve() called")


class Solver:
    """A ``solve`` callback that counts its calls and keeps what it returned."""

    def __init__(self, scene):
        self.scene, self.calls, self.results = scene, 0, []

    def __call__(self):
        self.calls += 1
        self.results.append(pipeline.run_all(self.scene, Settings(point_count=512)))
        return self.results[-1]


def texel_mean(result, name):
    """The mean over the texels of object ``name`` (3,) and its standard error (from the batch
    means: with path reuse a tile's texels share paths)."""
    return result.object(name).mean_and_error()


@pytest.fixture(scope="module")
def narrow():
    return scenes.build_scene_arrays("NARROW_OPENING")


@pytest.fixture(scope="module")
def narrow_solved(narrow):
    return pipeline.run_all(narrow, Settings(point_count=512))


# ---- (b) quiet: no solve -------------------------------------------------------------------------

def test_quiet_cornell_floor_is_unguided_without_a_solve(cornell):
    """The Cornell floor (relative variance ~2.4 - 3 per path), 16 px, 32 samples: ``solve`` is
    never called, and the bake is UNGUIDED's of the same seed, byte for byte."""
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16), threads=2, solve=never)
    choice = result.auto
    assert result.mode == "AUTO" and isinstance(choice, auto.AutoChoice)
    assert 0 < choice.relative_variance < auto.MODERATE
    assert not choice.solved and choice.mode == "UNGUIDED" and choice.lmdp is None
    assert np.isnan(choice.guided_gain)
    assert choice.samples == (("UNGUIDED", 32),)
    assert result.object("Floor").samples == 32
    assert "quiet" in choice.sentence()
    plain = baking.bake(cornell, ["Floor"], settings(bake_mode="UNGUIDED", bake_resolution=16), threads=2)
    np.testing.assert_array_equal(result.object("Floor").value, plain.object("Floor").value)
    np.testing.assert_array_equal(result.object("Floor").standard_error, plain.object("Floor").standard_error)


def test_a_small_bake_stays_unguided(narrow, monkeypatch):
    """Noisy, but 16 px x 16 samples: the LMDP's build (2048 points x 96 rays) would cost more
    than half the rays of the rest of the bake (``auto.worth_solving``): no solve, UNGUIDED, and
    the report says why; at 64 px x 64 samples the same scene solves."""
    monkeypatch.setattr(auto, "SOLVE_SHARE", 0.5)
    result = baking.bake(narrow, ["RoomAFloor"], settings(bake_resolution=16, bake_samples=16), threads=2,
                         solve=never)
    assert result.auto.too_small and not result.auto.solved and result.auto.relative_variance >= auto.NOISY
    assert "too small" in result.auto.sentence() and result.auto.samples == (("UNGUIDED", 16),)
    assert not auto.worth_solving(6.0, 200, settings(), 16)                # 2048 x 96 rays > 0.5 x 19 200
    assert auto.worth_solving(6.0, 9000, settings(), 64)


def test_a_noisy_bake_without_a_solver_says_so(narrow):
    """Noisy and large enough to solve (64 px x 64 samples), but no solution given and no
    ``solve`` to call (an engine caller): UNGUIDED, and the report says it was noisy and why it
    was not guided, not that it was quiet."""
    result = baking.bake(narrow, ["RoomAFloor"], settings(bake_resolution=64, bake_samples=64), threads=2)
    choice = result.auto
    assert choice.relative_variance >= auto.NOISY and not choice.too_small
    assert choice.no_solution and not choice.solved and choice.mode == "UNGUIDED"
    assert "noisy" in choice.sentence() and "no LMDP solution" in choice.sentence()
    assert "quiet" not in choice.sentence() and choice.as_dict()["no_solution"]


def test_a_moderately_noisy_small_bake_does_not_solve(cornell, monkeypatch):
    """Moderately noisy (``MODERATE`` lowered below the Cornell floor's ~2.4-3) but 16 px x 32
    samples: the build would cost more than ``MODERATE_SOLVE_SHARE`` of the bake's rays: no solve,
    UNGUIDED's bake byte for byte, and the report says so."""
    monkeypatch.setattr(auto, "MODERATE", 0.0)
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16), threads=2, solve=never)
    choice = result.auto
    assert not choice.solved and not choice.moderate and choice.too_small and choice.mode == "UNGUIDED"
    assert "moderately noisy" in choice.sentence() and "too small" in choice.sentence()
    plain = baking.bake(cornell, ["Floor"], settings(bake_mode="UNGUIDED", bake_resolution=16), threads=2)
    np.testing.assert_array_equal(result.object("Floor").value, plain.object("Floor").value)
    assert not auto.worth_solving(6.0, 16384, settings(), 64, auto.MODERATE_SOLVE_SHARE)  # 196 608 > 0.02 x 6.3 M
    assert auto.worth_solving(6.0, 16384, settings(), 256, auto.MODERATE_SOLVE_SHARE)     # < 0.02 x 25 M


def test_a_moderately_noisy_pilot_pilots_guided_without_splitting(narrow, monkeypatch):
    """Between ``MODERATE`` and ``NOISY`` (here: the narrow opening with NOISY raised above it) the
    LMDP is solved once and the guided pilot runs GUIDED *without* splitting; the bake is that
    mode's own bake with the solution (same bytes, not GUIDED's with splitting) and keeps plain
    UNGUIDED's mean (5 s.e.)."""
    monkeypatch.setattr(auto, "NOISY", float("inf"))
    monkeypatch.setattr(auto, "MODERATE_SOLVE_SHARE", float("inf"))
    monkeypatch.setattr(auto, "GUIDED_RAY_COST", 0.1)   # (at 32 px, 512 points: 0.73x at 1.3) GUIDED wins
    pilots = []
    real = baking._auto_pilot
    monkeypatch.setattr(baking, "_auto_pilot",
                        lambda *a, **k: pilots.append((a[2].bake_mode, a[2].splitting)) or real(*a, **k))
    solver = Solver(narrow)
    result = baking.bake(narrow, ["RoomAFloor"], settings(seed=1), threads=2, solve=solver)
    choice = result.auto
    assert solver.calls == 1 and choice.solved and choice.moderate and not choice.sure
    assert pilots == [("UNGUIDED", True), ("GUIDED", False)]
    assert np.isfinite(choice.guided_gain) and choice.guided_gain > 1
    assert choice.mode == "GUIDED" and "GUIDED without splitting" in choice.sentence()
    assert result.stats()["auto"]["moderate"] is True
    same = baking.bake(narrow, ["RoomAFloor"], settings(seed=1, bake_mode="GUIDED", splitting=False),
                       choice.lmdp, threads=2)
    np.testing.assert_array_equal(result.object("RoomAFloor").value, same.object("RoomAFloor").value)
    with_split = baking.bake(narrow, ["RoomAFloor"], settings(seed=1, bake_mode="GUIDED"), choice.lmdp, threads=2)
    assert not np.array_equal(result.object("RoomAFloor").value, with_split.object("RoomAFloor").value)
    plain = baking.bake(narrow, ["RoomAFloor"], settings(bake_mode="UNGUIDED", bake_samples=512, seed=2), threads=2)
    (ma, sa), (mb, sb) = texel_mean(result, "RoomAFloor"), texel_mean(plain, "RoomAFloor")
    s = np.sqrt(sa ** 2 + sb ** 2)
    assert np.all(np.abs(ma - mb) <= K * s), (ma, mb, s)


# ---- (c) noisy: solve once, keep the mean --------------------------------------------------------

def test_noisy_narrow_opening_solves_once_and_keeps_the_mean(narrow):
    """RoomAFloor of the narrow opening, 32 px, 32 samples: the pilot is noisy, ``solve`` is
    called once and its solution is ``auto.lmdp``, a GUIDED pilot runs, its gain is finite; the
    bake is the chosen mode's own bake with that solution (same bytes), its standard errors finite
    and positive at the lit texels, and its mean over the texels agrees with a plain UNGUIDED
    bake of 512 samples within 5 standard errors (combined, from the batch means)."""
    solver = Solver(narrow)
    result = baking.bake(narrow, ["RoomAFloor"], settings(seed=1), threads=2, solve=solver)
    choice = result.auto
    assert solver.calls == 1 and choice.solved and choice.lmdp is solver.results[0]
    assert choice.relative_variance >= auto.NOISY
    assert np.isfinite(choice.guided_gain) and choice.guided_gain > 0
    assert choice.mode == ("GUIDED" if choice.guided_gain > 1 else "UNGUIDED")
    assert choice.samples == ((choice.mode, 32),)
    assert "solve" in result.seconds and "auto" in result.seconds
    ob = result.object("RoomAFloor")
    assert ob.samples == 32
    same = baking.bake(narrow, ["RoomAFloor"], settings(seed=1, bake_mode=choice.mode),
                       choice.lmdp if choice.mode == "GUIDED" else None, threads=2)
    np.testing.assert_array_equal(ob.value, same.object("RoomAFloor").value)
    lit = ob.value.max(axis=1) > 0          # (texels no path reached: 0, error 0)
    assert lit.mean() > 0.3         # (measured 0.39: the floor slab has faces no light reaches)
    assert np.all(np.isfinite(ob.standard_error)) and np.all(ob.standard_error[lit].max(axis=1) > 0)
    plain = baking.bake(narrow, ["RoomAFloor"], settings(bake_mode="UNGUIDED", bake_samples=512, seed=2), threads=2)
    (ma, sa), (mb, sb) = texel_mean(result, "RoomAFloor"), texel_mean(plain, "RoomAFloor")
    s = np.sqrt(sa ** 2 + sb ** 2)
    assert np.all(s < 0.1 * mb), (mb, s)
    assert np.all(np.abs(ma - mb) <= K * s), (ma, mb, s)


def test_a_very_noisy_pilot_bakes_guided_without_a_guided_pilot(narrow, narrow_solved, monkeypatch):
    """Above ``auto.SURE`` (the narrow opening's RoomAFloor: measured 76-126) no guided pilot runs:
    the bake is GUIDED's own with the given solution and the larger table (``SURE_TABLE_RAYS``),
    byte for byte, and the report says so."""
    monkeypatch.setattr(auto, "SURE", auto.NOISY)
    pilots = []
    real = baking._auto_pilot
    monkeypatch.setattr(baking, "_auto_pilot", lambda *a, **k: pilots.append(a[2].bake_mode) or real(*a, **k))
    result = baking.bake(narrow, ["RoomAFloor"], settings(), narrow_solved, threads=2, solve=never)
    choice = result.auto
    assert pilots == ["UNGUIDED"] and choice.sure and choice.solved and choice.mode == "GUIDED"
    assert np.isnan(choice.guided_gain) and "very noisy" in choice.sentence()
    s = settings()
    assert result.guide_info["fine_resolution"] == fine_guide.fine_resolution(
        narrow_solved.states.n_points, s.bake_resolution ** 2 * s.bake_samples,
        minimum=max(4, narrow_solved.states.strata_u), rays_per_path=auto.SURE_TABLE_RAYS)
    same = baking.bake(narrow, ["RoomAFloor"], settings(bake_mode="GUIDED", guide_table_rays=auto.SURE_TABLE_RAYS),
                       narrow_solved, threads=2)
    np.testing.assert_array_equal(result.object("RoomAFloor").value, same.object("RoomAFloor").value)


# ---- (d), (e) without a solution; with one given -------------------------------------------------

def test_noisy_without_a_solution_or_a_callback_stays_unguided(narrow):
    """The noisy RoomAFloor with no ``lmdp`` and no ``solve``: UNGUIDED for all 32 samples."""
    result = baking.bake(narrow, ["RoomAFloor"], settings(), threads=2)
    choice = result.auto
    assert choice.relative_variance >= auto.NOISY
    assert not choice.solved and choice.mode == "UNGUIDED" and choice.lmdp is None
    assert choice.samples == (("UNGUIDED", 32),)
    assert "solve" not in result.seconds


def test_a_given_solution_is_reused(narrow, narrow_solved):
    """The noisy RoomAFloor with ``lmdp`` given (and a ``solve`` that must not run): the given
    solution guides the GUIDED pilot; ``auto.lmdp`` stays None (nothing was solved here)."""
    result = baking.bake(narrow, ["RoomAFloor"], settings(), narrow_solved, threads=2, solve=never)
    choice = result.auto
    assert choice.solved and choice.lmdp is None and np.isfinite(choice.guided_gain)
    if choice.mode == "GUIDED":
        assert result.guide_info["points"] == narrow_solved.states.n_points


# ---- (g) determinism -----------------------------------------------------------------------------

def test_auto_is_deterministic_and_the_same_with_one_or_two_threads(narrow, narrow_solved, monkeypatch):
    """The noisy RoomAFloor (the guided pilot runs, a given solution), 16 px, 32 samples, small
    work units: the same value, standard errors and choice (its gain too) with 1 and 2 threads;
    another seed gives other values."""
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 256)
    s = settings(bake_resolution=16, seed=7)

    def run(st, threads):
        r = baking.bake(narrow, ["RoomAFloor"], st, narrow_solved, threads=threads)
        return r, r.object("RoomAFloor")

    (r1, a), (r2, b) = run(s, 1), run(s, 2)
    assert r1.auto.solved and r1.auto.mode == r2.auto.mode
    assert r1.auto.relative_variance == r2.auto.relative_variance
    assert r1.auto.guided_gain == r2.auto.guided_gain     # the choice by rays, not seconds
    np.testing.assert_array_equal(a.value, b.value)
    np.testing.assert_array_equal(a.standard_error, b.standard_error)
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.value, run(replace(s, seed=8), 2)[1].value)


class Clock:
    """A ``time`` whose ``perf_counter`` jumps by random amounts (lognormal, σ = 3): bakes that
    took wildly different times."""

    def __init__(self, seed):
        self.t, self.rng = 0.0, np.random.default_rng(seed)

    def perf_counter(self):
        self.t += float(self.rng.lognormal(0.0, 3.0))
        return self.t


@pytest.mark.parametrize("clock", [0, 3])
def test_the_choice_does_not_depend_on_the_clock(narrow, narrow_solved, monkeypatch, clock):
    """The noisy RoomAFloor with a given solution, seed 7 (GUIDED ~2x as efficient on the pilots):
    the same choice and the same bytes however long the parts seem to take (the driver's clock
    replaced by :class:`Clock`): a bake is deterministic for a seed, on any machine and load."""
    s = settings(bake_resolution=16, seed=7)
    ref = baking.bake(narrow, ["RoomAFloor"], s, narrow_solved, threads=1)
    monkeypatch.setattr(baking, "time", SimpleNamespace(perf_counter=Clock(clock).perf_counter))
    other = baking.bake(narrow, ["RoomAFloor"], s, narrow_solved, threads=1)
    assert other.auto.mode == ref.auto.mode and other.auto.guided_gain == ref.auto.guided_gain
    np.testing.assert_array_equal(other.object("RoomAFloor").value, ref.object("RoomAFloor").value)


# ---- (h) the stats -------------------------------------------------------------------------------

def test_stats_have_the_auto_entry(cornell):
    """``BakeResult.stats()`` (bake_stats.json) of an AUTO bake has "auto" with the choice and
    (JSON-serialisable); a plain bake's has none."""
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16), threads=2)
    stats = result.stats()
    entry = stats["auto"]
    assert entry == result.auto.as_dict()
    assert entry["solved"] is False and entry["mode"] == "UNGUIDED"
    assert entry["samples"] == [["UNGUIDED", 32]]
    assert stats["mode"] == "AUTO" and stats["objects"]["Floor"]["samples"] == 32
    json.loads(json.dumps(stats))
    plain = baking.bake(cornell, ["Floor"], settings(bake_mode="UNGUIDED", bake_resolution=16, bake_samples=4))
    assert "auto" not in plain.stats()


# ---- (i) too few samples for pilots --------------------------------------------------------------

@pytest.mark.parametrize("samples", [1, 8, 15])
def test_few_samples_are_one_unguided_bake(narrow, samples):
    """Below 16 samples: no pilot, no solve even where noisy, the relative variance not measured
    (NaN); the bake is UNGUIDED's of the same seed, byte for byte."""
    s = settings(bake_resolution=16, bake_samples=samples, seed=3)
    result = baking.bake(narrow, ["RoomAFloor"], s, threads=2, solve=never)
    choice = result.auto
    assert np.isnan(choice.relative_variance) and not choice.solved and choice.mode == "UNGUIDED"
    assert choice.samples == (("UNGUIDED", samples),)
    plain = baking.bake(narrow, ["RoomAFloor"], replace(s, bake_mode="UNGUIDED"), threads=2)
    np.testing.assert_array_equal(result.object("RoomAFloor").value, plain.object("RoomAFloor").value)
    np.testing.assert_array_equal(result.object("RoomAFloor").standard_error,
                                  plain.object("RoomAFloor").standard_error)
    np.testing.assert_array_equal(result.object("RoomAFloor").image, plain.object("RoomAFloor").image)
