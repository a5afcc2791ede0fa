"""scripts/install_venv.sh and scripts/pins.py: exact pins, and one line when PyPI is unreachable."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
import pins  # noqa: E402


def test_every_requirement_is_an_exact_pin():
    pinned = pins.read_pins(ROOT / "requirements-dev.txt")
    for name in ("bpy", "numpy", "scipy", "embreex", "pytest", "matplotlib", "requests", "zstandard",
                 "cython", "certifi", "charset-normalizer", "idna", "urllib3"):
        assert name in pinned, f"{name} is not pinned"
    assert pinned["bpy"] == "5.0.1" and pinned["numpy"] == "1.26.4"


def test_unpinned_lines_are_rejected(tmp_path):
    requirements = tmp_path / "requirements.txt"
    requirements.write_text("numpy==1.26.4\nscipy>=1.15\n")
    with pytest.raises(ValueError, match="not an exact pin"):
        pins.read_pins(requirements)


def test_the_venv_holds_exactly_the_pins():
    """`pip freeze` of the interpreter running the tests equals the pinned set (make venv)."""
    if not (Path(sys.prefix) / "pyvenv.cfg").exists():
        pytest.skip("not running inside a venv")
    if Path(sys.prefix).resolve() != (ROOT / ".venv").resolve():
        pytest.skip("tests are not running in this checkout's .venv")
    diff = pins.differences(pins.read_pins(ROOT / "requirements-dev.txt"), pins.frozen(sys.executable))
    assert diff == []


def test_differences_are_reported():
    assert pins.differences({"numpy": "1.26.4"}, {"numpy": "2.0.0", "rich": "13"}) == [
        "numpy is 2.0.0, pinned 1.26.4", "rich==13 is installed but not pinned"]


def offline_env(tmp_path):
    """pip pointed at a closed local port, with no config, cache or local wheel sources."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("PIP_")}
    env.update({
        "PIP_CONFIG_FILE": os.devnull,
        "PIP_INDEX_URL": "http://127.0.0.1:9/simple",
        "PIP_RETRIES": "0",
        "PIP_TIMEOUT": "5",
        "PIP_NO_CACHE_DIR": "1",
        "PYTHON": shutil.which("python3.11") or sys.executable,
    })
    for key in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY"):
        env.pop(key, None)
    return env


@pytest.mark.skipif(shutil.which("python3.11") is None, reason="needs python3.11")
def test_no_network_is_one_clear_line(tmp_path):
    requirements = tmp_path / "requirements.txt"
    requirements.write_text("bpy==5.0.1\n")
    run = subprocess.run(["bash", str(ROOT / "scripts" / "install_venv.sh"), str(tmp_path / "venv"),
                          str(requirements)], capture_output=True, text=True, env=offline_env(tmp_path),
                         timeout=600)
    assert run.returncode != 0
    errors = [line for line in run.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, run.stderr
    assert "could not download bpy==5.0.1 from PyPI: check the network / proxy" in errors[0]
