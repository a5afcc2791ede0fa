"""Arrow geometry of the optimal policy: which points, which arrows, lines and meshes."""
import numpy as np
import pytest

from lmdp_addon.display import arrows as A
from lmdp_addon.model.hemisphere import stratum_centers, stratum_cosine_weights, tangent_frame


def frames_for(normals):
    normals = np.asarray(normals, dtype=np.float64)
    return tangent_frame(normals / np.linalg.norm(normals, axis=1, keepdims=True))


def test_stratum_arrows_follow_the_strata_and_the_probabilities():
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0]])
    frames = frames_for(normals)
    points = np.array([[0, 0, 0], [1, 2, 3], [-1, 0, 0.5]], float)
    rng = np.random.default_rng(0)
    u = rng.random((3, 16))
    u[1, 3] = 0.0
    u /= u.sum(axis=1, keepdims=True)
    arrows = A.stratum_arrows(points, frames, u, 4, 4, scale=0.5, lift=0.01)
    assert arrows.count == 3 * 16 - 1                     # u = 0 gets no arrow
    assert np.allclose(arrows.lengths, 0.5 * u[arrows.point, arrows.stratum])
    assert np.allclose(arrows.probability, u[arrows.point, arrows.stratum])
    # Directions are the strata centres, rotated into each point's frame: in the upper hemisphere.
    local = stratum_centers(4, 4)[arrows.stratum]
    world = np.einsum("nj,njk->nk", local, frames[arrows.point])
    assert np.allclose(arrows.directions, world)
    assert np.all(np.einsum("ij,ij->i", arrows.directions, normals[arrows.point]) > 0)
    assert np.allclose(arrows.starts, points[arrows.point] + 0.01 * normals[arrows.point])
    assert np.allclose(np.linalg.norm(arrows.ends - arrows.starts, axis=1), arrows.lengths)
    few = A.stratum_arrows(points, frames, u, 4, 4, scale=1.0, min_probability=0.1)
    assert np.all(few.probability > 0.1) and few.count == int((u > 0.1).sum())
    with pytest.raises(ValueError, match="strata"):
        A.stratum_arrows(points, frames, u, 2, 4, scale=1.0)


def test_divergence_and_entropy():
    w = stratum_cosine_weights(4, 4)
    passive = np.tile(w, (3, 1))
    sharp = np.zeros(16)
    sharp[5] = 1.0
    half = np.zeros(16)
    half[[2, 9]] = 0.5
    u = np.vstack([passive[0], sharp, half])
    kl = A.policy_divergence(u, w)
    assert kl[0] == pytest.approx(0.0, abs=1e-12)
    assert kl[1] == pytest.approx(-np.log(w[5]))
    assert kl[2] == pytest.approx(0.5 * np.log(0.5 / w[2]) + 0.5 * np.log(0.5 / w[9]))
    H = A.policy_entropy(u)
    assert H[1] == 0.0 and H[2] == pytest.approx(np.log(2)) and H[0] > H[2]


def test_most_informative_takes_the_best_and_spreads_them():
    rng = np.random.default_rng(1)
    # 900 points on a 1 m floor; the score peaks in one corner (like the states under a light).
    xy = rng.random((900, 2))
    points = np.column_stack([xy, np.zeros(900)])
    score = np.exp(-8 * np.linalg.norm(xy, axis=1))
    chosen = A.most_informative(points, score, 20)
    assert len(chosen) == 20 and len(set(chosen.tolist())) == 20
    assert chosen[0] == np.argmax(score)
    assert np.all(np.diff(score[chosen]) <= 0)
    # Spread: no two chosen points closer than a quarter of the cell size.
    cell = np.sqrt(2 * 1.0 / (2 * 20))
    d = np.linalg.norm(points[chosen][:, None] - points[chosen][None], axis=2) + np.eye(20) * 9
    assert d.min() > 0.25 * cell
    # The plain top 20 would all crowd into the corner.
    top = np.argsort(-score)[:20]
    assert np.linalg.norm(points[top], axis=1).max() < np.linalg.norm(points[chosen], axis=1).max()
    # Candidates restrict the choice; asking for more than there are returns them all.
    cand = np.arange(100, 110)
    assert set(A.most_informative(points, score, 50, candidates=cand)) == set(cand)
    assert len(A.most_informative(points, score, 0)) == 0


def test_even_subset():
    idx = np.arange(100, 200)
    sub = A.even_subset(idx, 10)
    assert len(sub) == 10 and np.all(np.diff(sub) == 10)
    assert np.array_equal(A.even_subset(idx[:5], 10), idx[:5])


def test_nearest_state_respects_the_side_of_a_thin_wall():
    # A 2 mm wall: states on the front (+z) and back (-z) faces at the same x, y.
    points = np.array([[0, 0, 0.001], [0, 0, -0.001], [0.5, 0, 0.001]])
    normals = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    assert A.nearest_state(points, normals, [0.0, 0.0, 0.0015]) == 0
    assert A.nearest_state(points, normals, [0.0, 0.0, -0.0015]) == 1
    # Inside the wall, nearer to the back face: the back face has it in front (the front does not).
    assert A.nearest_state(points, normals, [0.0, 0.0, -0.0009]) == 1
    assert A.nearest_state(points, normals, [0.4, 0.0, 0.01]) == 2
    assert A.nearest_state(points, normals, [0.0, 0.0, 0.01], candidates=[1, 2]) == 2
    assert A.nearest_state(points, normals, [0, 0, 0], candidates=[]) == -1
    # No state has the location in front: the nearest of all.
    assert A.nearest_state(points[:1], normals[:1], [0.0, 0.0, -1.0]) == 0


def test_next_state_targets():
    cols = np.array([4, 0, 7, 2, 5])
    vals = np.array([0.1, 0.3, 0.05, 0.5, 0.05])
    pts, prob, terminal = A.next_state_targets(cols, vals, n_points=5, count=2)
    assert list(pts) == [2, 0] and np.allclose(prob, [0.5, 0.3])
    assert terminal == pytest.approx(0.1)      # columns 5 and 7 are terminals
    pts, prob, _ = A.next_state_targets(cols, vals, n_points=5)
    assert list(pts) == [2, 0, 4]


def test_arrows_between():
    a = A.arrows_between([[0, 0, 0], [1, 1, 1]], [[0, 0, 2], [1, 1, 1]], [0.7, 0.3], 4, shorten=0.5)
    assert np.allclose(a.directions[0], [0, 0, 1]) and a.lengths[0] == pytest.approx(1.5)
    assert a.lengths[1] == 0.0 and np.all(a.point == 4) and np.all(a.stratum == -1)


def sample_arrows(n=5, seed=2):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return A.Arrows(rng.normal(size=(n, 3)), d, rng.uniform(0.2, 1.0, n), rng.random(n),
                    np.arange(n), np.zeros(n, dtype=np.int64))


def test_arrow_lines():
    arrows = sample_arrows()
    verts, which = A.arrow_lines(arrows, head_fraction=0.25, head_width=0.4)
    assert verts.shape == (50, 3) and verts.dtype == np.float32 and np.all(which == np.repeat(range(5), 10))
    seg = verts.reshape(5, 5, 2, 3)
    assert np.allclose(seg[:, 0, 0], arrows.starts, atol=1e-6) and np.allclose(seg[:, 0, 1], arrows.ends, atol=1e-6)
    # Barbs start at the tip, reach back 25 % of the length and 0.4 x that sideways.
    barb = seg[:, 1:, 1] - arrows.ends[:, None, :]
    along = np.einsum("nbj,nj->nb", barb, arrows.directions)
    assert np.allclose(along, -0.25 * arrows.lengths[:, None], atol=1e-5)
    side = np.linalg.norm(barb - along[..., None] * arrows.directions[:, None, :], axis=2)
    assert np.allclose(side, 0.1 * arrows.lengths[:, None], atol=1e-5)
    assert A.arrow_lines(A.Arrows.empty())[0].shape == (0, 3)


def signed_volume(verts, tris):
    c = verts[tris].astype(np.float64)
    return np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6.0


@pytest.mark.parametrize("sides", [3, 6, 8])
def test_arrow_mesh_is_closed_outward_and_has_the_right_volume(sides):
    arrows = sample_arrows(4)
    r = np.array([0.01, 0.02, 0.015, 0.03])
    verts, tris, which = A.arrow_mesh(arrows, r, sides=sides)
    nv, nf = 3 * sides + 1, 6 * sides - 2
    assert verts.shape == (4 * nv, 3) and tris.shape == (4 * nf, 3) and np.all(which == np.repeat(range(4), nv))
    polygon = 0.5 * sides * np.sin(2 * np.pi / sides)          # area of the unit-radius polygon
    for i in range(4):
        t = tris[i * nf:(i + 1) * nf] - i * nv
        v = verts[i * nv:(i + 1) * nv]
        # Closed 2-manifold: every edge is used exactly twice, once in each direction.
        edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        assert len({tuple(e) for e in edges.tolist()}) == len(edges)
        assert {tuple(e) for e in edges.tolist()} == {tuple(e[::-1]) for e in edges.tolist()}
        hl = min(6 * r[i], 0.45 * arrows.lengths[i])
        expected = polygon * r[i] ** 2 * (arrows.lengths[i] - hl) + polygon * (2.5 * r[i]) ** 2 * hl / 3
        assert signed_volume(v - v.mean(axis=0), t) == pytest.approx(expected, rel=1e-4)  # > 0: outward
        tip = v[3 * sides]
        assert np.allclose(tip, arrows.ends[i], atol=1e-5)
    with pytest.raises(ValueError):
        A.arrow_mesh(arrows, 0.01, sides=2)
    assert A.arrow_mesh(A.Arrows.empty(), 0.01)[0].shape == (0, 3)


def test_marker_mesh():
    verts, tris, which = A.marker_mesh([[0, 0, 0], [1, 2, 3]], [0.1, 0.2])
    assert verts.shape == (12, 3) and tris.shape == (16, 3) and list(which) == [0] * 6 + [1] * 6
    vol0 = signed_volume(verts[:6], tris[:8])
    vol1 = signed_volume(verts[6:] - [1, 2, 3], tris[8:] - 6)
    assert vol0 == pytest.approx(4 / 3 * 0.1 ** 3, rel=1e-5) and vol1 == pytest.approx(4 / 3 * 0.2 ** 3, rel=1e-5)


def test_concatenate():
    a, b = sample_arrows(2, 3), sample_arrows(3, 4)
    c = A.Arrows.concatenate([a, None, b])
    assert c.count == 5 and np.allclose(c.starts[2:], b.starts)
    assert A.Arrows.concatenate([]).count == 0


# -- on a solved LMDP -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cornell():
    from lmdp_addon.model import pipeline
    from lmdp_addon.model import policy
    from lmdp_addon.demo_geometry import build_scene_arrays
    from lmdp_addon.settings import Settings
    scene = build_scene_arrays("CORNELL_BOX")
    settings = Settings(point_count=400, rays_per_stratum=2)
    result = pipeline.run_all(scene, settings)
    u = policy.stratum_policy(result.dynamics, result.solution, "all")
    return scene, result, u, policy.optimal_policy(result.lmdp, result.solution)


def test_policy_view_most_informative_and_active_object(cornell):
    scene, result, u, _ = cornell
    states = result.states
    floor = np.flatnonzero(states.point_object == scene.object_names.index("Floor"))
    view = A.policy_view(states, u, "ACTIVE_OBJECT", 10, 0.2, floor)
    assert len(view.points) == 10 and set(view.points) <= set(floor)
    assert set(view.arrows.point) <= set(view.points)
    assert np.all(view.arrows.probability > A.default_min_probability(16))
    assert np.allclose(view.arrows.lengths, 0.2 * u[view.arrows.point, view.arrows.stratum])
    everyone = np.arange(states.n_points)
    best = A.policy_view(states, u, "MOST_INFORMATIVE", 15, 0.2, everyone)
    kl = A.policy_divergence(u, states.stratum_weight)
    assert len(best.points) == 15 and best.points[0] == np.argmax(kl)
    assert np.median(kl[best.points]) > np.percentile(kl, 75)   # informative, if spread out
    verts, colors = best.lines()
    assert len(verts) == 10 * best.arrows.count and colors.shape == (len(verts), 4)
    with pytest.raises(ValueError):
        A.policy_view(states, u, "EVERYTHING", 5, 0.1, everyone)


def test_probe_reads_the_state_under_the_cursor(cornell):
    """Like the thesis's Figure 5: the whole u*(.|x) of the state under the probe."""
    scene, result, u, U = cornell
    states = result.states

    def row(i):
        return U.indices[U.indptr[i]:U.indptr[i + 1]], U.data[U.indptr[i]:U.indptr[i + 1]]

    i = 37
    location = states.points[i] + 1e-4 * states.normals[i]
    p = A.probe(states, u, row, location, scale=0.3, next_states=10)
    assert p.state == i
    assert p.arrows.count == int((u[i] > 0).sum()) and np.allclose(p.arrows.probability.sum(), u[i].sum())
    assert len(p.targets) <= 10 and np.all(np.diff(p.target_probability) <= 0)
    cols, vals = row(i)
    surface = vals[cols < states.n_points]
    assert p.target_probability[0] == pytest.approx(surface.max())
    assert p.terminal_probability + surface.sum() == pytest.approx(1.0)
    view = A.PolicyView(A.Arrows.empty(), probe=p)
    verts, colors = view.lines()
    assert len(verts) == 10 * p.arrows.count + 6 * len(p.targets) + 2 * len(p.targets)
    links = p.links()
    assert np.allclose(links.ends, p.target_points) and np.allclose(links.probability, p.target_probability)
    assert np.allclose(links.starts, p.arrows.starts[0])
    assert "probe at state 37" in view.summary()


def test_arrow_colors():
    c = A.arrow_colors([0.0, 0.5, 1.0])
    assert c.shape == (3, 4)
    assert np.all(np.diff(c[:, :3].sum(axis=1)) > 0)            # brighter for more probable
    assert np.allclose(c[2], A.arrow_colors([2.0], vmax=2.0)[0])
