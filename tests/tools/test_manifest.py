"""blender_manifest.toml: Blender's own validator accepts it; its wheels match the pins."""
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
import fetch_wheels  # noqa: E402
import pins  # noqa: E402


def blender_ext():
    found = sorted(Path(sys.prefix).glob(
        "lib/python3.11/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        pytest.skip("bpy (with Blender's blender_ext.py) is not installed in this interpreter")
    return found[0]


def manifest():
    with open(ROOT / "blender_manifest.toml", "rb") as fh:
        return tomllib.load(fh)


def test_blender_validates_the_manifest():
    run = subprocess.run([sys.executable, str(blender_ext()), "validate", str(ROOT)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "Success" in run.stdout


def test_blender_rejects_a_broken_manifest(tmp_path):
    """The validator can fail: a manifest with a bad version is refused."""
    (tmp_path / "__init__.py").write_text("")
    text = (ROOT / "blender_manifest.toml").read_text().replace('version = "0.1.0"', 'version = "one"')
    (tmp_path / "blender_manifest.toml").write_text(text)
    run = subprocess.run([sys.executable, str(blender_ext()), "validate", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode != 0


def test_manifest_fields():
    data = manifest()
    assert data["id"] == "lmdp_light_transport"
    assert data["blender_version_min"] == "4.2.0"
    assert set(data["platforms"]) == {"linux-x64", "windows-x64", "macos-arm64"}
    excluded = data["build"]["paths_exclude_pattern"]
    for path in ("/tests/", "/bench/", "/docs/", "/.venv/"):
        assert path in excluded
    assert "files" in data["permissions"]


def test_manifest_wheels_are_the_pinned_versions_for_every_platform():
    pinned = pins.read_pins(ROOT / "requirements.txt")
    platforms = {"scipy": set(), "embreex": set()}
    for relative in manifest()["wheels"]:
        name, version, python_tag, abi, tags = fetch_wheels.parse_wheel_name(Path(relative).name)
        assert relative.startswith("./wheels/")
        assert python_tag == "cp311" and abi == "cp311"
        assert pinned[pins.normalise(name)] == version, f"{relative} is not the pinned {name}"
        platforms[name].add("linux" if "linux" in tags[0] else "windows" if "win" in tags[0] else "macos")
    assert platforms == {"scipy": {"linux", "windows", "macos"}, "embreex": {"linux", "windows", "macos"}}


def test_download_command_asks_pip_for_exactly_that_wheel():
    command = fetch_wheels.download_command(
        "python", "embreex-4.4.0.post1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl", "d")
    assert command[1:4] == ["-m", "pip", "download"]
    for flag in ("--no-deps", "--only-binary=:all:"):
        assert flag in command
    assert command[command.index("--python-version") + 1] == "3.11"
    assert command[command.index("--implementation") + 1] == "cp"
    assert "embreex==4.4.0.post1" in command
    platforms = [command[i + 1] for i, arg in enumerate(command) if arg == "--platform"]
    assert platforms == ["manylinux_2_27_x86_64", "manylinux_2_28_x86_64"]
