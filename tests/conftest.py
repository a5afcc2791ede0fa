"""Test setup shared by every layer.

* ``BLENDER_USER_RESOURCES`` is pointed at a temporary directory *here, at import time*, before
  any test module can import bpy: Blender reads it once, when bpy is imported, for its
  preferences, extension repositories and installed wheels. The user's own Blender setup is
  never read or written by the tests.
* Tests marked ``@pytest.mark.slow`` run only with ``LMDP_SLOW_TESTS=1`` (``make test-all``).

Layers: ``tests/engine`` (lmdp_addon, never bpy), ``tests/addon`` (the extension loaded into
bpy through Blender's extension repositories), ``tests/tools`` (Makefile, scripts, manifest).
"""
import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

if "bpy" in sys.modules:
    raise RuntimeError("bpy was imported before tests/conftest.py could set BLENDER_USER_RESOURCES")

USER_RESOURCES = tempfile.mkdtemp(prefix="lmdp_blender_user_")
os.environ["BLENDER_USER_RESOURCES"] = USER_RESOURCES
atexit.register(shutil.rmtree, USER_RESOURCES, True)


def slow_tests_enabled():
    return os.environ.get("LMDP_SLOW_TESTS", "") not in ("", "0")


def pytest_collection_modifyitems(config, items):
    if slow_tests_enabled():
        return
    skip = pytest.mark.skip(reason="slow: run with `make test-all` (LMDP_SLOW_TESTS=1)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def repo_root():
    """The repository root (= the extension root)."""
    return ROOT


@pytest.fixture(scope="session")
def venv_python():
    """The interpreter running the tests (the project's .venv under `make test`)."""
    return sys.executable
