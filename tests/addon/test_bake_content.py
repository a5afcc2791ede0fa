"""What is baked (issue 21, item 5): direct + indirect, and either times the diffuse colour,
against Cycles' DIFFUSE bake of the same texels with the same ``pass_filter``.

``bake_content`` 'DIRECT_INDIRECT' is Cycles' {'DIRECT', 'INDIRECT'}; ``multiply_color`` adds
'COLOR'. Clamping off and 8 bounces on both sides, two Cycles seeds, tolerances from the two
estimates' variances as in ``test_bake_vs_cycles`` (mean within 2 % and within 5 standard
errors; per texel the squared differences as large as the variances predict). The combined test
uses the Cornell floor cut into a 4 x 4 checker of two materials (white and blue), so the
colour varies texel to texel.
"""
import hashlib
import os

import bpy
import numpy as np
import pytest

from helpers import add_material, select
from test_bake_vs_cycles import BOUNCES, CACHE, K, assert_means_agree, build, compare, lmdp_bake

RESOLUTION = 16
CYCLES_SAMPLES = 2048
SAMPLES = 1024


def reference(lmdp_ext, demo, name, pass_filter, resolution=RESOLUTION, samples=CYCLES_SAMPLES, seeds=(1, 2)):
    """Cycles' DIFFUSE bakes of ``name`` with ``pass_filter`` and ``seeds``, cached; (2, R, R, 3)."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    scene = bpy.context.scene
    arrays = extract.extract_scene(bpy.context, [bpy.data.objects[name]])
    out = []
    for seed in seeds:
        key = "|".join(map(str, (checks.scene_fingerprint(arrays), name, resolution, samples, seed, BOUNCES,
                                 scene.cycles.sample_clamp_indirect, bpy.app.version_string, sorted(pass_filter))))
        path = os.path.join(CACHE, hashlib.sha1(key.encode()).hexdigest()[:20] + ".npy")
        if os.path.exists(path):
            out.append(np.load(path))
            continue
        px = demo.bake_cycles(bpy.context, bpy.data.objects[name], 'DIFFUSE', tuple(pass_filter), resolution,
                              samples=samples, margin=0, max_bounces=BOUNCES, seed=seed)[..., :3]
        os.makedirs(CACHE, exist_ok=True)
        np.save(path, px.astype(np.float32))
        out.append(px)
    return np.stack(out)


def checker_floor(cells=4, colors=((0.8, 0.8, 0.8), (0.15, 0.25, 0.8))):
    """The Cornell floor cut into ``cells`` x ``cells`` quads of alternating materials (its UV
    chart is cut with it: one island)."""
    floor = bpy.data.objects["Floor"]
    select([floor])
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='SELECT')
    bpy.ops.mesh.subdivide(number_cuts=cells - 1)
    bpy.ops.object.mode_set(mode='OBJECT')
    mesh = floor.data
    mesh.materials.clear()
    for k, color in enumerate(colors):
        mesh.materials.append(add_material(f"Checker {k}", color))
    centres = np.array([p.center[:2] for p in mesh.polygons])
    cell = np.floor((centres + 0.5) * cells).astype(int)
    mesh.polygons.foreach_set("material_index", ((cell[:, 0] + cell[:, 1]) % 2).astype(np.int32))
    mesh.update()
    return floor


def agree(ob, refs, label):
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"{label}: ours {ours.mean(axis=0)} cycles {cyc.mean(axis=0)}: {np.round(rel * 100, 2)} % "
          f"± {np.round(rel_sigma * 100, 2)} % (1 s.e.); per-texel excess {excess.mean():.3g} "
          f"± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()
    return ours, cyc


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED"])
def test_direct_indirect_matches_cycles(fresh_scene, lmdp_ext, demo, mode):
    """The Cornell floor, direct + indirect: Cycles' {'DIRECT', 'INDIRECT'}. The direct part is
    most of it (the indirect-only bake is far below), so a bake without the direct term fails.
    GUIDED draws x0's first direction from the solution's policy: the MIS of its hits still adds
    up (the cosine density in both weights, ``lights.EmitterSampler.next_event``)."""
    build("CORNELL_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", ("DIRECT", "INDIRECT"))
    if mode == "GUIDED":
        fresh_scene.lmdp.point_count = 1024
        select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
        assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    ob = lmdp_bake(lmdp_ext, "Floor", mode, RESOLUTION, SAMPLES, bake_content="DIRECT_INDIRECT")
    ours, cyc = agree(ob, refs, f"Floor direct + indirect, {mode}")
    indirect = lmdp_bake(lmdp_ext, "Floor", mode, RESOLUTION, 64, bake_content="INDIRECT")
    assert indirect.value.mean() < 0.7 * ours.mean()    # the direct term is not a rounding error


@pytest.mark.parametrize("content, pass_filter", [
    ("DIRECT_INDIRECT", ("DIRECT", "INDIRECT", "COLOR")),
    ("INDIRECT", ("INDIRECT", "COLOR")),
], ids=["direct_indirect_color", "indirect_color"])
def test_times_color_matches_cycles_on_a_checker(fresh_scene, lmdp_ext, demo, content, pass_filter):
    """The checker floor times its diffuse colour: Cycles' pass_filter with 'COLOR', texel for
    texel; on the blue cells the blue-to-red ratio is that of the white cells times the albedos'
    5.3 (without the colour, the same)."""
    build("CORNELL_BOX", lmdp_ext)
    checker_floor()
    refs = reference(lmdp_ext, demo, "Floor", pass_filter)
    ob = lmdp_bake(lmdp_ext, "Floor", "UNGUIDED", RESOLUTION, SAMPLES, bake_content=content, multiply_color=True)
    ours, cyc = agree(ob, refs, f"checker floor {content} x colour")
    lit = (cyc[:, 0] > 0) & (ours[:, 0] > 0)       # the floor under the boxes is dark
    ours, cyc = ours[lit], cyc[lit]
    ratio = cyc[:, 2] / cyc[:, 0]
    blue = ratio > np.sqrt(ratio.min() * ratio.max())
    assert 0.3 < blue.mean() < 0.7, blue.mean()     # half the cells are blue
    ours_ratio = ours[:, 2] / ours[:, 0]            # blue / white albedo ratio of b/r: 5.3
    assert np.median(ours_ratio[blue]) > 3.0 * np.median(ours_ratio[~blue])
