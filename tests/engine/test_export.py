"""The .npz export is self-contained: every equation checks from the file with numpy/scipy."""
import json

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.special import logsumexp

from lmdp_addon.model.export import export_npz
from lmdp_addon.model.pipeline import run_all
from lmdp_addon.demo_geometry import build_scene_arrays
from lmdp_addon.settings import Settings


@pytest.mark.parametrize("mode,scale", [("PHYSICAL", 1.0), ("THESIS", 1.0), ("THESIS", 20.0)])
def test_export_reloads_and_satisfies_the_first_exit_equation(tmp_path, mode, scale):
    scene = build_scene_arrays("CORNELL_BOX")
    settings = Settings(point_count=400, rays_per_stratum=2, cost_mode=mode, lambda_scale=scale,
                        solver="DIRECT")
    r = run_all(scene, settings)
    path = export_npz(tmp_path / "lmdp.npz", r.states, r.dynamics, r.lmdp, r.solution)
    f = np.load(path)
    for key in ("points", "normals", "state_point", "state_stratum", "terminal", "P_data", "P_indices",
                "P_indptr", "P_shape", "q", "log_q", "z", "log_z", "convergence", "lambda_", "cost_mode"):
        assert key in f.files, key
    P = sp.csr_matrix((f["P_data"], f["P_indices"], f["P_indptr"]), shape=tuple(f["P_shape"]))
    m = int((~f["terminal"]).sum())
    assert P.shape == (m, len(f["terminal"])) and np.all(f["state_stratum"] == -1)
    assert np.array_equal(f["state_point"][:m], np.arange(m)) and np.all(f["state_point"][m:] == -1)
    assert str(f["cost_mode"]) == mode
    z, log_z, q, log_q = f["z"], f["log_z"], f["q"], f["log_q"]
    # Linear domain, where z is representable: z_N = q_N (P z).
    assert np.allclose(z[:m], q[:m] * (P @ z), rtol=1e-8, atol=1e-300)
    # Log domain: log z_i = log q_i + logsumexp_j(log P_ij + log z_j), exact even where z underflows.
    coo = P.tocoo()
    for c in range(z.shape[1]):
        terms = np.log(coo.data) + log_z[coo.col, c]
        rhs = np.full(m, -np.inf)
        order = np.argsort(coo.row, kind="stable")
        rows, terms = coo.row[order], terms[order]
        starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        rhs[rows[starts]] = [logsumexp(t) for t in np.split(terms, starts[1:])]
        rhs = log_q[:m, c] + rhs
        finite = np.isfinite(log_z[:m, c])
        assert np.array_equal(finite, np.isfinite(rhs))
        assert np.allclose(log_z[:m, c][finite], rhs[finite], rtol=1e-9, atol=1e-9)
    # Optimal policy and cost-to-go from the file.
    u = sp.csr_matrix((f["u_star_data"], f["u_star_indices"], f["u_star_indptr"]), shape=P.shape)
    assert np.allclose(np.asarray(u.sum(axis=1)).ravel(), 1.0)
    assert np.allclose(f["cost_to_go"][:m][finite[:, None].repeat(z.shape[1], 1)],
                       (-log_z[:m] / float(f["lambda_"]))[finite[:, None].repeat(z.shape[1], 1)])
    assert f["u_star_strata"].shape == (m, r.states.n_strata)
    assert json.loads(str(f["counts"]))["rays"] == r.dynamics.rays
    if mode == "THESIS" and scale == 20.0:
        assert np.any(z[:m] == 0) and np.all(np.isfinite(log_z[:m][r.solution.reachable]))
