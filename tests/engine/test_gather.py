"""Final gather (lmdp_addon.bake.gather): ẑ_ind of the states, its source b, and FINAL_GATHER
paths against analytic light and against path tracing."""
import numpy as np

from bake_scenes import (K, PATCH_ALBEDO, assert_within, expected_patch_indirect, patch_over_lamp,
                         solved_patch_under_sky, trace_at)
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.gather import build_gather, direct_after_one_bounce
from lmdp_addon.bake.guide import build_guide
from lmdp_addon.bake.tracer import IndirectTracer
from lmdp_addon.model import pipeline
from lmdp_addon.model.states import sample_states
from lmdp_addon.settings import Settings


def test_patch_under_sky_final_gather():
    """FINAL_GATHER reads ẑ_ind of the patch states: here all of z/ρ, since the sky is the only
    light and it is not an emitter triangle, i.e. their sky fraction estimated by the dynamics'
    rays. Its bias is the discretisation error of that fraction, measured against the analytic
    value. The bound is the spread of ẑ over the patch states it interpolates."""
    scene, lmdp = solved_patch_under_sky()
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp)
    tracer = IndirectTracer(scene, "FINAL_GATHER", guide=guide, gather=gather)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 50_000, state=state)
    assert stats.gathered == stats.vertices and stats.gather_fallback == 0  # every hit is on the patch
    patch = lmdp.states.point_object == scene.object_names.index("Patch")
    spread = gather.irradiance[patch].std(axis=0)
    assert_within(values, expected_patch_indirect(),
                  extra=np.asarray(PATCH_ALBEDO) * spread / np.sqrt(patch.sum()) * 5 + 1e-3)
    assert stats.rays == stats.paths  # one ray per path


def test_final_gather_reads_the_paths_of_its_bounce_budget():
    """With ``max_bounces`` = N the gathered light has N - 1 vertices after the gather point:
    none for N = 1 (black world: ẑ_ind = 0), and the converged solution's for large N; in
    between it grows with N."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    assert np.all(build_gather(guide, lmdp, 1).irradiance == 0.0)
    two, eight = build_gather(guide, lmdp, 2).irradiance, build_gather(guide, lmdp, 8).irradiance
    converged, many = build_gather(guide, lmdp).irradiance, build_gather(guide, lmdp, 500).irradiance
    assert np.all(two <= eight + 1e-12) and np.all(eight <= many + 1e-12) and eight.sum() < many.sum()
    np.testing.assert_allclose(many, converged, rtol=1e-6, atol=1e-9)


def test_final_gather_takes_direct_light_at_the_gather_point():
    """Over a lamp just below the patch, FINAL_GATHER is unbiased: the patch's light is all
    direct, which the tracer samples at the exact gather point, and the gathered indirect part
    ẑ (``gather.build_gather``) is zero on the patch (black receiver and world). The states'
    z/ρ, read at the nearest states instead, carries the gap's light across the lamp's edge
    several times over, so the test can tell the two apart."""
    scene = patch_over_lamp()
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp)
    patch = lmdp.states.point_object == scene.object_names.index("Patch")
    assert np.all(gather.irradiance[patch] == 0.0)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    fg, stats = trace_at(IndirectTracer(scene, "FINAL_GATHER", guide=guide, gather=gather),
                         (0.0, 0.0, 0.0), (0, 0, 1), 200_000, state=state)
    assert stats.gathered > 0 and stats.shadow_rays > 0
    pt, _ = trace_at(IndirectTracer(scene, "UNGUIDED", max_bounces=1), (0.0, 0.0, 0.0), (0, 0, 1), 200_000, seed=1)
    se = np.sqrt(fg.var(axis=0, ddof=1) / len(fg) + pt.var(axis=0, ddof=1) / len(pt))
    assert np.all(np.abs(fg.mean(axis=0) - pt.mean(axis=0)) <= K * se), (fg.mean(axis=0), pt.mean(axis=0), se)


def test_direct_after_one_bounce_is_the_one_bounce_light_of_the_states():
    """b(x), FINAL_GATHER's source term, is the light that reaches a state point after exactly
    one reflection: the tracer's estimate with one bounce at the same point, within the two
    estimates' standard errors (b's per-ray variance is that of the tracer's light-sampling
    half, so its standard error is taken equal to the tracer's). The points include ceiling
    states beside the Cornell box's lamp, whose 5 mm gap made the old gather leak."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    lmdp = pipeline.run_all(scene, Settings(point_count=512, cost_mode="PHYSICAL"))
    st = lmdp.states
    ceiling = np.flatnonzero(st.point_object == scene.object_names.index("Ceiling"))
    lamp_edge = ceiling[np.argsort(np.abs(np.abs(st.points[ceiling, 0]) - 0.125))[:2]]
    others = [np.flatnonzero(st.point_object == scene.object_names.index(n))[0]
              for n in ("Floor", "LeftWall", "TallBox")]
    points = np.concatenate([lamp_edge, others])
    n = 40_000
    b = direct_after_one_bounce(lmdp, n, seed=3, points=points)
    assert np.all(np.delete(b, points, axis=0) == 0.0)
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=1, caster=lmdp.dynamics.caster)
    for k, i in enumerate(points):
        pt, _ = trace_at(tracer, st.points[i], st.normals[i], n, seed=10 + k)
        se = np.sqrt(2.0) * pt.std(axis=0, ddof=1) / np.sqrt(n)
        assert np.all(np.abs(b[i] - pt.mean(axis=0)) <= K * se + 1e-12), (i, b[i], pt.mean(axis=0), se)
    assert b[points].sum() > 0


def test_final_gather_does_not_gather_through_a_solid():
    """A point of the Cornell floor under the short box starts its paths inside the box (the ray
    origin is lifted above the floor, which the box's bottom face covers): its first rays meet
    the back of the box's faces. States describe the front of their faces only, so those
    gathers fall back to path tracing, which finds no light in the closed box. Gathering there
    would take the light of the states outside the box."""
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    lmdp = pipeline.run_all(scene, Settings(point_count=2048, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp, 8)
    box = scene.vertices[np.unique(scene.triangles[scene.triangle_object == scene.object_names.index("ShortBox")])]
    centre = 0.5 * (box.min(axis=0) + box.max(axis=0)) * np.array([1.0, 1.0, 0.0])   # on the floor
    up = np.array([[0.0, 0.0, 1.0]])
    state = guide.states_at(centre[None], up, np.array([scene.object_names.index("Floor")]))[0]
    assert state >= 0
    fg, stats = trace_at(IndirectTracer(scene, "FINAL_GATHER", guide=guide, gather=gather),
                         centre, up[0], 4000, state=state)
    assert stats.gather_fallback == 4000 and stats.gathered == 0
    assert np.all(fg == 0.0)
    # The field itself: NaN at back-face hits, a value at the front hits of the same cells.
    tri = np.flatnonzero(scene.triangle_object == scene.object_names.index("ShortBox"))[:1].repeat(2)
    n = scene.triangle_geometry()[0][tri]
    pos = scene.corners()[tri].mean(axis=1)
    value = gather.value_at(tri, np.full(2, 1 / 3), np.full(2, 1 / 3), pos, n * [[1], [-1]],
                            np.array([True, False]), scene.triangle_object[tri])
    assert np.all(np.isfinite(value[0])) and np.all(np.isnan(value[1]))


def test_final_gather_path_traces_hits_closer_than_half_a_state_spacing():
    """On a bumpy floor (the HEAVY scene's, coarser), the floor under a box is a thin gap
    between the bumps and the box's bottom. Its states are buried, so a ray that meets the next
    bump a few millimetres away would gather the ẑ of the floor states outside the box, far too
    bright. Hits closer than half a state spacing are path traced (``GatherField.too_close``),
    and FINAL_GATHER then agrees with UNGUIDED path tracing there."""
    parts = scenes._cornell_parts(subdivisions=30, bump=0.01)
    scene = scenes.parts_to_scene_arrays(parts, None, (0, 0, 0))
    lmdp = pipeline.run_all(scene, Settings(point_count=2048, cost_mode="PHYSICAL"))
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp, 8)
    floor = scene.object_names.index("Floor")
    # Covered floor points: a front face within 2 cm straight above them. The candidates are
    # the state sampler's area-uniform points of the floor alone (the same geometry).
    candidates = sample_states(scenes.parts_to_scene_arrays(parts, ["Floor"], (0, 0, 0)), 20_000, seed=0)
    p, n = candidates.points, candidates.normals
    normals = scene.triangle_geometry()[0]
    hit, dist = lmdp.dynamics.caster.intersect(p + 1e-3 * n, n)
    front = np.einsum("ij,ij->i", normals[np.maximum(hit, 0)], n) < 0
    covered = np.flatnonzero((hit >= 0) & (dist < 0.02) & front)
    covered = covered[np.linspace(0, len(covered) - 1, 100).astype(int)]   # spread over all of them
    assert len(np.unique(covered)) == 100
    m = 2000
    P, N = np.repeat(p[covered], m, axis=0), np.repeat(n[covered], m, axis=0)
    states = np.repeat(guide.states_at(p[covered], n[covered], np.full(len(covered), floor)), m)
    luminance = np.array([0.2126, 0.7152, 0.0722])
    estimates = {}
    for mode, seed in (("UNGUIDED", 1), ("FINAL_GATHER", 2)):
        r = np.random.default_rng(seed)
        tracer = IndirectTracer(scene, mode, guide=guide, gather=gather if mode == "FINAL_GATHER" else None,
                                caster=lmdp.dynamics.caster)
        values, stats = tracer.trace(P, N, states, r.random((len(P), 2)), r.random(len(P)), r)
        estimates[mode] = values.astype(np.float64) @ luminance
    assert stats.gathered > 0 and stats.gather_fallback > 0
    fg, pt = estimates["FINAL_GATHER"], estimates["UNGUIDED"]
    se = np.sqrt(fg.var(ddof=1) / len(fg) + pt.var(ddof=1) / len(pt))
    assert abs(fg.mean() - pt.mean()) <= K * se, (fg.mean(), pt.mean(), se)
    # The rule itself: objects without states never count as close.
    d = np.array([0.0, 1e-3, 1.0])
    close = gather.too_close(d, np.full(3, floor))
    assert close[0] and close[1] and not close[2]
    lamp = scene.object_names.index("Light")
    assert not gather.too_close(d, np.full(3, lamp)).any()
