"""Helpers shared by the LMDP operators: selection, error reporting, synchronous UI progress."""
import traceback

import bmesh
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


class MeshSelection(list):
    """The selected meshes that can carry states (a list, in name order), and ``skipped``:
    ``[(object, reason)]`` for the selected meshes that cannot (no faces ...), which
    :func:`~.adapters.extract.extract_scene` reports as warnings when given this list."""

    def __init__(self, meshes, skipped=()):
        super().__init__(meshes)
        self.skipped = list(skipped)


def mode_holding_mesh(obj):
    """"Edit Mode" or "Sculpt Mode with Dynamic Topology" when the mesh of ``obj`` lives in a
    BMesh that reaches ``obj.data`` only when that mode is left (attributes written into the
    mesh meanwhile are lost), else None."""
    if obj.type != 'MESH':
        return None
    if obj.data.is_editmode:
        return "Edit Mode"
    if obj.mode == 'SCULPT' and getattr(obj, "use_dynamic_topology_sculpting", False):
        return "Sculpt Mode with Dynamic Topology"
    return None


def face_count(obj, context=None, instancers=None):
    """Faces of the mesh object ``obj`` as the LMDP captures it.

    With ``context`` and modifiers: the faces of the evaluated mesh (modifiers may make faces,
    like Screw or Skin, or remove them all). Otherwise the faces of its mesh, in Edit Mode those
    of the edit mesh (what the user sees). An object whose instances carry its states (vertex /
    face instancing, geometry-nodes instances: its ``session_uid`` in ``instancers``) counts as
    1 face; so does, without ``context`` (``poll``, which never evaluates the depsgraph), a
    faceless mesh with modifiers or instancing."""
    mesh = obj.data
    if context is not None and obj.modifiers:
        evaluated = obj.evaluated_get(context.evaluated_depsgraph_get())
        count = len(evaluated.data.polygons) if evaluated.data is not None else 0
    elif mesh.is_editmode:
        count = len(bmesh.from_edit_mesh(mesh).faces)
    else:
        count = len(mesh.polygons)
    if count:
        return count
    if context is None:
        return int(bool(obj.modifiers) or obj.instance_type != 'NONE')
    return int(instancers is not None and obj.session_uid in instancers)


def instancer_uids(context):
    """``session_uid`` of every object whose evaluated instances are in ``context``'s depsgraph."""
    return {inst.parent.original.session_uid for inst in context.evaluated_depsgraph_get().object_instances
            if inst.is_instance and inst.parent is not None}


def no_faces_reason(obj):
    """Why the mesh object ``obj`` (:func:`face_count` 0) carries no states: "has no vertices",
    "has no faces", "has no faces after its modifiers"..."""
    mesh = obj.data
    if obj.modifiers and (mesh.is_editmode or len(mesh.polygons)):
        return "has no faces after its modifiers"
    if mesh.is_editmode:
        return "has no faces (in Edit Mode)"
    return "has no faces" if len(mesh.vertices) else "has no vertices"


def selected_meshes(context, evaluate=True):
    """The selected mesh objects that can carry states, in a stable (name) order (:class:`MeshSelection`).

    Raises :class:`SceneError` with a message for the user when nothing is selected or the
    selection holds no such mesh: the selected meshes are the ones that carry LMDP states.
    Selected meshes without faces or disabled in renders (which the capture ignores) are left
    out and listed in ``skipped``, so every operator treats them alike. ``evaluate=False`` (``poll``): never evaluate the depsgraph
    (see :func:`face_count`).
    """
    selected = list(getattr(context, "selected_objects", None) or ())
    if not selected:
        raise SceneError("Select at least one mesh object: nothing is selected "
                         "(the selected meshes carry the LMDP states)")
    meshes = sorted((obj for obj in selected if obj.type == 'MESH'), key=lambda obj: obj.name)
    if not meshes:
        names = ", ".join(sorted(obj.name for obj in selected)[:5])
        more = "" if len(selected) <= 5 else f" and {len(selected) - 5} more"
        raise SceneError(f"Select at least one mesh object: the selection ({names}{more}) "
                         "has no mesh (the selected meshes carry the LMDP states)")
    usable, skipped, instancers = [], [], None
    for obj in meshes:
        if obj.hide_render:  # the capture ignores it, as Cycles does
            skipped.append((obj, "is disabled in renders (camera icon off)"))
            continue
        if evaluate and instancers is None and not face_count(obj, context):
            instancers = instancer_uids(context)  # once, and only for a faceless mesh
        if face_count(obj, context if evaluate else None, instancers):
            usable.append(obj)
        else:
            skipped.append((obj, no_faces_reason(obj)))
    if not usable:
        listed = "; ".join(f"'{obj.name}' {reason}" for obj, reason in skipped[:5])
        more = "" if len(skipped) <= 5 else f" and {len(skipped) - 5} more"
        raise SceneError(f"Select at least one mesh object that can carry states: {listed}{more} "
                         "(LMDP states lie on the faces of rendered meshes)")
    return MeshSelection(usable, skipped)


def skipped_mesh_messages(selection):
    """One warning per selected mesh :func:`selected_meshes` left out, naming it."""
    return [f"Skipped '{obj.name}': it {reason}, so it carries no LMDP states"
            for obj, reason in getattr(selection, "skipped", ())]


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
    """Report each engine warning (``SceneArrays.warnings`` ...) as a WARNING, the first ``limit``
    one by one and the rest in one last line (so none goes unnamed)."""
    warnings = list(warnings or ())
    for text in warnings[:limit]:
        operator.report({'WARNING'}, str(text))
    if len(warnings) > limit:
        operator.report({'WARNING'}, f"... and {len(warnings) - limit} more warnings: "
                                     + " | ".join(str(text) for text in warnings[limit:]))


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
