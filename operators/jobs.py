"""Engine operators: read Blender data, compute without Blender, write the results back.

An LMDP operator subclasses :class:`EngineJob` (a mixin, before ``bpy.types.Operator``) and
implements three steps::

    class LMDP_OT_solve(EngineJob, bpy.types.Operator):
        bl_idname = "lmdp.solve"
        bl_label = "Solve"
        bl_options = {'REGISTER', 'UNDO'}
        stage = "solve"

        @classmethod
        def poll(cls, context):                     # may it run? (reads only; the reason if not)
            return ready(cls, context, selection=True, stage="dynamics")
        def prepare(self, context):                 # main thread: read bpy, check, may raise LMDPError
            return session_for(context.scene).require("dynamics")
        def compute(self, inputs, settings, progress):  # no bpy: may run in a worker thread
            return solvers.solve_desirability(inputs, settings, progress)
        def apply(self, context, result):           # main thread: write bpy data + session
            session_for(context.scene).store("solution", result, seconds=self.compute_seconds)
            return f"Solved in {result.iterations} iterations"   # the report message

``poll`` (:func:`ready`; the default refuses only while another job runs) greys the button out
with the reason as its tooltip, and ``bpy.ops`` raises ``RuntimeError`` with that reason in
scripts. ``prepare`` runs every check of the call once, on the main thread, and hands what the
checks computed to ``compute`` in its inputs, so the worker never checks again.
``execute`` (scripts, ``bpy.ops.lmdp.solve()``, headless) runs the three steps in turn and, in
background mode, prints one line per stage (:class:`~lmdp_addon.progress.LogProgress`).
``invoke`` (a button in the UI) runs ``compute`` in a worker thread while a modal timer shows
``window_manager.progress_*`` and a status-bar text; Esc sets the flag that
``Progress.should_cancel`` polls, so the engine raises :class:`~lmdp_addon.errors.Cancelled` at
its next ``progress.update``. ``apply`` runs only on the main thread, only after success: a
cancelled or failed job changes nothing. An :class:`~lmdp_addon.errors.LMDPError` from any step
is reported as an error and the operator returns ``{'CANCELLED'}``.
"""
import threading
import time

import bpy
from bpy.app.handlers import persistent

from ..lmdp_addon.errors import Cancelled, LMDPError, SceneError
from ..lmdp_addon.progress import LogProgress, Progress
from .common import WindowManagerProgress, report_error, selected_meshes
from .properties import settings_from_scene
from .session import MISSING_STAGE_MESSAGES, format_seconds, peek, session_for


class ThreadProgress(Progress):
    """Progress of a job in a worker thread.

    ``emit`` only records the latest ``(stage, fraction, message)`` under a lock (the main
    thread reads it with :meth:`snapshot`; Blender is never called from the worker), and
    ``should_cancel`` polls ``cancel_event``. ``echo`` (another Progress, e.g. a LogProgress to
    the console) receives every emit too.
    """

    def __init__(self, cancel_event=None, echo=None):
        super().__init__()
        self.cancel_event = cancel_event if cancel_event is not None else threading.Event()
        self.echo = echo
        self._lock = threading.Lock()
        self._state = ("", 0.0, "")

    def emit(self, stage, fraction, message):
        with self._lock:
            self._state = (stage, fraction, message)
        if self.echo is not None:
            self.echo.emit(stage, fraction, message)

    def should_cancel(self):
        return self.cancel_event.is_set()

    def snapshot(self):
        """The latest ``(stage, fraction, message)``."""
        with self._lock:
            return self._state


class JobRunner:
    """Runs ``compute(inputs, settings, progress)`` in a daemon thread.

    ``cancel()`` asks the engine to stop (its next ``progress.update`` raises ``Cancelled``);
    ``outcome()`` returns the result or raises the error; a job cancelled after its computation
    finished still counts as cancelled, so nothing is applied.
    """

    def __init__(self, compute, inputs, settings, *, name="LMDP job", echo=None):
        self.name = name
        self._compute = compute
        self.inputs = inputs
        self.settings = settings
        self.cancel_event = threading.Event()
        self.progress = ThreadProgress(self.cancel_event, echo=echo)
        self.result = None
        self.error = None
        self.seconds = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self):
        start = time.perf_counter()
        try:
            self.result = self._compute(self.inputs, self.settings, self.progress)
        except BaseException as error:  # handed to the main thread by outcome()
            self.error = error
        finally:
            self.seconds = time.perf_counter() - start
            self._done.set()

    def start(self):
        self._thread.start()
        return self

    def cancel(self):
        self.cancel_event.set()

    @property
    def cancelled(self):
        return self.cancel_event.is_set()

    @property
    def done(self):
        return self._done.is_set()

    def wait(self, timeout=None):
        """Block until the job ends (or ``timeout`` seconds); True when it has ended."""
        return self._done.wait(timeout)

    def snapshot(self):
        return self.progress.snapshot()

    def outcome(self):
        """The result of a finished job; raises its error, or ``Cancelled`` if it was cancelled."""
        if not self.done:
            raise RuntimeError(f"{self.name} is still running")
        if self.error is not None:
            raise self.error
        if self.cancelled:
            raise Cancelled(f"{self.name} was cancelled")
        return self.result


def staged_compute(compute, stage):
    """``compute`` wrapped in ``progress.begin(stage)`` / ``progress.end()`` (nothing if no stage)."""
    def run(inputs, settings, progress):
        if stage:
            progress.begin(stage)
        result = compute(inputs, settings, progress)
        if stage:
            progress.end()
        return result
    return run


# The job running in the UI, if any: one at a time (the machine's cores are the bottleneck and
# two jobs writing the same session would race).
_active = {"runner": None, "label": ""}


def running_job():
    """``(label, (stage, fraction, message))`` of the job running in the UI, or None."""
    runner = _active["runner"]
    if runner is None or runner.done:
        return None
    return _active["label"], runner.snapshot()


def cancel_running_job():
    """Ask the running UI job, if any, to stop; True if there was one."""
    runner = _active["runner"]
    if runner is None or runner.done:
        return False
    runner.cancel()
    return True


def _busy_message():
    job = running_job()
    return f"Another LMDP job is running ({job[0]}): wait for it or press Esc to cancel it" if job else ""


def _check_idle():
    message = _busy_message()
    if message:
        raise LMDPError(message)


def ready(cls, context, selection=False, stage=None, message=None):
    """``poll()`` of an LMDP operator class ``cls``: False, with the reason set as its poll message,
    while another job runs, without a mesh selection (``selection``) or without the session's
    ``stage`` (``message``: what to say then; default "Solve first" ...). Reads only: never
    creates the session, so it is safe wherever Blender polls (panel drawing included)."""
    reason = _busy_message()
    if not reason and selection:
        try:
            selected_meshes(context, evaluate=False)
        except SceneError as error:
            reason = str(error)
    if not reason and stage is not None:
        session = peek(getattr(context, "scene", None))
        if session is None or not session.has(stage):
            reason = message or MISSING_STAGE_MESSAGES[stage]
    if reason:
        cls.poll_message_set(reason)
        return False
    return True


class EngineJob:
    """Mixin for operators that run engine work; see the module docstring.

    Subclasses set ``stage`` (the name shown in progress lines, e.g. ``"solve"``; leave it empty
    when ``compute`` calls ``progress.begin/end`` for several stages itself) and implement
    :meth:`prepare`, :meth:`compute` and :meth:`apply`. While the steps run, ``self.settings``
    holds the engine :class:`~lmdp_addon.settings.Settings`; during ``apply``,
    ``self.compute_seconds`` holds the wall time of ``compute``.
    """

    stage = ""
    #: seconds between progress refreshes of the modal UI job
    timer_interval = 0.1

    @classmethod
    def poll(cls, context):
        return ready(cls, context)

    # -- the three steps subclasses implement -----------------------------------------------------
    def read_settings(self, context):
        """The engine settings for this run (default: ``scene.lmdp``)."""
        return settings_from_scene(context.scene)

    def prepare(self, context):
        """Main thread: read Blender data into plain inputs for :meth:`compute`."""
        return None

    def compute(self, inputs, settings, progress):
        """No bpy access: the engine work. May run in a worker thread."""
        raise NotImplementedError(f"{type(self).__name__} must implement compute()")

    def apply(self, context, result):
        """Main thread, after success only: write Blender data and the session; return the
        report message. Validate before writing so that an error leaves nothing half-written."""
        raise NotImplementedError(f"{type(self).__name__} must implement apply()")

    # -- synchronous path ---------------------------------------------------------------------------
    def execute(self, context):
        try:
            _check_idle()
            self.settings = self.read_settings(context)
            inputs = self.prepare(context)
            progress = self._sync_progress(context)
            start = time.perf_counter()
            try:
                result = staged_compute(self.compute, self.stage)(inputs, self.settings, progress)
            finally:
                if isinstance(progress, WindowManagerProgress):
                    progress.close()
            return self._finish(context, result, time.perf_counter() - start)
        except Exception as error:
            return report_error(self, error)

    def _sync_progress(self, context):
        if bpy.app.background:
            return LogProgress(prefix="LMDP")
        if getattr(context, "window_manager", None) is not None and getattr(context, "window", None):
            return WindowManagerProgress(context.window_manager)
        return Progress()

    def _finish(self, context, result, seconds):
        self.compute_seconds = seconds
        message = self.apply(context, result)
        if not message:
            message = f"{self.bl_label}: done in {format_seconds(seconds)}"
        session_for(context.scene).note(self.stage or self.bl_idname, message)
        self.report({'INFO'}, message)
        return {'FINISHED'}

    # -- threaded path (UI) ------------------------------------------------------------------------
    def invoke(self, context, event):
        if bpy.app.background or getattr(context, "window", None) is None:
            return self.execute(context)
        try:
            _check_idle()
            self.settings = self.read_settings(context)
            inputs = self.prepare(context)
        except Exception as error:
            return report_error(self, error)

        self._runner = JobRunner(staged_compute(self.compute, self.stage), inputs, self.settings,
                                 name=f"LMDP {self.bl_label}")
        _active["runner"], _active["label"] = self._runner, self.bl_label
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(self.timer_interval, window=context.window)
        window_manager.progress_begin(0, WindowManagerProgress.STEPS)
        window_manager.modal_handler_add(self)
        self._set_status(context, f"LMDP {self.bl_label}: starting (Esc to cancel)")
        self._runner.start()
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        runner = self._runner
        if event.type == 'ESC' and event.value == 'PRESS':
            runner.cancel()
            self._set_status(context, f"LMDP {self.bl_label}: cancelling...")
            return {'RUNNING_MODAL'}
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        if not runner.done:
            stage, fraction, message = runner.snapshot()
            context.window_manager.progress_update(int(round(fraction * WindowManagerProgress.STEPS)))
            text = f"LMDP {self.bl_label}: {stage} {100.0 * fraction:.0f}% {message}".rstrip()
            self._set_status(context, f"{text} (Esc to cancel)")
            _tag_redraw(context)
            return {'PASS_THROUGH'}

        self._end_ui(context)
        try:
            result = runner.outcome()
        except Cancelled as error:
            self.report({'WARNING'}, f"{self.bl_label} cancelled: nothing was changed ({error})")
            return {'CANCELLED'}
        except Exception as error:
            return report_error(self, error)
        try:
            return self._finish(context, result, runner.seconds)
        except Exception as error:
            return report_error(self, error)

    def cancel(self, context):
        """Blender ends the modal operator (file load, window closed): stop the worker too."""
        runner = getattr(self, "_runner", None)
        if runner is not None:
            runner.cancel()
        self._end_ui(context)

    def _end_ui(self, context):
        timer = getattr(self, "_timer", None)
        if timer is not None:
            context.window_manager.event_timer_remove(timer)
            self._timer = None
            context.window_manager.progress_end()
        if _active["runner"] is getattr(self, "_runner", None):
            _active["runner"], _active["label"] = None, ""
        self._set_status(context, None)
        _tag_redraw(context)

    @staticmethod
    def _set_status(context, text):
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(text)


def _tag_redraw(context):
    screen = getattr(context, "screen", None)
    for area in (screen.areas if screen is not None else ()):
        if area.type == 'VIEW_3D':
            area.tag_redraw()


@persistent
def _on_load_pre(*_args):
    cancel_running_job()


def register():
    if _on_load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load_pre)


def unregister():
    cancel_running_job()
    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
