"""Directional unknowns of glossy points (``model/unknowns.py``, ``model/dynamics.py``): the index
map, the rows of the glossy unknowns, their state costs, the optimal policy of a sharp glossy
state, the solve, the memory estimate and the consumers (display, export, gather)."""
import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from lmdp_addon import bsdf
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.gather import build_gather
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.display.vertex_field import state_quantity
from lmdp_addon.errors import BudgetError
from lmdp_addon.model import pipeline
from lmdp_addon.model.costs import build_first_exit_lmdp
from lmdp_addon.model.dynamics import build_passive_dynamics, estimate_build_bytes
from lmdp_addon.model.export import export_npz
from lmdp_addon.model.hemisphere import stratum_centers
from lmdp_addon.model.policy import optimal_policy
from lmdp_addon.model.solvers import solve_desirability
from lmdp_addon.model.states import sample_states
from lmdp_addon.model.unknowns import UnknownMap
from lmdp_addon.scene_arrays import LUMINANCE
from lmdp_addon.settings import Settings


def glossy_floor_box(roughness, colour=0.8):
    """The Cornell box with a Glossy BSDF floor (no diffuse lobe) of ``roughness``."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    floor = scene.triangle_object == scene.object_names.index("Floor")
    scene.materials = bsdf.MaterialTable.from_lobes(
        [[{"kind": bsdf.GLOSSY, "weight": (colour,) * 3, "roughness": roughness}]], ["Glossy floor"])
    scene.triangle_material = np.where(floor, 0, -1).astype(np.int32)
    albedo = np.array(scene.triangle_albedo)
    albedo[floor] = 0.0
    scene.triangle_albedo = albedo
    return scene


def test_unknown_map_indexes_points_and_strata():
    u = UnknownMap(np.array([False, True, False, True]), 2, 2)
    assert u.n_unknowns == 1 + 4 + 1 + 4 and not u.identity and u.n_glossy == 2
    np.testing.assert_array_equal(u.first, [0, 1, 5, 6])
    np.testing.assert_array_equal(u.point, [0, 1, 1, 1, 1, 2, 3, 3, 3, 3])
    np.testing.assert_array_equal(u.stratum, [-1, 0, 1, 2, 3, -1, 0, 1, 2, 3])
    # a landing goes to the stratum of the reversed ray direction on a glossy point
    centres = stratum_centers(2, 2)
    cols = u.columns(np.array([0, 1, 1, 3, 2]), np.vstack([centres[2], centres[3], centres[0], centres[1],
                                                          centres[1]]))
    np.testing.assert_array_equal(cols, [0, 1 + 3, 1 + 0, 6 + 1, 5])
    # grazing directions (z <= 0 after a tilt) keep to the horizon's stratum instead of -1
    assert u.columns(np.array([1]), np.array([[1.0, 0.0, -1e-3]]))[0] >= 1
    values = np.arange(10, dtype=float)[:, None]
    w = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(u.point_values(values, w)[:, 0], [0, w @ [1, 2, 3, 4], 5, w @ [6, 7, 8, 9]])
    np.testing.assert_allclose(np.exp(u.point_log_values(np.log(values + 1), w))[:, 0],
                               u.point_values(values + 1, w)[:, 0])
    np.testing.assert_array_equal(u.point_max(values[:, 0]), [0, 4, 5, 9])
    # one stratum resolves no direction: glossy points keep one unknown; no points, no unknowns
    assert UnknownMap(np.array([True, False]), 1, 1).identity
    assert UnknownMap(np.zeros(0, bool), 4, 4).n_unknowns == 0


def test_lambertian_scenes_keep_one_unknown_per_point():
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 300, seed=1)
    assert states.glossy is None and states.unknowns.identity and states.n_unknowns == 300
    dyn = build_passive_dynamics(scene, states, 2, seed=1, light_samples=4)
    assert dyn.P.shape == (300, dyn.n_columns) and dyn.n_unknowns == 300 and dyn.glossy_albedo is None


def test_glossy_points_carry_a_row_per_outgoing_stratum():
    """Without next-event estimation every ray lands somewhere: a Lambertian point's row sums to
    exactly one (float32); a glossy unknown's row sums to the mean of its rays' f cos / p over
    its directional albedo a_k, one in expectation (their mean over the unknowns within Monte
    Carlo error of one); their cosine stratum rows (the guide's) still sum to the strata's
    cosine masses."""
    scene = scenes.build_scene_arrays("GLOSSY_BOX")
    states = sample_states(scene, 400, seed=2)
    u = states.unknowns
    assert u.n_glossy == np.count_nonzero(scene.glossy_triangles()[states.point_triangle]) > 0
    assert states.n_unknowns == states.n_points + (states.n_strata - 1) * u.n_glossy
    dyn = build_passive_dynamics(scene, states, 4, seed=2, light_samples=0)
    assert dyn.P.shape == (states.n_unknowns, dyn.n_columns)
    sums = np.asarray(dyn.P.sum(axis=1)).ravel()
    lamb = u.stratum < 0
    np.testing.assert_allclose(sums[lamb], 1.0, atol=2e-6)
    lit = dyn.glossy_albedo @ LUMINANCE > 0
    glossy = sums[~lamb][lit]
    assert abs(glossy.mean() - 1.0) < 5.0 * glossy.std() / np.sqrt(len(glossy)) + 1e-3, (glossy.mean(), glossy.std())
    strata = np.asarray(dyn.stratum_transitions.sum(axis=1)).reshape(states.n_points, -1)
    np.testing.assert_allclose(strata, np.tile(states.stratum_weight, (states.n_points, 1)), atol=2e-6)
    # rows of the glossy unknowns land on glossy unknowns too (the floor sees the sphere)
    P = sp.csr_matrix(dyn.P)
    g_rows = np.flatnonzero(u.stratum >= 0)
    cols = P[g_rows].indices
    assert np.any((cols < u.n_unknowns) & (u.stratum[np.minimum(cols, u.n_unknowns - 1)] >= 0))


def test_directional_albedo_is_the_bsdfs():
    """q of a glossy unknown (PHYSICAL) is its directional albedo (``dynamics.directional_albedo``,
    tabulated per material over cos θ): within 1 % of the BSDF's own for the stratum's centre
    (``VertexBSDF.albedo``, 32 x 32 stratified samples)."""
    scene = glossy_floor_box(0.3)
    states = sample_states(scene, 200, seed=3)
    dyn = build_passive_dynamics(scene, states, 32, seed=3, light_samples=0)
    lmdp = build_first_exit_lmdp(dyn, states, "PHYSICAL")
    u = states.unknowns
    g = np.flatnonzero(u.stratum >= 0)
    pts = u.point[g]
    wo = np.einsum("ki,kij->kj", stratum_centers(4, 4)[u.stratum[g]], states.frames[pts])
    vertex = bsdf.VertexBSDF(scene.materials, scene.triangle_material[states.point_triangle[pts]],
                             np.zeros((len(g), 3)), states.normals[pts], wo)
    want = vertex.albedo(32)
    got = lmdp.q[g]
    assert np.abs(got - want).max() < 0.01
    assert abs(got.mean() - want.mean()) < 0.002
    # grazing strata reflect less than the ones near the normal (no Fresnel: the masking G1)
    cos = stratum_centers(4, 4)[u.stratum[g], 2]
    assert got[cos > 0.9, 0].mean() > got[cos < 0.5, 0].mean()


def test_sharp_glossy_policy_concentrates_around_the_mirror_direction():
    """u*(x'|x, k) of a sharp (roughness 0.05) glossy floor state: the next states it chooses lie
    around the mirror direction of ω_k, while a Lambertian point's u* spreads over its hemisphere."""
    scene = glossy_floor_box(0.05)
    s = Settings(point_count=1500, rays_per_stratum=8, light_samples=16, seed=4, cost_mode="PHYSICAL")
    result = pipeline.run_all(scene, s)
    states, u = result.states, result.states.unknowns
    U = sp.csr_matrix(optimal_policy(result.lmdp, result.solution))
    centres = stratum_centers(4, 4)
    k = int(np.argmin(np.abs(centres[:, 2] - 0.65)))   # a stratum about 50° from the normal
    floor = np.flatnonzero(states.glossy & (np.abs(states.points[:, :2]).max(axis=1) < 0.3)
                           & result.dynamics.locator.targets)        # not under the boxes (buried)

    def spread(row, point, axis):
        cols, p = U.indices[U.indptr[row]:U.indptr[row + 1]], U.data[U.indptr[row]:U.indptr[row + 1]]
        on = cols < u.n_unknowns
        d = states.points[u.point[cols[on]]] - states.points[point]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.sum(p[on] * (d @ axis)) / max(p[on].sum(), 1e-300)

    mirror_cos = []
    for x in floor[:20]:
        wo = centres[k] @ states.frames[x]
        n = states.normals[x]
        mirror = 2.0 * (wo @ n) * n - wo
        mirror_cos.append(spread(u.first[x] + k, x, mirror))
    walls = np.flatnonzero(states.point_object == scene.object_names.index("BackWall"))[:20]
    lambert_cos = [spread(u.first[x], x, states.normals[x]) for x in walls]
    # the u*-weighted mean cosine to the mirror direction: within about 25° of it on average
    assert np.median(mirror_cos) > np.cos(np.radians(25.0)), np.round(mirror_cos, 3)
    # a Lambertian point's mean direction of its next states lies well off its normal's cone
    assert np.median(lambert_cos) < np.median(mirror_cos) - 0.1, (np.median(lambert_cos), np.median(mirror_cos))


def test_glossy_solve_converges_and_solvers_agree():
    scene = scenes.build_scene_arrays("GLOSSY_BOX")
    s = Settings(point_count=400, rays_per_stratum=4, light_samples=8, seed=5, cost_mode="PHYSICAL")
    states, _ = pipeline.run_sample(scene, s)
    dyn, _ = pipeline.run_build(scene, states, s)
    lmdp = build_first_exit_lmdp(dyn, states, "PHYSICAL")
    direct = solve_desirability(lmdp, "DIRECT", 1e-10, 1000)
    iterative = solve_desirability(lmdp, "ITERATIVE", 1e-10, 5000)
    assert direct.converged and iterative.converged and iterative.residual < 1e-8
    np.testing.assert_allclose(iterative.z, direct.z, rtol=1e-6, atol=1e-9)
    thesis = pipeline.run_solve(scene, states, dyn, dataclasses.replace(s, cost_mode="THESIS"))[1]
    assert thesis.converged and thesis.y.shape == (states.n_unknowns, 1)


def test_memory_estimate_counts_the_directional_unknowns():
    assert estimate_build_bytes(1000, 16, 4, 32, 100, n_glossy=500) > estimate_build_bytes(1000, 16, 4, 32, 100)
    glossy = scenes.build_scene_arrays("GLOSSY_BOX")
    s = Settings(point_count=4096)
    need = pipeline.check_build(glossy, s)
    plain = dataclasses.replace(glossy, materials=None, triangle_material=None)
    need_plain = pipeline.check_build(plain, s)
    assert need > need_plain
    states, _ = pipeline.run_sample(glossy, s)
    assert pipeline.check_build(glossy, s, states) > need_plain
    with pytest.raises(BudgetError):
        pipeline.check_build(glossy, dataclasses.replace(s, memory_budget_gb=(need + need_plain) / 2 / 1024 ** 3))


def test_display_export_and_gather_read_the_unknowns(tmp_path):
    """The display shows one value per point (a glossy point: Σ_k w_k z(x, k)); the export holds
    the index map and z = q (P z) over the unknowns; the gather holds one ẑ per point."""
    scene = scenes.build_scene_arrays("GLOSSY_BOX")
    result = pipeline.run_all(scene, Settings(point_count=300, rays_per_stratum=2, light_samples=8, seed=6,
                                              cost_mode="PHYSICAL"))
    states, sol, u = result.states, result.solution, result.states.unknowns
    sq = state_quantity(sol, "Z", states=states)
    assert len(sq.value) == states.n_points
    x = u.glossy_points[0]
    zx = sol.z[u.first[x]:u.first[x] + u.count[x]] @ LUMINANCE
    lum = np.log10(states.stratum_weight @ zx)
    assert abs(sq.log10_z[x] - lum) < 1e-9
    path = export_npz(tmp_path / "glossy", states, result.dynamics, result.lmdp, sol)
    data = np.load(path)
    N = states.n_unknowns
    np.testing.assert_array_equal(data["state_point"][:N], u.point)
    np.testing.assert_array_equal(data["state_stratum"][:N], u.stratum)
    P = sp.csr_matrix((data["P_data"], data["P_indices"], data["P_indptr"]), shape=tuple(data["P_shape"]))
    np.testing.assert_allclose(data["z"][:N], data["q"][:N] * (P @ data["z"]), rtol=1e-6, atol=1e-6)
    gather = build_gather(build_guide(scene, result), result, max_bounces=8, seed=1)
    assert gather.irradiance.shape == (states.n_points, 3) and np.all(np.isfinite(gather.irradiance))


def test_policy_arrows_of_a_sharp_glossy_point_point_along_the_mirror():
    """The arrows of a glossy point show u* of its unknown looking straight down on it
    (``arrows.directional_policy``): on a roughness-0.05 floor they gather in the stratum of
    that direction's mirror image; Lambertian points keep ``stratum_policy``'s rows."""
    from lmdp_addon.display.arrows import directional_policy, probe_unknowns
    from lmdp_addon.model.policy import stratum_policy
    from lmdp_addon.model.hemisphere import stratum_of_local_direction
    scene = glossy_floor_box(0.05)
    result = pipeline.run_all(scene, Settings(point_count=1500, rays_per_stratum=8, light_samples=16, seed=4,
                                              cost_mode="PHYSICAL"))
    states = result.states
    u = stratum_policy(result.dynamics, result.solution, "all")
    U = optimal_policy(result.lmdp, result.solution)
    shown = directional_policy(scene, states, result.dynamics, u, U)
    lamb = ~states.glossy
    np.testing.assert_array_equal(shown[lamb], u[lamb])
    floor = np.flatnonzero(states.glossy & (np.abs(states.points[:, :2]).max(axis=1) < 0.3)
                           & result.dynamics.locator.targets)        # not under the boxes (buried)
    k = states.unknowns.stratum[probe_unknowns(states, floor)]
    wo = stratum_centers(4, 4)[k]
    mirror = wo * [-1.0, -1.0, 1.0]                       # the mirror image about the normal (local z)
    k_mirror = stratum_of_local_direction(mirror, 4, 4)
    np.testing.assert_allclose(shown[floor].sum(axis=1), 1.0)
    on_mirror = shown[floor, k_mirror]
    assert np.median(on_mirror) > 0.5, np.round(on_mirror, 2)
    assert np.median(u[floor, k_mirror]) < 0.3      # the cosine rows (the guide's) spread out


def test_gather_source_reflects_direct_light_through_glossy_hits():
    """b(x) (``gather.direct_after_one_bounce``) at box states near the Cornell box's sharp
    (roughness 0.1) Glossy floor: the light reaching them after exactly one reflection, much
    of it the light's image in the floor, is the tracer's one-bounce estimate at the same points
    within 5 standard errors of both (b's from 8 seeds: its one light sample per glossy hit is
    noisier than the tracer's MIS). With the floor's hemispherical albedo in place of its BSDF
    b was 30 % to 5x too bright there."""
    from bake_scenes import K, trace_at
    from lmdp_addon.bake.gather import direct_after_one_bounce
    from lmdp_addon.bake.tracer import IndirectTracer
    scene = glossy_floor_box(0.1)
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL", seed=7))
    st = lmdp.states
    low = lmdp.dynamics.locator.targets & (st.points[:, 2] > 0.02) & (st.points[:, 2] < 0.35)
    points = np.concatenate([np.flatnonzero(low & (st.point_object == scene.object_names.index(n)))[:3]
                             for n in ("ShortBox", "TallBox")])
    assert len(points) == 6
    n, seeds = 5000, 8
    b = np.stack([direct_after_one_bounce(lmdp, n, seed=s, points=points)[points] for s in range(seeds)])
    b_se = b.std(axis=0, ddof=1) / np.sqrt(seeds)
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=1, caster=lmdp.dynamics.caster)
    for k, i in enumerate(points):
        pt, _ = trace_at(tracer, st.points[i], st.normals[i], 40_000, seed=10 + k)
        se = np.sqrt(b_se[k] ** 2 + pt.var(axis=0, ddof=1) / len(pt))
        assert np.all(np.abs(b[:, k].mean(axis=0) - pt.mean(axis=0)) <= K * se + 1e-12), \
            (i, b[:, k].mean(axis=0), pt.mean(axis=0), se)


def test_glossy_build_is_byte_identical_whatever_the_thread_count(monkeypatch):
    """The glossy rows are drawn at set-up and per batch (their own generators), so one build
    thread or several give the same matrices to the byte."""
    from lmdp_addon.model import dynamics as dynamics_module
    scene = scenes.build_scene_arrays("GLOSSY_BOX")
    states = sample_states(scene, 300, seed=8)
    monkeypatch.setattr(dynamics_module, "RAYS_PER_BATCH", 1 << 11)     # several batches
    out = []
    for threads in (1, 3):
        monkeypatch.setattr(dynamics_module, "BUILD_THREADS", threads)
        out.append(build_passive_dynamics(scene, states, 2, seed=8, light_samples=4))
    for name in ("P", "stratum_transitions"):
        a, b = getattr(out[0], name), getattr(out[1], name)
        for part in ("data", "indices", "indptr"):
            assert np.array_equal(getattr(a, part), getattr(b, part)), (name, part)
    assert np.array_equal(out[0].glossy_albedo, out[1].glossy_albedo)
