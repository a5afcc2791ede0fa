"""Hostile-but-realistic input through the operators (issue 22, engine classes 1, 10, 14, 16, 17).

The engine tests (``tests/engine/test_hostile_input.py``) pin the fixes down; these check that a
user in Blender sees them: far-away and broken meshes in the scene, a bake beyond the memory
budget, Max Iterations 1, broken UVs and a desirability that is 0 everywhere.
"""
import math

import bpy
import numpy as np
import pytest

from helpers import add_material, select


@pytest.fixture
def cornell(fresh_scene):
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    s = fresh_scene.lmdp
    s.point_count = 300
    s.rays_per_stratum = 2
    s.light_samples = 8
    s.bake_resolution = 16
    s.bake_samples = 8
    s.bake_margin = 2
    s.bake_mode = 'UNGUIDED'
    return fresh_scene


def session(lmdp_ext):
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene)


def only(*names):
    select([bpy.data.objects[n] for n in names])


def floor_bake(lmdp_ext):
    only("Floor")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    result = session(lmdp_ext).require("bake")
    return result.object("Floor").image.copy(), list(result.warnings)


def add_plane(name, size, location, black=True):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location)
    obj = bpy.context.object
    obj.name = name
    obj.data.materials.append(add_material(name + "Black", color=(0.0, 0.0, 0.0) if black else (0.5, 0.5, 0.5)))
    return obj


# ---- class 1 -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["ground_100_km", "vertex_1e30", "vertex_inf"])
def test_a_far_away_or_broken_mesh_does_not_change_the_bake_of_the_room(cornell, lmdp_ext, case):
    reference, _ = floor_bake(lmdp_ext)
    if case == "ground_100_km":
        add_plane("Ground", 1e5, (0.0, 0.0, -0.01))
    else:
        stray = add_plane("Stray", 2.0, (0.0, 6.0, 0.0))      # behind the back wall, out of sight
        stray.data.vertices[0].co = (1e30 if case == "vertex_1e30" else math.inf, 0.0, 0.0)
        stray.data.update()
    image, warnings = floor_bake(lmdp_ext)
    assert image[..., :3].mean() > 0.5 * reference[..., :3].mean()
    np.testing.assert_allclose(image, reference, rtol=1e-4, atol=1e-6)
    if case != "ground_100_km":
        assert any("'Stray'" in w and "left out" in w for w in warnings), warnings


# ---- class 10 ----------------------------------------------------------------------------------------

def test_a_bake_beyond_the_memory_budget_is_refused_before_any_work(cornell, lmdp_ext, monkeypatch):
    def no_rasterising(*args, **kwargs):   # (an 8192 x 8192 rasterisation would take > 20 GB before)
        raise MemoryError("rasterised before the memory check")
    monkeypatch.setattr(lmdp_ext.sub("lmdp_addon.bake.checks"), "rasterize_texels", no_rasterising)
    cornell.lmdp.bake_resolution = 8192
    only("Floor", "TallBox")
    with pytest.raises(RuntimeError, match=r"8192 x 8192 would need about [0-9.]+ GiB.*Memory Budget"):
        bpy.ops.lmdp.bake()
    assert not any(im.name.endswith("_lmdp_indirect") for im in bpy.data.images)
    assert not session(lmdp_ext).has("bake")


# ---- class 14 ----------------------------------------------------------------------------------------

def test_max_iterations_1_stops_the_iterative_solver_and_says_so(cornell, lmdp_ext):
    cornell.lmdp.solver = 'ITERATIVE'
    cornell.lmdp.max_iterations = 1
    cornell.lmdp.tolerance = 1e-10
    only("Floor", "TallBox", "ShortBox", "BackWall", "LeftWall", "RightWall", "Ceiling")
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    solution = session(lmdp_ext).require("solution")
    assert solution.iterations <= 1 and not solution.converged
    assert "Max Iterations" in solution.message and "NOT converged" in solution.summary()


# ---- class 16 ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", [math.inf, 1e30])
def test_broken_uvs_are_named_as_such(cornell, lmdp_ext, bad):
    floor = bpy.data.objects["Floor"]
    floor.data.uv_layers.active.data[0].uv = (bad, 0.5)
    floor.data.update()
    only("Floor")
    cornell.lmdp.auto_lightmap_uvs = False    # on, the bake lays the lightmap out on a new "LMDP Lightmap"
    with pytest.raises(RuntimeError, match="UV map of 'Floor'.*non-finite or huge coordinates"):
        bpy.ops.lmdp.bake()
    assert "Floor_lmdp_indirect" not in bpy.data.images


# ---- class 17 ----------------------------------------------------------------------------------------

class Layout:
    """Stands in for a UI layout: records the labels the panel draws."""

    def __init__(self, texts):
        self.texts = texts

    def box(self):
        return self

    def column(self, align=False):
        return self

    def label(self, text="", **kwargs):
        self.texts.append(text)


def test_a_desirability_that_is_0_everywhere_has_an_honest_legend(fresh_scene, lmdp_ext):
    floor = add_plane("Floor", 2.0, (0.0, 0.0, 0.0), black=False)
    bpy.ops.object.light_add(type='AREA', location=(0.0, 0.0, -1.0))   # below, facing down
    bpy.context.object.data.energy = 100.0
    props = fresh_scene.lmdp
    props.point_count = 200
    props.rays_per_stratum = 2
    select([floor])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    assert not np.any(session(lmdp_ext).require("solution").z > 0)
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    record = session(lmdp_ext).require("display")
    text = record.scale.describe()
    assert "z is 0" in text and "no light reaches" in text, text
    colormap = lmdp_ext.sub("lmdp_addon.display.colormap")
    colors = np.empty(4 * len(floor.data.vertices), np.float32)
    floor.data.attributes["lmdp_z_color"].data.foreach_get("color", colors)
    missing = colormap.srgb_to_linear(colormap.MISSING_SRGB)
    np.testing.assert_allclose(colors.reshape(-1, 4)[:, :3], np.tile(missing, (len(floor.data.vertices), 1)),
                               atol=1e-6)
    texts = []
    lmdp_ext.sub("operators.ui.panel").draw_legend(Layout(texts), record)
    assert not any("1 .. 10" in t or t.startswith("1  (") or t.startswith("10  (") for t in texts), texts
    assert any("z is 0" in t for t in texts), texts
    assert not any("decades" in t or t.startswith("States:") for t in texts), texts
