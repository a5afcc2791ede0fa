"""The farm this process bakes and builds on, if any: ``with use(farm): ...``.

``bake.driver.bake`` and ``model.dynamics.build_passive_dynamics`` run their work units on
:func:`current` when they are not given a farm, so callers that reach them through other layers
(the headless script through Blender's operators) need not pass one down. Nothing here imports
dask; without a farm in use the engine runs its units on local threads.
"""
import threading
from contextlib import contextmanager

_LOCK = threading.Lock()
_FARM = [None]


def current():
    """The :class:`~lmdp_addon.farm.cluster.Farm` in use, or None (local threads)."""
    return _FARM[0]


@contextmanager
def use(farm):
    """Within this block bakes and builds without a ``farm`` argument run on ``farm``."""
    with _LOCK:
        previous, _FARM[0] = _FARM[0], farm
    try:
        yield farm
    finally:
        with _LOCK:
            _FARM[0] = previous
