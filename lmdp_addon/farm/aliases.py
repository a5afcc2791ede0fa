"""The engine under another package name: inside Blender the engine is
``bl_ext.<repository>.lmdp_light_transport.lmdp_addon`` (the extension's copy), while a worker
imports it as plain ``lmdp_addon``. Pickles name the classes and functions by module, so both
sides alias the other's name to their own modules: the workers (through a worker plugin, so that
a worker that joins or restarts later gets it too) and the client (for the results)."""
import importlib
import pkgutil
import sys
import types

#: The engine package's name on the workers.
WORKER_NAME = "lmdp_addon"


def engine_name():
    """The engine package's name in this process (``lmdp_addon`` or the extension's)."""
    return __name__.rsplit(".farm.", 1)[0]


def alias_engine(own, other):
    """Make every module of the engine package ``own`` (imported) also importable as ``other``
    (``other``'s parent packages become empty modules where they do not exist)."""
    package = importlib.import_module(own)
    modules = {own: package}
    for info in pkgutil.walk_packages(package.__path__, own + "."):
        modules[info.name] = importlib.import_module(info.name)
    parts = other.split(".")
    for i in range(1, len(parts)):
        parent = ".".join(parts[:i])
        if parent not in sys.modules:
            stub = types.ModuleType(parent)
            stub.__path__ = []
            sys.modules[parent] = stub
    for name, module in modules.items():
        sys.modules.setdefault(other + name[len(own):], module)


def worker_plugin(client_name):
    """A Dask worker plugin that aliases ``lmdp_addon`` on the worker as ``client_name``; made
    here so that cloudpickle sends the class by value (the worker cannot import the client's
    package name)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class EngineAlias(WorkerPlugin):
        name = "lmdp-engine-alias"

        def __init__(self, other):
            self.other = other

        def setup(self, worker):
            import importlib as _importlib
            aliases = _importlib.import_module(WORKER_NAME + ".farm.aliases")
            aliases.alias_engine(WORKER_NAME, self.other)

    return EngineAlias(client_name)


def install(client):
    """Alias the engine both ways when this process's package name is not :data:`WORKER_NAME`."""
    own = engine_name()
    if own == WORKER_NAME:
        return False
    if WORKER_NAME not in sys.modules:      # the workers' results name lmdp_addon.*
        alias_engine(own, WORKER_NAME)
    client.register_plugin(worker_plugin(own))
    return True
