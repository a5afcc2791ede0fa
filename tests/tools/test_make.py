"""The Makefile's targets and .ci/run."""
import os
import shutil
import stat
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TARGETS = ("venv", "test", "test-all", "demo", "extension", "validate", "bench", "bench-quick", "clean")


def make_dry_run(target):
    return subprocess.run(["make", "--no-print-directory", "-n", "-C", str(ROOT), target], capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
@pytest.mark.parametrize("target", TARGETS)
def test_target_exists(target):
    run = make_dry_run(target)
    assert run.returncode == 0, run.stderr


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_targets_run_the_environment_check_first():
    for target in ("test", "demo"):
        lines = make_dry_run(target).stdout.splitlines()
        assert lines[0] == "scripts/check_env.sh", lines


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_commands():
    assert "pytest tests" in make_dry_run("test").stdout
    assert "LMDP_SLOW_TESTS=1" in make_dry_run("test-all").stdout
    demo = make_dry_run("demo").stdout
    assert "scripts/lmdp_headless.py --demo cornell --output out/demo" in demo
    assert "bench/run.py --quick" in make_dry_run("bench-quick").stdout
    extension = make_dry_run("extension").stdout
    assert "scripts/fetch_wheels.py" in extension
    assert "build --source-dir . --output-dir dist --split-platforms" in extension


def test_ci_runs_make_test():
    ci = ROOT / ".ci" / "run"
    assert ci.stat().st_mode & stat.S_IXUSR
    text = ci.read_text()
    assert text.startswith("#!/usr/bin/env bash") and "set -euo pipefail" in text
    assert "make test" in text.split("set -euo pipefail", 1)[1]


@pytest.mark.slow
def test_make_extension_builds_the_linux_zip_with_its_wheels(tmp_path):
    dist = tmp_path / "dist"
    run = subprocess.run(["make", "-C", str(ROOT), "extension", f"DIST={dist}"],
                         capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    zips = sorted(p.name for p in dist.glob("*.zip"))
    assert zips == ["lmdp_light_transport-0.1.0-linux_x64.zip", "lmdp_light_transport-0.1.0-macos_arm64.zip",
                    "lmdp_light_transport-0.1.0-windows_x64.zip"]
    with zipfile.ZipFile(dist / "lmdp_light_transport-0.1.0-linux_x64.zip") as archive:
        names = archive.namelist()
    wheels = sorted(n for n in names if n.startswith("wheels/"))
    assert wheels == [
        "wheels/embreex-4.4.0.post1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl",
        "wheels/scipy-1.15.3-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    ]
    for required in ("blender_manifest.toml", "__init__.py", "operators/__init__.py", "lmdp_addon/__init__.py"):
        assert required in names
    for forbidden in ("tests/", "bench/", "docs/", ".venv/", "scripts/", ".git/", "Makefile", "out/"):
        assert not any(n.startswith(forbidden) for n in names), f"{forbidden} is in the zip"


@pytest.mark.slow
def test_the_linux_zip_installs_in_blender_and_runs_on_its_bundled_wheels(tmp_path):
    """Install the built zip through Blender's extension mechanism (Install from Disk) into a
    fresh user folder; with the venv's scipy and embreex hidden, the extension must import the
    wheels Blender extracted from the zip and run the whole pipeline."""
    dist = tmp_path / "dist"
    run = subprocess.run(["make", "-C", str(ROOT), "extension", f"DIST={dist}"],
                         capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "BLENDER_USER_RESOURCES")}
    run = subprocess.run([str(ROOT / ".venv" / "bin" / "python"), str(ROOT / "tests" / "tools" / "data" / "install_zip.py"),
                          str(dist / "lmdp_light_transport-0.1.0-linux_x64.zip"), str(tmp_path / "user")],
                         capture_output=True, text=True, timeout=900, env=env, cwd=tmp_path)
    assert run.returncode == 0 and "INSTALLED-AND-RAN" in run.stdout, run.stdout[-3000:] + run.stderr[-3000:]
