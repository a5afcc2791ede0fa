"""The per-scene session store: the latest result of every LMDP stage, in memory only.

This is the add-on's one cache (STYLE.md: no other global caches). The engine's stages are kept
as one :class:`~lmdp_addon.model.pipeline.LMDPResult` (:attr:`SceneSession.result`: ``scene``,
``states``, ``dynamics``, ``lmdp``, ``solution`` and the engine steps' ``seconds``), the very
object the bake and the export take; the add-on's own stages (``policy``, ``display``,
``bake``) sit beside it. Nothing here is written into the .blend file except
``scene.lmdp.session_id``, a random key that ties a scene to its session (so renaming a scene
keeps its results and a copied scene starts empty). Every session is dropped when a file is
loaded.

Stages form a dependency graph (:data:`STAGE_INPUTS`): storing a stage, or
:meth:`SceneSession.invalidate_from`, clears that stage and everything computed from it, so the
session never holds a solution of dynamics that are no longer there. A stored ``LMDPResult`` is
never changed in place: storing makes a new one, so a job that holds the previous one keeps a
consistent set of stages.

Results are tied to Blender objects by ``session_uid`` (:func:`captured_index`), never by name.

Only the main thread touches the store (operators write it in ``apply``; the panel and the
operators' ``poll`` read it with :func:`peek`).
"""
import numbers
import time
import uuid
from collections import deque
from dataclasses import replace

import bpy
from bpy.app.handlers import persistent

from ..lmdp_addon.errors import StageOrderError
from ..lmdp_addon.model.pipeline import LMDPResult
from .adapters.extract import object_fingerprint

#: stage -> the stages it is computed from (in pipeline order).
STAGE_INPUTS = {
    "scene": (),
    "states": ("scene",),
    "dynamics": ("states",),
    "lmdp": ("dynamics",),
    "solution": ("lmdp",),
    "policy": ("solution",),
    "display": ("solution",),
    "bake": ("scene", "solution"),
}
STAGES = tuple(STAGE_INPUTS)
#: The engine's stages: the fields of ``LMDPResult``, held in :attr:`SceneSession.result`.
ENGINE_STAGES = ("scene", "states", "dynamics", "lmdp", "solution")
#: The ``LMDPResult.seconds`` key of the engine step that computes a stage.
STEP_OF_STAGE = {"states": "sample", "dynamics": "build", "solution": "solve"}

#: What to tell the user when a stage is required but missing.
MISSING_STAGE_MESSAGES = {
    "scene": "Sample the states first (LMDP panel > Sample)",
    "states": "Sample the states first (LMDP panel > Sample)",
    "dynamics": "Build the dynamics first (LMDP panel > Build)",
    "lmdp": "Build the dynamics first (LMDP panel > Build)",
    "solution": "Solve first (LMDP panel > Solve)",
    "policy": "Solve first (LMDP panel > Solve)",
    "display": "Show the desirability first (LMDP panel > Show)",
    "bake": "Bake first (LMDP panel > Bake)",
}

MAX_MESSAGES = 20


def downstream(stage):
    """``stage`` and every stage computed from it, directly or not, in :data:`STAGES` order."""
    if stage not in STAGE_INPUTS:
        raise KeyError(f"unknown LMDP stage {stage!r}; known stages: {', '.join(STAGES)}")
    found = {stage}
    for candidate in STAGES:  # STAGES is topologically ordered
        if any(parent in found for parent in STAGE_INPUTS[candidate]):
            found.add(candidate)
    return [s for s in STAGES if s in found]


class SceneSession:
    """Results, timings and messages of the LMDP stages of one scene."""

    def __init__(self, scene_name):
        self.scene_name = scene_name
        self.result = LMDPResult(scene=None)  #: the engine stages (never changed in place)
        self._own = {}             #: policy / display / bake -> result
        self._seconds = {}         #: wall time of the stages without an engine step
        self.object_names = ()     #: names of the meshes that carry the states
        self.messages = deque(maxlen=MAX_MESSAGES)  #: (time, stage, level, text), newest last

    # -- stage results ----------------------------------------------------------------------------
    def get(self, stage, default=None):
        downstream(stage)  # validates the name
        value = getattr(self.result, stage) if stage in ENGINE_STAGES else self._own.get(stage)
        return default if value is None else value

    def has(self, stage):
        return self.get(stage) is not None

    def require(self, stage, message=None):
        """The result of ``stage``; raises :class:`StageOrderError` ("Solve first") if missing."""
        result = self.get(stage)
        if result is None:
            raise StageOrderError(message or MISSING_STAGE_MESSAGES[stage])
        return result

    @property
    def results(self):
        """``{stage: result}`` of every stored stage, in :data:`STAGES` order."""
        return {stage: self.get(stage) for stage in STAGES if self.has(stage)}

    @property
    def timings(self):
        """``{stage: wall time in seconds}`` of the stored stages that have one."""
        seconds = {}
        for stage in STAGES:
            value = self.result.seconds.get(STEP_OF_STAGE[stage]) if stage in STEP_OF_STAGE \
                else self._seconds.get(stage)
            if value is not None and self.has(stage):
                seconds[stage] = value
        return seconds

    def store(self, stage, result, *, seconds=None):
        """Keep ``result`` as the latest ``stage``; clears every stage computed from the old one."""
        self.invalidate_from(stage)
        if stage in ENGINE_STAGES:
            times = dict(self.result.seconds)
            if seconds is not None and stage in STEP_OF_STAGE:
                times[STEP_OF_STAGE[stage]] = float(seconds)
            self.result = replace(self.result, **{stage: result}, seconds=times)
        else:
            self._own[stage] = result
        if seconds is not None and stage not in STEP_OF_STAGE:
            self._seconds[stage] = float(seconds)

    def store_result(self, result, object_names):
        """Keep the engine's ``LMDPResult`` of a whole run (Run All) and the meshes that carry
        its states; clears every stage of the previous run."""
        self.invalidate_from("scene")
        self.result = result
        self.object_names = tuple(object_names)

    def invalidate_from(self, stage):
        """Forget ``stage`` and everything downstream of it; returns the stages that were set."""
        stages = downstream(stage)
        cleared = [name for name in stages if self.has(name)]
        engine = [name for name in stages if name in ENGINE_STAGES]
        if engine:
            steps = {STEP_OF_STAGE.get(name) for name in engine}
            self.result = replace(self.result, **{name: None for name in engine},
                                  seconds={k: v for k, v in self.result.seconds.items() if k not in steps})
        for name in stages:
            self._own.pop(name, None)
            self._seconds.pop(name, None)
        return cleared

    def clear(self):
        self.invalidate_from("scene")
        self.messages.clear()
        self.object_names = ()

    # -- messages ---------------------------------------------------------------------------------
    def note(self, stage, text, level="INFO"):
        """Remember a message shown to the user (the panel shows the latest ones)."""
        self.messages.append((time.time(), stage, level, str(text)))

    @property
    def last_message(self):
        return self.messages[-1][3] if self.messages else ""

    # -- summaries for the panel ------------------------------------------------------------------
    def status_lines(self):
        """``[(stage, text)]`` for every stored stage: counts, memory, wall time."""
        lines = []
        timings = self.timings
        for stage, result in self.results.items():
            parts = [describe(result)]
            nbytes = result_nbytes(result)
            if nbytes:
                parts.append(format_bytes(nbytes))
            if stage in timings:
                parts.append(format_seconds(timings[stage]))
            lines.append((stage, ", ".join(p for p in parts if p)))
        return lines


# -- describing results (engine results are plain objects; no protocol is required) ------------------
_COUNT_ATTRIBUTES = (
    ("n_triangles", "triangles"), ("n_points", "points"), ("n_states", "states"),
    ("n_terminals", "terminals"), ("nnz", "non-zeros"), ("iterations", "iterations"),
    ("residual", "residual"), ("n_texels", "texels"),
)


def describe(result):
    """Short text for a stage result: its ``summary()`` if it has one, else its counts."""
    summary = getattr(result, "summary", None)
    if callable(summary):
        try:
            text = summary()
        except Exception as ex:  # a summary must never break the panel
            text = f"(summary failed: {ex})"
        if isinstance(text, str):
            return text
    parts = []
    for attribute, label in _COUNT_ATTRIBUTES:
        value = getattr(result, attribute, None)
        if isinstance(value, bool) or not isinstance(value, numbers.Number):
            continue
        if isinstance(value, numbers.Integral):
            parts.append(f"{int(value):,} {label}")
        else:
            parts.append(f"{label} {float(value):.3g}")
    return ", ".join(parts) if parts else type(result).__name__


def result_nbytes(result):
    """Bytes held by the numpy arrays / scipy sparse matrices that are attributes of ``result``."""
    try:
        values = vars(result).values()
    except TypeError:
        return 0
    total = 0
    for value in values:
        nbytes = getattr(value, "nbytes", None)
        if isinstance(nbytes, numbers.Integral):
            total += int(nbytes)
            continue
        for part in ("data", "indices", "indptr"):  # scipy.sparse
            nbytes = getattr(getattr(value, part, None), "nbytes", None)
            if isinstance(nbytes, numbers.Integral):
                total += int(nbytes)
    return total


def format_bytes(nbytes):
    for unit in ("B", "KiB", "MiB", "GiB"):
        if nbytes < 1024 or unit == "GiB":
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024.0
    return ""


def format_seconds(seconds):
    if seconds < 1.0:
        return f"{1000.0 * seconds:.0f} ms"
    if seconds < 120.0:
        return f"{seconds:.2f} s"
    return f"{seconds / 60.0:.1f} min"


# -- the objects of the captured scene ----------------------------------------------------------------
# Results are tied to Blender objects by ``session_uid`` (adapters.extract.CapturedScene), never
# by name: renaming or swapping names keeps each object's states on that object.

def captured_lookup(scene):
    """A function ``obj -> index of the Blender object obj in the captured scene, or None``,
    matched by ``session_uid`` (renames do not matter; a plain ``SceneArrays`` without
    ``object_uids`` is matched by name)."""
    uids = getattr(scene, "object_uids", None)
    if uids is None:
        by_name = {}
        for index, name in enumerate(scene.object_names):
            by_name.setdefault(name, index)
        return lambda obj: by_name.get(obj.name)
    by_uid = {}
    for index, uid in enumerate(uids.tolist()):
        if uid >= 0:
            by_uid.setdefault(uid, index)
    return lambda obj: by_uid.get(obj.session_uid)


def captured_index(scene, obj):
    """Index of the Blender object ``obj`` in the captured ``scene`` or None (:func:`captured_lookup`)."""
    return captured_lookup(scene)(obj)


def changed_since_capture(scene, index, obj):
    """True when the mesh or the transform of ``obj`` (object ``index`` of ``scene``) changed
    since the capture."""
    fingerprints = getattr(scene, "object_fingerprints", None)
    known = fingerprints[index] if fingerprints is not None else None
    return bool(known) and known != object_fingerprint(obj)


def current_names(scene, view_layer=None):
    """The object names of ``scene`` as they are now: a renamed object's new name (objects that
    no longer exist keep their captured name)."""
    uids = getattr(scene, "object_uids", None)
    if uids is None:
        return list(scene.object_names)
    objects = view_layer.objects if view_layer is not None else bpy.data.objects
    by_uid = {obj.session_uid: obj.name for obj in objects}
    return [by_uid.get(int(uid), name) for uid, name in zip(uids, scene.object_names)]


# -- the store ----------------------------------------------------------------------------------------
_sessions = {}  # session_id -> SceneSession


def _lookup(scene):
    """The session of ``scene`` or None; never writes Blender data (safe in draw callbacks)."""
    session_id = scene.lmdp.session_id
    session = _sessions.get(session_id) if session_id else None
    if session is None:
        return None
    if session.scene_name != scene.name_full:
        # Either the scene was renamed (keep its results) or it is a copy of the scene that owns
        # the session (Blender copies the session_id with the scene): a copy starts empty.
        for other in bpy.data.scenes:
            if other != scene and other.name_full == session.scene_name and \
                    other.lmdp.session_id == session_id:
                return None
        session.scene_name = scene.name_full
    return session


def peek(scene):
    """The session of ``scene`` if it has one, else None. Safe to call from ``Panel.draw``."""
    if scene is None or getattr(scene, "lmdp", None) is None:
        return None
    return _lookup(scene)


def session_for(scene):
    """The session of ``scene``, created on first use (may write ``scene.lmdp.session_id``).

    Call from an operator on the main thread, not from a draw callback.
    """
    session = _lookup(scene)
    if session is not None:
        return session
    _prune()
    session_id = scene.lmdp.session_id
    if not session_id or session_id in _sessions:  # no id yet, or a copy of another scene's id
        session_id = uuid.uuid4().hex
        scene.lmdp.session_id = session_id
    session = _sessions[session_id] = SceneSession(scene.name_full)
    return session


def _prune():
    """Drop sessions of scenes that no longer exist."""
    alive = {scene.lmdp.session_id for scene in bpy.data.scenes if scene.lmdp.session_id}
    for session_id in list(_sessions):
        if session_id not in alive:
            del _sessions[session_id]


def remove(scene):
    """Forget every result of ``scene``."""
    session = _lookup(scene)
    if session is not None:
        del _sessions[scene.lmdp.session_id]


def clear_all():
    """Forget every session (a new file is being loaded, or the add-on is disabled)."""
    _sessions.clear()


def all_sessions():
    """``{session_id: SceneSession}`` snapshot (for tests and diagnostics)."""
    return dict(_sessions)


@persistent
def _on_load_pre(*_args):
    clear_all()


def register():
    if _on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load_pre)


def unregister():
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    clear_all()
