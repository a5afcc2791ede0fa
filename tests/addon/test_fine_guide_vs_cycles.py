"""GUIDED with the fine guide at its full resolution (16 x 16 cells per state: the ray budget
raised so that small test bakes get it too) against Cycles' own bake of the same texels
(DIFFUSE / INDIRECT, clamping off, 8 bounces on both sides, two seeds), compared as in
``test_bake_vs_cycles``: the mean within 5 standard errors of both estimates (and within 2 % on
the glTF). The Cornell floor in the default suite; the glTF sample "Suzanne" (imported with
``bpy.ops.import_scene.gltf``, ``test_residual_vs_cycles``) on the Cornell box's floor in the slow
one."""
import os

import numpy as np
import pytest

from test_bake_vs_cycles import assert_means_agree, build, compare, lmdp_bake, reference
from test_residual_vs_cycles import RESOLUTION, SUZANNE, import_suzanne


@pytest.fixture
def full_resolution(lmdp_ext, monkeypatch):
    """The fine guide's G = 16 whatever the bake's size (the budget is 1/8 ray per path)."""
    monkeypatch.setattr(lmdp_ext.sub("lmdp_addon.bake.fine_guide"), "FINE_RAYS_PER_PATH", 8.0)


def _fine_resolution(lmdp_ext):
    import bpy
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake").guide_info.get(
        "fine_resolution")


def test_fine_guided_cornell_floor_matches_cycles(fresh_scene, lmdp_ext, demo, full_resolution):
    build("CORNELL_BOX", lmdp_ext)
    refs = reference(lmdp_ext, demo, "Floor", 16, 1024)
    fresh_scene.lmdp.point_count = 1024
    ob = lmdp_bake(lmdp_ext, "Floor", "GUIDED", 16, 512)   # the first bake samples, builds and solves
    assert _fine_resolution(lmdp_ext) == 16
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"fine GUIDED vs Cycles, Cornell floor: {np.round(100 * rel, 2)} % ± {np.round(100 * rel_sigma, 2)} %")


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(SUZANNE), reason=f"no glTF sample at {SUZANNE}")
def test_fine_guided_imported_gltf_matches_cycles(fresh_scene, lmdp_ext, demo, full_resolution):
    build("CORNELL_BOX", lmdp_ext)
    import_suzanne()
    refs = reference(lmdp_ext, demo, "Suzanne", RESOLUTION, 2048)
    ob = lmdp_bake(lmdp_ext, "Suzanne", "GUIDED", RESOLUTION, 2048)
    assert _fine_resolution(lmdp_ext) == 16
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"fine GUIDED vs Cycles, glTF Suzanne ({len(ours)} texels): {np.round(100 * rel, 2)} % "
          f"± {np.round(100 * rel_sigma, 2)} % (1 s.e.)")
    assert np.all(np.abs(rel) < 0.02), rel
