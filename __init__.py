"""LMDP Light Transport: light transport as a linearly-solvable optimal control problem.

Blender extension entry point: registration only. The engine lives in ``lmdp_addon`` (no bpy),
the Blender layer in ``operators``; see README.md and docs/design.md.
"""
from . import operators


def register():
    operators.register()


def unregister():
    operators.unregister()
