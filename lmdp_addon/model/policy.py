"""Optimal policy (thesis eq. 2.23 / 3.2); the cost-to-go (2.24) is ``Solution.cost_to_go``.

``u*(x'|x) = p(x'|x) z(x') / Σ_x'' p(x''|x) z(x'')`` is evaluated on the rescaled solution:
for state i every weight is multiplied by ``exp(δ_i - c̄)``, which makes the weights
``p_ij exp(δ_i - c̄ - δ_j) y_j`` with a non-positive exponent and a largest term of order one, so
u* is exact even where z underflows. RGB desirabilities (PHYSICAL mode) are reduced to Rec.709
luminance. States that cannot reach a light keep the passive dynamics as their policy.
"""
import numpy as np
import scipy.sparse as sp

from .costs import scalar_desirability


def _column_weights(solution):
    """Scalar ``y`` per column (points then terminals) and the column log-scale ``δ``."""
    y = scalar_desirability(solution.y)
    zt = scalar_desirability(solution.z_terminal)
    values = np.concatenate([y, zt])
    delta = np.concatenate([solution.delta, np.zeros(len(zt))])
    return values, delta


def _scaled_entries(matrix, row_unknown, solution, row_delta=None):
    """``p_ij z_j`` of a CSR matrix rescaled per row by ``exp(δ_i - c̄)`` (finite, exact ratios);
    ``row_unknown``: the unknown whose δ scales each row, or ``row_delta`` the scale itself."""
    matrix = sp.csr_matrix(matrix)
    values, col_delta = _column_weights(solution)
    rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    cols = matrix.indices
    row_delta = solution.delta[row_unknown[rows]] if row_delta is None else row_delta[rows]
    with np.errstate(invalid="ignore", over="ignore"):
        expo = np.where(np.isfinite(row_delta) & np.isfinite(col_delta[cols]),
                        row_delta - solution.c_bar - col_delta[cols], -np.inf)
    return rows, cols, matrix.data.astype(np.float64) * np.exp(np.minimum(expo, 0.0)) * values[cols]


def optimal_policy(lmdp, solution):
    """u*(x'|x) over next states as a CSR (N, N + nT) matrix whose rows sum to one (eq. 2.23),
    one row per unknown (a glossy point's unknown (x, k): u*(x'|x, k) ∝ p(x'|x, k) z(x')).

    Uses the same P as the solve (with the ε self-loop in THESIS mode).
    """
    P = sp.csr_matrix(lmdp.P)
    m = P.shape[0]
    rows, cols, w = _scaled_entries(P, np.arange(m), solution)
    sums = np.bincount(rows, weights=w, minlength=m)
    passive = sums <= 0
    p_sums = np.asarray(P.sum(axis=1)).reshape(-1)
    data = np.where(passive[rows], P.data / np.where(p_sums[rows] > 0, p_sums[rows], 1.0),
                    w / np.where(sums[rows] > 0, sums[rows], 1.0))
    return sp.csr_matrix((data, cols, P.indptr.copy()), shape=P.shape)


def stratum_policy(dynamics, solution, columns="all"):
    """Directional optimal policy ``u*(k | x)``: (m, S) probability of leaving x through stratum k.

    Summing eq. 2.23 over the next states reached through stratum k gives
    ``u*(k|x) ∝ Σ_j p_k(j|x) z_j``. ``columns`` selects which next states count:

    * ``"all"``: every next state (the thesis's u*, used for display),
    * ``"points"``: surface states only: the guide for *indirect* light at a bake texel,
      where light arriving straight from emitters or the world is not wanted,
    * ``"points+world"``: surface states and the world: the guide at later path vertices, where
      next-event estimation already handles the emitters.

    The ε self-loop has no direction and is left out. Points whose selected weights are all
    zero fall back to the passive dynamics, ``w_k`` (BRDF·cos mass of each stratum).
    On glossy points the rows are their cosine stratum rays (``stratum_transitions``): the
    directions that lead to light under a Lambertian lobe, which the guide mixes with the BSDF.
    """
    Pk = sp.csr_matrix(dynamics.stratum_transitions)
    m, S = dynamics.n_points, dynamics.n_strata
    N = dynamics.n_unknowns
    if columns == "points":
        Pk = Pk[:, :N]
    elif columns == "points+world":
        keep = np.zeros(dynamics.n_columns, dtype=bool)
        keep[:N] = True
        keep[dynamics.world_columns] = True
        Pk = sp.csr_matrix(Pk.multiply(keep[None, :]))
    elif columns != "all":
        raise ValueError(f"columns must be 'all', 'points' or 'points+world', not {columns!r}")
    unknowns = dynamics.unknown_map
    if unknowns.identity:
        rows, _, w = _scaled_entries(Pk, np.repeat(np.arange(m), S), solution)
    else:   # a glossy point's rows are scaled by the smallest δ of its unknowns
        point_delta = np.minimum.reduceat(np.asarray(solution.delta, dtype=np.float64), unknowns.first)
        rows, _, w = _scaled_entries(Pk, None, solution, row_delta=np.repeat(point_delta, S))
    per_stratum = np.bincount(rows, weights=w, minlength=m * S).reshape(m, S)
    sums = per_stratum.sum(axis=1, keepdims=True)
    lamps = getattr(dynamics, "n_lamps", 0)   # lamp masses are not probabilities (lamps.py)
    passive_mass = (dynamics.stratum_transitions[:, :dynamics.n_columns - lamps] if lamps
                    else dynamics.stratum_transitions)
    weights = np.asarray(passive_mass.sum(axis=1)).reshape(m, S)
    passive = weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)
    u = np.where(sums > 0, per_stratum / np.where(sums > 0, sums, 1.0), passive)
    return u.astype(np.float64)
