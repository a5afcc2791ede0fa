"""Helpers shared by the LMDP operators: selection, error reporting, synchronous UI progress."""
import traceback

import bpy

from ..lmdp_addon.errors import LMDPError, SceneError
from ..lmdp_addon.progress import Progress

#: Pipeline operators in stage order (the public scripting API; see README.md).
PIPELINE_OPERATORS = (
    "lmdp.sample_states",
    "lmdp.build_dynamics",
    "lmdp.solve",
    "lmdp.show_desirability",
    "lmdp.show_policy",
    "lmdp.bake",
    "lmdp.run_pipeline",
    "lmdp.export_npz",
)

#: Operators of the pipeline that work on the selected meshes.
SELECTION_OPERATORS = PIPELINE_OPERATORS[:-1]


def selected_meshes(context):
    """The selected mesh objects, in a stable (name) order.

    Raises :class:`SceneError` with a message for the user when nothing is selected or the
    selection holds no mesh: the selected meshes are the ones that carry LMDP states.
    """
    selected = list(getattr(context, "selected_objects", None) or ())
    if not selected:
        raise SceneError("Select at least one mesh object: nothing is selected "
                         "(the selected meshes carry the LMDP states)")
    meshes = [obj for obj in selected if obj.type == 'MESH']
    if not meshes:
        names = ", ".join(sorted(obj.name for obj in selected)[:5])
        more = "" if len(selected) <= 5 else f" and {len(selected) - 5} more"
        raise SceneError(f"Select at least one mesh object: the selection ({names}{more}) "
                         "has no mesh (the selected meshes carry the LMDP states)")
    return sorted(meshes, key=lambda obj: obj.name)


def operator_idname_to_type(idname):
    """``'lmdp.solve'`` -> ``'LMDP_OT_solve'``, the name Blender registers the operator type under."""
    category, _, name = idname.partition(".")
    return f"{category.upper()}_OT_{name}"


def operator_available(idname):
    """True when the operator ``idname`` (``'lmdp.solve'``) is registered."""
    return hasattr(bpy.types, operator_idname_to_type(idname))


def available_operators(idnames=PIPELINE_OPERATORS):
    """The registered subset of ``idnames``, in order."""
    return [idname for idname in idnames if operator_available(idname)]


def call_operator(idname, *args, **kwargs):
    """Call ``bpy.ops.<idname>(...)``; returns its result set (raises like ``bpy.ops`` does)."""
    category, _, name = idname.partition(".")
    return getattr(getattr(bpy.ops, category), name)(*args, **kwargs)


def report_error(operator, error):
    """Report ``error`` on ``operator`` and return ``{'CANCELLED'}``.

    An :class:`LMDPError` carries a message written for the user and is shown as is; anything
    else is a bug: its traceback goes to the console and the user is told where to look.
    """
    if isinstance(error, LMDPError):
        operator.report({'ERROR'}, str(error))
    else:
        traceback.print_exception(type(error), error, error.__traceback__)
        operator.report({'ERROR'}, f"Internal error in {operator.bl_idname}: "
                                   f"{type(error).__name__}: {error} (traceback in the system console)")
    return {'CANCELLED'}


def report_warnings(operator, warnings, limit=5):
    """Report each engine warning (``SceneArrays.warnings`` ...) as a WARNING, at most ``limit``."""
    warnings = list(warnings or ())
    for text in warnings[:limit]:
        operator.report({'WARNING'}, str(text))
    if len(warnings) > limit:
        operator.report({'WARNING'}, f"... and {len(warnings) - limit} more warnings")


class WindowManagerProgress(Progress):
    """Synchronous progress in the UI: ``window_manager.progress_*`` (call on the main thread).

    Used by an operator's ``execute`` when Blender has a window; ``invoke`` runs the engine in a
    thread instead (see :mod:`.jobs`), where Esc can cancel.
    """

    STEPS = 1000

    def __init__(self, window_manager):
        super().__init__()
        self.window_manager = window_manager
        self._open = False

    def emit(self, stage, fraction, message):
        if not self._open:
            self.window_manager.progress_begin(0, self.STEPS)
            self._open = True
        self.window_manager.progress_update(int(round(fraction * self.STEPS)))

    def close(self):
        if self._open:
            self.window_manager.progress_end()
            self._open = False
