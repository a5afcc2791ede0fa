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


# ---- class 17: the legend of a z that is 0 everywhere ----------------------------------------------

def unlit_solution(channels):
    """A solved problem whose only terminal with light is unreachable: z = 0 on every state."""
    lmdp = random_lmdp(m=50, channels=channels)
    lmdp.z_terminal[:] = 0.0
    return solve_desirability(lmdp, "ITERATIVE")


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("quantity", ["Z", "COST_TO_GO"])
def test_a_z_that_is_0_everywhere_gets_an_empty_legend_and_the_missing_colour(channels, quantity):
    from lmdp_addon.display.colormap import MISSING_SRGB, srgb_to_linear
    from lmdp_addon.display.vertex_field import FieldWeights, state_quantity, vertex_field
    sol = unlit_solution(channels)
    assert not np.any(sol.z > 0)
    sq = state_quantity(sol, quantity)
    text = sq.scale.describe()
    assert ("z is 0" if quantity == "Z" else "J is +inf") in text and "no light reaches" in text, text
    assert "decades" not in text and ".." not in text
    assert sq.scale.empty and sq.scale.decades == 0.0
    m = len(sol.y)
    weights = FieldWeights(sp.identity(m, format="csr", dtype=np.float32), np.arange(m), np.zeros(m, bool))
    field = vertex_field(weights, sq)
    assert np.all(np.isnan(field.position))
    assert np.allclose(field.color[:, :3], srgb_to_linear(MISSING_SRGB), atol=1e-6)
    # The legend's values say what the data is: z = 0, J = +inf.
    assert set(sq.scale.tick_labels(5)) == ({"0"} if quantity == "Z" else {"inf"})


def test_a_partly_lit_z_keeps_its_range():
    from lmdp_addon.display.colormap import log_scale_from_log10
    scale = log_scale_from_log10(np.array([-np.inf, -2.0, 0.0]), "z", 0.0, 100.0, empty_note="never")
    assert not scale.empty and scale.describe() == "z: 0.01 .. 1 (log, 2.0 decades)"
