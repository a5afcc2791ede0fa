"""Path reuse (lmdp_addon.bake.reuse): tiles of texels share their first bounces, weighted by the
balance heuristic. The tiles (one sample number each, at most tile² texels, moving from sample to
sample), a tile of one path giving back its own estimate, unbiased against plain path tracing
(through the narrow opening's hatch, UNGUIDED and GUIDED; direct + indirect content on the
Cornell box), lower per-texel variance, the region errors from batch means (the texels of a
tile are correlated, so the independent-texel formula would understate them), determinism
whatever the thread count, and off where it does not apply."""
from dataclasses import replace

import numpy as np
import pytest

from bake_scenes import K, small
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver as baking
from lmdp_addon.bake import reuse
from lmdp_addon.bake.clamp import SampleClamp
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.model import pipeline
from lmdp_addon.settings import Settings


@pytest.fixture(scope="module")
def narrow():
    scene = scenes.build_scene_arrays("NARROW_OPENING")
    return scene, pipeline.run_all(scene, Settings(point_count=1024))


def agree(a, b):
    """The region means of two bakes (``(mean, error)`` pairs) agree within K errors of both."""
    (ma, sa), (mb, sb) = a, b
    assert np.all(np.abs(ma - mb) <= K * np.sqrt(sa ** 2 + sb ** 2)), (ma, mb, sa, sb)


def test_tiles_hold_one_sample_at_most_tile_squared_texels_and_move_with_the_sample():
    rng = np.random.default_rng(0)
    n = 5000
    row, col = rng.integers(0, 64, n), rng.integers(0, 64, n)
    sample = rng.integers(0, 6, n)
    g = reuse.groups(row, col, sample, 4)
    np.testing.assert_array_equal(g, reuse.groups(row, col, sample, 4))            # a hash, no stream
    for k in np.unique(g):
        members = g == k
        assert len(np.unique(sample[members])) == 1 and members.sum() <= 16
        assert np.ptp(row[members]) < 8 and np.ptp(col[members]) < 8               # one 8 x 8 block
    every = np.arange(64 * 64)
    r, c = every // 64, every % 64
    a = reuse.groups(r, c, np.zeros_like(every), 4)
    b = reuse.groups(r, c, np.ones_like(every), 4)
    assert np.bincount(a).max() == 16
    assert not np.array_equal(a[:, None] == a[None, :], b[:, None] == b[None, :])   # other tiles
    m = reuse.members(a)
    assert m.shape == (256, 16) and np.array_equal(np.sort(m[m >= 0]), every)


def test_a_tile_of_one_path_is_the_paths_own_estimate(cornell):
    """Each path in a tile of its own: (reuse) is f_j(y_j) L̂_j / p_j(y_j) = the path's light."""
    tracer = IndirectTracer(cornell, "UNGUIDED", light_share=0.0, path_reuse=4)
    n = 4000
    rng = np.random.default_rng(5)
    points = np.tile([0.1, 0.2, 0.001], (n, 1)) + rng.normal(0, 0.05, (n, 3)) * [1, 1, 0]
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    args = (points, normals, np.full(n, -1), rng.random((n, 2)), rng.random(n))
    own, _ = tracer.trace(*args, np.random.default_rng(1))
    alone, stats = tracer.trace(*args, np.random.default_rng(1), reuse_groups=np.arange(n))
    assert stats.shared_hits == 0 and np.any(own > 0)
    np.testing.assert_allclose(alone, own, rtol=2e-5, atol=1e-7)


def test_path_reuse_is_unbiased_through_the_hatch(narrow):
    """RoomA of the narrow opening is lit only through the hatch: UNGUIDED and GUIDED with path
    reuse against plain path tracing (no reuse, no light connections), equal high samples: the
    floor's means agree within 5 errors of both (the reuse bakes' errors from their batch
    means), each resolved to better than 10 %."""
    scene, lmdp = narrow
    settings = small(bake_resolution=16, bake_samples=1024, bake_margin=0)
    plain = baking.bake(scene, ["RoomAFloor"], replace(settings, seed=3, path_reuse=1, light_share=0.0)).objects[0]
    shared = baking.bake(scene, ["RoomAFloor"], replace(settings, seed=4, path_reuse=4)).objects[0]
    guided = baking.bake(scene, ["RoomAFloor"], replace(settings, bake_mode="GUIDED", seed=5, path_reuse=4),
                         lmdp).objects[0]
    assert shared.stats.shared_hits > 2 * shared.stats.paths and guided.stats.shared_hits > 2 * guided.stats.paths
    for ob in (plain, shared, guided):
        mean, se = ob.mean_and_error()
        assert np.all(se < 0.1 * mean), (ob.name, se / mean)
    agree(plain.mean_and_error(), shared.mean_and_error())
    agree(plain.mean_and_error(), guided.mean_and_error())


def test_path_reuse_keeps_the_direct_light_of_each_texel_its_own(cornell):
    """Direct + indirect content on the Cornell box's floor (the direct light at x_0 stays each
    texel's own; only the light after y_1 is shared): the mean agrees with the bake without reuse."""
    settings = small(bake_resolution=16, bake_samples=256, bake_margin=0, bake_content="DIRECT_INDIRECT")
    plain = baking.bake(cornell, ["Floor"], replace(settings, seed=1, path_reuse=1)).objects[0]
    shared = baking.bake(cornell, ["Floor"], replace(settings, seed=2, path_reuse=4)).objects[0]
    assert shared.stats.shared_hits > 0
    agree(plain.mean_and_error(), shared.mean_and_error())


def test_path_reuse_lowers_the_variance_of_each_texel(cornell):
    """Same texels, same samples: per-texel variances with tiles of about 4 x 4 texels are below
    the paths' own (the mean log ratio below 0 by 5 of its standard errors, and below log 1/2)."""
    settings = small(bake_resolution=64, bake_samples=32, bake_margin=0)
    own = baking.bake(cornell, ["Floor"], replace(settings, seed=1, path_reuse=1)).objects[0]
    shared = baking.bake(cornell, ["Floor"], replace(settings, seed=2, path_reuse=4)).objects[0]
    vo = (own.standard_error.astype(float) ** 2).sum(axis=1)
    vs = (shared.standard_error.astype(float) ** 2).sum(axis=1)
    lit = (vo > 0) & (vs > 0)
    log_ratio = np.log(vs[lit] / vo[lit])
    assert log_ratio.mean() < min(np.log(0.5), -K * log_ratio.std() / np.sqrt(lit.sum())), log_ratio.mean()


def test_region_errors_come_from_batch_means_and_predict_the_seed_to_seed_spread(cornell):
    """With path reuse a tile's texels share paths: the floor mean's error from the batch means
    is well above the independent-texel formula, and it predicts the spread between seeds
    (the squared differences of 8 seed pairs, over their predicted variances, average about 1)."""
    settings = small(bake_resolution=32, bake_samples=64, bake_margin=0, path_reuse=4)
    bakes = [baking.bake(cornell, ["Floor"], replace(settings, seed=s)).objects[0] for s in range(16)]
    ob = bakes[0]
    independent = np.sqrt((ob.standard_error.astype(float) ** 2).sum(axis=0)) / ob.n_texels
    assert np.all(ob.mean_and_error()[1] > 1.5 * independent)
    z2 = []
    for a, b in zip(bakes[::2], bakes[1::2]):
        (ma, sa), (mb, sb) = a.mean_and_error(), b.mean_and_error()
        z2.append((ma - mb) ** 2 / (sa ** 2 + sb ** 2))
    z2 = np.mean(z2)           # ~1; each term is F-distributed (7 dof a side), so a wide bound
    assert 0.2 < z2 < 4.0, z2


def test_path_reuse_is_deterministic_whatever_the_threads(cornell, monkeypatch):
    monkeypatch.setattr(baking, "PATHS_PER_UNIT", 96)                     # many units, out of order
    bake = lambda threads: baking.bake(cornell, ["Floor"], small(seed=7, path_reuse=4), threads=threads).objects[0]
    a, b = bake(1), bake(2)
    assert a.stats.shared_hits > 0
    np.testing.assert_array_equal(a.value, b.value)
    np.testing.assert_array_equal(a.batch_means, b.batch_means)


def test_path_reuse_is_off_under_a_clamp_and_in_the_gather_modes(cornell):
    tracer = IndirectTracer(cornell, "UNGUIDED", path_reuse=4, clamp=SampleClamp(direct=0.0, indirect=10.0))
    assert tracer.path_reuse == 1
    assert "clamp" in reuse.unavailable("UNGUIDED", SampleClamp(direct=0.0, indirect=10.0), None)
    assert reuse.unavailable("FINAL_GATHER", None, None) and reuse.unavailable("GUIDED", None, None) is None
    assert reuse.off_reason(cornell, Settings(bake_mode="AUTO", clamp_indirect=10.0)).startswith("path reuse off")
    assert reuse.off_reason(cornell, Settings(path_reuse=1)) is None
    ob = baking.bake(cornell, ["Floor"], small(clamp_indirect=10.0)).objects[0]
    assert ob.stats.shared_hits == 0
