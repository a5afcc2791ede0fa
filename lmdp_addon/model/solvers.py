"""Solvers for the desirability z of the first-exit LMDP (thesis 2.2.2, 3.1.4, 4.1.1).

All solvers work on an exactly rescaled unknown ``y = z ⊙ exp(δ)`` (``design.md``): with
``δ_i = c̄ · hops_i`` (hops to the nearest lit terminal, ``c̄ = min λg = min -log q``) the
rescaled matrix ``A = D Q P_NN D^-1`` has entries no larger than P's, so nothing over- or underflows for any λ,
and ``log z = log y - δ`` stays exact where z itself underflows float64.

* ``POWER``     the thesis's iteration ``z <- QPz`` with terminal z fixed (eq. 2.22), random
                initial values in [0, 1), stopped when the relative change falls below the
                tolerance or at ``max_iterations``; the history of ``||z_i - z_{i-1}||_2`` is kept.
* ``DIRECT``    sparse LU of ``(I - Q_NN P_NN) z_N = Q_NN P_NT z_T``.
* ``ITERATIVE`` restarted GMRES with a Jacobi preconditioner, started from a few power
                iterations; if it stalls, the power iteration continues from its iterate.
                ``max_iterations`` caps all of it together (per channel).
"""
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import shortest_path

from ..errors import BudgetError, SceneError
from ..settings import SOLVERS

#: Above this many unknowns the DIRECT solver refuses: the LU of a visibility graph fills in.
DIRECT_MAX_UNKNOWNS = 40000
#: Up to this many unknowns DIRECT factorises densely with LAPACK (1.4 GB at 13000).
DENSE_LU_MAX = 13000


@dataclass
class Solution:
    """Desirability of the unknowns (``StateSpace.unknowns``: one per Lambertian point, S per
    glossy point), stored rescaled.

    y          (N, C) float64 rescaled desirability, ``z = y * exp(-delta)``
    delta      (N,)   log scale of each unknown (+inf where no lit terminal is reachable)
    z_terminal (nT, C) desirability of the terminal states
    lambda_    λ; J = -(log z)/λ
    reachable  (N,) bool: some lit terminal is reachable (otherwise z = 0, J = +inf)
    residual   relative residual ``||y - (A y + b)||_∞ / ||y||_∞`` of the rescaled system
    residual_z ``||z - Q P z||_∞`` over the non-terminal states, in z units
    history    ``||z_i - z_{i-1}||_2`` per power iteration (empty for DIRECT)
    """

    y: np.ndarray
    delta: np.ndarray
    z_terminal: np.ndarray
    lambda_: float
    cost_mode: str
    solver: str
    reachable: np.ndarray
    iterations: int
    converged: bool
    residual: float
    residual_z: float
    seconds: float
    history: list = field(default_factory=list)
    history_relative: list = field(default_factory=list)
    message: str = ""
    c_bar: float = 0.0

    @property
    def n_unreachable(self):
        return int(np.count_nonzero(~self.reachable))

    @property
    def z(self):
        """(m, C) desirability; underflows to 0 where log_z < -745 (use :attr:`log_z`)."""
        with np.errstate(over="ignore", invalid="ignore"):
            return np.where(np.isfinite(self.delta)[:, None], self.y * np.exp(-self.delta)[:, None], 0.0)

    @property
    def log_z(self):
        """(m, C) natural log of z, exact where z underflows; -inf where z = 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.log(np.maximum(self.y, 0.0)) - self.delta[:, None]
        return np.where(np.isnan(out), -np.inf, out)

    @property
    def cost_to_go(self):
        """J = -(log z)/λ (thesis eq. 2.24 in our convention for its Q = exp(-λ g), see
        ``design.md``; +inf where z = 0)."""
        return -self.log_z / self.lambda_

    def summary(self):
        state = "converged" if self.converged else "NOT converged"
        return (f"{self.solver} {state} in {self.iterations} iterations, {self.seconds:.2f} s, "
                f"relative residual {self.residual:.2e}"
                + (f"; {self.n_unreachable} states cannot reach a light (z = 0)" if self.n_unreachable else ""))


def hops_to_light(lmdp):
    """Fewest transitions from each non-terminal state to a terminal with z > 0 (inf if none)."""
    m = lmdp.n_points
    P = sp.csr_matrix(lmdp.P)
    lit = np.flatnonzero(np.any(lmdp.z_terminal > 0, axis=1)) + m
    # Graph on m + 1 nodes: every lit terminal column collapses into the super node m.
    coo = P.tocoo()
    keep = coo.data > 0
    rows, cols = coo.row[keep], coo.col[keep]
    to_point = cols < m
    to_lit = np.isin(cols, lit)
    r = np.concatenate([rows[to_point], rows[to_lit]])
    c = np.concatenate([cols[to_point], np.full(int(to_lit.sum()), m)])
    graph = sp.csr_matrix((np.ones(len(r)), (c, r)), shape=(m + 1, m + 1))  # reversed edges
    dist = shortest_path(graph, directed=True, unweighted=True, indices=m)
    return dist[:m]


def rescaled_system(lmdp, dtype=np.float64):
    """Rescaled system ``y = A y + b`` with ``A_c = diag(q̃_c) S``; see the module docstring.

    ``S_ij = P_ij exp(δ_i - δ_j - c̄) <= P_ij`` and ``q̃ = exp(log q + c̄) <= 1`` are both formed
    from logarithms, so nothing underflows even where q = exp(-λ g) itself is 0 in float64.
    Returns ``(S, q̃, b, delta, c_bar, reachable)``.
    """
    m = lmdp.n_points
    hops = hops_to_light(lmdp)
    reachable = np.isfinite(hops)
    log_q = np.asarray(lmdp.log_q, dtype=np.float64)
    c = -log_q
    finite_c = c[np.isfinite(c) & reachable[:, None]]
    c_bar = float(max(finite_c.min(), 0.0)) if finite_c.size else 0.0
    delta = np.where(reachable, c_bar * np.where(reachable, hops, 0.0), np.inf)

    P_NN = sp.csr_matrix(lmdp.P_NN).tocoo()
    keep = reachable[P_NN.row] & reachable[P_NN.col] & (P_NN.data > 0)
    rows, cols = P_NN.row[keep], P_NN.col[keep]
    # hops_i <= hops_j + 1 along every transition, so the exponent is <= 0.
    data = P_NN.data[keep] * np.exp(np.minimum(delta[rows] - delta[cols] - c_bar, 0.0))
    S = sp.csr_matrix((data.astype(dtype), (rows, cols)), shape=(m, m))
    q_scaled = np.exp(np.minimum(log_q + c_bar, 0.0))
    drive = lmdp.terminal_drive()
    # Only states one hop from a lit terminal have drive > 0, and there δ = c̄.
    b = np.where(reachable[:, None] & (hops[:, None] == 1), q_scaled * drive, 0.0)
    return S, q_scaled.astype(dtype), b.astype(dtype), delta, c_bar, reachable


def state_residuals(lmdp, solution):
    """Per-state residual of the first-exit equation, relative to the state's own z:
    ``|y_i - (A y + b)_i| / max(|y_i|, tiny)`` in the rescaled variables (= |z - QPz|_i / z_i),
    max over channels; 0 for states that cannot reach a light (their z = 0 is exact)."""
    S, q, b, _, _, reachable = rescaled_system(lmdp)
    y = solution.y
    r = np.abs(y - (_apply(S, q, y) + b))
    rel = r / np.maximum(np.abs(y), 1e-300)
    return np.where(reachable, rel.max(axis=1), 0.0)


def _apply(S, q, y):
    return q * (S @ y)


def solve_desirability(lmdp, solver="ITERATIVE", tolerance=1e-8, max_iterations=10000,
                       seed=0, progress=None, dtype=np.float64, direct_max_unknowns=DIRECT_MAX_UNKNOWNS,
                       memory_budget_gb=None):
    """Solve the first-exit LMDP for z (module docstring); returns a :class:`Solution`."""
    if solver not in SOLVERS:
        raise SceneError(f"Unknown solver {solver!r}: use one of {', '.join(SOLVERS)}")
    if not (tolerance > 0):
        raise SceneError(f"Tolerance must be positive (got {tolerance})")
    if int(max_iterations) < 1 and solver != "DIRECT":
        raise SceneError(f"Max iterations must be at least 1 (got {max_iterations}): set LMDP > "
                         "Solve > Max Iterations")
    t0 = time.perf_counter()
    S, q, b, delta, c_bar, reachable = rescaled_system(lmdp, dtype=dtype)
    m, C = q.shape
    history, history_rel = [], []
    iterations = 0
    message = ""
    if not np.any(reachable):
        y = np.zeros((m, C), dtype=np.float64)
        converged = True
        message = "no state can reach a light: z = 0 everywhere"
    elif solver == "POWER":
        rng = np.random.default_rng(seed)
        y0 = np.where(reachable[:, None], rng.random((m, C)), 0.0).astype(dtype)
        y, iterations, converged, history, history_rel = _power(
            S, q, b, y0, delta, tolerance, max_iterations, progress)
    elif solver == "DIRECT":
        n_active = int(reachable.sum())
        if n_active > direct_max_unknowns:
            raise BudgetError(
                f"The DIRECT solver is limited to {direct_max_unknowns} unknowns (its LU fills in on "
                f"visibility graphs); this problem has {n_active}: use the ITERATIVE solver")
        y = _direct(S, q, b, reachable, progress, memory_budget_gb)
        iterations, converged = 1, True
    else:
        y, iterations, converged, history, history_rel, message = _iterative(
            S, q, b, delta, reachable, tolerance, max_iterations, seed, progress)

    y = np.asarray(y, dtype=np.float64)
    y = np.where(reachable[:, None], np.maximum(y, 0.0), 0.0)
    S64 = S.astype(np.float64)
    r = y - (_apply(S64, q.astype(np.float64), y) + b.astype(np.float64))
    scale = max(float(np.abs(y).max()), 1e-300)
    residual = float(np.abs(r).max() / scale)
    with np.errstate(over="ignore", invalid="ignore"):
        residual_z = float(np.nanmax(np.abs(r) * np.exp(-np.where(reachable, delta, np.inf))[:, None])) if m else 0.0
    if solver == "DIRECT":
        converged = residual <= max(tolerance, 1e3 * np.finfo(dtype).eps)
        if not converged:
            message = f"the LU solve left a relative residual of {residual:.2e}"
    if not converged and not message:
        message = (f"stopped after {iterations} iterations with relative change "
                   f"{history_rel[-1] if history_rel else float('nan'):.2e} > tolerance {tolerance:g}")
    return Solution(y=y, delta=delta, z_terminal=np.asarray(lmdp.z_terminal, dtype=np.float64),
                    lambda_=lmdp.lambda_, cost_mode=lmdp.cost_mode, solver=solver,
                    reachable=reachable, iterations=int(iterations), converged=bool(converged),
                    residual=residual, residual_z=residual_z, seconds=time.perf_counter() - t0,
                    history=history, history_relative=history_rel, message=message, c_bar=c_bar)


def _power(S, q, b, y, delta, tolerance, max_iterations, progress, history=None, history_rel=None):
    """Fixed-point iteration y <- A y + b (the rescaled z <- QPz), eq. 2.22."""
    history = [] if history is None else history
    history_rel = [] if history_rel is None else history_rel
    with np.errstate(over="ignore"):
        z_scale = np.exp(-delta)[:, None]
    z_scale = np.where(np.isfinite(z_scale), z_scale, 0.0)
    converged = False
    it = 0
    for it in range(1, int(max_iterations) + 1):
        y_new = _apply(S, q, y) + b
        diff = y_new - y
        history.append(float(np.linalg.norm(diff * z_scale)))
        rel = float(np.abs(diff).max() / max(float(np.abs(y_new).max()), 1e-300))
        history_rel.append(rel)
        y = y_new
        if rel <= tolerance:
            converged = True
            break
        if progress is not None and it % 16 == 0:
            progress.update(min(1.0, np.log(max(rel, 1e-300)) / np.log(tolerance)),
                            f"power iteration {it}: relative change {rel:.2e}")
    return y, it, converged, history, history_rel


def _direct(S, q, b, reachable, progress, memory_budget_gb=None):
    """LU factorisation of (I - A) on the reachable states, once per distinct channel.

    The visibility graph of a scene is dense (every point sees most others), so the LU of
    ``I - A`` fills in almost completely: below ``DENSE_LU_MAX`` unknowns LAPACK's dense LU is
    used (much faster than a sparse LU of a matrix that becomes dense); above it SuperLU.
    """
    idx = np.flatnonzero(reachable)
    n = len(idx)
    Sr = S[idx][:, idx].astype(np.float64)
    m, C = q.shape
    y = np.zeros((m, C))
    dense = n <= DENSE_LU_MAX
    if dense and memory_budget_gb is not None and 8.0 * n * n > memory_budget_gb * 1024 ** 3:
        raise BudgetError(f"The DIRECT solver needs {8.0 * n * n / 1024 ** 3:.1f} GiB for {n} unknowns, "
                          f"above the memory budget of {memory_budget_gb:g} GiB: use the ITERATIVE solver")
    factors = {}
    for c in range(C):
        key = q[idx, c].tobytes()
        if key not in factors:
            if progress is not None:
                progress.update(c / C, f"LU factorisation of channel {c + 1}/{C} ({n} unknowns)")
            if dense:
                A = np.eye(n) - q[idx, c, None].astype(np.float64) * Sr.toarray()
                lu = scipy.linalg.lu_factor(A, overwrite_a=True, check_finite=False)
                factors[key] = lambda rhs, lu=lu: scipy.linalg.lu_solve(lu, rhs, check_finite=False)
            else:
                A = sp.identity(n, format="csc") - sp.diags(q[idx, c].astype(np.float64)) @ Sr
                factors[key] = spla.splu(sp.csc_matrix(A)).solve
        y[idx, c] = factors[key](b[idx, c].astype(np.float64))
    return y


def _iterative(S, q, b, delta, reachable, tolerance, max_iterations, seed, progress):
    """GMRES(restart) with Jacobi preconditioning on the reachable block, power fallback.

    ``max_iterations`` caps the iterations of every channel's solve, all stages together: the
    warm-start power iterations, then at most the rest as GMRES inner iterations (restart
    cycles are shortened to fit), then the power fallback with whatever is left. Returns
    ``(y, iterations, converged, history, history_rel, message)``; ``iterations`` is the warm
    start plus the most GMRES iterations any channel took plus the fallback's, and
    ``converged`` says whether the true residual reached the tolerance within the cap.
    """
    cap = int(max_iterations)
    idx = np.flatnonzero(reachable)
    Sr = S[idx][:, idx]
    m, C = q.shape
    y = np.zeros((m, C), dtype=S.dtype)
    # Warm start: a few power iterations from the thesis's random initial values.
    rng = np.random.default_rng(seed)
    y[idx] = rng.random((len(idx), C))
    y, iterations, _, history, history_rel = _power(S, q, b, y, delta, 0.0, min(8, cap), None)
    budget = cap - iterations
    converged_all = budget > 0
    message = ""
    if budget > 0:
        used, converged_all = _gmres_channels(S, Sr, q, b, y, idx, tolerance, budget, progress)
        iterations += used
    remaining = cap - iterations
    if not converged_all and remaining > 0:
        # GMRES stalled: continue with the power iteration from its iterate (fallback).
        y, used, converged_all, history, history_rel = _power(S, q, b, y, delta, tolerance, remaining,
                                                              progress, history, history_rel)
        iterations += used
        message = "GMRES did not reach the tolerance; continued with the power iteration"
    # Verify against the true residual (GMRES's own estimate is preconditioned).
    threshold = max(10 * tolerance, 1e3 * np.finfo(S.dtype).eps)
    rel = _relative_residual(S, q, b, y)
    remaining = cap - iterations
    if rel > threshold and converged_all and remaining > 0:
        y, used, converged_all, history, history_rel = _power(S, q, b, y, delta, tolerance, remaining,
                                                              progress, history, history_rel)
        iterations += used
        rel = _relative_residual(S, q, b, y)
    if iterations >= cap and not converged_all:
        # The cap cut a stage short: the true residual decides.
        converged_all = rel <= threshold
        if not converged_all:
            message = (f"stopped at the cap of {cap} iteration{'s' if cap != 1 else ''} (Max Iterations) "
                       f"with relative residual {rel:.2e} > tolerance {tolerance:g}")
    return y, iterations, converged_all, history, history_rel, message


def _relative_residual(S, q, b, y):
    """``||y - (A y + b)||_∞ / ||y||_∞`` of the rescaled system."""
    r = y - (_apply(S, q, y) + b)
    return float(np.abs(r).max() / max(float(np.abs(y).max()), 1e-300))


def _gmres_channels(S, Sr, q, b, y, idx, tolerance, budget, progress):
    """Restarted GMRES of every channel on the reachable block, at most ``budget`` inner
    iterations each; writes the solutions into ``y``. Returns ``(the most iterations any
    channel took, every channel reached the tolerance)``."""
    m, C = q.shape
    diag = Sr.diagonal()
    identity = sp.identity(len(idx), format="csr", dtype=S.dtype)
    restart = min(60, budget)
    cycles = budget // restart          # restart x cycles <= budget inner iterations
    most, converged_all = 0, True
    for c in range(C):
        A = identity - sp.diags(q[idx, c]) @ Sr
        precond = sp.diags(1.0 / np.maximum(1.0 - q[idx, c] * diag, 1e-12))
        count = [0]

        def callback(_res, c=c, count=count):
            count[0] += 1
            if progress is not None and count[0] % 20 == 0:
                progress.update((c + min(count[0] / budget, 1.0)) / C,
                                f"GMRES channel {c + 1}/{C}, iteration {count[0]}")

        sol, info = spla.gmres(A, b[idx, c], x0=y[idx, c], rtol=tolerance, atol=0.0,
                               restart=restart, maxiter=cycles, M=precond,
                               callback=callback, callback_type="pr_norm")
        y[idx, c] = sol
        most = max(most, count[0])
        if info != 0:
            converged_all = False
    return most, converged_all
