"""Engine tests: ``lmdp_addon`` imported from the repository root, never bpy.

The repository root goes on ``sys.path`` so that ``import lmdp_addon`` works exactly as it does
for scripts and benchmarks. Nothing in this layer may import bpy (see test_engine_imports.py).
"""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
