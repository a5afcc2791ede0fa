"""Batched ray casting (lmdp_addon.raycast) against hits computed by hand."""
import numpy as np
import pytest

from lmdp_addon import raycast
from lmdp_addon.scene_arrays import SceneArrays


def two_squares(degenerate_first):
    """Two unit squares facing up at z = 1 (x in [0, 1]) and z = 2 (x in [2, 3]), optionally
    after a degenerate and a non-finite triangle, which the BVH leaves out: then embree's
    primitive ids are not the scene's triangle indices."""
    v = [[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
         [2, 0, 2], [3, 0, 2], [3, 1, 2], [2, 1, 2],
         [0, 0, 0], [1, 0, 0], [2, 0, 0], [np.nan, 0, 0]]
    squares = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    bad = [[8, 9, 10], [11, 8, 9]]
    tris = bad + squares if degenerate_first else squares
    n = len(tris)
    return SceneArrays(np.array(v, dtype=np.float64), np.array(tris), np.zeros(n, dtype=np.int64),
                       np.full((n, 3), 0.5), np.zeros((n, 3)), ["Squares"], np.array([True]))


@pytest.mark.parametrize("batch", [raycast.BATCH, 3])
@pytest.mark.parametrize("degenerate_first", [False, True])
def test_hits_are_scene_triangles_with_distance_barycentrics_and_misses(degenerate_first, batch,
                                                                        monkeypatch):
    monkeypatch.setattr(raycast, "BATCH", batch)  # 3: several embreex calls per query
    scene = two_squares(degenerate_first)
    caster = raycast.RayCaster(scene)
    shift = 2 if degenerate_first else 0
    assert caster._identity == (not degenerate_first)
    rng = np.random.default_rng(0)
    n = 10
    xy = rng.random((n, 2)) * 0.98 + 0.01
    x = np.where(np.arange(n) % 3 == 2, xy[:, 0] + 5.0, np.where(np.arange(n) % 3 == 1, xy[:, 0] + 2.0, xy[:, 0]))
    origins = np.stack([x, xy[:, 1], np.full(n, -1.0)], axis=1).astype(np.float32)
    up = np.tile(np.array([0, 0, 1], np.float32), (n, 1))
    tri, dist, bu, bv = caster.intersect(origins, up, barycentrics=True)
    on_first = np.arange(n) % 3 == 0
    on_second = np.arange(n) % 3 == 1
    miss = np.arange(n) % 3 == 2
    # Which triangle of each square: (0, 1, 2) covers x >= y, (0, 2, 3) the rest.
    local = (xy[:, 0] < xy[:, 1]).astype(np.int64)
    np.testing.assert_array_equal(tri[on_first], shift + local[on_first])
    np.testing.assert_array_equal(tri[on_second], shift + 2 + local[on_second])
    assert np.all(tri[miss] == -1) and np.all(np.isinf(dist[miss]))
    np.testing.assert_allclose(dist[on_first], 2.0, rtol=1e-6)
    np.testing.assert_allclose(dist[on_second], 3.0, rtol=1e-6)
    # The barycentrics give back the hit point on the hit triangle.
    hit = ~miss
    c = scene.corners()[tri[hit]]
    p = c[:, 0] + bu[hit, None] * (c[:, 1] - c[:, 0]) + bv[hit, None] * (c[:, 2] - c[:, 0])
    np.testing.assert_allclose(p[:, :2], origins[hit, :2], atol=1e-5)
    # Occlusion: segments ending before the first square are free, longer ones are blocked.
    short = caster.occluded(origins, up, np.full(n, 1.5, np.float32))
    long = caster.occluded(origins, up, np.full(n, 10.0, np.float32))
    assert not np.any(short)
    np.testing.assert_array_equal(long, hit)
    assert caster.rays_cast == 3 * n


def test_empty_queries():
    caster = raycast.RayCaster(two_squares(False))
    empty = np.zeros((0, 3), np.float32)
    tri, dist, bu, bv = caster.intersect(empty, empty, barycentrics=True)
    assert len(tri) == len(dist) == len(bu) == len(bv) == 0 and tri.dtype == np.int64
    assert len(caster.occluded(empty, empty, np.zeros(0, np.float32))) == 0
