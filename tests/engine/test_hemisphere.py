"""Shirley–Chiu strata: equal solid angle, tiling, exact inverse, cosine weights (thesis 3.1.1)."""
import numpy as np
import pytest

from lmdp_addon.model import hemisphere as H


@pytest.fixture(scope="module")
def uniform_square():
    rng = np.random.default_rng(1)
    return rng.random(400_000), rng.random(400_000)


def test_square_to_hemisphere_gives_unit_upper_directions(uniform_square):
    d = H.square_to_hemisphere(*uniform_square)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert d[:, 2].min() >= 0.0


def test_inverse_map_round_trips(uniform_square):
    u, v = uniform_square
    uu, vv = H.hemisphere_to_square(H.square_to_hemisphere(u, v))
    assert np.abs(uu - u).max() < 1e-9 and np.abs(vv - v).max() < 1e-9


def test_map_is_equal_area(uniform_square):
    """Uniform points on the square are uniform in solid angle: E[z] = 1/2, E[z^2] = 1/3, and
    each of 8 azimuth sectors x 4 z-bands (equal solid angles) gets 1/32 of the samples."""
    d = H.square_to_hemisphere(*uniform_square)
    n = len(d)
    assert abs(d[:, 2].mean() - 0.5) < 5 * np.sqrt(1 / 12 / n)
    assert abs((d[:, 2] ** 2).mean() - 1 / 3) < 5 * np.sqrt(4 / 45 / n)
    sector = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
    band = np.minimum((d[:, 2] * 4).astype(int), 3)  # z uniform in [0,1] <=> equal solid angle
    counts = np.bincount(sector * 4 + band, minlength=32) / n
    sigma = np.sqrt((1 / 32) * (31 / 32) / n)
    assert np.abs(counts - 1 / 32).max() < 5 * sigma


@pytest.mark.parametrize("su,sv", [(1, 1), (2, 2), (4, 4), (3, 5), (8, 8)])
def test_strata_have_equal_solid_angle_and_tile_the_hemisphere(su, sv):
    rng = np.random.default_rng(su * 100 + sv)
    n = 300_000
    # Uniform directions on the hemisphere by an independent method (normalised Gaussians).
    g = rng.normal(size=(n, 3))
    g[:, 2] = np.abs(g[:, 2])
    d = g / np.linalg.norm(g, axis=1, keepdims=True)
    k = H.stratum_of_local_direction(d, su, sv)
    assert k.min() >= 0 and k.max() < su * sv  # every direction lies in exactly one stratum
    share = np.bincount(k, minlength=su * sv) / n
    p = 1.0 / (su * sv)
    assert np.abs(share - p).max() <= 5 * np.sqrt(p * (1 - p) / n) + 1e-12
    assert H.stratum_solid_angle(su, sv) == pytest.approx(2 * np.pi / (su * sv))


def test_directions_below_horizon_have_no_stratum():
    assert H.stratum_of_local_direction(np.array([[0.0, 0.6, -0.8]]), 4, 4)[0] == -1


def test_stratum_lookup_matches_the_inverse_concentric_map():
    """The one-arctangent stratum lookup agrees with ``hemisphere_to_square`` (arctan2 and a
    four-way select), float64 and float32 directions alike."""
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for su, sv in ((4, 4), (3, 5), (8, 8), (1, 1)):
        u, v = H.hemisphere_to_square(d)
        iu = np.minimum((u * su).astype(np.int64), su - 1)
        iv = np.minimum((v * sv).astype(np.int64), sv - 1)
        expected = np.where(d[:, 2] > 0, iu * sv + iv, -1)
        np.testing.assert_array_equal(H.stratum_of_local_direction(d, su, sv), expected)
        k32 = H.stratum_of_local_direction(d.astype(np.float32), su, sv)
        assert np.mean(k32 == expected) > 0.9999


def test_stratum_samples_land_in_their_stratum():
    su, sv = 4, 6
    rng = np.random.default_rng(3)
    k = rng.integers(0, su * sv, 10_000)
    u, v = H.stratum_square_samples(k, rng.random(10_000), rng.random(10_000), su, sv)
    assert np.array_equal(H.stratum_of_local_direction(H.square_to_hemisphere(u, v), su, sv), k)


@pytest.mark.parametrize("su,sv", [(1, 1), (4, 4), (3, 5)])
def test_cosine_weights_are_the_projected_solid_angles(su, sv):
    w = H.stratum_cosine_weights(su, sv)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(7)
    u, v = rng.random(2_000_000), rng.random(2_000_000)
    d = H.square_to_hemisphere(u, v)
    k = H.stratum_of_local_direction(d, su, sv)
    # ∫_k cos dω / π = (2π/S)/π · E[cos | k] ... estimated directly: 2 E[z · 1_k].
    estimate = 2.0 * np.bincount(k, weights=d[:, 2], minlength=su * sv) / len(u)
    assert np.abs(estimate - w).max() < 5 * np.sqrt(2.0 / len(u))
    if su == sv == 1:
        assert w[0] == pytest.approx(1.0)


def test_tangent_frames_are_orthonormal_and_deterministic():
    rng = np.random.default_rng(5)
    n = rng.normal(size=(1000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[0] = [0, 0, -1]
    n[1] = [0, 0, 1]
    f = H.tangent_frame(n)
    assert np.allclose(np.einsum("nij,nkj->nik", f, f), np.eye(3), atol=1e-12)
    assert np.allclose(f[:, 2], n)
    assert np.allclose(np.linalg.det(f), 1.0)
    assert np.array_equal(H.tangent_frame(n), f)
    local = H.square_to_hemisphere(rng.random(1000), rng.random(1000))
    world = H.local_to_world(local, f)
    assert np.allclose(H.world_to_local(world, f), local, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", world, n) >= -1e-12)
