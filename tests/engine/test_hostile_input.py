"""Hostile-but-realistic input to the engine (issue 22, classes 1, 10, 14, 16, 17).

Each test here failed before its fix: far-away or non-finite geometry changing a room's bake,
bakes without a memory estimate, ITERATIVE running past ``max_iterations``, non-finite UVs
reported as overlaps, and a legend for a z that is 0 everywhere.
"""
import numpy as np
import pytest
import scipy.sparse as sp

from lmdp_addon.errors import SceneError
from lmdp_addon.model.costs import FirstExitLMDP
from lmdp_addon.model.solvers import solve_desirability


def random_lmdp(m=400, seed=3, channels=1):
    """A random sparse first-exit problem: 6 successors per state, some mass to the light."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(m), 6)
    P = sp.csr_matrix((rng.random(len(rows)), (rows, rng.integers(0, m, len(rows)))),
                      shape=(m, m + 2)).tolil()
    P[np.flatnonzero(rng.random(m) < 0.2), m] = 0.3
    P[np.arange(m), m + 1] = 0.01
    P = sp.csr_matrix(P)
    P = sp.csr_matrix(sp.diags(1 / np.asarray(P.sum(1)).ravel()) @ P)
    q = np.tile(np.exp(-0.1 * np.ones((m, 1))), (1, channels)) * np.linspace(1.0, 0.8, channels)
    z_terminal = np.zeros((2, channels))
    z_terminal[0] = 1.0
    return FirstExitLMDP(P=P, q=q, z_terminal=z_terminal, lambda_=0.1,
                         cost_mode="THESIS" if channels == 1 else "PHYSICAL", g=-np.log(q))


# ---- class 14: ITERATIVE honours max_iterations -------------------------------------------------

@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("cap", [1, 2, 8, 9, 20])
def test_iterative_stops_at_max_iterations_and_says_it_did_not_converge(channels, cap):
    lmdp = random_lmdp(channels=channels)
    sol = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-10, max_iterations=cap)
    assert sol.iterations <= cap
    assert not sol.converged
    assert sol.residual > 1e-9
    assert f"cap of {cap} iterations" in sol.message and "Max Iterations" in sol.message
    assert "NOT converged" in sol.summary()


def test_iterative_with_enough_iterations_still_converges():
    lmdp = random_lmdp(channels=3)
    sol = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-10, max_iterations=10000)
    assert sol.converged and sol.residual <= 1e-9 and sol.iterations < 100


@pytest.mark.parametrize("solver", ["POWER", "ITERATIVE"])
def test_max_iterations_below_one_is_refused_naming_the_setting(solver):
    with pytest.raises(SceneError, match="Max Iterations"):
        solve_desirability(random_lmdp(), solver, max_iterations=0)
