"""The bake follows the scene's Cycles light paths by default (issue 19, item 3).

Cycles stops a path after the vertex whose bounce count reaches Max Bounces or whose diffuse
bounce count reaches Diffuse (``path_state_next``); the engine makes only diffuse bounces, so its
path length is N = min(max_bounces, diffuse_bounces). Measured against Cycles' bakes of the
Cornell floor (16², 1024 samples, clamp 0): Cycles (12, 4) vs N = 3 / 4 / 5: −9.9 / +0.1 / +5.1 %;
(12, 2) vs N = 1 / 2 / 3: −49 / −0.2 / +21 %; (3, 8) vs N = 2 / 3 / 4: −18 / −0.2 / +11 %
(σ ≈ 0.4 %). The scene's Cycles clamps (Clamping > Direct / Indirect Light) are applied as Cycles
applies them (``test_clamp_vs_cycles``). ``scene.lmdp.light_paths = 'CUSTOM'`` uses
``scene.lmdp.max_bounces``, ``clamp_direct`` and ``clamp_indirect`` instead.
"""
import hashlib
import json
import os
import subprocess
import sys

import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import CACHE, assert_means_agree, compare


def tiny_bake(lmdp_ext, tmp_path, name="Floor", **settings):
    """An UNGUIDED 8² bake of ``name`` with 4 samples into ``tmp_path``; (BakeResult, bake_stats.json)."""
    s = bpy.context.scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin = 'UNGUIDED', 8, 4, 0
    s.output_dir = str(tmp_path)
    for key, value in settings.items():
        setattr(s, key, value)
    select([bpy.data.objects[name]])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    result = lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake")
    with open(tmp_path / "bake_stats.json", encoding="utf-8") as fh:
        return result, json.load(fh)


@pytest.fixture
def cornell(fresh_scene):
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    return fresh_scene


def test_light_paths_path_length_is_the_smaller_limit(lmdp_ext):
    LightPaths = lmdp_ext.sub("lmdp_addon.settings").LightPaths
    assert LightPaths.from_cycles(12, 4).path_length == 4      # Cycles' defaults
    assert LightPaths.from_cycles(3, 8).path_length == 3
    assert LightPaths.from_cycles(12, 0).path_length == 0
    assert LightPaths.custom(7).path_length == 7
    assert LightPaths.from_cycles(12, 4, clamp_indirect=10).clamped
    assert not LightPaths.from_cycles(12, 4, clamp_indirect=0).clamped


def test_a_new_scene_follows_cycles_default_light_paths(fresh_scene, lmdp_ext):
    props = lmdp_ext.sub("operators.properties")
    assert fresh_scene.lmdp.light_paths == 'SCENE'
    settings, paths = props.bake_settings_from_scene(fresh_scene)
    cycles = fresh_scene.cycles
    assert (paths.max_bounces, paths.diffuse_bounces) == (cycles.max_bounces, cycles.diffuse_bounces) == (12, 4)
    assert settings.max_bounces == paths.path_length == 4
    # Cycles' default clamps (direct off, indirect 10) reach the engine's settings
    assert (paths.clamp_direct, paths.clamp_indirect) == (cycles.sample_clamp_direct, cycles.sample_clamp_indirect) \
        == (0.0, 10.0)
    assert (settings.clamp_direct, settings.clamp_indirect) == (0.0, 10.0)
    assert paths.min_light_bounces == settings.min_light_bounces == cycles.min_light_bounces == 0
    cycles.min_light_bounces = 2
    assert props.bake_settings_from_scene(fresh_scene)[0].min_light_bounces == 2
    panel = lmdp_ext.sub("operators.ui.panel")   # the Bake section's status line under Light Paths
    assert panel._light_paths_line(fresh_scene) == ("Cycles: 4 bounces (Max 12, Diffuse 4), indirect clamped at 10 "
                                                   "(biased, like Cycles)")
    cycles.sample_clamp_indirect = 0.0
    assert panel._light_paths_line(fresh_scene).endswith("Diffuse 4), no clamp")
    assert props.settings_from_scene(fresh_scene).max_bounces == 8   # scene.lmdp itself is unchanged


@pytest.mark.parametrize("max_bounces, diffuse, expected", [(12, 2, 2), (12, 6, 6), (3, 6, 3)])
def test_default_bake_reads_the_scene_light_paths(cornell, lmdp_ext, tmp_path, max_bounces, diffuse, expected):
    cornell.cycles.max_bounces, cornell.cycles.diffuse_bounces = max_bounces, diffuse
    cornell.cycles.sample_clamp_indirect = 0.0
    result, stats = tiny_bake(lmdp_ext, tmp_path)
    assert result.settings["max_bounces"] == expected          # what the tracer was given
    assert stats["settings"]["max_bounces"] == expected
    paths = stats["light_paths"]
    assert paths["source"] == "SCENE" and paths["path_length"] == expected
    assert (paths["max_bounces"], paths["diffuse_bounces"]) == (max_bounces, diffuse)
    assert paths["clamp_indirect"] == 0.0 and paths["clamp_applied"] is False
    assert not any("clamp" in w for w in stats["warnings"])


def test_custom_overrides_the_scene(cornell, lmdp_ext, tmp_path):
    cornell.cycles.max_bounces, cornell.cycles.diffuse_bounces = 12, 2
    cornell.cycles.sample_clamp_indirect, cornell.cycles.sample_clamp_direct = 10.0, 4.0
    result, stats = tiny_bake(lmdp_ext, tmp_path, light_paths='CUSTOM', max_bounces=5)
    assert result.settings["max_bounces"] == 5
    assert stats["light_paths"]["source"] == "CUSTOM" and stats["light_paths"]["path_length"] == 5
    # CUSTOM does not follow the scene's clamps: its own, off by default
    assert (result.settings["clamp_direct"], result.settings["clamp_indirect"]) == (0.0, 0.0)
    assert stats["light_paths"]["clamp_applied"] is False
    assert not any("clamp" in w for w in stats["warnings"])
    result, stats = tiny_bake(lmdp_ext, tmp_path, light_paths='CUSTOM', max_bounces=5, clamp_indirect=2.5)
    assert (result.settings["clamp_direct"], result.settings["clamp_indirect"]) == (0.0, 2.5)
    assert (stats["light_paths"]["clamp_indirect"], stats["light_paths"]["clamp_applied"]) == (2.5, True)


def test_scene_clamps_are_applied_and_reported(cornell, lmdp_ext, tmp_path):
    cornell.cycles.sample_clamp_indirect = 10.0   # Cycles' default
    cornell.cycles.sample_clamp_direct = 0.25
    result, stats = tiny_bake(lmdp_ext, tmp_path, bake_content='DIRECT_INDIRECT')
    assert (result.settings["clamp_direct"], result.settings["clamp_indirect"]) == (0.25, 10.0)
    paths = stats["light_paths"]
    assert (paths["clamp_direct"], paths["clamp_indirect"], paths["clamp_applied"]) == (0.25, 10.0, True)
    assert stats["settings"]["clamp_indirect"] == 10.0
    assert not any("not applied" in w for w in stats["warnings"])   # UNGUIDED clamps as Cycles does
    assert stats["objects"]["Floor"]["trace"]["clamped"] > 0       # the demo light's direct samples
    summary = lmdp_ext.sub("operators.properties").light_paths_from_scene(cornell).summary()
    assert summary.endswith("direct clamped at 0.25 and indirect clamped at 10 (biased, like Cycles)")
    assert stats["objects"]["Floor"]["trace"]["light_vertices"] == 0   # light connections off under a clamp


def test_light_connections_follow_the_clamp_and_the_report_says_so(cornell, lmdp_ext, tmp_path):
    """Without a clamp the default bake joins light vertices; Cycles' default Clamp Indirect 10
    turns them off, and the Bake report says why (``connections.off_reason``)."""
    cornell.cycles.sample_clamp_indirect = 0.0
    cornell.cycles.sample_clamp_direct = 0.0
    _, stats = tiny_bake(lmdp_ext, tmp_path)
    assert stats["objects"]["Floor"]["trace"]["light_vertices"] > 0
    assert stats["objects"]["Floor"]["trace"]["connections"] > 0
    cornell.cycles.sample_clamp_indirect = 10.0
    settings, _ = lmdp_ext.sub("operators.properties").bake_settings_from_scene(cornell)
    scene = lmdp_ext.sub("operators.adapters.extract").extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    reason = lmdp_ext.sub("lmdp_addon.bake.connections").off_reason(scene, settings)
    assert reason.startswith("light connections off: a sample clamp is on")
    _, stats = tiny_bake(lmdp_ext, tmp_path)
    assert stats["objects"]["Floor"]["trace"]["light_vertices"] == 0


def test_no_diffuse_bounce_is_refused_with_the_reason(cornell, lmdp_ext):
    cornell.cycles.diffuse_bounces = 0
    select([bpy.data.objects["Floor"]])
    cornell.lmdp.bake_mode = 'UNGUIDED'
    with pytest.raises(RuntimeError, match="Light Paths allow no indirect diffuse light.*Custom"):
        bpy.ops.lmdp.bake()
    cornell.lmdp.light_paths = 'CUSTOM'
    cornell.lmdp.bake_resolution, cornell.lmdp.bake_samples = 8, 2
    assert bpy.ops.lmdp.bake() == {'FINISHED'}


def test_run_all_follows_the_scene_light_paths(cornell, lmdp_ext):
    cornell.cycles.max_bounces, cornell.cycles.diffuse_bounces = 12, 3
    s = cornell.lmdp
    s.point_count, s.bake_mode, s.bake_resolution, s.bake_samples = 256, 'FINAL_GATHER', 8, 4
    select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
    assert bpy.ops.lmdp.run_pipeline(show=False) == {'FINISHED'}
    result = lmdp_ext.sub("operators.session").session_for(cornell).require("bake")
    assert result.settings["max_bounces"] == 3
    assert result.stats()["light_paths"]["source"] == "SCENE"


def test_headless_default_follows_the_scene_and_set_custom_works(repo_root, tmp_path, lit_scene):
    scene_file = tmp_path / "lit.blend"
    bpy.context.scene.cycles.diffuse_bounces = 3
    bpy.ops.wm.save_as_mainfile(filepath=str(scene_file), copy=True)

    def light_paths(output, *args):
        env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender_user"))
        run = subprocess.run([sys.executable, str(repo_root / "scripts" / "lmdp_headless.py"), str(scene_file),
                              "--output", str(output), "--dry-run", *args],
                             capture_output=True, text=True, env=env, timeout=900)
        assert run.returncode == 0, run.stderr
        with open(output / "summary.json", encoding="utf-8") as fh:
            return json.load(fh)["light_paths"]

    default = light_paths(tmp_path / "default")
    assert default["source"] == "SCENE" and default["path_length"] == 3
    assert (default["clamp_direct"], default["clamp_indirect"], default["clamp_applied"]) == (0.0, 10.0, True)
    custom = light_paths(tmp_path / "custom", "--set", "light_paths=CUSTOM", "--set", "max_bounces=6",
                         "--set", "clamp_indirect=2.5")
    assert custom["source"] == "CUSTOM" and custom["path_length"] == 6
    assert (custom["clamp_direct"], custom["clamp_indirect"], custom["clamp_applied"]) == (0.0, 2.5, True)


# -- slow: the default bake against Cycles' bake with Cycles' default light paths -------------------

@pytest.mark.slow
def test_default_bake_matches_cycles_with_default_light_paths(fresh_scene, lmdp_ext):
    """Cornell floor, Cycles' light paths as a new scene has them (max 12, diffuse 4: the demo
    scene's own 8 / 8 are put back to the defaults of the property definitions), indirect clamp 0
    on both sides: the add-on's default bake (UNGUIDED, light_paths SCENE) and Cycles' bake of the
    same texels agree within 2 % and within 5 standard errors of both estimates."""
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    cycles = fresh_scene.cycles
    for key in ("max_bounces", "diffuse_bounces"):
        setattr(cycles, key, cycles.bl_rna.properties[key].default)
    assert (cycles.max_bounces, cycles.diffuse_bounces) == (12, 4)
    cycles.sample_clamp_indirect = 0.0
    demo = lmdp_ext.sub("operators.adapters.demo_scenes")
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    extract = lmdp_ext.sub("operators.adapters.extract")
    R, samples = 32, 4096
    floor = bpy.data.objects["Floor"]
    arrays = extract.extract_scene(bpy.context, [floor])
    refs = []
    for seed in (1, 2):
        key = "|".join(map(str, (checks.scene_fingerprint(arrays), "Floor", R, samples, seed, "scene 12/4",
                                 0.0, bpy.app.version_string)))
        path = os.path.join(CACHE, hashlib.sha1(key.encode()).hexdigest()[:20] + ".npy")
        if not os.path.exists(path):
            px = demo.bake_cycles(bpy.context, floor, 'DIFFUSE', ('INDIRECT',), R, samples=samples, margin=0,
                                  seed=seed)[..., :3]     # max_bounces None: the scene's 12 / 4
            os.makedirs(CACHE, exist_ok=True)
            np.save(path, px.astype(np.float32))
        refs.append(np.load(path))
    refs = np.stack(refs)
    assert (cycles.max_bounces, cycles.diffuse_bounces) == (12, 4)   # bake_cycles restored them
    s = fresh_scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin, s.seed = 'UNGUIDED', R, 2048, 0, 11
    select([floor])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    result = lmdp_ext.sub("operators.session").session_for(fresh_scene).require("bake")
    assert result.settings["max_bounces"] == 4
    ours, cyc, var_o, var_c = compare(result.object("Floor"), refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    print(f"default light paths (12 / 4 -> N = 4): mean difference {np.round(rel * 100, 2)} % "
          f"(1 sigma {np.round(rel_sigma * 100, 2)} %)")
    assert np.all(np.abs(rel) < 0.02), rel
