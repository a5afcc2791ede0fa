"""Smooth and custom split normals against Cycles' bake of the same texels (issue 18, item 1).

In the Cornell box: a subdivided, shade-smooth UV sphere floating in the room and a grid with
custom split normals (every corner turned 35° about x) floating 0.15 m above the short box. (At
z = 0.3 the grid lay in the plane of the short box's top face: coplanar surfaces, where Cycles'
rays from the grid hit the box top at t ~ 0 and the engine's lifted origins do not; the flat grid
there was +60-69 % above Cycles as well, so that was no shading-normal effect.) Both are baked by lmdp.bake (UNGUIDED)
and by Cycles (DIFFUSE / INDIRECT, clamping off, 8 bounces on both sides, two seeds), and
compared as in ``test_bake_vs_cycles``: the mean within 2 % and within 5 standard errors of both
estimates, the per-texel squared differences equal to the two variance estimates. Flat shading
of the same meshes is far outside those bounds (the test says by how much).
"""
import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import K, assert_means_agree, build, compare, lmdp_bake, reference

RESOLUTION = 24
TILT = np.radians(35.0)


def smooth_sphere():
    bpy.ops.mesh.primitive_uv_sphere_add(segments=12, ring_count=6, radius=0.13, location=(0.0, -0.3, 0.62))
    obj = bpy.context.active_object
    obj.name = "SmoothSphere"
    modifier = obj.modifiers.new("Subdivision", 'SUBSURF')
    modifier.levels = modifier.render_levels = 1
    select([obj])
    bpy.ops.object.modifier_apply(modifier=modifier.name)
    bpy.ops.object.shade_smooth()
    return obj


def custom_normal_grid():
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=4, y_subdivisions=4, size=0.3, location=(0.05, -0.3, 0.45))
    obj = bpy.context.active_object
    obj.name = "CustomGrid"
    mesh = obj.data
    normal = (0.0, -np.sin(TILT), np.cos(TILT))
    mesh.normals_split_custom_set([normal] * len(mesh.loops))
    return obj


def lightmap_uvs(obj):
    select([obj])
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='SELECT')
    bpy.ops.uv.smart_project(island_margin=0.08)
    bpy.ops.object.mode_set(mode='OBJECT')


def check(lmdp_ext, demo, name, samples=2048):  # noqa: F811
    # 2 x 4096 Cycles samples and 2048 of ours: one standard error of the mean stays near 0.4 %, so
    # the 2 % bound is 5 of them (at 512 / 2 x 1024 it was 2.4 and failed by chance on one layout
    # of Smart UV Project's islands, which vary from run to run: -2.02 % +- 0.82 %)
    refs = reference(lmdp_ext, demo, name, RESOLUTION, 4096)
    ob = lmdp_bake(lmdp_ext, name, "UNGUIDED", RESOLUTION, samples)
    ours, cyc, var_o, var_c = compare(ob, refs)
    lit = cyc.sum(axis=1) > 0
    print(f"{name}: ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}")
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"{name}: {len(ours)} texels ({lit.sum()} lit), mean rel. diff {np.round(rel * 100, 2)} % "
          f"± {np.round(rel_sigma * 100, 2)} % (1 s.e.), per-texel excess {excess.mean():.3g} "
          f"± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()
    return ours, cyc


def flat_mean_error(lmdp_ext, obj, ours_smooth):
    """Relative mean difference (luminance-free: channel mean) of the same mesh baked flat."""
    mesh = obj.data
    if mesh.has_custom_normals:
        select([obj])
        bpy.ops.mesh.customdata_custom_splitnormals_clear()
    select([obj])
    bpy.ops.object.shade_flat()
    flat = lmdp_bake(lmdp_ext, obj.name, "UNGUIDED", RESOLUTION, 128)
    return float(flat.value.mean() / ours_smooth.mean() - 1.0)


@pytest.mark.slow
@pytest.mark.parametrize("make", [
    smooth_sphere,
    custom_normal_grid,
], ids=["smooth_sphere", "custom_normals"])
def test_shading_normals_match_cycles(fresh_scene, lmdp_ext, demo, make):  # noqa: F811
    build("CORNELL_BOX", lmdp_ext)
    obj = make()
    lightmap_uvs(obj)
    extract = lmdp_ext.sub("operators.adapters.extract")
    arrays = extract.extract_scene(bpy.context, [obj])
    assert arrays.has_smooth_normals()
    ours, cyc = check(lmdp_ext, demo, obj.name)
    print(f"{obj.name}: flat shading would be {flat_mean_error(lmdp_ext, obj, ours) * 100:+.1f} % off")
