"""Hostile-but-realistic input to the engine (issue 22, classes 1, 10, 14, 16, 17).

Each test here failed before its fix: far-away or non-finite geometry changing a room's bake,
bakes without a memory estimate, ITERATIVE running past ``max_iterations``, non-finite UVs
reported as overlaps, and a legend for a z that is 0 everywhere.
"""
import numpy as np
import pytest
import scipy.sparse as sp

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake import driver
from lmdp_addon.errors import SceneError
from lmdp_addon.model import pipeline
from lmdp_addon.model.costs import FirstExitLMDP
from lmdp_addon.model.solvers import solve_desirability
from lmdp_addon.raycast import RayCaster
from lmdp_addon.settings import Settings


def random_lmdp(m=400, seed=3, channels=1):
    """A random sparse first-exit problem: 6 successors per state, some mass to the light."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(m), 6)
    P = sp.csr_matrix((rng.random(len(rows)), (rows, rng.integers(0, m, len(rows)))),
                      shape=(m, m + 2)).tolil()
    P[np.flatnonzero(rng.random(m) < 0.2), m] = 0.3
    P[np.arange(m), m + 1] = 0.01
    P = sp.csr_matrix(P)
    P = sp.csr_matrix(sp.diags(1 / np.asarray(P.sum(1)).ravel()) @ P)
    q = np.tile(np.exp(-0.1 * np.ones((m, 1))), (1, channels)) * np.linspace(1.0, 0.8, channels)
    z_terminal = np.zeros((2, channels))
    z_terminal[0] = 1.0
    return FirstExitLMDP(P=P, q=q, z_terminal=z_terminal, lambda_=0.1,
                         cost_mode="THESIS" if channels == 1 else "PHYSICAL", g=-np.log(q))


# ---- class 14: ITERATIVE honours max_iterations -------------------------------------------------

@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("cap", [1, 2, 8, 9, 20])
def test_iterative_stops_at_max_iterations_and_says_it_did_not_converge(channels, cap):
    lmdp = random_lmdp(channels=channels)
    sol = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-10, max_iterations=cap)
    assert sol.iterations <= cap
    assert not sol.converged
    assert sol.residual > 1e-9
    assert f"cap of {cap} iteration" in sol.message and "Max Iterations" in sol.message
    assert "NOT converged" in sol.summary()


def test_iterative_with_enough_iterations_still_converges():
    lmdp = random_lmdp(channels=3)
    sol = solve_desirability(lmdp, "ITERATIVE", tolerance=1e-10, max_iterations=10000)
    assert sol.converged and sol.residual <= 1e-9 and sol.iterations < 100


@pytest.mark.parametrize("solver", ["POWER", "ITERATIVE"])
def test_max_iterations_below_one_is_refused_naming_the_setting(solver):
    with pytest.raises(SceneError, match="Max Iterations"):
        solve_desirability(random_lmdp(), solver, max_iterations=0)


# ---- class 17: the legend of a z that is 0 everywhere ----------------------------------------------

def unlit_solution(channels):
    """A solved problem whose only terminal with light is unreachable: z = 0 on every state."""
    lmdp = random_lmdp(m=50, channels=channels)
    lmdp.z_terminal[:] = 0.0
    return solve_desirability(lmdp, "ITERATIVE")


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("quantity", ["Z", "COST_TO_GO"])
def test_a_z_that_is_0_everywhere_gets_an_empty_legend_and_the_missing_colour(channels, quantity):
    from lmdp_addon.display.colormap import MISSING_SRGB, srgb_to_linear
    from lmdp_addon.display.vertex_field import FieldWeights, state_quantity, vertex_field
    sol = unlit_solution(channels)
    assert not np.any(sol.z > 0)
    sq = state_quantity(sol, quantity)
    text = sq.scale.describe()
    assert ("z is 0" if quantity == "Z" else "J is +inf") in text and "no light reaches" in text, text
    assert "decades" not in text and ".." not in text
    assert sq.scale.empty and sq.scale.decades == 0.0
    m = len(sol.y)
    weights = FieldWeights(sp.identity(m, format="csr", dtype=np.float32), np.arange(m), np.zeros(m, bool))
    field = vertex_field(weights, sq)
    assert np.all(np.isnan(field.position))
    assert np.allclose(field.color[:, :3], srgb_to_linear(MISSING_SRGB), atol=1e-6)
    # The legend's values say what the data is: z = 0, J = +inf.
    assert set(sq.scale.tick_labels(5)) == ({"0"} if quantity == "Z" else {"inf"})


def test_a_partly_lit_z_keeps_its_range():
    from lmdp_addon.display.colormap import log_scale_from_log10
    scale = log_scale_from_log10(np.array([-np.inf, -2.0, 0.0]), "z", 0.0, 100.0, empty_note="never")
    assert not scale.empty and scale.describe() == "z: 0.01 .. 1 (log, 2.0 decades)"


# ---- class 1: nothing far away changes the bake of a room ------------------------------------------

CORNELL_STATES = scenes.state_part_names("CORNELL_BOX")


def stray_quad(name, far_corner):
    """A quad behind the Cornell box's back wall (out of sight) with one corner at ``far_corner``:
    one of its triangles reaches it, the other stays near the box."""
    corners = np.array([(-1.0, 5.0, 0.0), far_corner, (1.0, 6.0, 0.0), (-1.0, 6.0, 0.0)])
    uv = np.array([[(0.1, 0.1), (0.9, 0.1), (0.9, 0.9), (0.1, 0.9)]], np.float32)
    return scenes.Part(name, corners, [[0, 1, 2, 3]], uv, albedo=(0.5, 0.5, 0.5))


def ground_plane(half_width, z=-0.01, albedo=(0.0, 0.0, 0.0)):
    """A square ground plane under the box, facing up; black, so no light it reflects could
    change the room (only its size can)."""
    e = half_width
    corners = [(-e, -e, z), (e, -e, z), (e, e, z), (-e, e, z)]
    return scenes._quad_part("Ground", corners, albedo)


FAR_AWAY = {
    "inf_vertex": lambda: stray_quad("Stray", (np.inf, 6.0, 0.0)),
    "nan_vertex": lambda: stray_quad("Stray", (1.0, np.nan, 0.0)),
    "1e30_vertex": lambda: stray_quad("Stray", (1e30, 6.0, 0.0)),
    "1e11_m_vertex": lambda: stray_quad("Stray", (1e11, 6.0, 0.0)),
    "100_km_ground_plane": lambda: ground_plane(5e4),
}


def cornell_with(*extra):
    """The Cornell box (its own parts carry the states) and ``extra`` unselected parts."""
    parts = scenes.scene_parts("CORNELL_BOX") + list(extra)
    return scenes.parts_to_scene_arrays(parts, CORNELL_STATES)


@pytest.fixture(scope="module")
def cornell_floor_bake():
    scene = cornell_with()
    return driver.bake(scene, ["Floor"], small_bake()).objects[0]


def small_bake(**kw):
    return Settings(**{**dict(bake_mode="UNGUIDED", bake_resolution=16, bake_samples=8, bake_margin=0,
                              max_bounces=4), **kw})


@pytest.mark.parametrize("case", sorted(FAR_AWAY))
def test_far_away_or_broken_geometry_does_not_change_the_bake_of_a_room(case, cornell_floor_bake):
    scene = cornell_with(FAR_AWAY[case]())
    floor = driver.bake(scene, ["Floor"], small_bake()).objects[0]
    reference = cornell_floor_bake.value
    assert floor.value.mean() > 0.5 * reference.mean()
    # The far geometry is out of the box's sight: the same paths, the same numbers.
    np.testing.assert_allclose(floor.value, reference, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("case", ["inf_vertex", "nan_vertex", "1e30_vertex"])
def test_broken_triangles_are_left_out_and_named(case):
    scene = cornell_with(FAR_AWAY[case]())
    stray = scene.object_names.index("Stray")
    usable = scene.usable_triangles()[scene.triangle_object == stray]
    assert usable.tolist() == [False, True]                  # (a, b, c) reaches the bad corner b
    assert any("'Stray'" in w and "1 triangle " in w and "left out" in w for w in scene.warnings), scene.warnings
    assert scene.bounding_diagonal() < 10.0                  # the scene bounds ignore it
    caster = RayCaster(scene)
    assert len(caster.triangle_ids) == scene.n_triangles - 1


def test_ray_offsets_follow_the_coordinates_where_rays_start():
    plain, far = RayCaster(cornell_with()), RayCaster(cornell_with(ground_plane(5e4)))
    room = np.arange(plain.scene.n_triangles)
    np.testing.assert_array_equal(far.offset(room), plain.offset(room))
    assert np.all(plain.offset(room) <= 2.0 ** -20) and np.all(plain.offset(room) >= 2.0 ** -23)
    ground = np.flatnonzero(far.scene.triangle_object == far.scene.object_names.index("Ground"))
    np.testing.assert_allclose(far.offset(ground), 2.0 ** -20 * 5e4)


@pytest.mark.parametrize("bad", [np.inf, 1e30])
def test_an_emitter_with_a_broken_triangle_still_lights_the_room(bad, cornell_floor_bake):
    """A 1e30 triangle used to take nearly all of the light sampling's probability (its area)."""
    scene = with_extra_triangle(cornell_with(), "Light", [(0.0, 0.0, 0.995), (bad, 0.0, 0.995), (0.0, 0.1, 0.995)],
                                [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)])
    light = scene.object_names.index("Light")
    scene.triangle_emission[-1] = scene.triangle_emission[scene.triangle_object == light][0]
    assert any("'Light': 1 triangle " in w for w in scene.warnings)
    floor = driver.bake(scene, ["Floor"], small_bake()).objects[0]
    np.testing.assert_allclose(floor.value, cornell_floor_bake.value, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("distance", [100.0, 1000.0])
def test_a_room_far_from_the_world_origin_bakes_like_one_at_the_origin(distance):
    """float32 positions there are only 8 to 60 µm apart: offsets of a fixed size self-intersect,
    offsets much larger than the precision blur the 5 mm gap above the light."""
    settings = small_bake(bake_samples=256)
    here = driver.bake(cornell_with(), ["Floor"], settings).objects[0]
    moved = cornell_with()
    moved.vertices += np.array([distance, -distance, 0.0])
    there = driver.bake(moved, ["Floor"], settings).objects[0]
    (a, sa), (b, sb) = here.mean_and_error(), there.mean_and_error()   # errors from the batch means
    sigma = np.hypot(sa, sb)
    assert np.all(np.abs(a - b) <= 5 * sigma), (a, b, sigma)


@pytest.mark.parametrize("case", ["1e30_vertex", "100_km_ground_plane"])
def test_far_away_geometry_does_not_change_the_solved_states_of_a_room(case):
    settings = Settings(point_count=256, rays_per_stratum=2, light_samples=8)
    plain = pipeline.run_all(cornell_with(), settings)
    far = pipeline.run_all(cornell_with(FAR_AWAY[case]()), settings)
    np.testing.assert_array_equal(far.states.points, plain.states.points)
    np.testing.assert_allclose(far.solution.z, plain.solution.z, rtol=1e-6, atol=1e-12)


def with_extra_triangle(scene, object_name, corners, uv):
    """``scene`` with one more triangle on ``object_name`` (new vertices ``corners (3, 3)``)."""
    from lmdp_addon.scene_arrays import SceneArrays
    o = scene.object_names.index(object_name)
    V = len(scene.vertices)
    return SceneArrays(
        vertices=np.vstack([scene.vertices, corners]),
        triangles=np.vstack([scene.triangles, [[V, V + 1, V + 2]]]),
        triangle_object=np.append(scene.triangle_object, o),
        triangle_albedo=np.vstack([scene.triangle_albedo, scene.triangle_albedo[scene.triangle_object == o][:1]]),
        triangle_emission=np.vstack([scene.triangle_emission, np.zeros((1, 3))]),
        object_names=scene.object_names, object_carries_states=scene.object_carries_states,
        world_radiance=scene.world_radiance,
        triangle_emission_two_sided=np.append(scene.triangle_emission_two_sided, True),
        triangle_uv=np.vstack([scene.triangle_uv, np.asarray(uv, np.float32)[None]]),
        object_has_uv=scene.object_has_uv)


@pytest.mark.parametrize("bad", [np.inf, np.nan, 1e30])
def test_a_baked_object_with_a_broken_triangle_bakes_the_rest_and_says_so(bad, cornell_floor_bake):
    scene = with_extra_triangle(cornell_with(), "Floor", [(0.5, -0.5, 0.0), (bad, 0.0, 0.0), (0.5, 0.5, 0.0)],
                                [(0.0, 0.0), (bad, 0.5), (0.0, 1.0)])
    assert any("'Floor': 1 triangle " in w for w in scene.warnings), scene.warnings
    floor = driver.bake(scene, ["Floor"], small_bake()).objects[0]
    np.testing.assert_array_equal(floor.texels.row, cornell_floor_bake.texels.row)
    np.testing.assert_allclose(floor.value, cornell_floor_bake.value, rtol=1e-4, atol=1e-6)


# ---- class 16: non-finite or huge UVs are named as such --------------------------------------------

@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan, 1e30, 1e10, 1e6])
@pytest.mark.parametrize("name", ["Floor", "TallBox"])
def test_non_finite_or_huge_uvs_are_refused_as_such(name, bad):
    """Inf / NaN UVs used to leave holes silently, huge ones to be reported as overlapping UVs."""
    from lmdp_addon.bake.checks import check_bake
    scene = cornell_with()
    tris = np.flatnonzero(scene.triangle_object == scene.object_names.index(name))
    uv = scene.triangle_uv[tris]
    shared = np.all(uv == uv[0, 1], axis=-1)          # the corners sharing that UV vertex
    uv[shared, 0] = bad
    scene.triangle_uv[tris] = uv
    with pytest.raises(SceneError) as error:
        check_bake(scene, [name], small_bake(bake_resolution=64))
    message = str(error.value)
    assert f"UV map of '{name}'" in message and "non-finite or huge coordinates" in message, message
    assert "Overlapping" not in message
    assert "±262144" in message                       # 2^24 / 64: where float32 UVs stop placing texels


def test_uvs_outside_the_unit_square_but_not_huge_are_still_judged_by_their_texels():
    from lmdp_addon.bake.checks import check_bake
    scene = cornell_with()
    tris = np.flatnonzero(scene.triangle_object == scene.object_names.index("Floor"))
    scene.triangle_uv[tris] += 5.0                    # a legal tile outside [0, 1]: covers nothing
    with pytest.raises(SceneError, match="covers no texel"):
        check_bake(scene, ["Floor"], small_bake(bake_resolution=64))


# ---- class 10: the memory budget covers bakes --------------------------------------------------------

def no_rasterising(*args, **kwargs):
    raise AssertionError("rasterised before the memory check")


def test_a_bake_beyond_the_memory_budget_is_refused_at_once_with_the_figure(monkeypatch):
    from lmdp_addon.bake import checks
    from lmdp_addon.errors import BudgetError
    monkeypatch.setattr(checks, "rasterize_texels", no_rasterising)
    scene = cornell_with()
    with pytest.raises(BudgetError) as error:
        checks.check_bake(scene, ["Floor"], small_bake(bake_resolution=8192, bake_samples=1))
    message = str(error.value)
    assert "8192 x 8192" in message and "GiB" in message and "'Floor'" in message
    assert "Memory Budget (memory_budget_gb)" in message and "Resolution" in message
    need = float(message.split("about ")[1].split(" GiB")[0])
    assert 8.0 < need < 20.0


def test_the_memory_budget_setting_decides(monkeypatch):
    from lmdp_addon.bake import checks
    from lmdp_addon.errors import BudgetError
    scene = cornell_with()
    with pytest.raises(BudgetError, match="above the memory budget of 0.05 GiB"):
        checks.check_bake(scene, ["Floor", "TallBox"], small_bake(bake_resolution=1024, memory_budget_gb=0.05))
    plan = checks.check_bake(scene, ["Floor", "TallBox"], small_bake(bake_resolution=1024, memory_budget_gb=2.0))
    assert 0.05 * 1024 ** 3 < plan.memory_bytes < 2.0 * 1024 ** 3


def test_the_texel_bound_holds_and_is_tight_for_large_triangles():
    from lmdp_addon.bake.checks import object_texels
    from lmdp_addon.bake.texels import texel_count_bound
    scene = scenes.build_scene_arrays("HEAVY")
    for name in ("Floor", "TallBox"):
        index = scene.object_names.index(name)
        uv = scene.triangle_uv[scene.triangle_object == index]
        for R in (64, 512):
            n = len(object_texels(scene, index, R)[0])
            bound = texel_count_bound(uv, R)
            assert n <= bound
    floor = cornell_with()
    uv = floor.triangle_uv[floor.triangle_object == floor.object_names.index("Floor")]
    n = len(object_texels(floor, floor.object_names.index("Floor"), 1024)[0])
    assert n <= texel_count_bound(uv, 1024) <= 1.01 * n


def traced_peak(call):
    """(result, peak bytes allocated by numpy and Python during ``call``)."""
    import tracemalloc
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        result = call()
        return result, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_texels_and_their_rasterisation_are_lean():
    """The root of the 6.3 GB at 4096 x 4096: ~120 B held and ~380 B at the peak of rasterising
    per texel (positions, normals, differentials and their temporaries per texel)."""
    from lmdp_addon.bake.texels import RASTER_BYTES_PER_TEXEL, TEXEL_BYTES, rasterize_texels
    from lmdp_addon.bake.memory import CANDIDATE_BYTES
    scene = cornell_with()
    index = scene.object_names.index("Floor")
    tris = scene.triangle_object == index
    chunk = 1 << 16
    uv, corners, normals = scene.triangle_uv[tris], scene.corners()[tris], scene.triangle_geometry()[0][tris]
    ts, peak = traced_peak(lambda: rasterize_texels(uv, corners, normals, 512, max_candidates=chunk))
    n = len(ts)
    assert n == 512 * 512
    held = sum(a.nbytes for a in (ts.row, ts.col, ts.triangle, ts.barycentric, ts.overlap))
    assert held <= TEXEL_BYTES * n
    assert peak <= RASTER_BYTES_PER_TEXEL * n + CANDIDATE_BYTES * chunk
    # What is derived on demand is what was stored before.
    np.testing.assert_allclose(ts.position, np.einsum("nk,nkj->nj", ts.barycentric, corners[ts.triangle]))
    np.testing.assert_allclose(ts.normal, np.tile([0.0, 0.0, 1.0], (n, 1)))


def test_the_estimate_covers_a_bake():
    from lmdp_addon.bake import checks
    scene = cornell_with()
    settings = small_bake(bake_resolution=256, bake_samples=2, bake_margin=8, max_bounces=2)
    names = ["Floor", "TallBox", "LeftWall"]
    plan = checks.check_bake(scene, names, settings)
    result, peak = traced_peak(lambda: driver.bake(scene, names, settings, plan=plan))
    assert peak <= plan.memory_bytes <= 4 * peak + 256 * 1024 ** 2
    for ob in result.objects:   # what each baked object keeps
        kept = (ob.value.nbytes + ob.standard_error.nbytes + ob.image.nbytes
                + sum(a.nbytes for a in (ob.texels.row, ob.texels.col, ob.texels.triangle, ob.texels.barycentric)))
        assert kept <= 65 * ob.n_texels + 16 * 256 * 256


def test_the_margin_dilation_works_on_the_ring_not_on_copies_of_the_image():
    from lmdp_addon.bake.texels import dilate
    R = 512
    mask = np.zeros((R, R), bool)
    mask[50:200, 50:450] = True
    mask[300:500, 25:250] = True
    image = np.random.default_rng(0).random((R, R, 3)).astype(np.float32)
    (out, filled), peak = traced_peak(lambda: dilate(image, mask, 16, return_mask=True))
    assert peak <= 48 * R * R               # a float64 copy and masks (was ~110 B per pixel)
    assert filled.sum() > mask.sum() and np.all(out[mask] == image[mask])
