"""scripts/lmdp_headless.py as users run it: PyPI bpy form, and the `--` form of
`blender --background scene.blend --python scripts/lmdp_headless.py -- ...` (argument parsing
checked under the venv python, since no `blender` binary is installed here)."""
import json
import os
import subprocess
import sys

import bpy
import pytest

from helpers import remove_uv_maps


def run_script(repo_root, tmp_path, *args):
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender_user")  # never the user's Blender
    return subprocess.run([sys.executable, str(repo_root / "scripts" / "lmdp_headless.py"), *args],
                          capture_output=True, text=True, env=env, timeout=900)


@pytest.fixture
def scene_file(lit_scene, tmp_path):
    path = tmp_path / "lit.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def read_summary(output):
    with open(output / "summary.json", encoding="utf-8") as fh:
        return json.load(fh)


def test_pypi_form_selects_non_emitting_meshes_and_applies_settings(repo_root, tmp_path, scene_file):
    output = tmp_path / "out"
    run = run_script(repo_root, tmp_path, str(scene_file), "--output", str(output), "--dry-run",
                     "--set", "point_count=64", "--set", "cost_mode=thesis", "--set", "tolerance=1e-6")
    assert run.returncode == 0, run.stderr
    summary = read_summary(output)
    assert summary["objects"] == ["Box", "Floor"]  # Lamp emits, Camera is no mesh
    assert summary["settings"]["point_count"] == 64
    assert summary["settings"]["cost_mode"] == "THESIS"
    assert summary["settings"]["tolerance"] == 1e-6
    assert summary["settings"]["output_dir"] == str(output)
    assert summary["extension"]["module"].endswith(".lmdp_light_transport")
    assert summary["extension"]["origin"].startswith("checkout")
    assert summary["steps"] == [] and summary["error"] is None


def test_blender_form_arguments_after_double_dash(repo_root, tmp_path, scene_file):
    output = tmp_path / "out"
    run = run_script(repo_root, tmp_path, "--", str(scene_file), "--output", str(output),
                     "--objects", "Floor", "--dry-run")
    assert run.returncode == 0, run.stderr
    assert read_summary(output)["objects"] == ["Floor"]


@pytest.mark.parametrize("args, message", [
    (["--objects", "Nope"], "no object named 'Nope'"),
    (["--objects", "Camera"], "'Camera' is a camera, not a mesh"),
    (["--set", "no_such_setting=1"], "unknown setting 'no_such_setting'"),
    (["--set", "cost_mode=NONSENSE"], "expected one of THESIS, PHYSICAL"),
    (["--set", "point_count=many"], "--set point_count=many"),
])
def test_bad_arguments_exit_2_with_a_message(repo_root, tmp_path, scene_file, args, message):
    run = run_script(repo_root, tmp_path, str(scene_file), "--output", str(tmp_path / "out"), *args)
    assert run.returncode == 2
    assert message in run.stderr


def test_no_file_and_no_demo_is_a_usage_error(repo_root, tmp_path):
    run = run_script(repo_root, tmp_path, "--output", str(tmp_path / "out"))
    assert run.returncode == 2
    assert "no .blend file" in run.stderr


def test_full_run_on_a_saved_file(repo_root, tmp_path, scene_file, lmdp_ext):
    common = lmdp_ext.sub("operators.common")
    output = tmp_path / "out"
    run = run_script(repo_root, tmp_path, str(scene_file), "--output", str(output),
                     "--set", "point_count=64", "--set", "bake_resolution=16", "--set", "bake_samples=4")
    summary = read_summary(output)
    stage_ops = [i for i in common.PIPELINE_OPERATORS if i != "lmdp.export_npz"]
    if not common.available_operators(stage_ops):
        assert run.returncode == 1
        assert "no LMDP pipeline operators yet" in run.stderr
        return
    assert run.returncode == 0, run.stderr
    assert summary["steps"] and all(step["status"] == "FINISHED" for step in summary["steps"])
    assert os.path.isfile(summary["result_blend"])
    if common.operator_available("lmdp.export_npz"):
        assert (output / "lmdp.npz").is_file()
    # Every mesh has a UV map: Run All bakes them into --output.
    assert summary["bake"] is True
    for name in summary["objects"]:
        assert (output / f"{name}_lmdp_indirect.exr").is_file()
    assert json.loads((output / "bake_stats.json").read_text())["settings"]["bake_resolution"] == 16


def test_meshes_without_uv_map_are_left_out_of_the_bake_or_skip_it_when_named(repo_root, tmp_path, lit_scene):
    """With auto_lightmap_uvs off a mesh without UV map is left out (and named), the others are
    baked; named in --objects it skips the bake, and --bake refuses it before any work."""
    remove_uv_maps(lit_scene["Box"])
    path = tmp_path / "no_uv.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    small = ["--set", "point_count=64", "--set", "bake_resolution=16", "--set", "bake_samples=4",
             "--set", "auto_lightmap_uvs=false"]   # on (the default), Box gets "LMDP Lightmap" and is baked
    output = tmp_path / "out"
    run = run_script(repo_root, tmp_path, str(path), "--output", str(output), *small)
    assert run.returncode == 0, run.stderr
    assert "left out Box: it has no UV map, so it cannot be baked" in run.stdout
    summary = read_summary(output)
    assert summary["objects"] == ["Floor"] and summary["bake"] is True
    assert (output / "Floor_lmdp_indirect.exr").is_file() and not (output / "Box_lmdp_indirect.exr").exists()
    named = tmp_path / "named"
    run = run_script(repo_root, tmp_path, str(path), "--output", str(named), "--objects", "Box,Floor", *small)
    assert run.returncode == 0, run.stderr
    assert "no bake: Box has no UV map" in run.stdout
    assert read_summary(named)["bake"] is False and not (named / "bake_stats.json").exists()
    run = run_script(repo_root, tmp_path, str(path), "--output", str(tmp_path / "insist"),
                     "--objects", "Box,Floor", "--bake", *small)
    assert run.returncode == 2 and "--bake: Box has no UV map" in run.stderr
    assert read_summary(tmp_path / "insist")["steps"] == []


def test_demo(repo_root, tmp_path, lmdp_ext):
    common = lmdp_ext.sub("operators.common")
    output = tmp_path / "demo"
    run = run_script(repo_root, tmp_path, "--demo", "cornell", "--output", str(output), "--dry-run")
    if not common.operator_available("lmdp.add_demo_scene"):
        assert run.returncode == 1
        assert "lmdp.add_demo_scene is not registered" in run.stderr
        return
    assert run.returncode == 0, run.stderr
    assert read_summary(output)["objects"]
