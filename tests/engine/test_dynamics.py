"""Passive dynamics by ray casting (thesis 3.1.2, eq. 3.1) against geometry with known answers."""
import numpy as np
import pytest

from lmdp_addon.model.dynamics import build_passive_dynamics, estimate_build_bytes
from lmdp_addon.errors import BudgetError
from lmdp_addon.demo_geometry import (PARALLEL_SQUARES, Part, build_scene_arrays, parts_to_scene_arrays,
                                      point_to_parallel_square_form_factor, scene_parts)
from lmdp_addon.model.states import sample_states


@pytest.fixture(scope="module")
def cornell():
    """Stratum rays only (no light samples): every row sums to exactly one."""
    scene = build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 1500, 4, 4, seed=3)
    return scene, states, build_passive_dynamics(scene, states, 4, seed=3, light_samples=0)


def test_rows_are_stochastic_and_strata_carry_their_cosine_mass(cornell):
    scene, states, dyn = cornell
    assert dyn.P.shape == (states.n_points, states.n_points + dyn.n_emitters + 2)
    assert dyn.P.dtype == np.float32 and dyn.P.indices.dtype == np.int32
    assert dyn.row_sum_error < 1e-5
    per_stratum = np.asarray(dyn.stratum_transitions.sum(axis=1)).reshape(-1, states.n_strata)
    assert np.allclose(per_stratum, states.stratum_weight[None, :], atol=1e-6)
    c = dyn.counts
    assert c["points"] + c["emitters"] + c["world"] + c["void"] == dyn.rays == 1500 * 16 * 4
    # The Cornell box is open at the front: some rays escape into the black world (void).
    assert c["void_escape"] > 0 and c["emitters"] > 0 and c["world"] == 0


def test_deterministic_for_a_seed(cornell):
    scene, states, dyn = cornell
    again = build_passive_dynamics(scene, states, 4, seed=3, light_samples=0)
    assert (abs(again.P - dyn.P)).max() == 0
    other = build_passive_dynamics(scene, states, 4, seed=4, light_samples=0)
    assert (abs(other.P - dyn.P)).max() > 0
    a = build_passive_dynamics(scene, states, 4, seed=3, light_samples=16)
    b = build_passive_dynamics(scene, states, 4, seed=3, light_samples=16)
    assert (abs(a.P - b.P)).max() == 0


def test_points_under_the_boxes_are_buried():
    """The floor under the boxes standing on it (and the boxes' bottoms) sees only the boxes'
    insides: those points get no light (rows to the void) and no ray lands on them, so their
    darkness does not spread to the floor beside the boxes."""
    scene = build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 3000, 4, 4, seed=2)
    dyn = build_passive_dynamics(scene, states, 4, seed=2, light_samples=8)
    buried = ~dyn.locator.targets
    assert dyn.counts["buried_points"] == buried.sum() > 0
    floor = states.point_object == scene.object_names.index("Floor")
    bottoms = floor & (states.points[:, 2] < 0.01)
    normals = scene.triangle_geometry()[0]
    feet = scene.corners()[(normals[:, 2] < -0.9) & (scene.corners()[:, :, 2].max(axis=1) < 1e-6)][:, :, :2]

    def under_a_box(xy):
        """Inside one of the boxes' bottom triangles (2-D barycentric test)."""
        a, b, c = feet[:, 0][None], feet[:, 1][None], feet[:, 2][None]
        v0, v1, v2 = c - a, b - a, xy[:, None] - a
        d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
        d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
        den = d00 * d11 - d01 * d01
        u, v = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        return np.any((u >= 0) & (v >= 0) & (u + v <= 1), axis=1)

    shifts = [np.array(d) for d in ((0, 0), (0.02, 0), (-0.02, 0), (0, 0.02), (0, -0.02))]
    xy = states.points[:, :2]
    inside = bottoms & np.all([under_a_box(xy + d) for d in shifts], axis=0)
    outside = bottoms & ~np.any([under_a_box(xy + 2.5 * d) for d in shifts], axis=0)
    assert len(feet) >= 4 and inside.sum() > 5 and outside.sum() > 100
    assert np.all(buried[inside]) and not np.any(buried[outside])
    P = dyn.P.tocsc()
    assert np.asarray(P[:, np.flatnonzero(buried)].sum(axis=0)).max() == 0      # nothing lands on them
    assert np.allclose(dyn.P[np.flatnonzero(buried), dyn.void_column].toarray(), 1.0, atol=1e-6)


def test_an_object_in_a_room_with_outward_normals_is_buried_and_named():
    """A room made of a closed box with outward normals (a scaled default cube) shows only back
    faces from inside: the box standing in it is buried, and the build says which object and
    what to do; in the same room with inward normals it is not."""
    from lmdp_addon.demo_geometry import WHITE, _box_part, _quad_part
    lamp = _quad_part("Lamp", [(-0.2, -0.2, 1.9), (-0.2, 0.2, 1.9), (0.2, 0.2, 1.9), (0.2, -0.2, 1.9)],
                      emission=(10.0, 10.0, 10.0))
    crate = _box_part("Crate", (0.0, 0.0, 0.5), (0.6, 0.6, 0.6), WHITE)
    for flip, expect in ((False, True), (True, False)):
        room = _box_part("Room", (0.0, 0.0, 1.0), (4.0, 4.0, 2.0), WHITE)
        if flip:
            room = Part(room.name, room.vertices, room.faces[:, ::-1], room.face_uv, room.albedo)
        scene = parts_to_scene_arrays([room, crate, lamp], selected=["Crate"])
        states = sample_states(scene, 300, 4, 4, seed=0)
        dyn = build_passive_dynamics(scene, states, 2, seed=0, light_samples=4)
        named = [w for w in dyn.warnings if "Crate" in w and "flip" in w]
        assert bool(named) == expect, dyn.warnings
        if expect:
            assert dyn.counts["buried_points"] > 150


def test_plane_under_sky_sends_every_ray_to_the_world():
    scene = build_scene_arrays("PLANE_UNDER_SKY")
    states = sample_states(scene, 200, 4, 4, seed=0)
    dyn = build_passive_dynamics(scene, states, 2, seed=0)
    assert np.allclose(dyn.P[:, dyn.world_column].toarray(), 1.0, atol=1e-5)
    assert dyn.counts["world"] == dyn.rays


def _moved(part, name, dz=0.0, scale=1.0, flip=False, emitter=None):
    """Copy of a part, scaled in x/y, moved along z, optionally flipped or made emitting."""
    v = part.vertices * [scale, scale, 1.0] + [0, 0, dz]
    faces = part.faces[:, ::-1] if flip else part.faces
    if emitter is None:
        return Part(name, v, faces, part.face_uv, part.albedo)
    return Part(name, v, faces, part.face_uv, np.zeros(3), part.emission, two_sided_emission=emitter == "two")


def test_back_face_hits_go_to_the_void():
    receiver, light = scene_parts("PARALLEL_SQUARES")
    below = _moved(receiver, "Below", dz=-0.5, scale=0.5)  # faces up, into Receiver's back
    scene = parts_to_scene_arrays([receiver, light, below], selected=["Receiver", "Below"])
    states = sample_states(scene, 400, 4, 4, seed=1)
    dyn = build_passive_dynamics(scene, states, 4, seed=1)
    below_ids = np.flatnonzero(states.point_object == 2)
    assert dyn.counts["back_faces"] > 0 and dyn.counts["void"] >= dyn.counts["back_faces"]
    # Straight up from "Below" is Receiver's back: most of its mass goes to the void.
    assert dyn.P[below_ids, dyn.void_column].toarray().mean() > 0.5


def test_unselected_geometry_occludes_and_absorbs():
    receiver, light = scene_parts("PARALLEL_SQUARES")
    ceiling = _moved(receiver, "Ceiling", dz=2.0, scale=6.0, flip=True)  # faces down, not selected
    scene = parts_to_scene_arrays([receiver, light, ceiling], selected=["Receiver"])
    states = sample_states(scene, 300, 4, 4, seed=2)
    dyn = build_passive_dynamics(scene, states, 4, seed=2)
    assert dyn.counts["void_unmodelled"] > 0 and dyn.counts["emitters"] > 0


@pytest.mark.parametrize("sidedness,expect_light", [("one", False), ("two", True)])
def test_back_of_a_one_sided_emitter_is_dark(sidedness, expect_light):
    receiver, light = scene_parts("PARALLEL_SQUARES")
    emitter = _moved(light, "Lamp", emitter=sidedness)              # faces down at z = 1
    top = _moved(receiver, "Top", dz=1.5, flip=True)                # faces down, onto its back
    scene = parts_to_scene_arrays([emitter, top], selected=["Top"])
    states = sample_states(scene, 200, 4, 4, seed=0)
    assert np.allclose(states.normals, [0, 0, -1])
    dyn = build_passive_dynamics(scene, states, 4, seed=0)
    assert (dyn.counts["emitters"] > 0) == expect_light
    assert (dyn.counts["void_emitter_back"] > 0) != expect_light


def test_form_factor_to_a_parallel_square_matches_the_analytic_value():
    """P(point -> emitter) is the point-to-square form factor F. Tolerance from the estimator's
    variance: stratum k contributes w_k times the mean of R Bernoulli(f_k) draws (f_k: the
    chance that a cosine-distributed ray of the stratum hits), so Var <= Σ_k w_k^2 / (4R) per
    point; the mean error over n points has variance <= that / n."""
    scene = build_scene_arrays("PARALLEL_SQUARES")
    R = 16
    states = sample_states(scene, 600, 4, 4, seed=5)
    dyn = build_passive_dynamics(scene, states, R, seed=5, light_samples=0)
    p = PARALLEL_SQUARES
    F = point_to_parallel_square_form_factor(p["emitter_side"], p["height"], offset=-states.points[:, :2])
    est = dyn.P[:, states.n_points].toarray().ravel()
    sigma = np.sqrt(np.sum(states.stratum_weight ** 2) / (4 * R))
    err = est - F
    assert np.abs(err).max() < 5 * sigma
    assert abs(err.mean()) < 5 * sigma / np.sqrt(len(err))


def test_form_factor_at_the_centre_with_fine_strata():
    scene = build_scene_arrays("PARALLEL_SQUARES")
    states = sample_states(scene, 1, 8, 8, seed=0)
    states.points[0] = [0.0, 0.0, 0.0]
    R = 256
    dyn = build_passive_dynamics(scene, states, R, seed=0, light_samples=0)
    p = PARALLEL_SQUARES
    F = point_to_parallel_square_form_factor(p["emitter_side"], p["height"])
    sigma = np.sqrt(np.sum(states.stratum_weight ** 2) / (4 * R))
    assert dyn.P[0, 1] == pytest.approx(F, abs=5 * sigma)
    assert abs(dyn.P[0, 1] - F) / F < 0.01  # in practice far tighter than the bound


def test_memory_budget_is_checked_before_any_work():
    scene = build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 1000, 4, 4)
    need = estimate_build_bytes(1000, 16, 4)
    with pytest.raises(BudgetError, match=r"GiB.*budget"):
        build_passive_dynamics(scene, states, 4, memory_budget_gb=need / 2 / 1024 ** 3)


def test_light_samples_keep_the_form_factor_unbiased_and_cut_its_variance():
    """Next-event estimation + MIS (light_samples > 0): per point, the spread over independent
    seeds gives σ̂; the mean over seeds and points must match F within 5 σ̂ / sqrt(n), and the
    error must be well below the stratum-rays-only estimator's at the same ray count."""
    scene = build_scene_arrays("PARALLEL_SQUARES", selected=["Receiver"])
    states = sample_states(scene, 300, 4, 4, seed=5)
    p = PARALLEL_SQUARES
    F = point_to_parallel_square_form_factor(p["emitter_side"], p["height"], offset=-states.points[:, :2])
    runs = np.array([build_passive_dynamics(scene, states, 4, seed=s, light_samples=64).P[:, 300].toarray().ravel()
                     for s in range(8)])
    sigma = runs.std(axis=0, ddof=1)
    err = runs.mean(axis=0) - F
    assert abs(err.mean()) < 5 * np.sqrt(np.mean(sigma ** 2) / (runs.size))
    # Per point, t = err / (σ̂/√8) follows Student's t with 7 degrees of freedom if unbiased:
    # E[t²] = 7/5, Var[t²] = 7.84, so the mean of t² over n points is 1.4 ± 2.8/√n.
    t = err / (sigma / np.sqrt(len(runs)))
    assert np.mean(t ** 2) < 1.4 + 5 * 2.8 / np.sqrt(len(t))
    brdf_only = build_passive_dynamics(scene, states, 4, seed=0, light_samples=0).P[:, 300].toarray().ravel()
    assert np.sqrt(np.mean((runs[0] - F) ** 2)) < 0.5 * np.sqrt(np.mean((brdf_only - F) ** 2))


def test_light_samples_keep_rows_unbiased_next_to_a_light():
    """The Cornell ceiling touches the (two-sided) light: MIS keeps every row near one."""
    scene = build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 1500, 4, 4, seed=3)
    dyn = build_passive_dynamics(scene, states, 4, seed=3, light_samples=64)
    sums = np.asarray(dyn.P.sum(axis=1)).ravel()
    assert abs(sums.mean() - 1) < 5 * sums.std() / np.sqrt(len(sums))
    assert dyn.row_sum_error < 0.25
    assert dyn.counts["nee_rays"] == 1500 * 64


def test_grazing_shadow_rays_next_to_a_light_are_not_clipped():
    """Ceiling points 5 mm above the Cornell light see its two-sided back at grazing angles. The
    next-event estimate of p(light | point) must agree with the stratum-rays-only estimate (no
    shadow rays at all); a shadow ray whose direction is measured from the surface point but
    traced from the lifted one crosses the light's own plane and comes out low. Bound: 5 σ of
    the difference, σ from the spread of the per-seed means."""
    scene = build_scene_arrays("CORNELL_BOX", selected=["Ceiling"])
    states = sample_states(scene, 400, 4, 4, seed=1)
    m = states.n_points
    nee = np.array([build_passive_dynamics(scene, states, 4, seed=s, light_samples=64).P[:, m].mean()
                    for s in range(6)])
    rays = np.array([build_passive_dynamics(scene, states, 128, seed=s, light_samples=0).P[:, m].mean()
                     for s in range(6)])
    sigma = np.sqrt(nee.var(ddof=1) / len(nee) + rays.var(ddof=1) / len(rays))
    assert abs(nee.mean() - rays.mean()) < 5 * sigma
    assert abs(nee.mean() / rays.mean() - 1) < 0.01
