"""The build's ray patterns (lmdp_addon.model.patterns)."""
import numpy as np

from lmdp_addon.model import hemisphere as H
from lmdp_addon.model.patterns import DirectionPatterns


def test_ray_directions_follow_brdf_cos_within_each_stratum():
    """Rays in stratum k have density ∝ cos θ there: E[1/cos] over stratum k's rays equals
    Ω_k / (π w_k) (the solid angle over the cosine mass)."""
    su, sv, R = 4, 4, 4096
    pat = DirectionPatterns(su, sv, R, np.random.default_rng(0), pool=1)
    d = pat.local[0].astype(np.float64)
    k = H.stratum_of_local_direction(d, su, sv)
    assert np.array_equal(k, pat.ray_stratum)
    w = H.stratum_cosine_weights(su, sv)
    inv_cos = (1.0 / d[:, 2]).reshape(su * sv, R)
    expected = H.stratum_solid_angle(su, sv) / (np.pi * w)
    sem = inv_cos.std(axis=1) / np.sqrt(R)
    assert np.all(np.abs(inv_cos.mean(axis=1) - expected) < 5 * sem)
