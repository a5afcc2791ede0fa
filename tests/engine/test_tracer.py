"""The wavefront tracer (lmdp_addon.bake.tracer) against analytic indirect light.

Tolerances are Monte Carlo bounds computed from the samples themselves: an estimate m of n
independent path values with sample standard deviation s must lie within 5 s / sqrt(n) of the
analytic value (plus the analytic model's own error where it has one, stated at the test).
"""
import numpy as np
import pytest

from lmdp_addon.bake import driver as baking
from lmdp_addon.model import pipeline
from lmdp_addon import demo_geometry as scenes
from lmdp_addon.model.hemisphere import stratum_of_local_direction, tangent_frame
from lmdp_addon.settings import Settings
from lmdp_addon.model.states import sample_states
from lmdp_addon.bake.tracer import IndirectTracer, StateGuide, TraceStats
from lmdp_addon.bake.driver import build_guide, build_gather

K = 5.0  # standard errors


def assert_within(values, expected, extra=0.0, k=K):
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    mean = values.mean(axis=0)
    se = values.std(axis=0, ddof=1) / np.sqrt(n)
    bound = k * se + extra
    assert np.all(np.abs(mean - expected) <= bound), f"mean {mean} expected {expected} bound {bound}"
    return mean, se


def trace_at(tracer, point, normal, n, seed=0, state=-1):
    rng = np.random.default_rng(seed)
    p = np.tile(np.asarray(point, dtype=np.float64), (n, 1))
    nn = np.tile(np.asarray(normal, dtype=np.float64), (n, 1))
    values, stats = tracer.trace(p, nn, np.full(n, state), rng.random((n, 2)), rng.random(n), rng)
    return values, stats


# -- scenes with a known answer ------------------------------------------------------------------

SKY = 1.5
PATCH_ALBEDO = (0.5, 0.6, 0.8)


def patch_under_sky():
    """A 1 m square patch (albedo ρ) facing down 1 m above a 4 cm receiver, uniform sky L.

    The patch's underside sees the sky (the receiver's 0.0016 m² change that by < 1e-3 in
    relative terms), so its radiance is ρ L and the receiver's indirect light is ρ L F, F the
    point-to-parallel-square form factor. Nothing else bounces.
    """
    e, r = 0.5, 0.02
    parts = [
        scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.7, 0.7, 0.7)),
        scenes._quad_part("Patch", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], PATCH_ALBEDO),
    ]
    return scenes.parts_to_scene_arrays(parts, world=(SKY, SKY, SKY))


def expected_patch_indirect(offset=(0.0, 0.0)):
    F = scenes.point_to_parallel_square_form_factor(1.0, 1.0, offset)
    return np.asarray(PATCH_ALBEDO) * SKY * F


def furnace(albedo=0.5, radiance=1.0):
    """A closed unit cube whose inside walls both emit L (two-sided) and reflect ρ.

    The radiance everywhere inside is L (1 + ρ + ρ² + ...); the indirect light at a wall point is
    what has bounced at least once: L (ρ + ... + ρ^N) with N bounces.
    """
    box = scenes._box_part("Box", (0, 0, 0), (1, 1, 1), (albedo,) * 3)
    inward = scenes.Part("Box", box.vertices, box.faces[:, ::-1], box.face_uv[:, ::-1], (albedo,) * 3,
                         (radiance,) * 3)
    return scenes.parts_to_scene_arrays([inward])


@pytest.mark.parametrize("bounces", [1, 2, 8])
def test_furnace_indirect_is_the_geometric_series(bounces):
    scene = furnace()
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=bounces)
    values, stats = trace_at(tracer, (0.1, 0.2, -0.5), (0, 0, 1), 100_000, seed=bounces)
    expected = sum(0.5 ** k for k in range(1, bounces + 1))
    assert_within(values[:, 0], expected)
    # Russian roulette starts at vertex 3: at most one closest-hit ray per vertex, plus the last.
    assert stats.rays <= stats.paths * (bounces + 1)
    assert stats.vertices > 0 and stats.shadow_rays > 0


def test_direct_light_is_excluded():
    """Parallel squares: the receiver sees only the (black, emitting) square: no indirect light."""
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    tracer = IndirectTracer(scene, "UNGUIDED")
    values, stats = trace_at(tracer, (0.1, 0.0, 0.0), (0, 0, 1), 20_000)
    assert np.all(values == 0.0)
    assert stats.rays > 0


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.015, -0.01)])
def test_patch_under_sky_unguided(offset):
    scene = patch_under_sky()
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    values, _ = trace_at(tracer, (*offset, 0.0), (0, 0, 1), 200_000)
    assert_within(values, expected_patch_indirect(offset), extra=1e-3 * expected_patch_indirect(offset))


@pytest.fixture(scope="module")
def solved_patch():
    scene = patch_under_sky()
    settings = Settings(point_count=512, cost_mode="PHYSICAL")
    return scene, pipeline.run_all(scene, settings)


def test_patch_under_sky_guided_is_unbiased(solved_patch):
    scene, lmdp = solved_patch
    guide = build_guide(scene, lmdp)
    tracer = IndirectTracer(scene, "GUIDED", max_bounces=4, guide=guide, guide_fraction=0.7)
    n = 200_000
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    assert state >= 0
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), n, state=state)
    assert_within(values, expected_patch_indirect(), extra=1e-3 * expected_patch_indirect())
    assert stats.guided_vertices > 0


def test_patch_under_sky_final_gather(solved_patch):
    """FINAL_GATHER reads ẑ_ind of the patch states: here all of z/ρ, since the sky is the only
    light and it is not an emitter triangle, i.e. their sky fraction estimated by the dynamics'
    rays. Its bias is the discretisation error of that fraction, measured against the analytic
    value. The bound is the spread of ẑ over the patch states it interpolates."""
    scene, lmdp = solved_patch
    guide = build_guide(scene, lmdp)
    gather = build_gather(guide, lmdp)
    tracer = IndirectTracer(scene, "FINAL_GATHER", guide=guide, gather=gather)
    state = guide.states_at(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([0]))[0]
    values, stats = trace_at(tracer, (0.0, 0.0, 0.0), (0, 0, 1), 50_000, state=state)
    assert stats.gathered == stats.vertices and stats.gather_fallback == 0  # every hit is on the patch
    patch = lmdp.states.point_object == scene.object_names.index("Patch")
    spread = gather.irradiance[patch].std(axis=0)
    mean, _ = assert_within(values, expected_patch_indirect(),
                            extra=np.asarray(PATCH_ALBEDO) * spread / np.sqrt(patch.sum()) * 5 + 1e-3)
    assert stats.rays == stats.paths  # one ray per path


def patch_over_lamp(gap=0.005):
    """The patch of :func:`patch_under_sky` lit by a two-sided 0.2 m lamp ``gap`` below it, over
    a black receiver, in a black world: the patch's radiance is ρ D_e(y), all of it direct, and
    D_e is large only in the gap above the lamp (which the receiver cannot see)."""
    e, r, lx = 0.5, 0.02, 0.1
    z = 1.0 - gap
    parts = [
        scenes._quad_part("Receiver", [(-r, -r, 0), (r, -r, 0), (r, r, 0), (-r, r, 0)], (0.0, 0.0, 0.0)),
        scenes._quad_part("Patch", [(-e, -e, 1), (-e, e, 1), (e, e, 1), (e, -e, 1)], PATCH_ALBEDO),
        scenes._quad_part("Lamp", [(-lx, -lx, z), (-lx, lx, z), (lx, lx, z), (lx, -lx, z)], emission=(10.0,) * 3),
    ]
    return scenes.parts_to_scene_arrays(parts)


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
    ẑ (``baking.build_gather``) is zero on the patch (black receiver and world). The states' z/ρ, read at
    the nearest states instead, carries the gap's light across the lamp's edge: measured 4.6 x
    with 512 points, so the test can tell the two apart."""
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
    b = baking.direct_after_one_bounce(lmdp, n, seed=3, points=points)
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
    took the light of the states outside the box: 1.1 points of FINAL_GATHER's +1.75 % bias
    on the floor at 32768 points (128 px, 256 samples, against the benchmark's Cycles
    reference), about 6.5 % of the floor's mean light on each texel under a box."""
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
    bump a few millimetres away would gather the ẑ of the floor states outside the box: +23 %
    (10 standard errors) at these covered points with no distance limit, +81 % on the HEAVY
    floor's covered texels.
    Hits closer than half a state spacing are path traced (``GatherField.too_close``), and
    FINAL_GATHER then agrees with UNGUIDED path tracing there."""
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
    print("DBG", fg.mean(), pt.mean(), se); assert abs(fg.mean() - pt.mean()) <= K * se, (fg.mean(), pt.mean(), se)
    # The rule itself: objects without states never count as close.
    d = np.array([0.0, 1e-3, 1.0])
    close = gather.too_close(d, np.full(3, floor))
    assert close[0] and close[1] and not close[2]
    lamp = scene.object_names.index("Light")
    assert not gather.too_close(d, np.full(3, lamp)).any()


# -- the guide's density ---------------------------------------------------------------------------

def random_guide(strata_u=3, strata_v=5, m=4, seed=0):
    rng = np.random.default_rng(seed)
    S = strata_u * strata_v
    u = rng.random((m, S)) ** 3
    u[:, 2] = 0.0  # a stratum the guide never picks
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return StateGuide(locator=None, frames=tangent_frame(normals), first=u, later=u[::-1].copy(),
                      strata_u=strata_u, strata_v=strata_v), normals


def test_guide_samples_follow_the_policy_and_the_density_integrates_to_one():
    guide, normals = random_guide()
    rng = np.random.default_rng(2)
    S = guide.n_strata
    for s in range(len(normals)):
        n = 200_000
        states = np.full(n, s)
        d = guide.sample(states, rng.random((n, 2)), first=True)
        local = np.einsum("ij,kj->ki", guide.frames[s], d)
        k = stratum_of_local_direction(local, guide.strata_u, guide.strata_v)
        freq = np.bincount(k, minlength=S) / n
        p = guide.first[s]
        assert np.all(np.abs(freq - p) <= K * np.sqrt(p * (1 - p) / n) + 1e-12), (freq, p)
        # ∫ g dω over the sphere by uniform sampling: 4π E[g] = 1.
        w = rng.normal(size=(n, 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        g = guide.density(states, w, first=True) * 4 * np.pi
        assert_within(g, 1.0)
        # Within a stratum the samples are uniform in solid angle: the density at the samples
        # equals u*(k) S / 2π.
        np.testing.assert_allclose(guide.density(states, d, first=True), p[k] * S / (2 * np.pi), rtol=1e-9)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.9])
def test_mixture_weights_have_expectation_one(alpha):
    """E[cos/(π p)] = ∫ cos/π dω = 1 for the mixture pdf: the GUIDED direction sampling is
    unbiased. The shading normal is tilted from the state's (directions below its horizon get
    weight 0, the pdf stays exact)."""
    guide, normals = random_guide(m=1, seed=3)
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    tracer = IndirectTracer(scene, "GUIDED", guide=guide, guide_fraction=alpha)
    n = 400_000
    rng = np.random.default_rng(4)
    tilted = normals[0] + 0.3 * np.cross(normals[0], [0.0, 0.0, 1.0])
    tilted /= np.linalg.norm(tilted)
    shading = np.tile(tilted.astype(np.float32), (n, 1))
    d, w, cos = tracer._sample(shading, np.zeros(n, dtype=np.int64), rng.random((n, 2)), rng.random(n), first=True)
    assert_within(w, 1.0)
    assert np.all(w[cos <= 0] == 0)


def test_guided_vertices_without_a_state_use_cosine_sampling():
    guide, _ = random_guide(m=1)
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    tracer = IndirectTracer(scene, "GUIDED", guide=guide, guide_fraction=0.8)
    n = 1000
    rng = np.random.default_rng(5)
    normals = np.tile(np.array([0, 0, 1], np.float32), (n, 1))
    _, w, cos = tracer._sample(normals, np.full(n, -1), rng.random((n, 2)), rng.random(n), first=True)
    np.testing.assert_array_equal(w, 1.0)
    assert np.all(cos > 0)


def test_trace_stats_add_up():
    a = TraceStats(paths=2, rays=3, shadow_rays=1)
    a.add(TraceStats(paths=1, rays=1, shadow_rays=4, gathered=2))
    assert a.as_dict()["paths"] == 3 and a.total_rays == 9 and a.gathered == 2


def test_modes_need_their_inputs():
    scene = scenes.build_scene_arrays("PARALLEL_SQUARES")
    with pytest.raises(ValueError):
        IndirectTracer(scene, "GUIDED")
    with pytest.raises(ValueError):
        IndirectTracer(scene, "FINAL_GATHER", guide=random_guide()[0])
    with pytest.raises(ValueError):
        IndirectTracer(scene, "PHOTON")


def test_cosine_warps_are_shirley_chiu_and_polar():
    """The texel's stratified first bounce uses the concentric map (as hemisphere.py), later
    bounces the polar map; both give cosine-distributed directions: E[cos θ] = 2/3 and the
    fraction within θ < 60° is sin²(60°) = 3/4."""
    from lmdp_addon.model.hemisphere import concentric_square_to_disk
    rng = np.random.default_rng(6)
    u = rng.random((100_000, 2))
    normals = np.tile(np.array([0, 0, 1], np.float32), (len(u), 1))
    d = IndirectTracer._cosine_directions(normals, u, stratified=True)
    x, y = concentric_square_to_disk(u[:, 0], u[:, 1])
    np.testing.assert_allclose(d[:, 0], x, atol=2e-6)
    np.testing.assert_allclose(d[:, 1], y, atol=2e-6)
    for stratified in (True, False):
        d = IndirectTracer._cosine_directions(normals, u, stratified=stratified).astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
        assert_within(d[:, 2], 2.0 / 3.0)
        assert_within((d[:, 2] > 0.5).astype(float), 0.75)


@pytest.mark.parametrize("height", [0.02, 0.3, 1.0, 3.0])
def test_light_sampling_gives_the_form_factor_near_and_far(height):
    """D_e = (1/π) ∫ L cos θ dω below a square emitter (both MIS halves: light samples with
    solid-angle sampling close to the light, area sampling far from it, and cosine rays that hit
    it) equals L F, F the analytic point-to-square form factor."""
    from lmdp_addon.bake.tracer import spherical_triangle_sample
    p = scenes.PARALLEL_SQUARES
    parts = [scenes._quad_part("Emitter", [(-.5, -.5, height), (-.5, .5, height), (.5, .5, height), (.5, -.5, height)],
                               emission=p["radiance"])]
    scene = scenes.parts_to_scene_arrays(parts)
    tracer = IndirectTracer(scene, "UNGUIDED")
    n = 200_000
    rng = np.random.default_rng(7)
    pts = np.tile(np.array([0.2, 0.1, 0.0], np.float32), (n, 1))
    nrm = np.tile(np.array([0, 0, 1], np.float32), (n, 1))
    stats = TraceStats()
    light = tracer._direct(pts, nrm, rng, stats)[:, 0].astype(np.float64)
    d = tracer._cosine_directions(nrm, rng.random((n, 2)), stratified=False)
    origin = pts + tracer.eps * nrm
    tri, dist = tracer.caster.intersect(origin, d)
    hit = tri >= 0
    rays = np.zeros(n)
    cos = np.einsum("ij,ij->i", nrm, d)
    lit, value = tracer._emission_hits(origin, d, tri, dist, cos, np.flatnonzero(hit))
    rays[lit] = value[:, 0]
    near = tracer._near(origin[:1].astype(np.float64), np.array([0]))[0]
    assert near == (height < np.sqrt(2.0))
    F = scenes.point_to_parallel_square_form_factor(1.0, height, (-0.2, -0.1))
    assert_within(light + rays, p["radiance"][0] * F)
    # Every solid-angle sample points into its triangle.
    c = scene.corners()[:1] - origin[:1].astype(np.float64)[:, None, :]
    dirs, omega = spherical_triangle_sample(np.repeat(c, 1000, axis=0), rng.random(1000), rng.random(1000))
    assert np.all(omega > 0)
    e1, e2 = c[0, 1] - c[0, 0], c[0, 2] - c[0, 0]
    M = np.stack([np.broadcast_to(e1, dirs.shape), np.broadcast_to(e2, dirs.shape), -dirs], axis=2)
    bary = np.linalg.solve(M, np.broadcast_to(-c[0, 0], dirs.shape)[..., None])[..., 0]
    assert np.all(bary[:, 0] >= -1e-7) and np.all(bary[:, 1] >= -1e-7) and np.all(bary[:, :2].sum(1) <= 1 + 1e-7)


def test_neighbour_average_is_a_distribution_over_shared_strata_and_denoises_the_guide():
    """u* from 4 rays per stratum, averaged over 16 same-normal neighbours, is closer to u* of the
    same points from 256 rays per stratum than the raw rows are (mean L1 distance 0.26 vs 0.36);
    rows stay distributions; only points with the same normal (hence the same strata) are mixed."""
    from lmdp_addon.bake.driver import GUIDE_NEIGHBOURS
    from lmdp_addon.model.locator import StateLocator
    from lmdp_addon.model.policy import stratum_policy
    from lmdp_addon.bake.tracer import neighbour_average
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    raw = pipeline.run_all(scene, Settings(point_count=1024, rays_per_stratum=4))
    ref = pipeline.run_all(scene, Settings(point_count=1024, rays_per_stratum=256))
    states = raw.states
    locator = StateLocator(scene, states)
    u_raw = stratum_policy(raw.dynamics, raw.solution, "points")
    u_ref = stratum_policy(ref.dynamics, ref.solution, "points")
    u_avg = neighbour_average(u_raw, locator, states.normals, GUIDE_NEIGHBOURS)
    np.testing.assert_allclose(u_avg.sum(axis=1), 1.0, atol=1e-12)
    assert np.all(u_avg >= 0)
    err_raw = np.abs(u_raw - u_ref).sum(axis=1).mean()
    err_avg = np.abs(u_avg - u_ref).sum(axis=1).mean()
    assert err_avg < 0.8 * err_raw, (err_avg, err_raw)
    # One neighbour is the identity; a point whose normal is farther than NEIGHBOUR_MAX_ANGLE
    # from every other point's keeps its row.
    np.testing.assert_array_equal(neighbour_average(u_raw, locator, states.normals, 1), u_raw)
    lonely = states.normals.copy()
    lonely[0] = _unit_vector(lonely[0] + 0.5 * _unit_vector(np.cross(lonely[0], [0.3, 0.5, 0.8])))
    np.testing.assert_array_equal(neighbour_average(u_raw, locator, lonely, GUIDE_NEIGHBOURS)[0], u_raw[0])


def test_neighbour_average_mixes_nearly_equal_normals_on_the_same_frame_branch():
    """Within NEIGHBOUR_MAX_ANGLE normals count as equal, but never across a sign change of the
    normal's z (where the tangent frame jumps); each point's row is the mean of exactly those."""
    from lmdp_addon.model.locator import StateLocator
    from lmdp_addon.model.states import sample_states
    from lmdp_addon.bake.tracer import NEIGHBOUR_MAX_ANGLE, neighbour_average
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, 256, 2, 2, seed=3)
    locator = StateLocator(scene, states)
    rng = np.random.default_rng(4)
    # Tilt every normal at random by up to 2 x the tolerance; on the back wall (normal -y,
    # z = 0) the tilt flips the sign of z at random.
    normals = np.array([_unit_vector(n + np.tan(np.radians(2 * NEIGHBOUR_MAX_ANGLE)) * rng.random()
                                     * _unit_vector(rng.normal(size=3))) for n in states.normals])
    rows = np.eye(len(normals))                   # row i marks point i: the mean shows who is in
    out = neighbour_average(rows, locator, normals, 16)
    cos_max = np.cos(np.radians(NEIGHBOUR_MAX_ANGLE))
    mixed_any = flipped = 0
    for o, tree in locator.trees.items():
        ids = locator.index[o]
        _, nn = tree.query(tree.data, k=min(16, len(ids)))
        for i, row in zip(ids, ids[nn]):
            ok = (normals[row] @ normals[i] >= cos_max) & ((normals[row, 2] >= 0) == (normals[i, 2] >= 0))
            expected = np.zeros(len(normals))
            expected[row[ok]] = 1.0 / ok.sum()
            np.testing.assert_allclose(out[i], expected, atol=1e-12)
            mixed_any += ok.sum() > 1
            flipped += np.any((normals[row] @ normals[i] >= cos_max) & ~ok)
    assert mixed_any > 0 and flipped > 0  # both rules were exercised


def _unit_vector(v):
    return v / np.linalg.norm(v)
