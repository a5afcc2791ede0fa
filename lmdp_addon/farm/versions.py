"""What a farm's client and its workers must agree on: the engine's sources and the versions of
its dependencies. Plain Python, no dask: the workers run :func:`probe` as well."""
import hashlib
import importlib
import os
import platform
import socket

from ..errors import LMDPError

#: The engine's dependencies a worker must have, as the module names that are imported.
DEPENDENCIES = ("numpy", "scipy", "embreex")
#: The engine package's directory (its ``*.py`` sources are hashed).
ENGINE_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def engine_version():
    """``"<first 12 hex digits of sha256>"`` of the engine's sources: every ``*.py`` under
    ``lmdp_addon/`` by relative path and content, so two checkouts agree exactly when their
    engines would compute the same thing."""
    digest = hashlib.sha256()
    for root, dirs, files in os.walk(ENGINE_DIR):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(root, name)
            digest.update(os.path.relpath(path, ENGINE_DIR).replace(os.sep, "/").encode())
            digest.update(b"\0")
            with open(path, "rb") as fh:
                digest.update(fh.read())
            digest.update(b"\0")
    return digest.hexdigest()[:12]


def dependency_versions():
    """``{module: version}`` of :data:`DEPENDENCIES` and Python (``"missing"`` where a module
    cannot be imported)."""
    found = {"python": platform.python_version()}
    for name in DEPENDENCIES:
        try:
            module = importlib.import_module(name)
        except ImportError:
            found[name] = "missing"
            continue
        found[name] = str(getattr(module, "__version__", "unknown"))
    return found


def probe():
    """``{"engine": engine_version(), **dependency_versions()}`` of this process."""
    return {"engine": engine_version(), **dependency_versions()}


class FarmError(LMDPError):
    """The farm cannot be used: dask missing, scheduler unreachable, a worker that differs."""


class EngineMismatch(FarmError):
    """A worker that joined after the connect check runs another engine (raised by its first
    unit of a recipe, re-raised by the client)."""


def this_worker():
    """This worker's Dask address (or host and process id outside a Dask worker)."""
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):
        return f"{socket.gethostname()} (pid {os.getpid()})"


def check_engine(expected):
    """Raise :class:`EngineMismatch` unless this process's :func:`probe` is ``expected`` (the
    client's; None: no check)."""
    if expected is None:
        return
    wrong = mismatches(expected, probe())
    if wrong:
        raise EngineMismatch(mismatch_message(this_worker(), wrong))


def mismatch_message(worker, wrong):
    """The refusal of ``worker`` for the ``(key, client's, worker's)`` differences ``wrong``."""
    what = "; ".join(f"{key} {theirs} on the worker, {ours} here" for key, ours, theirs in wrong)
    return (f"worker {worker} runs a different engine or dependencies ({what}): install the same "
            "checkout and the pinned requirements there, or leave that worker out")


def mismatches(local, remote):
    """``[(key, local value, remote value)]`` where ``remote`` (a worker's :func:`probe`)
    differs from ``local``."""
    return [(key, local[key], remote.get(key, "missing")) for key in local if remote.get(key) != local[key]]
