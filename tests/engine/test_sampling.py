"""Shared sequences and warps (lmdp_addon.sampling)."""
import numpy as np

from bake_scenes import assert_within
from lmdp_addon.model.hemisphere import concentric_square_to_disk
from lmdp_addon.sampling import cosine_directions, radical_inverse2, stratified_first_uniforms


def test_stratified_first_uniforms_are_stratified():
    rng = np.random.default_rng(0)
    u, mix = stratified_first_uniforms(3, 16, rng)
    assert u.shape == (3, 16, 2) and mix.shape == (3, 16)
    for t in range(3):
        # one sample in each of the 16 columns and each of the 16 rows of the unit square
        assert len(np.unique(np.floor(u[t, :, 0] * 16))) == 16
        assert len(np.unique(np.floor(u[t, :, 1] * 16))) == 16
    np.testing.assert_allclose(radical_inverse2([0, 1, 2, 3, 5]), [0, 0.5, 0.25, 0.75, 0.625])


def test_cosine_warps_are_shirley_chiu_and_polar():
    """The texel's stratified first bounce uses the concentric map (as hemisphere.py), later
    bounces the polar map; both give cosine-distributed directions: E[cos θ] = 2/3 and the
    fraction within θ < 60° is sin²(60°) = 3/4."""
    rng = np.random.default_rng(6)
    u = rng.random((100_000, 2))
    normals = np.tile(np.array([0, 0, 1], np.float32), (len(u), 1))
    d = cosine_directions(normals, u, stratified=True)
    x, y = concentric_square_to_disk(u[:, 0], u[:, 1])
    np.testing.assert_allclose(d[:, 0], x, atol=2e-6)
    np.testing.assert_allclose(d[:, 1], y, atol=2e-6)
    for stratified in (True, False):
        d = cosine_directions(normals, u, stratified=stratified).astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
        assert_within(d[:, 2], 2.0 / 3.0)
        assert_within((d[:, 2] > 0.5).astype(float), 0.75)
