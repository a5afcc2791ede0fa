"""The guide (lmdp_addon.bake.guide): g_s's sampling and density, the mixture's weights, and the
neighbour average of the optimal policies."""
import numpy as np
import pytest

from bake_scenes import K, assert_within, random_guide, unit_vector
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.guide import (GUIDE_NEIGHBOURS, NEIGHBOUR_MAX_ANGLE, GuidedDirections,
                                   neighbour_average)
from lmdp_addon.model import pipeline
from lmdp_addon.model.hemisphere import stratum_of_local_direction
from lmdp_addon.model.locator import StateLocator
from lmdp_addon.model.policy import stratum_policy
from lmdp_addon.model.states import sample_states
from lmdp_addon.settings import Settings


def test_guide_samples_follow_the_policy_and_the_density_integrates_to_one():
    guide, normals = random_guide()
    rng = np.random.default_rng(2)
    S = guide.n_strata
    for s in range(len(normals)):
        n = 200_000
        states = np.full(n, s)
        d = guide.sample(states, rng.random((n, 2)), first=True)
        local = np.einsum("ij,kj->ki", guide.frames[s], d)
        k = stratum_of_local_direction(local, guide.strata_u, guide.strata_v)
        freq = np.bincount(k, minlength=S) / n
        p = guide.first[s]
        assert np.all(np.abs(freq - p) <= K * np.sqrt(p * (1 - p) / n) + 1e-12), (freq, p)
        # ∫ g dω over the sphere by uniform sampling: 4π E[g] = 1.
        w = rng.normal(size=(n, 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        g = guide.density(states, w, first=True) * 4 * np.pi
        assert_within(g, 1.0)
        # Within a stratum the samples are uniform in solid angle: the density at the samples
        # equals u*(k) S / 2π.
        np.testing.assert_allclose(guide.density(states, d, first=True), p[k] * S / (2 * np.pi), rtol=1e-9)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.9])
def test_mixture_weights_have_expectation_one(alpha):
    """E[cos/(π p)] = ∫ cos/π dω = 1 for the mixture pdf: the GUIDED direction sampling is
    unbiased. The shading normal is tilted from the state's (directions below its horizon get
    weight 0, the pdf stays exact)."""
    guide, normals = random_guide(m=1, seed=3)
    directions = GuidedDirections(guide, alpha)
    n = 400_000
    rng = np.random.default_rng(4)
    tilted = normals[0] + 0.3 * np.cross(normals[0], [0.0, 0.0, 1.0])
    tilted /= np.linalg.norm(tilted)
    shading = np.tile(tilted.astype(np.float32), (n, 1))
    d, w, cos = directions.sample(shading, np.zeros(n, dtype=np.int64), rng.random((n, 2)), rng.random(n),
                                  first=True)
    assert_within(w, 1.0)
    assert np.all(w[cos <= 0] == 0)


def test_guided_vertices_without_a_state_use_cosine_sampling():
    guide, _ = random_guide(m=1)
    directions = GuidedDirections(guide, 0.8)
    n = 1000
    rng = np.random.default_rng(5)
    normals = np.tile(np.array([0, 0, 1], np.float32), (n, 1))
    _, w, cos = directions.sample(normals, np.full(n, -1), rng.random((n, 2)), rng.random(n), first=True)
    np.testing.assert_array_equal(w, 1.0)
    assert np.all(cos > 0)


def test_neighbour_average_is_a_distribution_over_shared_strata_and_denoises_the_guide():
    """u* from 4 rays per stratum, averaged over 16 same-normal neighbours, is closer to u* of the
    same points from 256 rays per stratum than the raw rows are (mean L1 distance below 0.8 x);
    rows stay distributions; only points with the same normal (hence the same strata) are mixed."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    raw = pipeline.run_all(scene, Settings(point_count=1024, rays_per_stratum=4))
    ref = pipeline.run_all(scene, Settings(point_count=1024, rays_per_stratum=256))
    states = raw.states
    locator = StateLocator(scene, states)
    u_raw = stratum_policy(raw.dynamics, raw.solution, "points")
    u_ref = stratum_policy(ref.dynamics, ref.solution, "points")
    u_avg = neighbour_average(u_raw, locator, states.normals, GUIDE_NEIGHBOURS)
    np.testing.assert_allclose(u_avg.sum(axis=1), 1.0, atol=1e-12)
    assert np.all(u_avg >= 0)
    err_raw = np.abs(u_raw - u_ref).sum(axis=1).mean()
    err_avg = np.abs(u_avg - u_ref).sum(axis=1).mean()
    assert err_avg < 0.8 * err_raw, (err_avg, err_raw)
    # One neighbour is the identity; a point whose normal is farther than NEIGHBOUR_MAX_ANGLE
    # from every other point's keeps its row.
    np.testing.assert_array_equal(neighbour_average(u_raw, locator, states.normals, 1), u_raw)
    lonely = states.normals.copy()
    lonely[0] = unit_vector(lonely[0] + 0.5 * unit_vector(np.cross(lonely[0], [0.3, 0.5, 0.8])))
    np.testing.assert_array_equal(neighbour_average(u_raw, locator, lonely, GUIDE_NEIGHBOURS)[0], u_raw[0])


def test_neighbour_average_mixes_nearly_equal_normals_on_the_same_frame_branch():
    """Within NEIGHBOUR_MAX_ANGLE normals count as equal, but never across a sign change of the
    normal's z (where the tangent frame jumps); each point's row is the mean of exactly those."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 256, 2, 2, seed=3)
    locator = StateLocator(scene, states)
    rng = np.random.default_rng(4)
    # Tilt every normal at random by up to 2 x the tolerance; on the back wall (normal -y,
    # z = 0) the tilt flips the sign of z at random.
    normals = np.array([unit_vector(n + np.tan(np.radians(2 * NEIGHBOUR_MAX_ANGLE)) * rng.random()
                                    * unit_vector(rng.normal(size=3))) for n in states.normals])
    rows = np.eye(len(normals))                   # row i marks point i: the mean shows who is in
    out = neighbour_average(rows, locator, normals, 16)
    cos_max = np.cos(np.radians(NEIGHBOUR_MAX_ANGLE))
    mixed_any = flipped = 0
    for o, tree in locator.trees.items():
        ids = locator.index[o]
        _, nn = tree.query(tree.data, k=min(16, len(ids)))
        for i, row in zip(ids, ids[nn]):
            ok = (normals[row] @ normals[i] >= cos_max) & ((normals[row, 2] >= 0) == (normals[i, 2] >= 0))
            expected = np.zeros(len(normals))
            expected[row[ok]] = 1.0 / ok.sum()
            np.testing.assert_allclose(out[i], expected, atol=1e-12)
            mixed_any += ok.sum() > 1
            flipped += np.any((normals[row] @ normals[i] >= cos_max) & ~ok)
    assert mixed_any > 0 and flipped > 0  # both rules were exercised
