"""Solvers of the first-exit LMDP (thesis 2.2.2 / 3.1.4) on problems with known answers.

The scene-free problems here pin down the numerics: exact log-domain answers for any λ, the
near-singular λ -> 0 limit, unreachable states, float32 vs float64.
"""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.special import logsumexp

from lmdp_addon.model.costs import FirstExitLMDP
from lmdp_addon.errors import BudgetError
from lmdp_addon.model.policy import optimal_policy
from lmdp_addon.model.solvers import hops_to_light, solve_desirability

SOLVERS = ("POWER", "DIRECT", "ITERATIVE")
LAMBDAS = (1e-6, 1e-3, 0.1, 1.0, 31.4, 1e3)


def thesis_lmdp(P, lam, z_terminal):
    """THESIS-mode problem: g = 1 on every non-terminal state."""
    m = P.shape[0]
    g = np.ones((m, 1))
    return FirstExitLMDP(P=sp.csr_matrix(P), q=np.exp(-lam * g), z_terminal=np.asarray(z_terminal, float).reshape(-1, 1),
                         lambda_=lam, cost_mode="THESIS", g=g)


def chain(m):
    """State i moves to i-1; state 0 moves to the emitter terminal (column m); void is column m+1."""
    rows = np.arange(m)
    cols = np.where(rows == 0, m, rows - 1)
    return sp.csr_matrix((np.ones(m), (rows, cols)), shape=(m, m + 2))


def random_problem(m, seed, leak=0.05):
    """Random sparse stochastic P: each state has 6 successors, some mass to the emitter/void."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(m), 6)
    cols = rng.integers(0, m, len(rows))
    w = rng.random(len(rows))
    P = sp.csr_matrix((w, (rows, cols)), shape=(m, m + 2)).tolil()
    to_light = rng.random(m) < 0.2
    P[np.flatnonzero(to_light), m] = leak * 6
    P[np.arange(m), m + 1] = 0.01
    P = sp.csr_matrix(P)
    P = sp.diags(1 / np.asarray(P.sum(1)).ravel()) @ P
    return sp.csr_matrix(P)


def log_neumann_reference(P, lam, z_terminal, terms=400):
    """Independent log-domain Neumann series: log z = logsumexp_k log(q^(k+1) P_NN^k P_NT z_T)."""
    P = sp.csr_matrix(P)
    m = P.shape[0]
    logP = np.full((m, P.shape[1]), -np.inf)
    dense = P.toarray()
    logP[dense > 0] = np.log(dense[dense > 0])
    with np.errstate(divide="ignore"):
        logzt = np.log(np.asarray(z_terminal, float))
    v = logsumexp(logP[:, m:] + logzt[None, :], axis=1)   # log(P_NT z_T)
    acc = -lam + v
    for k in range(1, terms):
        v = logsumexp(logP[:, :m] + v[None, :], axis=1)     # log(P_NN^k P_NT z_T)
        acc = np.logaddexp(acc, -(k + 1) * lam + v)
    return acc


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("lam", LAMBDAS)
def test_chain_has_exact_log_desirability_for_any_lambda(solver, lam):
    m = 60
    sol = solve_desirability(thesis_lmdp(chain(m), lam, [1.0, 0.0]), solver, tolerance=1e-12,
                             max_iterations=5000)
    hops = np.arange(m) + 1
    assert sol.converged, sol.message
    assert np.all(np.isfinite(sol.log_z))
    assert np.allclose(sol.log_z[:, 0], -lam * hops, rtol=1e-10, atol=1e-12)
    # J = -(log z)/λ is the number of transitions to the light, whatever λ.
    assert np.allclose(sol.cost_to_go[:, 0], hops, rtol=1e-9)
    if lam == 1e3:
        assert np.all(sol.z[1:] == 0.0)  # z itself underflows: log_z is the exact answer


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("lam", LAMBDAS)
def test_random_graph_matches_log_domain_reference(solver, lam):
    m = 150
    P = random_problem(m, seed=3)
    zt = [1.0, 0.0]
    sol = solve_desirability(thesis_lmdp(P, lam, zt), solver, tolerance=1e-13, max_iterations=100000)
    assert sol.converged, sol.message
    assert not np.any(np.isnan(sol.log_z)) and not np.any(np.isnan(sol.z))
    if lam >= 0.1:  # the reference series converges fast enough only away from λ -> 0
        ref = log_neumann_reference(P, lam, zt, terms=400 if lam >= 1 else 2000)
        assert np.allclose(sol.log_z[:, 0], ref, rtol=1e-9, atol=1e-9)
    else:
        dense = np.eye(m) - np.exp(-lam) * P[:, :m].toarray()
        z = np.linalg.solve(dense, np.exp(-lam) * P[:, m:].toarray() @ np.array(zt))
        assert np.allclose(sol.z[:, 0], z, rtol=1e-8)
    u = optimal_policy(thesis_lmdp(P, lam, zt), sol)
    sums = np.asarray(u.sum(axis=1)).ravel()
    assert np.all(np.isfinite(u.data)) and np.allclose(sums, 1.0, atol=1e-12)


def test_solvers_agree_with_each_other_in_physical_rgb():
    m = 200
    P = random_problem(m, seed=11)
    rng = np.random.default_rng(2)
    albedo = rng.uniform(0.1, 0.9, (m, 3))
    lmdp = FirstExitLMDP(P=P, q=albedo, z_terminal=np.array([[10.0, 5.0, 1.0], [0, 0, 0]]), lambda_=1.0,
                         cost_mode="PHYSICAL", g=-np.log(albedo))
    sols = {s: solve_desirability(lmdp, s, tolerance=1e-12, max_iterations=100000) for s in SOLVERS}
    ref = np.linalg.solve(np.eye(m)[None] - albedo.T[:, :, None] * P[:, :m].toarray()[None],
                          (albedo * (P[:, m:] @ lmdp.z_terminal)).T[:, :, None])[:, :, 0].T
    for name, sol in sols.items():
        assert sol.converged, name
        assert np.allclose(sol.z, ref, rtol=1e-9), name


def test_lambda_to_zero_near_singular_either_meets_residual_or_says_not():
    """I - QP is near-singular when λ -> 0 and almost no mass leaves the surface states."""
    m = 100
    P = random_problem(m, seed=5, leak=1e-7).tolil()
    P[:, m + 1] = 0.0
    P = sp.csr_matrix(P)
    P = sp.csr_matrix(sp.diags(1 / np.asarray(P.sum(1)).ravel()) @ P)
    lmdp = thesis_lmdp(P, 1e-9, [1.0, 0.0])
    capped = solve_desirability(lmdp, "POWER", tolerance=1e-12, max_iterations=200)
    assert not capped.converged
    assert "200 iterations" in capped.message
    for solver in ("DIRECT", "ITERATIVE"):
        sol = solve_desirability(lmdp, solver, tolerance=1e-10, max_iterations=3000)
        if sol.converged:
            assert sol.residual <= 1e-8
        else:
            assert sol.message
        assert np.all(np.isfinite(sol.z))


def test_states_that_cannot_reach_a_light_get_zero_and_infinite_cost():
    # States 0..4 form a closed loop with no exit; 5..9 a chain to the emitter.
    m = 10
    rows = list(range(5)) + list(range(5, 10))
    cols = [(i + 1) % 5 for i in range(5)] + [10 if i == 5 else i - 1 for i in range(5, 10)]
    P = sp.csr_matrix((np.ones(10), (rows, cols)), shape=(m, m + 2))
    lmdp = thesis_lmdp(P, 2.0, [1.0, 0.0])
    for solver in SOLVERS:
        sol = solve_desirability(lmdp, solver, tolerance=1e-12)
        assert sol.n_unreachable == 5
        assert np.all(sol.z[:5] == 0) and np.all(np.isinf(sol.cost_to_go[:5]))
        assert np.all(sol.z[5:] > 0)
        assert "5 states cannot reach a light" in sol.summary()
    u = optimal_policy(lmdp, sol)
    assert np.allclose(u[:5].toarray(), P[:5].toarray())  # passive fallback
    assert np.array_equal(hops_to_light(lmdp)[5:], np.arange(1, 6))


def test_no_reachable_light_at_all():
    m = 4
    P = sp.csr_matrix((np.ones(m), (np.arange(m), (np.arange(m) + 1) % m)), shape=(m, m + 2))
    sol = solve_desirability(thesis_lmdp(P, 1.0, [1.0, 0.0]), "ITERATIVE")
    assert sol.converged and sol.n_unreachable == m and np.all(sol.z == 0)


@pytest.mark.parametrize("solver", ("POWER", "ITERATIVE", "DIRECT"))
def test_float32_agrees_with_float64(solver):
    P = random_problem(300, seed=8)
    lmdp = thesis_lmdp(P, 0.7, [1.0, 0.0])
    a = solve_desirability(lmdp, solver, tolerance=1e-6, dtype=np.float32, max_iterations=10000)
    b = solve_desirability(lmdp, solver, tolerance=1e-12, dtype=np.float64, max_iterations=10000)
    assert a.converged and b.converged
    assert np.allclose(a.z, b.z, rtol=2e-5)


def test_power_history_and_thesis_behaviour_in_lambda():
    """Larger λ converges in fewer iterations (thesis Figs. 3-4); the history decreases."""
    P = random_problem(300, seed=9)
    its = []
    for lam in (0.01, 0.1, 1.0):
        sol = solve_desirability(thesis_lmdp(P, lam, [1.0, 0.0]), "POWER", tolerance=1e-10,
                                 max_iterations=100000, seed=1)
        assert sol.converged and len(sol.history) == sol.iterations
        assert sol.history[-1] < sol.history[0]
        its.append(sol.iterations)
    assert its[0] > its[1] > its[2]


def test_direct_refuses_oversized_problems_with_a_message():
    P = random_problem(50, seed=1)
    with pytest.raises(BudgetError, match="ITERATIVE"):
        solve_desirability(thesis_lmdp(P, 1.0, [1.0, 0.0]), "DIRECT", direct_max_unknowns=10)
