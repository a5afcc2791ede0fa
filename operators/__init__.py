"""The Blender layer of LMDP Light Transport: properties, session store, operators, panel.

Submodules are registered in the order of :data:`MODULE_NAMES` and unregistered in reverse.
Each listed module must exist and define ``register()`` / ``unregister()`` (most build them with
``bpy.utils.register_classes_factory``). Nothing is tolerated silently: an import or register
error undoes what was registered so far and is raised. Adding a module is one line here.
(``common``, ``bake_steps`` and ``adapters`` are plain libraries; ``jobs`` is listed for its load
handler.)
"""
import importlib

MODULE_NAMES = (
    "properties",
    "session",
    "jobs",
    "ui.panel",
    "ops.scenes",
    "ops.pipeline",
    "ops.display",
    "ops.policy",
    "ui.gizmos",
    "ops.bake",
    "ops.lightmap_uvs",
)

_registered = []


def _load(name):
    module = importlib.import_module(f".{name}", __name__)
    for function in ("register", "unregister"):
        if not callable(getattr(module, function, None)):
            raise AttributeError(f"{module.__name__} has no {function}() function")
    return module


def register():
    modules = [_load(name) for name in MODULE_NAMES]  # import everything before registering
    try:
        for module in modules:
            module.register()
            _registered.append(module)
    except Exception:
        unregister()
        raise


def unregister():
    errors = []
    while _registered:
        module = _registered.pop()
        try:
            module.unregister()
        except Exception as error:  # keep unregistering the others, then raise the first
            errors.append(error)
    if errors:
        raise errors[0]
