"""scripts/check_env.sh: one line naming the Debian/Ubuntu packages, non-zero exit."""
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHECK = ROOT / "scripts" / "check_env.sh"
LIBRARIES = ["libX11.so.6", "libXi.so.6", "libXrender.so.1", "libXfixes.so.3", "libxkbcommon.so.0",
             "libSM.so.6", "libGL.so.1"]
PACKAGES = "libx11-6 libxi6 libxrender1 libxfixes3 libxkbcommon0 libsm6 libgl1"
TOOLS = ["bash", "env", "grep", "uname", "cat", "sed", "tr", "printf", "dirname", "head"]


def real_python311():
    """The interpreter behind `python3.11` (not a pyenv shim, which needs pyenv's environment)."""
    if shutil.which("python3.11") is None:
        return None
    run = subprocess.run(["python3.11", "-c", "import sys; print(sys.executable)"],
                         capture_output=True, text=True, timeout=60)
    return run.stdout.strip() or None


def tool_dir(tmp_path, with_python=True):
    """A PATH directory with only the basic tools (and python3.11 if asked)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in TOOLS:
        found = shutil.which(tool)
        if found:
            (bin_dir / tool).symlink_to(found)
    if with_python:
        (bin_dir / "python3.11").symlink_to(real_python311())
    return bin_dir


def stub_ldconfig(bin_dir, libraries):
    """An `ldconfig -p` that lists only ``libraries``."""
    lines = "".join(f"\\t{lib} (libc6,x86-64) => /lib/x86_64-linux-gnu/{lib}\\n" for lib in libraries)
    script = bin_dir / "ldconfig"
    script.write_text(f"#!/bin/bash\nprintf '{len(libraries)} libs found in cache\\n{lines}'\n")
    script.chmod(0o755)


def run_check(bin_dir, *args):
    env = {"PATH": str(bin_dir), "HOME": os.environ.get("HOME", "/root")}
    return subprocess.run([shutil.which("bash"), str(CHECK), *args], capture_output=True, text=True,
                          env=env, timeout=60)


@pytest.mark.skipif(real_python311() is None, reason="needs python3.11")
def test_passes_when_everything_is_there(tmp_path):
    bin_dir = tool_dir(tmp_path)
    stub_ldconfig(bin_dir, LIBRARIES)
    run = run_check(bin_dir)
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""


@pytest.mark.skipif(real_python311() is None, reason="needs python3.11")
def test_missing_libraries_name_their_packages(tmp_path):
    bin_dir = tool_dir(tmp_path)
    stub_ldconfig(bin_dir, [])
    run = run_check(bin_dir)
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1
    assert f"sudo apt-get install {PACKAGES}" in lines[0]
    for lib in LIBRARIES:
        assert lib in lines[0]


@pytest.mark.skipif(real_python311() is None, reason="needs python3.11")
def test_only_the_missing_libraries_are_named(tmp_path):
    bin_dir = tool_dir(tmp_path)
    stub_ldconfig(bin_dir, [lib for lib in LIBRARIES if lib not in ("libGL.so.1", "libXi.so.6")])
    run = run_check(bin_dir)
    assert run.returncode != 0
    assert run.stderr.strip().endswith("sudo apt-get install libxi6 libgl1")


@pytest.mark.skipif(real_python311() is None, reason="needs python3.11")
def test_no_libs_mode_skips_the_library_check(tmp_path):
    bin_dir = tool_dir(tmp_path)
    stub_ldconfig(bin_dir, [])
    assert run_check(bin_dir, "--no-libs").returncode == 0


def test_missing_python_names_its_packages(tmp_path):
    bin_dir = tool_dir(tmp_path, with_python=False)
    stub_ldconfig(bin_dir, LIBRARIES)
    run = run_check(bin_dir)
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "sudo apt-get install python3.11 python3.11-venv" in lines[0]


def test_a_python_that_is_not_3_11_is_refused(tmp_path):
    bin_dir = tool_dir(tmp_path, with_python=False)
    fake = bin_dir / "python3.11"
    fake.write_text("#!/bin/bash\nexit 1\n")  # e.g. a pyenv shim without that version installed
    fake.chmod(0o755)
    run = run_check(bin_dir, "--no-libs")
    assert run.returncode != 0
    assert "python3.11 python3.11-venv" in run.stderr
