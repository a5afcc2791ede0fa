"""Engine tests: ``lmdp_addon`` imported from the repository root, never bpy.

The repository root goes on ``sys.path`` so that ``import lmdp_addon`` works exactly as it does
for scripts and benchmarks. Nothing in this layer may import bpy (see test_engine_imports.py).
"""
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@pytest.fixture(scope="module")
def cornell():
    """The built-in Cornell box as scene arrays (a module may define its own ``cornell``)."""
    from lmdp_addon import demo_geometry
    return demo_geometry.build_scene_arrays("CORNELL_BOX")


@pytest.fixture(scope="module")
def cornell_solved(cornell):
    """``cornell`` sampled, built and solved with 512 points (the defaults otherwise)."""
    from lmdp_addon.model import pipeline
    from lmdp_addon.settings import Settings
    return pipeline.run_all(cornell, Settings(point_count=512))
