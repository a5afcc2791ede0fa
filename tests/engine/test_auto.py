"""AUTO, the default bake mode (lmdp_addon.bake.auto, ``driver._bake_auto``): an UNGUIDED pilot
of S / 16 samples (at least 2; none below 16 samples); quiet (relative variance per path below
NOISY) the rest UNGUIDED with no solve; noisy the LMDP solved (the ``solve`` callback, or the
given ``lmdp``), a GUIDED pilot, and the last S - 2n samples by the more efficient; the parts
(seeds AUTO_PARTS * seed + k) pooled with their sample counts as weights.

The tests: the pilot sizes; the quiet Cornell floor never solves; the narrow opening's RoomAFloor
(lit only through a hatch) solves once and keeps plain UNGUIDED's mean; no solution and no
callback stays unguided; a given solution is reused; the pooling's exact numbers; determinism
and threads; the stats entry; fewer than 16 samples.
"""
import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from bake_scenes import K
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import auto
from lmdp_addon.bake import driver as baking
from lmdp_addon.bake.results import BakeResult, ObjectBake
from lmdp_addon.bake.tracer import TraceStats
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings


@pytest.fixture(autouse=True)
def any_size(monkeypatch):
    """These bakes are far smaller than a solve pays for (``auto.worth_solving``): let them solve
    anyway (:func:`test_a_small_bake_stays_unguided` keeps the rule)."""
    monkeypatch.setattr(auto, "SOLVE_SHARE", float("inf"))


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


class PoolSpy:
    """Wraps ``auto.pooled`` (as the driver calls it) and keeps the parts it pooled."""

    def __init__(self):
        self.parts = None
        self.pooled = auto.pooled

    def __call__(self, parts, *args):
        self.parts = list(parts)
        return self.pooled(parts, *args)


def texel_mean(result, name):
    """The mean over the texels of object ``name`` (3,) and its standard error."""
    ob = result.object(name)
    return ob.value.astype(np.float64).mean(axis=0), np.sqrt(
        np.square(ob.standard_error.astype(np.float64)).sum(axis=0)) / ob.n_texels


@pytest.fixture(scope="module")
def narrow():
    return scenes.build_scene_arrays("NARROW_OPENING")


@pytest.fixture(scope="module")
def narrow_solved(narrow):
    return pipeline.run_all(narrow, Settings(point_count=512))


# ---- (a) the pilot's size ------------------------------------------------------------------------

def test_pilot_samples():
    """No pilot below 16 samples; S / 32 (even) from there on, at least 2."""
    for S, n in ((1, 0), (8, 0), (15, 0), (16, 2), (31, 2), (32, 2), (64, 2), (128, 4), (256, 8), (1024, 32)):
        assert auto.pilot_samples(S) == n, (S, auto.pilot_samples(S))


def test_every_pilot_has_a_standard_error():
    """The pilot decides by its standard errors: for every bake of 16 to 1024 samples it has at
    least two batches (``driver.batch_count``) and at least 2 samples (an 11-sample pilot had one
    batch: NaN standard errors, relative variance 0, never solved); the rest after one or two
    pilots has two batches too wherever the bake of S samples has."""
    for S in range(16, 1025):
        n = auto.pilot_samples(S)
        assert baking.batch_count(n) >= 2 and 2 <= n <= max(S // 32, 2) or n <= (S - 4) // 2, (S, n)
        if baking.batch_count(S) > 1:
            assert baking.batch_count(S - n) > 1 and baking.batch_count(S - 2 * n) > 1, (S, n)


def test_a_pilot_of_eleven_samples_still_sees_the_noise(narrow):
    """RoomAFloor at S = 352 (S / 32 = 11, a prime: one batch, no standard error): the pilot
    (10 samples) still measures the noise (relative variance well above NOISY) and solves."""
    solver = Solver(narrow)
    result = baking.bake(narrow, ["RoomAFloor"], settings(bake_resolution=8, bake_samples=352), threads=2,
                         solve=solver)
    assert result.auto.relative_variance >= auto.NOISY, result.auto.parts
    assert result.auto.solved and solver.calls == 1
    assert sum(n for _, n, _ in result.auto.parts) == 352


# ---- (b) quiet: no solve -------------------------------------------------------------------------

def test_quiet_cornell_floor_is_unguided_without_a_solve(cornell):
    """The Cornell floor (relative variance ~2.4 - 3 per path), 16 px, 32 samples: ``solve`` is
    never called, the rest is UNGUIDED, the parts add up to the 32 samples."""
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16), threads=2, solve=never)
    choice = result.auto
    assert result.mode == "AUTO" and isinstance(choice, auto.AutoChoice)
    assert 0 < choice.relative_variance < auto.NOISY
    assert not choice.solved and choice.mode == "UNGUIDED" and choice.lmdp is None
    assert np.isnan(choice.guided_gain)
    assert choice.samples == (("UNGUIDED", 32),)
    assert [(m, n) for m, n, _ in choice.parts] == [("UNGUIDED", 2), ("UNGUIDED", 30)]
    assert result.object("Floor").samples == 32
    assert "quiet" in choice.sentence()


def test_auto_has_standard_errors_where_a_plain_bake_has_them(cornell):
    """S = 25 (five batches UNGUIDED): the quiet Cornell floor's AUTO bake has finite standard
    errors too (its parts were 2 + 23 samples, and 23 is one batch; the pilot is now 10)."""
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16, bake_samples=25), threads=2, solve=never)
    assert np.all(np.isfinite(result.object("Floor").standard_error))


def test_a_small_bake_stays_unguided(narrow, monkeypatch):
    """Noisy, but 16 px x 16 samples: the LMDP's build (2048 points x 96 rays) would cost more
    than half the rays of the rest of the bake (``auto.worth_solving``): no solve, UNGUIDED, and
    the report says why; at 64 px x 64 samples the same scene solves."""
    monkeypatch.setattr(auto, "SOLVE_SHARE", 0.5)
    result = baking.bake(narrow, ["RoomAFloor"], settings(bake_resolution=16, bake_samples=16), threads=2,
                         solve=never)
    assert result.auto.too_small and not result.auto.solved and result.auto.relative_variance >= auto.NOISY
    assert "too small" in result.auto.sentence() and result.auto.samples == (("UNGUIDED", 16),)
    pilot = baking.bake(narrow, ["RoomAFloor"], settings(bake_mode="UNGUIDED", bake_resolution=64, bake_samples=2),
                        threads=2)
    assert auto.worth_solving(pilot, settings(), 62)


# ---- (c) noisy: solve once, keep the mean --------------------------------------------------------

def test_noisy_narrow_opening_solves_once_and_keeps_the_mean(narrow, monkeypatch):
    """RoomAFloor of the narrow opening, 32 px, 32 samples: the pilot is noisy, ``solve`` is
    called once and its solution is ``auto.lmdp``, a GUIDED pilot of 2 samples runs, its gain is
    finite; the pooled bake is the parts' Σ n_k v_k / S with standard error sqrt(Σ n_k² se_k²) / S,
    finite at every texel and positive at the lit ones, and its mean over the texels agrees with a plain
    UNGUIDED bake of 128 samples within 5 standard errors (combined)."""
    spy = PoolSpy()
    monkeypatch.setattr(auto, "pooled", spy)
    solver = Solver(narrow)
    result = baking.bake(narrow, ["RoomAFloor"], settings(seed=1), threads=2, solve=solver)
    choice = result.auto
    assert solver.calls == 1 and choice.solved and choice.lmdp is solver.results[0]
    assert choice.relative_variance >= auto.NOISY
    assert np.isfinite(choice.guided_gain) and choice.guided_gain > 0
    assert choice.mode == ("GUIDED" if choice.guided_gain > 1 else "UNGUIDED")
    rest = 32 - 4
    assert [(m, n) for m, n, _ in choice.parts] == [("UNGUIDED", 2), ("GUIDED", 2), (choice.mode, rest)]
    assert dict(choice.samples) == {"UNGUIDED": 2 + rest * (choice.mode == "UNGUIDED"),
                                    "GUIDED": 2 + rest * (choice.mode == "GUIDED")}
    assert result.guide_info and "solve" in result.seconds
    ob = result.object("RoomAFloor")
    assert ob.samples == 32
    parts = [p.object("RoomAFloor") for p in spy.parts]
    assert [p.samples for p in parts] == [2, 2, rest]
    value = sum(p.value.astype(np.float64) * p.samples for p in parts) / 32
    se = np.sqrt(sum(np.square(p.standard_error.astype(np.float64)) * p.samples ** 2 for p in parts)) / 32
    np.testing.assert_allclose(ob.value, value, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(ob.standard_error, se, rtol=1e-6, atol=1e-9)
    lit = ob.value.max(axis=1) > 0          # (texels no path reached: 0, error 0)
    assert lit.mean() > 0.3         # (measured 0.39: the floor slab has faces no light reaches)
    assert np.all(np.isfinite(ob.standard_error)) and np.all(ob.standard_error[lit].max(axis=1) > 0)
    monkeypatch.undo()
    plain = baking.bake(narrow, ["RoomAFloor"], settings(bake_mode="UNGUIDED", bake_samples=128, seed=2), threads=2)
    (ma, sa), (mb, sb) = texel_mean(result, "RoomAFloor"), texel_mean(plain, "RoomAFloor")
    s = np.sqrt(sa ** 2 + sb ** 2)
    assert np.all(s < 0.1 * mb), (mb, s)
    assert np.all(np.abs(ma - mb) <= K * s), (ma, mb, s)


# ---- (d), (e) without a solution; with one given -------------------------------------------------

def test_noisy_without_a_solution_or_a_callback_stays_unguided(narrow):
    """The noisy RoomAFloor with no ``lmdp`` and no ``solve``: UNGUIDED for all 32 samples."""
    result = baking.bake(narrow, ["RoomAFloor"], settings(), threads=2)
    choice = result.auto
    assert choice.relative_variance >= auto.NOISY
    assert not choice.solved and choice.mode == "UNGUIDED" and choice.lmdp is None
    assert choice.samples == (("UNGUIDED", 32),)
    assert [(m, n) for m, n, _ in choice.parts] == [("UNGUIDED", 2), ("UNGUIDED", 30)]
    assert "solve" not in result.seconds


def test_a_given_solution_is_reused(narrow, narrow_solved):
    """The noisy RoomAFloor with ``lmdp`` given (and a ``solve`` that must not run): the given
    solution guides the GUIDED pilot; ``auto.lmdp`` stays None (nothing was solved here)."""
    result = baking.bake(narrow, ["RoomAFloor"], settings(), narrow_solved, threads=2, solve=never)
    choice = result.auto
    assert choice.solved and choice.lmdp is None
    assert [m for m, _, _ in choice.parts][:2] == ["UNGUIDED", "GUIDED"]
    assert result.guide_info["points"] == narrow_solved.states.n_points


# ---- (f) the pooling's numbers -------------------------------------------------------------------

def object_bake(value, se, samples, batches, rays, seconds):
    texels = np.arange(len(value))
    stats = TraceStats(paths=len(value) * samples, rays=rays)
    return ObjectBake(name="A", texels=texels, triangles=np.zeros(1, np.int64),
                      value=np.asarray(value, np.float32), standard_error=np.asarray(se, np.float32), image=None,
                      samples=samples, batches=batches, stats=stats, seconds=seconds)


def test_pooled_weights_the_parts_by_their_samples():
    """Two parts of 6 and 2 samples: value (6 v_1 + 2 v_2) / 8, standard error
    sqrt(36 se_1² + 4 se_2²) / 8, the samples, batches, trace stats and seconds summed, the
    image composed from the pooled object, the settings, seconds and choice carried."""
    a = object_bake([[1.0, 2.0, 0.0], [3.0, 1.0, 1.0]], [[0.4, 0.1, 0.0], [0.2, 0.4, 0.3]], 6, 6, 100, 1.5)
    b = object_bake([[5.0, 6.0, 4.0], [3.0, 9.0, 1.0]], [[0.9, 0.2, 0.5], [0.6, 0.9, 0.1]], 2, 2, 40, 0.5)
    parts = [BakeResult(mode="UNGUIDED", objects=[a], settings={}), BakeResult(mode="GUIDED", objects=[b], settings={})]
    choice = auto.AutoChoice(relative_variance=30.0, solved=True)
    composed = []

    def compose(ob):
        composed.append(ob)
        return np.full((2, 2, 4), 7.0, np.float32)

    s = Settings(bake_samples=8)
    out = auto.pooled(parts, s, {"bake": 3.0}, ["w"], {"points": 5}, choice, compose)
    ob = out.objects[0]
    np.testing.assert_allclose(ob.value, [[2.0, 3.0, 1.0], [3.0, 3.0, 1.0]], rtol=1e-6)
    se = np.sqrt(np.array([[36 * 0.16 + 4 * 0.81, 36 * 0.01 + 4 * 0.04, 4 * 0.25],
                           [36 * 0.04 + 4 * 0.36, 36 * 0.16 + 4 * 0.81, 36 * 0.09 + 4 * 0.01]])) / 8
    np.testing.assert_allclose(ob.standard_error, se, rtol=1e-6)
    np.testing.assert_allclose(ob.standard_error[0, 0], 0.375, rtol=1e-6)    # sqrt(5.76 + 3.24) / 8
    assert ob.samples == 8 and ob.batches == 8 and ob.seconds == pytest.approx(2.0)
    assert ob.stats.rays == 140 and ob.stats.paths == 2 * 6 + 2 * 2
    assert composed == [ob] and np.all(ob.image == 7.0)
    assert out.mode == "AUTO" and out.auto is choice and out.warnings == ["w"] and out.guide_info == {"points": 5}
    assert out.seconds == {"bake": 3.0} and out.settings == s.as_dict()
    assert ob.name == "A" and ob.texels is a.texels


# ---- (g) determinism -----------------------------------------------------------------------------

def test_auto_is_deterministic_and_the_same_with_one_or_two_threads(narrow, narrow_solved, monkeypatch):
    """The noisy RoomAFloor (the guided parts run, a given solution), 16 px, 32 samples, small
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
    its parts (JSON-serialisable); a plain bake's has none."""
    result = baking.bake(cornell, ["Floor"], settings(bake_resolution=16), threads=2)
    stats = result.stats()
    entry = stats["auto"]
    assert entry == result.auto.as_dict()
    assert entry["solved"] is False and entry["mode"] == "UNGUIDED"
    assert [p[:2] for p in entry["parts"]] == [["UNGUIDED", 2], ["UNGUIDED", 30]]
    assert all(p[2] >= 0 for p in entry["parts"])
    assert entry["samples"] == [["UNGUIDED", 32]]
    assert stats["mode"] == "AUTO" and stats["objects"]["Floor"]["samples"] == 32
    json.loads(json.dumps(stats))
    plain = baking.bake(cornell, ["Floor"], settings(bake_mode="UNGUIDED", bake_resolution=16, bake_samples=4))
    assert "auto" not in plain.stats()


# ---- (i) too few samples for pilots --------------------------------------------------------------

@pytest.mark.parametrize("samples", [1, 8, 15])
def test_few_samples_are_one_unguided_part(narrow, samples):
    """Below 16 samples: one UNGUIDED part of all S samples (seed AUTO_PARTS · seed), no solve
    even where noisy, the relative variance not measured (NaN); the bake is that UNGUIDED bake's
    bytes."""
    s = settings(bake_resolution=16, bake_samples=samples, seed=3)
    result = baking.bake(narrow, ["RoomAFloor"], s, threads=2, solve=never)
    choice = result.auto
    assert np.isnan(choice.relative_variance) and not choice.solved and choice.mode == "UNGUIDED"
    assert choice.samples == (("UNGUIDED", samples),)
    assert [(m, n) for m, n, _ in choice.parts] == [("UNGUIDED", samples)]
    plain = baking.bake(narrow, ["RoomAFloor"], replace(s, bake_mode="UNGUIDED", seed=auto.AUTO_PARTS * 3), threads=2)
    np.testing.assert_array_equal(result.object("RoomAFloor").value, plain.object("RoomAFloor").value)
    np.testing.assert_array_equal(result.object("RoomAFloor").standard_error,
                                  plain.object("RoomAFloor").standard_error)
    np.testing.assert_array_equal(result.object("RoomAFloor").image, plain.object("RoomAFloor").image)
