"""Built-in scenes (lmdp_addon.demo_geometry): geometry, orientation, UV layouts, analytic references."""
from collections import Counter

import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.errors import SceneError
from lmdp_addon.scene_arrays import SceneArrays
from lmdp_addon.bake.texels import rasterize_texels


def parts_by_name(kind):
    return {p.name: p for p in scenes.scene_parts(kind)}


def face_normal(part, f):
    c = part.vertices[part.faces[f]]
    n = np.cross(c[1] - c[0], c[2] - c[0])
    return n / np.linalg.norm(n)


def assert_closed_outward(part, expected_volume=None):
    """Every edge is used once in each direction (closed, consistent) and the volume is positive."""
    edges = Counter()
    for f in part.faces:
        for a, b in zip(f, np.roll(f, -1)):
            edges[(int(a), int(b))] += 1
    for (a, b), count in edges.items():
        assert count == 1 and edges[(b, a)] == 1, f"{part.name}: edge {a}-{b} is not closed"
    c = part.vertices[part.triangles]
    volume = np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6.0
    assert volume > 0, f"{part.name} has inward normals"
    if expected_volume is not None:
        assert volume == pytest.approx(expected_volume, rel=1e-9)


def texel_overlaps(part, resolution=128):
    """Number of texels claimed by more than one quad of ``part`` (0 for a clean UV layout)."""
    claims = np.zeros(resolution * resolution, dtype=int)
    for f in range(len(part.faces)):
        tri = slice(2 * f, 2 * f + 2)
        corners = part.vertices[part.triangles[tri]]
        ts = rasterize_texels(part.uv[tri], corners, np.tile([0, 0, 1.0], (2, 1)), resolution)
        claims[ts.flat_index] += 1
    return int((claims > 1).sum()), claims


@pytest.mark.parametrize("kind", scenes.SCENE_KINDS)
def test_every_scene_builds_consistent_scene_arrays(kind):
    sa = scenes.build_scene_arrays(kind)
    assert isinstance(sa, SceneArrays)
    parts = scenes.scene_parts(kind)
    assert sa.object_names == [p.name for p in parts]
    assert sa.n_triangles == sum(p.n_triangles for p in parts)
    assert sa.triangle_uv.shape == (sa.n_triangles, 3, 2)
    assert sa.object_has_uv.all()
    assert np.all(sa.valid_triangles())
    assert len(set(sa.object_names)) == len(sa.object_names)
    # Emitters never carry states by default; every other part does.
    emitters = [p.is_emitter for p in parts]
    np.testing.assert_array_equal(sa.object_carries_states, ~np.array(emitters))
    sa.check_for_lmdp()  # states and light: raises SceneError otherwise
    # Per triangle data follows the parts.
    for i, p in enumerate(parts):
        sel = sa.triangle_object == i
        np.testing.assert_allclose(sa.triangle_albedo[sel], p.triangle_albedo, rtol=1e-6)
        np.testing.assert_allclose(sa.triangle_emission[sel], np.broadcast_to(p.emission, (sel.sum(), 3)), rtol=1e-6)
        np.testing.assert_allclose(sa.corners()[sel], p.vertices[p.triangles])
        assert np.all(sa.triangle_uv[sel] >= 0) and np.all(sa.triangle_uv[sel] <= 1)


def test_cornell_box_objects_colours_and_orientation():
    parts = parts_by_name("CORNELL_BOX")
    assert set(parts) == {"Floor", "Ceiling", "BackWall", "LeftWall", "RightWall", "TallBox", "ShortBox", "Light"}
    np.testing.assert_allclose(parts["LeftWall"].albedo, scenes.RED)
    np.testing.assert_allclose(parts["RightWall"].albedo, scenes.GREEN)
    for name in ("Floor", "Ceiling", "BackWall", "TallBox", "ShortBox"):
        np.testing.assert_allclose(parts[name].albedo, scenes.WHITE)
    # Walls are single quads whose normals face into the room (towards its centre).
    centre = np.array([0.0, 0.0, 0.5])
    expected = {"Floor": (0, 0, 1), "Ceiling": (0, 0, -1), "BackWall": (0, -1, 0),
                "LeftWall": (1, 0, 0), "RightWall": (-1, 0, 0)}
    for name, normal in expected.items():
        p = parts[name]
        assert len(p.faces) == 1
        n = face_normal(p, 0)
        np.testing.assert_allclose(n, normal, atol=1e-12)
        assert np.dot(centre - p.vertices.mean(axis=0), n) > 0
    # Boxes: closed, outward, the classic 1:1:2 and 1:1:1 proportions.
    assert_closed_outward(parts["TallBox"], 0.3 * 0.3 * 0.6)
    assert_closed_outward(parts["ShortBox"], 0.3 ** 3)
    for name in ("TallBox", "ShortBox"):
        v = parts[name].vertices
        assert v[:, 2].min() == pytest.approx(0.0) and np.all(np.abs(v[:, :2]) < 0.5)
    # The light: just below the ceiling, facing down, inside the room, emitting the stated radiance.
    light = parts["Light"]
    assert light.is_emitter and light.two_sided_emission
    np.testing.assert_allclose(light.emission, scenes.CORNELL_LIGHT_RADIANCE)
    np.testing.assert_allclose(face_normal(light, 0), (0, 0, -1), atol=1e-12)
    assert 0.98 < light.vertices[:, 2].min() < 1.0
    np.testing.assert_allclose(light.albedo, 0.0)


def test_cornell_box_uv_layouts_cover_without_overlap():
    parts = parts_by_name("CORNELL_BOX")
    overlaps, claims = texel_overlaps(parts["Floor"])
    assert overlaps == 0
    assert np.all(claims == 1), "the floor's UVs must cover [0, 1]^2 exactly once at 128 x 128"
    for name in ("TallBox", "ShortBox"):
        overlaps, claims = texel_overlaps(parts[name])
        assert overlaps == 0
        # Six charts, each at least 20 x 20 texels at 128 x 128.
        assert (claims > 0).sum() > 6 * 400


def test_box_charts_keep_texel_density_uniform():
    part = parts_by_name("CORNELL_BOX")["TallBox"]
    uv = part.face_uv
    v = part.vertices[part.faces]
    world = np.linalg.norm(v[:, 1] - v[:, 0], axis=1) * np.linalg.norm(v[:, 3] - v[:, 0], axis=1)
    uv_area = np.abs(np.cross(uv[:, 1] - uv[:, 0], uv[:, 3] - uv[:, 0]))
    np.testing.assert_allclose(uv_area / world, (uv_area / world)[0], rtol=1e-9)


def test_narrow_opening_rooms_are_closed_solids_lit_only_through_the_hatch():
    parts = parts_by_name("NARROW_OPENING")
    for p in parts.values():
        if not p.is_emitter:
            assert_closed_outward(p)
            overlaps, _ = texel_overlaps(p)
            assert overlaps == 0, p.name
    wall = parts["DividingWall"]
    # Slab 0.1 x 1 x 1.2 minus a 0.2 x 0.3 hatch.
    assert_closed_outward(wall, 0.1 * 1.0 * 1.2 - 0.1 * 0.2 * 0.3)
    # Its two big faces cover the room's cross-section except the hatch: the faces at x = +-0.05
    # have total area 1.2 - 0.06 each.
    c = wall.vertices[wall.faces]
    for x in (-0.05, 0.05):
        on = np.all(np.isclose(c[..., 0], x), axis=1)
        area = np.abs(np.cross(c[on, 1] - c[on, 0], c[on, 3] - c[on, 0])).sum(axis=1).sum() if on.any() else 0
        assert area == pytest.approx(1.2 - 0.06)
    # The only emitter hangs in room B (x > 0), facing down.
    emitters = [p for p in parts.values() if p.is_emitter]
    assert [p.name for p in emitters] == ["Light"]
    assert emitters[0].vertices[:, 0].min() > 0.05
    np.testing.assert_allclose(face_normal(emitters[0], 0), (0, 0, -1), atol=1e-12)
    assert "RoomAFloor" in parts and parts["RoomAFloor"].vertices[:, 0].max() < 0


def test_heavy_scene_is_heavy_and_its_grids_still_meet():
    sa = scenes.build_scene_arrays("HEAVY")
    assert sa.n_triangles >= 200_000
    parts = parts_by_name("HEAVY")
    floor = parts["Floor"]
    border = (np.isclose(np.abs(floor.vertices[:, 0]), 0.5)) | (np.isclose(np.abs(floor.vertices[:, 1]), 0.5))
    np.testing.assert_allclose(floor.vertices[border, 2], 0.0, atol=1e-12)
    assert np.abs(floor.vertices[:, 2]).max() > 0.005  # really bumpy
    ts = rasterize_texels(floor.uv, floor.vertices[floor.triangles], np.tile([0, 0, 1.0], (floor.n_triangles, 1)), 128)
    assert len(ts) == 128 * 128


def test_plane_under_sky_and_parallel_squares_references():
    sa = scenes.build_scene_arrays("PLANE_UNDER_SKY")
    np.testing.assert_allclose(sa.world_radiance, scenes.SKY_RADIANCE)
    assert not sa.is_emissive().any()
    ps = parts_by_name("PARALLEL_SQUARES")
    np.testing.assert_allclose(face_normal(ps["Receiver"], 0), (0, 0, 1), atol=1e-12)
    np.testing.assert_allclose(face_normal(ps["Emitter"], 0), (0, 0, -1), atol=1e-12)
    assert ps["Emitter"].vertices[:, 2].min() == pytest.approx(scenes.PARALLEL_SQUARES["height"])
    np.testing.assert_allclose(scenes.world_radiance("CORNELL_BOX"), 0.0)


def _form_factor_quadrature(side, height, offset, n=1500):
    """Midpoint rule of ∫ h^2 / (π (h^2 + r^2)^2) dA over the square: an independent reference."""
    s = (np.arange(n) + 0.5) / n * side - side / 2
    x, y = np.meshgrid(s + offset[0], s + offset[1])
    r2 = x * x + y * y
    return float(np.sum(height ** 2 / (np.pi * (height ** 2 + r2) ** 2)) * (side / n) ** 2)


@pytest.mark.parametrize("side,height,offset", [(1.0, 1.0, (0, 0)), (0.3, 2.0, (0.4, -0.1)),
                                                (2.0, 0.5, (1.5, 1.5)), (1.0, 1.0, (0.5, 0.0))])
def test_point_to_parallel_square_form_factor_matches_quadrature(side, height, offset):
    f = scenes.point_to_parallel_square_form_factor(side, height, offset)
    assert f == pytest.approx(_form_factor_quadrature(side, height, offset), rel=1e-5)


def test_form_factor_limits_and_vectorisation():
    F = scenes.point_to_parallel_square_form_factor
    assert F(1.0, 1.0) == pytest.approx(0.2394564704607735, rel=1e-12)
    assert F(1e4, 1.0) == pytest.approx(1.0, abs=1e-3)            # infinite plane: F -> 1
    assert F(0.01, 10.0) == pytest.approx(1e-4 / (np.pi * 100), rel=1e-4)  # far: A / (π h^2)
    offsets = np.array([[0, 0], [0.3, 0], [-0.3, 0], [0, 0.3]])
    f = F(1.0, 1.0, offsets)
    assert f.shape == (4,)
    assert f[1] == pytest.approx(f[2]) == pytest.approx(f[3])
    assert f[0] > f[1]


def test_selection_and_bad_names():
    sa = scenes.build_scene_arrays("CORNELL_BOX", selected=["Floor", "TallBox"])
    carried = [n for n, s in zip(sa.object_names, sa.object_carries_states) if s]
    assert carried == ["Floor", "TallBox"]
    with pytest.raises(SceneError, match="Nope"):
        scenes.build_scene_arrays("CORNELL_BOX", selected=["Nope"])
    with pytest.raises(SceneError, match="CORNELL_BOX"):
        scenes.build_scene_arrays("teapot")
    assert scenes.check_kind("cornell_box") == "CORNELL_BOX"
    assert scenes.state_part_names("PARALLEL_SQUARES") == ["Receiver"]


def test_triangulation_matches_blenders_quad_split():
    p = parts_by_name("CORNELL_BOX")["Floor"]
    np.testing.assert_array_equal(p.triangles, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(p.uv[1], p.face_uv[0][[0, 2, 3]])
