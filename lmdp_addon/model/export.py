"""Export an LMDP and its solution to a self-describing ``.npz`` (numpy only to reload).

States are the N unknowns (``state_point``; ``state_stratum = -1`` on a Lambertian point, its
one unknown; 0..S-1 the outgoing strata of a glossy point's, ``point_first_unknown`` /
``point_unknowns`` the index map) followed by the terminal states (emitters, world, void). With ``P = csr_matrix((P_data, P_indices,
P_indptr), shape=P_shape)`` every equation can be checked from the file alone:

* first exit (eq. 2.22): ``z[:N] == q[:N] * (P @ z)`` (per channel), terminal rows fixed;
* in the log domain, where z underflows: ``log_z[i] == log_q[i] + logsumexp_j(log P_ij + log_z[j])``;
* optimal policy (eq. 2.23): ``u*(j|i) = P_ij z_j / Σ_j P_ij z_j`` (``u_star_*`` arrays);
* cost-to-go: ``J = -log_z / lambda_``.

The file is written to a temporary name in the same folder and renamed only once complete, so a
failed export leaves any earlier file of that name as it was.
"""
import json
import os
import tempfile

import numpy as np
import scipy.sparse as sp

from ..errors import LMDPError
from .policy import optimal_policy, stratum_policy


def export_npz(path, states, dynamics, lmdp, solution, extra=None):
    """Write every array of the problem and its solution to ``path`` (see module docstring;
    ``.npz`` is appended when missing); returns the path written. Raises ``LMDPError`` with the
    reason when the file cannot be written (nothing is left behind)."""
    unknowns = states.unknowns
    m = unknowns.n_unknowns
    nT = dynamics.n_terminals
    C = lmdp.n_channels
    P = sp.csr_matrix(lmdp.P)
    q = np.vstack([lmdp.q, np.ones((nT, C))])
    log_q = np.vstack([lmdp.log_q, np.zeros((nT, C))])  # exact where q = exp(-λ g) underflows
    with np.errstate(divide="ignore"):
        log_zt = np.log(solution.z_terminal)
    z = np.vstack([solution.z, solution.z_terminal])
    log_z = np.vstack([solution.log_z, log_zt])
    u = optimal_policy(lmdp, solution)
    Pk = sp.csr_matrix(dynamics.stratum_transitions)
    arrays = dict(
        points=states.points,
        normals=states.normals,
        point_albedo=states.point_albedo,
        point_area=states.point_area,
        point_object=states.point_object,
        state_point=np.concatenate([unknowns.point, np.full(nT, -1)]),
        state_stratum=np.concatenate([unknowns.stratum, np.full(nT, -1)]),
        point_first_unknown=unknowns.first, point_unknowns=unknowns.count,
        terminal=np.concatenate([np.zeros(m, bool), np.ones(nT, bool)]),
        terminal_labels=np.array(dynamics.terminal_labels()),
        strata_u=states.strata_u,
        strata_v=states.strata_v,
        stratum_weight=states.stratum_weight,
        P_data=P.data, P_indices=P.indices, P_indptr=P.indptr, P_shape=np.array(P.shape),
        stratum_P_data=Pk.data, stratum_P_indices=Pk.indices, stratum_P_indptr=Pk.indptr,
        stratum_P_shape=np.array(Pk.shape),
        q=q, log_q=log_q, g=lmdp.g,
        z=z, log_z=log_z,
        y=solution.y, delta=solution.delta,
        reachable=solution.reachable,
        cost_to_go=np.vstack([solution.cost_to_go, -log_zt / lmdp.lambda_]),
        u_star_data=u.data, u_star_indices=u.indices, u_star_indptr=u.indptr,
        u_star_strata=stratum_policy(dynamics, solution, "all"),
        convergence=np.asarray(solution.history, dtype=np.float64),
        convergence_relative=np.asarray(solution.history_relative, dtype=np.float64),
        residual=solution.residual,
        residual_z=solution.residual_z,
        iterations=solution.iterations,
        converged=solution.converged,
        solver=solution.solver,
        lambda_=lmdp.lambda_,
        epsilon=lmdp.epsilon,
        cost_mode=lmdp.cost_mode,
        counts=json.dumps(dynamics.counts),
        extra=json.dumps(extra or {}),
    )
    return write_npz(path, arrays)


def write_npz(path, arrays):
    """``np.savez_compressed`` of ``arrays`` to ``path``, atomically: a temporary file in the same
    folder, renamed over ``path`` once complete. A read-only ``path`` is never replaced."""
    path = os.fspath(path)
    if not path.lower().endswith(".npz"):
        path += ".npz"
    if os.path.isfile(path) and not os.stat(path).st_mode & 0o222:
        raise LMDPError(f"{path} is read-only: choose another file path, or make it writable")
    temporary = None
    try:
        fd, temporary = tempfile.mkstemp(prefix=".lmdp_", suffix=".npz", dir=os.path.dirname(path) or ".")
        with os.fdopen(fd, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        os.replace(temporary, path)
    except OSError as error:
        if temporary is not None and os.path.exists(temporary):
            os.remove(temporary)
        reason = error.strerror or str(error)
        raise LMDPError(f"Cannot write {path}: {reason}; choose another file path "
                        "(in a folder you can write to)") from error
    return path
