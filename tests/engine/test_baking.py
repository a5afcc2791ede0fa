"""The bake (lmdp_addon.bake.driver): images and stats, batches and work units, determinism,
standard errors, cancellation, and the build's BVH."""
import numpy as np
import pytest

from lmdp_addon.bake import driver as baking
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.errors import Cancelled
from lmdp_addon.progress import Progress
from lmdp_addon.raycast import RayCaster

from bake_scenes import small


def test_bake_image_layout_margin_and_stats(cornell):
    r = baking.bake(cornell, ["Floor", "TallBox"], small(bake_margin=3))
    assert [o.name for o in r.objects] == ["Floor", "TallBox"]
    box = r.object("TallBox")
    assert box.image.shape == (16, 16, 4) and box.image.dtype == np.float32
    covered = box.texels.covered_mask()
    filled = box.image[..., 3] > 0
    assert np.all(filled[covered]) and filled.sum() > covered.sum()
    np.testing.assert_allclose(box.image[box.texels.row, box.texels.col, :3], box.value)
    assert box.image_name == "TallBox_lmdp_indirect"
    stats = r.stats()
    assert stats["mode"] == "UNGUIDED" and stats["settings"]["bake_samples"] == 8
    s = stats["objects"]["Floor"]
    assert s["texels"] == 256 and s["samples"] == 8 and s["paths"] == 256 * 8
    assert s["rays"] == s["closest_hit_rays"] + s["shadow_rays"] > s["paths"]
    assert s["seconds"]["bake"] > 0
    assert "bake" in r.summary()


@pytest.mark.parametrize("paths_per_unit", [96, baking.PATHS_PER_UNIT])
def test_bake_is_deterministic_for_a_seed_and_independent_of_threads(cornell, monkeypatch, paths_per_unit):
    # 96: many small units finishing out of order; the default: units of several whole batches
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", paths_per_unit)
    a = baking.bake(cornell, ["Floor"], small(seed=3), threads=1).objects[0]
    b = baking.bake(cornell, ["Floor"], small(seed=3), threads=2).objects[0]
    c = baking.bake(cornell, ["Floor"], small(seed=4), threads=2).objects[0]
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)


def test_bake_threads_come_from_the_machine_and_a_cap(monkeypatch):
    import os
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    monkeypatch.delenv(baking.THREADS_VARIABLE, raising=False)
    assert baking.bake_threads() == cores and baking.bake_threads(0) == cores
    assert baking.bake_threads(1) == 1 and baking.bake_threads(cores + 5) == cores
    monkeypatch.setenv(baking.THREADS_VARIABLE, "1")
    assert baking.bake_threads() == 1
    monkeypatch.setenv(baking.THREADS_VARIABLE, "many")
    assert baking.bake_threads() == cores


def test_standard_error_predicts_the_seed_to_seed_spread(cornell):
    """Two independent bakes differ by sqrt(se1² + se2²) per texel: the batch-based standard
    error is the real error. The mean of d²/(se1² + se2²) over n texels is 1 ± a few / sqrt(n)
    for Gaussian texel errors; heavy-tailed paths make it noisier, so the bound is a factor 2."""
    s1 = small(bake_resolution=16, bake_samples=32, seed=1)
    s2 = small(bake_resolution=16, bake_samples=32, seed=2)
    a = baking.bake(cornell, ["Floor"], s1).objects[0]
    b = baking.bake(cornell, ["Floor"], s2).objects[0]
    assert a.batches == 8
    d2 = (a.value.astype(float) - b.value) ** 2
    v = a.standard_error.astype(float) ** 2 + b.standard_error.astype(float) ** 2
    lit = v > 0  # texels under the boxes get no light at all
    ratio = np.median(d2[lit] / v[lit])
    # median of chi²(1) is 0.455 (t² with 14 degrees of freedom: 0.48)
    assert 0.455 / 2 < ratio < 0.455 * 2, ratio


def test_batches_divide_the_samples():
    assert baking.batch_count(64) == 8
    assert baking.batch_count(12) == 6
    assert baking.batch_count(7) == 7
    assert baking.batch_count(11) == 1
    assert baking.batch_count(1) == 1


@pytest.mark.parametrize("n_texels, samples", [(16384, 1), (16384, 4), (16384, 16), (16384, 64), (16384, 256),
                                               (9004, 16), (100_000, 16), (10, 16), (3, 7), (1, 1), (0, 4)])
def test_work_units_cover_every_batch_of_every_texel_once(n_texels, samples):
    B = baking.batch_count(samples)
    per_batch = samples // B
    group, units = baking.work_units(n_texels, B, per_batch)
    assert B % group == 0
    count = np.zeros((B, n_texels), int)
    for b0, lo, hi in units:
        assert b0 % group == 0 and 0 <= lo < hi <= n_texels
        count[b0:b0 + group, lo:hi] += 1
        # bounded size: a unit is one texel chunk of one batch, or whole batches that fit
        assert group == 1 or group * (hi - lo) * per_batch <= baking.PATHS_PER_UNIT
        assert (hi - lo) * per_batch <= baking.PATHS_PER_UNIT + per_batch or hi - lo == 1
    assert np.all(count == 1)
    assert len(units) >= min(baking.BAKE_THREADS, n_texels * B)
    if samples in (4, 16) and n_texels * per_batch <= baking.PATHS_PER_UNIT // 4:
        assert group > 1    # small batches share units


class CancelAfter(Progress):
    def __init__(self, n):
        super().__init__()
        self.n = n
        self.calls = 0

    def should_cancel(self):
        self.calls += 1
        return self.calls > self.n


def test_cancel_stops_between_work_units(cornell, monkeypatch):
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 256)
    progress = CancelAfter(3)
    with pytest.raises(Cancelled):
        baking.bake(cornell, ["Floor"], small(bake_resolution=32), progress=progress)
    assert progress.calls == 4


def test_guided_bake_of_a_changed_scene_uses_exact_lookups(cornell_solved):
    moved = scenes.build_scene_arrays("CORNELL_BOX")
    moved.vertices[:, 2] += 1e-3  # everything moved: the guide maps objects by name
    r = baking.bake(moved, ["Floor"], small(bake_mode="GUIDED"), lmdp=cornell_solved)
    assert r.guide_info["same_scene"] is False
    assert r.objects[0].stats.guided_vertices > 0


def test_guided_bake_traces_with_the_builds_bvh_only_when_the_geometry_is_the_same(cornell, cornell_solved):
    """Same geometry: the bake reuses the build's ray caster (no second BVH) and bakes what a
    fresh caster bakes; a moved scene gets its own."""
    settings = small(bake_mode="GUIDED")
    tracer, guide, _ = baking.make_tracer(cornell, settings, cornell_solved)
    assert tracer.caster is cornell_solved.dynamics.caster
    shared = baking.bake(cornell, ["Floor"], settings, lmdp=cornell_solved)
    fresh_tracer, _, _ = baking.make_tracer(cornell, settings, cornell_solved,
                                            caster=RayCaster(cornell))
    assert fresh_tracer.caster is not cornell_solved.dynamics.caster
    fresh = baking.bake_object(fresh_tracer, cornell, "Floor", settings, guide=guide)
    np.testing.assert_array_equal(shared.objects[0].value, fresh.value)
    moved = scenes.build_scene_arrays("CORNELL_BOX")
    moved.vertices[:, 2] += 1e-3
    assert baking.make_tracer(moved, settings, cornell_solved)[0].caster is not cornell_solved.dynamics.caster
