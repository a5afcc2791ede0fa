"""What a farm's client and its workers must agree on: the engine's sources and the versions of
its dependencies. Plain Python, no dask: the workers run :func:`probe` as well."""
import hashlib
import importlib
import os
import platform

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


def mismatches(local, remote):
    """``[(key, local value, remote value)]`` where ``remote`` (a worker's :func:`probe`)
    differs from ``local``."""
    return [(key, local[key], remote.get(key, "missing")) for key in local if remote.get(key) != local[key]]
