"""The whole engine (states -> dynamics -> LMDP -> z, u*) on scenes with known answers, and the
hard cases the solver must survive (thesis 3.1; λ convention and rescaling in design.md)."""
import numpy as np
import pytest

from lmdp_addon.model.costs import build_first_exit_lmdp
from lmdp_addon.model.dynamics import build_passive_dynamics
from lmdp_addon.model.pipeline import lambda_for, run_all
from lmdp_addon.model.policy import optimal_policy, stratum_policy
from lmdp_addon.demo_geometry import (PARALLEL_SQUARES, SKY_RADIANCE, Part, build_scene_arrays,
                               parts_to_scene_arrays, point_to_parallel_square_form_factor, scene_parts)
from lmdp_addon.settings import Settings
from lmdp_addon.model.solvers import solve_desirability
from lmdp_addon.model.states import sample_states


def solve(scene, points=400, su=4, sv=4, R=4, mode="PHYSICAL", solver="ITERATIVE", lam=None, seed=0, **kw):
    states = sample_states(scene, points, su, sv, seed=seed)
    dyn = build_passive_dynamics(scene, states, R, seed=seed)
    lmdp = build_first_exit_lmdp(dyn, states, mode, lam)
    return states, dyn, lmdp, solve_desirability(lmdp, solver, seed=seed, **kw)


@pytest.mark.parametrize("solver", ("POWER", "DIRECT", "ITERATIVE"))
def test_plane_under_uniform_sky_has_z_equal_albedo_times_radiance(solver):
    scene = build_scene_arrays("PLANE_UNDER_SKY")
    states, dyn, lmdp, sol = solve(scene, solver=solver, tolerance=1e-12)
    expected = np.asarray(states.point_albedo, float) * np.asarray(SKY_RADIANCE)
    assert np.allclose(sol.z, expected, rtol=1e-5)


def test_plane_under_parallel_square_emitter_matches_the_form_factor():
    """PHYSICAL z = albedo · L · F(point): one bounce, everything else escapes to a black world.
    Tolerance from the estimator's variance (see test_dynamics): Var <= Σ w_k² / (4R)."""
    scene = build_scene_arrays("PARALLEL_SQUARES", selected=["Receiver"])
    R = 16
    states, dyn, lmdp, sol = solve(scene, points=500, R=R, seed=4, tolerance=1e-12)
    p = PARALLEL_SQUARES
    F = point_to_parallel_square_form_factor(p["emitter_side"], p["height"], offset=-states.points[:, :2])
    expected = np.outer(F, np.asarray(p["albedo"]) * np.asarray(p["radiance"]))
    sigma = np.sqrt(np.sum(states.stratum_weight ** 2) / (4 * R)) * np.asarray(p["albedo"]) * np.asarray(p["radiance"])
    err = sol.z - expected
    assert np.all(np.abs(err) < 5 * sigma)
    assert np.all(np.abs(err.mean(axis=0)) < 5 * sigma / np.sqrt(len(err)))


@pytest.fixture(scope="module")
def cornell_dynamics():
    scene = build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 800, 4, 4, seed=1)
    return scene, states, build_passive_dynamics(scene, states, 4, seed=1)


@pytest.mark.parametrize("scale", [1e-6, 1e-4, 1e-2, 1.0, 1e2, 1e3])
@pytest.mark.parametrize("solver", ("POWER", "DIRECT", "ITERATIVE"))
def test_thesis_mode_is_finite_for_lambda_over_nine_decades(cornell_dynamics, scale, solver):
    """λ = scale (absolute, 1e-6 .. 1e3): no NaN/Inf, u* rows sum to 1, log z exact (no silent
    underflow) and consistent with the power method's fixed point."""
    scene, states, dyn = cornell_dynamics
    lmdp = build_first_exit_lmdp(dyn, states, "THESIS", scale)
    sol = solve_desirability(lmdp, solver, tolerance=1e-10, max_iterations=3000, seed=2)
    assert not np.any(np.isnan(sol.z)) and not np.any(np.isnan(sol.log_z))
    assert np.all(np.isfinite(sol.log_z[sol.reachable]))
    if sol.converged:
        assert sol.residual < 1e-8
    else:
        assert sol.message  # λ -> 0: the solver says it did not meet the tolerance
    u = optimal_policy(lmdp, sol)
    assert np.all(np.isfinite(u.data)) and np.allclose(np.asarray(u.sum(axis=1)).ravel(), 1, atol=1e-9)
    g = stratum_policy(dyn, sol)
    assert np.all(np.isfinite(g)) and np.allclose(g.sum(axis=1), 1, atol=1e-9)
    if scale >= 1e2:
        # z underflows float64 for states several bounces from the light, log z does not:
        # log z is within one transition's worth of -λ·hops.
        assert np.all(sol.log_z[sol.reachable, 0] < 0)
        hops = np.round(sol.delta[sol.reachable] / sol.c_bar)
        assert np.all(np.abs(sol.log_z[sol.reachable, 0] + scale * hops) < scale)


def test_solvers_agree_in_the_log_domain_at_large_lambda(cornell_dynamics):
    scene, states, dyn = cornell_dynamics
    lmdp = build_first_exit_lmdp(dyn, states, "THESIS", 400.0)
    logs = [solve_desirability(lmdp, s, tolerance=1e-12, seed=1).log_z for s in ("POWER", "DIRECT", "ITERATIVE")]
    finite = np.isfinite(logs[1])  # -inf: states that cannot reach the light (buried: box bottoms)
    for other in (logs[0], logs[2]):
        assert np.array_equal(np.isfinite(other), finite)
        assert np.abs(other[finite] - logs[1][finite]).max() < 1e-6
    assert np.min(logs[1][finite]) < -745  # some z are below float64's smallest subnormal


def test_thesis_default_lambda_and_convention(cornell_dynamics):
    scene, states, dyn = cornell_dynamics
    settings = Settings(cost_mode="THESIS", lambda_scale=0.5)
    lam = lambda_for(scene, settings)
    _, radiance = scene.emitter_groups()
    assert lam == pytest.approx(0.5 * np.pi * (radiance @ [0.2126, 0.7152, 0.0722]).sum())
    lmdp = build_first_exit_lmdp(dyn, states, "THESIS", lam)
    sol = solve_desirability(lmdp, "DIRECT")
    assert np.allclose(sol.cost_to_go, -sol.log_z / lam)


def closed_box_with_light_outside():
    """A closed box (outward normals) selected from the inside would see only its own back
    faces; so: the room's walls enclose the box, and the light hangs *outside* the room."""
    parts = scene_parts("CORNELL_BOX")
    light = next(p for p in parts if p.name == "Light")
    moved = Part("Light", light.vertices + [0, 0, 2.0], light.faces, light.face_uv, light.albedo,
                 light.emission)
    floor = next(p for p in parts if p.name == "Floor")
    # The missing front wall: y = -0.5, facing +y into the room (corners counter-clockwise).
    lid = Part("FrontWall", [(-0.5, -0.5, 0), (-0.5, -0.5, 1), (0.5, -0.5, 1), (0.5, -0.5, 0)], [[0, 1, 2, 3]],
               floor.face_uv, floor.albedo)
    others = [p for p in parts if p.name != "Light"]
    return parts_to_scene_arrays(others + [lid, moved], selected=[p.name for p in others] + ["FrontWall"])


def test_closed_box_without_emitter_inside_has_zero_desirability():
    scene = closed_box_with_light_outside()
    states, dyn, lmdp, sol = solve(scene, points=300)
    assert dyn.counts["emitters"] == 0  # (rays from the boxes' bottoms escape below the floor)
    assert sol.n_unreachable == states.n_points
    assert np.all(sol.z == 0) and np.all(np.isinf(sol.cost_to_go))
    assert f"{states.n_points} states cannot reach a light" in sol.summary()
    g = stratum_policy(dyn, sol)
    assert np.allclose(g, states.stratum_weight[None, :] / states.stratum_weight.sum(), atol=1e-6)


def test_points_whose_rays_all_escape_into_a_black_world():
    receiver, light = scene_parts("PARALLEL_SQUARES")
    under = Part("Lamp", light.vertices - [0, 0, 2.0], light.faces[:, ::-1], light.face_uv, light.albedo, light.emission)
    scene = parts_to_scene_arrays([receiver, under], selected=["Receiver"])  # lamp below, pointing down
    states, dyn, lmdp, sol = solve(scene, points=100)
    assert dyn.counts["void_escape"] == dyn.rays
    assert sol.n_unreachable == 100 and np.all(sol.z == 0)


def test_single_point_scene():
    scene = build_scene_arrays("PARALLEL_SQUARES", selected=["Receiver"])
    for solver in ("POWER", "DIRECT", "ITERATIVE"):
        states, dyn, lmdp, sol = solve(scene, points=1, su=2, sv=2, R=64, solver=solver)
        assert sol.z.shape == (1, 3) and sol.converged and np.all(sol.z > 0)


def test_float32_and_float64_agree_on_a_scene(cornell_dynamics):
    scene, states, dyn = cornell_dynamics
    lmdp = build_first_exit_lmdp(dyn, states, "PHYSICAL")
    a = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-6, dtype=np.float32)
    b = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-12, dtype=np.float64)
    assert np.abs(a.z - b.z).max() < 1e-5 * np.abs(b.z).max()


def test_pipeline_runs_every_stage_with_settings():
    scene = build_scene_arrays("CORNELL_BOX")
    result = run_all(scene, Settings(point_count=300, rays_per_stratum=2, cost_mode="PHYSICAL"))
    assert result.solution.converged and set(result.seconds) == {"sample", "build", "solve"}
    assert np.all(result.solution.z[result.solution.reachable] > 0)
