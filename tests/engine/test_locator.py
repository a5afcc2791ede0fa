"""The state locator (lmdp_addon.model.locator): hits to the nearest state point, by table."""
import numpy as np
import pytest

from lmdp_addon.demo_geometry import build_scene_arrays
from lmdp_addon.model.locator import StateLocator
from lmdp_addon.model.states import sample_states


@pytest.fixture(scope="module")
def cornell():
    scene = build_scene_arrays("CORNELL_BOX")
    return scene, sample_states(scene, 1500, 4, 4, seed=3)


def test_grid_lookup_is_the_nearest_point_to_within_a_cell(cornell):
    """The tabulated lookup agrees with an exact cKDTree query up to one grid cell."""
    scene, states = cornell
    grid = StateLocator(scene, states)
    rng = np.random.default_rng(0)
    tri = rng.choice(np.flatnonzero(scene.state_triangles()), 100_000)
    u, v = rng.random(len(tri)), rng.random(len(tri))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    c = scene.corners()[tri]
    pos = c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0])
    approx = grid.locate_front(tri, u, v)
    exact = grid.locate(pos, grid.face_normals[tri], scene.triangle_object[tri])

    def dist6(ids):
        a = grid.spacing[scene.triangle_object[tri]][:, None]
        return np.linalg.norm(np.hstack([states.points[ids] - pos, a * (states.normals[ids] - grid.face_normals[tri])]), axis=1)

    extra = dist6(approx) - dist6(exact)
    spacing = grid.spacing[scene.triangle_object[tri]]
    cell_diagonal = np.sqrt(2) / grid.CELLS_PER_SPACING * spacing * 2  # cell sides <= spacing / 4 (x2: skew)
    assert np.all(extra >= -1e-12)
    assert np.all(extra <= cell_diagonal + 1e-12)
    assert np.mean(approx == exact) > 0.8
    exact_mode = StateLocator(scene, states, exact=True)
    assert np.array_equal(exact_mode.locate_front(tri, u, v, pos), exact)


@pytest.mark.parametrize("kind,points", [("CORNELL_BOX", 4000), ("NARROW_OPENING", 2048), ("HEAVY", 500)])
def test_grid_cells_hold_the_exact_nearest_point_of_their_centre(kind, points):
    """The tables filled block by block (candidates of the block's centre, certified) hold what
    a tree query for every cell centre gives; HEAVY's small triangles take the per-cell path."""
    scene = build_scene_arrays(kind)
    states = sample_states(scene, points, 4, 4, seed=1)
    grid = StateLocator(scene, states)
    t, i, j = grid._cells(np.flatnonzero(grid.gu > 0))
    pos = grid.cell_centres(t, i, j)
    exact = grid.locate(pos, grid.face_normals[t], scene.triangle_object[t])
    np.testing.assert_array_equal(grid.grid_point[grid.grid_offset[t] + i * grid.gv[t] + j], exact)
    if kind != "HEAVY":
        assert grid.cells_queried_exactly < 0.05 * len(t)   # the blocks did the work


def test_grid_spans_each_triangle_from_the_corner_opposite_its_longest_edge(cornell):
    """Hits find their cell whichever corner the grid starts from: the centre of the cell that
    ``cell_of`` returns lies within half a cell diagonal of the hit."""
    scene, states = cornell
    grid = StateLocator(scene, states)
    c = scene.corners()
    edge = np.linalg.norm(c[:, [2, 0, 1]] - c[:, [1, 2, 0]], axis=2)
    carriers = np.flatnonzero(grid.gu > 0)
    assert np.all(grid.grid_origin[carriers] == np.argmax(edge[carriers], axis=1))
    assert len(set(grid.grid_origin[carriers].tolist())) > 1      # the test covers several origins
    rng = np.random.default_rng(4)
    tri = rng.choice(carriers, 50_000)
    u, v = rng.random(len(tri)), rng.random(len(tri))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pos = c[tri, 0] + u[:, None] * (c[tri, 1] - c[tri, 0]) + v[:, None] * (c[tri, 2] - c[tri, 0])
    cell = grid.cell_of(tri, u, v) - grid.grid_offset[tri]
    centre = grid.cell_centres(tri, cell // grid.gv[tri], cell % grid.gv[tri])
    e1, e2 = grid.grid_edges()
    half_diagonal = 0.5 * np.maximum(np.linalg.norm(e1[tri] / grid.gu[tri, None] + e2[tri] / grid.gv[tri, None], axis=1),
                                     np.linalg.norm(e1[tri] / grid.gu[tri, None] - e2[tri] / grid.gv[tri, None], axis=1))
    assert np.all(np.linalg.norm(centre - pos, axis=1) <= half_diagonal * (1 + 1e-9))
