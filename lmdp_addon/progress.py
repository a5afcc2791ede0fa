"""Progress reporting and cancellation for long engine steps (sample, build, solve, bake).

The engine never talks to Blender: a step receives a ``Progress`` object, calls
``progress.update(fraction, message)`` between batches, and ``update`` raises
:class:`~lmdp_addon.errors.Cancelled` when the caller asked to stop. The Blender layer
subclasses it to drive ``window_manager.progress_*`` and to check for Esc; headless runs use
:class:`LogProgress`, which prints one line per step.
"""
import sys
import time

from .errors import Cancelled


class Progress:
    """Silent progress sink; subclass and override :meth:`emit` / :meth:`should_cancel`."""

    def __init__(self):
        self.step = ""
        self._step_start = time.perf_counter()

    def begin(self, step):
        """Start a named step (``"sample"``, ``"build"``, ``"solve"``, ``"bake"`` ...)."""
        self.step = step
        self._step_start = time.perf_counter()
        self.emit(step, 0.0, "started")

    def update(self, fraction, message=""):
        """Report ``fraction`` in [0, 1] of the current step; raise ``Cancelled`` if asked to."""
        if self.should_cancel():
            raise Cancelled(f"Cancelled during {self.step or 'work'}")
        self.emit(self.step, float(min(max(fraction, 0.0), 1.0)), message)

    def end(self, message=""):
        """Finish the current step; returns its wall time in seconds."""
        seconds = time.perf_counter() - self._step_start
        self.emit(self.step, 1.0, message or f"done in {seconds:.2f} s")
        return seconds

    # -- hooks ------------------------------------------------------------------------------
    def emit(self, step, fraction, message):
        """Show progress (default: nothing)."""

    def should_cancel(self):
        """Return True to make the next :meth:`update` raise ``Cancelled``."""
        return False


class LogProgress(Progress):
    """Headless progress: one line per step start/end (and sparse updates) on ``stream``."""

    def __init__(self, stream=None, prefix="LMDP", min_interval=5.0):
        super().__init__()
        self.stream = stream if stream is not None else sys.stderr
        self.prefix = prefix
        self.min_interval = min_interval
        self._last = 0.0

    def emit(self, step, fraction, message):
        now = time.perf_counter()
        final = fraction >= 1.0 or fraction == 0.0
        if not final and now - self._last < self.min_interval:
            return
        self._last = now
        print(f"[{self.prefix}] {step}: {100 * fraction:5.1f}% {message}", file=self.stream, flush=True)


class CallbackProgress(Progress):
    """Progress that forwards to ``emit_fn(step, fraction, message)`` and polls ``cancel_fn()``."""

    def __init__(self, emit_fn=None, cancel_fn=None):
        super().__init__()
        self._emit_fn = emit_fn
        self._cancel_fn = cancel_fn

    def emit(self, step, fraction, message):
        if self._emit_fn is not None:
            self._emit_fn(step, fraction, message)

    def should_cancel(self):
        return bool(self._cancel_fn()) if self._cancel_fn is not None else False
