"""States -> vertices: same-object, normal-compatible interpolation, quantities, display lattices."""
from types import SimpleNamespace

import numpy as np
import pytest

from lmdp_addon.display import vertex_field as VF
from lmdp_addon.display.colormap import linear_to_srgb, colormap_srgb
from lmdp_addon.scene_arrays import luminance


def plane_states(n, z=0.0, normal=(0, 0, 1), size=1.0, seed=0, obj=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    points = np.column_stack([xy, np.full(n, z)])
    normals = np.tile(np.asarray(normal, float), (n, 1))
    return points, normals, np.full(n, obj), np.full(n, size / np.sqrt(n))


def weights_for(samples, sample_normals, sample_objects, states, **kw):
    points, normals, objects, spacing = states
    return VF.interpolation_weights(samples, sample_normals, sample_objects, points, normals,
                                    objects, spacing, **kw)


def test_thin_wall_does_not_bleed():
    """A 1 mm thick wall, one object: the front face never sees the back face's states."""
    front = plane_states(400, z=0.0005, normal=(0, 0, 1), seed=1)
    back = plane_states(400, z=-0.0005, normal=(0, 0, -1), seed=2)
    states = tuple(np.concatenate(p) for p in zip(front, back))
    values = np.concatenate([np.full(400, 1.0), np.full(400, 100.0)])
    grid = np.linspace(-0.45, 0.45, 20)
    X, Y = np.meshgrid(grid, grid)
    samples = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    up = np.tile([0.0, 0.0, 1.0], (len(samples), 1))
    w = weights_for(np.vstack([samples, samples]), np.vstack([up, -up]), np.zeros(2 * len(samples), int), states)
    out = VF.interpolate(w, values)
    assert np.allclose(out[:len(samples)], 1.0, rtol=1e-12) and np.allclose(out[len(samples):], 100.0, rtol=1e-12)
    assert not w.fallback.any()
    # Without the normal test (min_cos = -2 accepts everything) the two faces would mix.
    mixed = VF.interpolate(weights_for(samples, up, np.zeros(len(samples), int), states, min_cos=-2.0), values)
    assert mixed.max() > 10.0


def test_states_of_other_objects_are_ignored():
    a = plane_states(200, obj=0, seed=3)
    b = plane_states(200, obj=1, seed=4)          # the same plane, another object
    states = tuple(np.concatenate(p) for p in zip(a, b))
    values = np.concatenate([np.zeros(200), np.ones(200)])
    samples = np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0], [0.1, 0.1, 0.0]])
    objects = np.array([0, 1, 2])                 # object 2 carries no state
    w = weights_for(samples, np.tile([0, 0, 1.0], (3, 1)), objects, states)
    out = VF.interpolate(w, values)
    assert out[0] == 0.0 and out[1] == 1.0 and np.isnan(out[2])
    assert list(w.empty) == [False, False, True]
    assert np.allclose(np.asarray(w.matrix.sum(axis=1)).ravel(), [1.0, 1.0, 0.0])


def test_vertex_without_a_compatible_state_takes_the_nearest_state_of_its_object():
    states = plane_states(50, seed=5)
    values = np.arange(50.0)
    sample = np.array([[0.1, -0.2, 0.0]])
    w = weights_for(sample, np.array([[1.0, 0.0, 0.0]]), np.array([0]), states)  # normal along the plane
    nearest = np.argmin(np.linalg.norm(states[0] - sample, axis=1))
    assert w.fallback[0] and w.nearest[0] == nearest
    assert VF.interpolate(w, values)[0] == values[nearest]
    # A zero normal (degenerate vertex) accepts every state of its object.
    w0 = weights_for(sample, np.zeros((1, 3)), np.array([0]), states)
    assert not w0.fallback[0] and w0.matrix.nnz > 1


def test_linear_field_is_reproduced_to_within_the_kernel_width():
    """For f linear, the weighted mean is f at the weighted centroid, at most h away."""
    states = plane_states(2000, seed=6)
    grad = np.array([3.0, -2.0])
    values = states[0][:, :2] @ grad
    rng = np.random.default_rng(7)
    samples = np.column_stack([rng.uniform(-0.4, 0.4, (500, 2)), np.zeros(500)])
    w = weights_for(samples, np.tile([0, 0, 1.0], (500, 1)), np.zeros(500, int), states)
    err = np.abs(VF.interpolate(w, values) - samples[:, :2] @ grad)
    h = VF.SMOOTHING * states[3][0]
    assert err.max() < np.linalg.norm(grad) * h
    assert np.median(err) < 0.25 * np.linalg.norm(grad) * h


def test_interpolate_skips_non_finite_values():
    states = plane_states(30, seed=8)
    values = np.ones(30)
    values[:15] = -np.inf                        # log z of unreachable states
    samples = states[0][:20] + [0, 0, 0.0]
    w = weights_for(samples, states[1][:20], np.zeros(20, int), states)
    out = VF.interpolate(w, values)
    assert np.all(out == 1.0)
    w_all_bad = VF.interpolate(w, np.full(30, -np.inf))
    assert np.all(w_all_bad == -np.inf)          # nothing finite nearby: the nearest state's value
    two = VF.interpolate(w, np.column_stack([np.ones(30), 2 * np.ones(30)]))
    assert two.shape == (20, 2) and np.allclose(two, [1.0, 2.0])


# -- quantities ------------------------------------------------------------------------------------

def fake_solution(log_z, cost_mode="THESIS", lambda_=10.0):
    log_z = np.asarray(log_z, dtype=np.float64)
    with np.errstate(under="ignore"):
        z = np.exp(log_z)
    return SimpleNamespace(log_z=log_z, z=z, cost_mode=cost_mode, lambda_=lambda_)


def test_thesis_desirability_is_exact_where_z_underflows():
    log_z = np.array([[-2000.0], [-1000.0], [-np.inf], [0.0]])
    sq = VF.state_quantity(fake_solution(log_z), "Z")
    assert np.allclose(sq.log10_z[:2], log_z[:2, 0] / np.log(10))
    assert sq.log10_z[2] == -np.inf
    assert sq.scale.log and sq.scale.data_hi == pytest.approx(0.0)
    assert sq.scale.data_lo == pytest.approx(-2000.0 / np.log(10))  # 869 decades below the top
    J = VF.state_quantity(fake_solution(log_z, lambda_=10.0), "COST_TO_GO")
    assert np.allclose(J.value[[0, 1, 3]], [200.0, 100.0, 0.0]) and J.value[2] == np.inf
    assert not J.scale.log and (J.scale.data_lo, J.scale.data_hi) == (0.0, 200.0)
    assert 0.0 < J.scale.lo < J.scale.hi < 200.0    # 1st and 99th percentiles


def test_residual_quantity_needs_residuals_and_floors_zeros():
    sol = fake_solution(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="residual"):
        VF.state_quantity(sol, "RESIDUAL")
    sq = VF.state_quantity(sol, "RESIDUAL", residuals=np.array([0.0, 1e-10, 1e-6]))
    assert np.allclose(sq.value, [-16.0, -10.0, -6.0])
    with pytest.raises(ValueError, match="quantity"):
        VF.state_quantity(sol, "ALBEDO")


def test_physical_field_interpolates_radiance_and_shows_its_luminance():
    states = plane_states(300, seed=9)
    rgb = np.column_stack([1.0 + states[0][:, 0], 2.0 + states[0][:, 1], np.full(300, 0.5)])
    sol = fake_solution(np.log(rgb), cost_mode="PHYSICAL", lambda_=1.0)
    sq = VF.state_quantity(sol, "Z")
    assert sq.z_rgb.shape == (300, 3)
    assert np.allclose(sq.log10_z, np.log10(luminance(rgb)))
    samples = np.column_stack([np.linspace(-0.3, 0.3, 25), np.zeros(25), np.zeros(25)])
    w = weights_for(samples, np.tile([0, 0, 1.0], (25, 1)), np.zeros(25, int), states)
    field = VF.vertex_field(w, sq, "VIRIDIS")
    assert np.allclose(field.z_rgb, VF.interpolate(w, rgb))
    assert np.allclose(field.z, luminance(field.z_rgb)) and np.allclose(field.quantity, field.z)
    expected = colormap_srgb(sq.scale.position(field.z))
    assert np.allclose(linear_to_srgb(field.color[:, :3]), expected, atol=1e-5)
    assert field.color.shape == (25, 4) and np.all(field.color[:, 3] == 1.0)


def test_thesis_field_colours_follow_log_z_even_below_float_range():
    states = plane_states(200, seed=10)
    log_z = (-900.0 - 200.0 * (states[0][:, 0] + 0.5))[:, None]   # z underflows everywhere
    sq = VF.state_quantity(fake_solution(log_z, lambda_=1.0), "Z")
    samples = np.column_stack([np.linspace(-0.4, 0.4, 9), np.zeros(9), np.zeros(9)])
    w = weights_for(samples, np.tile([0, 0, 1.0], (9, 1)), np.zeros(9, int), states)
    field = VF.vertex_field(w, sq)
    assert np.all(field.z == 0.0)                 # float64 cannot hold z ...
    assert np.all(np.diff(field.position) < 0)    # ... but the colour still follows log z
    assert np.all(np.isfinite(field.position))


# -- display lattices -------------------------------------------------------------------------------

def test_lattice_counts_area_and_planarity():
    corners = np.array([[[0, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 0, 1], [0, 1, 1], [1, 0, 2]]], float)
    for n in (1, 2, 5):
        pts, tris, src = VF.triangle_lattice(corners, n)
        assert len(pts) == 2 * (n + 1) * (n + 2) // 2 and len(tris) == 2 * n * n
        c = pts[tris]
        area = 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)
        assert np.allclose(area, area.reshape(2, -1)[:, :1].repeat(n * n, axis=1).ravel())  # similar
        full = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        assert np.allclose([area[:n * n].sum(), area[n * n:].sum()], full)
        assert np.all(tris // ((n + 1) * (n + 2) // 2) == np.repeat([0, 1], n * n)[:, None])
        assert np.all(src == np.repeat([0, 1], (n + 1) * (n + 2) // 2))
        assert np.allclose(pts[src == 0][:, 2], 0.0)
        # Every sub-triangle keeps the orientation of its parent.
        normal = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        parent = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        assert np.all(np.einsum("ij,ij->i", normal, parent[np.repeat([0, 1], n * n)]) > 0)


def test_lattice_of_a_quad_is_blenders_bilinear_grid():
    a, b, c, d = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    pts, _, _ = VF.triangle_lattice(np.array([[a, b, c], [a, c, d]]), 4)
    grid = np.array([[x, y, 0.0] for x in np.linspace(0, 1, 5) for y in np.linspace(0, 1, 5)])
    dist = np.linalg.norm(pts[:, None, :] - grid[None], axis=2).min(axis=1)
    assert dist.max() < 1e-12                     # every lattice node is a grid node
    with pytest.raises(ValueError):
        VF.lattice_template(0)


def test_subdivision_level():
    assert VF.subdivision_level(1.0, 0.056) == 6   # a Cornell wall at 2048 states
    assert VF.subdivision_level(1.0, 0.056, max_level=4) == 4
    assert VF.subdivision_level(0.01, 0.056) == 0  # already finer than the states
    assert VF.subdivision_level(0.0, 0.1) == 0 and VF.subdivision_level(1.0, 0.0) == 0
    assert VF.subdivision_level(0.4, 0.1) == 3     # 0.4 / 8 = 0.05 <= 0.1 / 2


def test_a_coarse_quad_needs_the_lattice_to_be_faithful():
    """A 1 m quad lit in its middle: the 4 corner vertices alone cannot show the bright spot; the
    lattice at :func:`subdivision_level` matches the state field everywhere."""
    states = plane_states(1500, seed=11)
    r2 = (states[0][:, :2] ** 2).sum(axis=1)
    values = np.log10(0.05 + np.exp(-r2 / 0.02))               # a bright spot, 1.3 decades
    quad = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], float)
    corners = np.array([quad[[0, 1, 2]], quad[[0, 2, 3]]])
    rng = np.random.default_rng(12)
    probes = np.column_stack([rng.uniform(-0.45, 0.45, (400, 2)), np.zeros(400)])
    w_probe = weights_for(probes, np.tile([0, 0, 1.0], (400, 1)), np.zeros(400, int), states)
    reference = VF.interpolate(w_probe, values)

    def shown(level):
        pts, tris, _ = VF.triangle_lattice(corners, 2 ** level)
        w = weights_for(pts, np.tile([0, 0, 1.0], (len(pts), 1)), np.zeros(len(pts), int), states)
        at_nodes = VF.interpolate(w, values)
        # What a renderer shows: barycentric interpolation of the node values (here on the
        # lattice of each probe's triangle, found through the lattice's regular structure).
        from scipy.interpolate import LinearNDInterpolator
        return LinearNDInterpolator(pts[:, :2], at_nodes)(probes[:, :2])

    level = VF.subdivision_level(1.0, states[3][0])
    fine_err = np.abs(shown(level) - reference)
    coarse_err = np.abs(shown(0) - reference)
    span = np.ptp(values)
    assert np.percentile(fine_err, 95) < 0.03 * span
    assert np.percentile(coarse_err, 95) > 0.3 * span   # four vertices miss the spot entirely


def test_state_spacing():
    assert np.allclose(VF.state_spacing([0.01, 0.0004, -1.0]), [0.1, 0.02, 0.0])


def test_a_crowd_of_back_face_states_does_not_hide_the_front_face():
    """All 12 nearest states face the other way: the search widens before falling back."""
    rng = np.random.default_rng(13)
    back = np.column_stack([rng.normal(0, 0.002, (30, 2)), np.full(30, -0.0005)])
    front = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), np.full(200, 0.0005)])
    front[np.linalg.norm(front[:, :2], axis=1) < 0.03] += [0.1, 0.0, 0.0]
    points = np.vstack([back, front])
    normals = np.vstack([np.tile([0, 0, -1.0], (30, 1)), np.tile([0, 0, 1.0], (200, 1))])
    values = np.r_[np.full(30, 100.0), np.full(200, 1.0)]
    w = VF.interpolation_weights([[0, 0, 0.001]], [[0, 0, 1.0]], [0], points, normals, np.zeros(230, int),
                                 np.full(230, 0.07))
    assert not w.fallback[0] and w.nearest[0] >= 30
    assert VF.interpolate(w, values)[0] == pytest.approx(1.0)
