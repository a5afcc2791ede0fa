"""scripts/lmdp_headless.py on a bake farm (--workers N: a local Dask cluster; --scheduler
ADDRESS: a running one): the same files as a local run, and farm arguments refused before any
work with a message that names them."""
import json
import os
import subprocess
import sys
import time

import pytest

SMALL = ["--demo", "cornell", "--no-pictures", "--set", "point_count=64", "--set", "bake_resolution=16",
         "--set", "bake_samples=4"]


def run_script(repo_root, tmp_path, *args):
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender_user")  # never the user's Blender
    return subprocess.run([sys.executable, str(repo_root / "scripts" / "lmdp_headless.py"), *args],
                          capture_output=True, text=True, env=env, timeout=900)


def read_summary(output):
    with open(output / "summary.json", encoding="utf-8") as fh:
        return json.load(fh)


def test_local_workers_bake_the_same_files_as_a_local_run(repo_root, tmp_path):
    local, farm = tmp_path / "local", tmp_path / "farm"
    run = run_script(repo_root, tmp_path, *SMALL, "--output", str(local))
    assert run.returncode == 0, run.stderr
    run = run_script(repo_root, tmp_path, *SMALL, "--output", str(farm), "--workers", "2")
    assert run.returncode == 0, run.stderr
    summary = read_summary(farm)
    assert summary["farm"]["workers"] == 2
    assert summary["farm"]["traffic"]["units"] >= 7           # every object's units ran on the farm
    images = sorted(p.name for p in local.glob("*_lmdp_indirect.exr"))
    assert len(images) == 7
    for name in images:
        assert (farm / name).read_bytes() == (local / name).read_bytes(), name


def test_an_unreachable_scheduler_is_refused_before_any_work(repo_root, tmp_path):
    output = tmp_path / "out"
    t0 = time.perf_counter()
    run = run_script(repo_root, tmp_path, *SMALL, "--output", str(output), "--scheduler", "tcp://127.0.0.1:9")
    assert time.perf_counter() - t0 < 60
    assert run.returncode == 2, run.stderr
    assert "--scheduler tcp://127.0.0.1:9: cannot reach the Dask scheduler at tcp://127.0.0.1:9 within 5 s" in run.stderr
    assert read_summary(output)["steps"] == []


@pytest.mark.parametrize("args, message", [
    (["--scheduler", "tcp://127.0.0.1:9", "--workers", "2"], "give either --scheduler"),
    (["--workers", "0"], "--workers 0: give at least 1 worker process"),
])
def test_farm_arguments_are_checked(repo_root, tmp_path, args, message):
    output = tmp_path / "out"
    run = run_script(repo_root, tmp_path, *SMALL, "--output", str(output), *args)
    assert run.returncode == 2
    assert message in run.stderr
