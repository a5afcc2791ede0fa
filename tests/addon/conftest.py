"""Add-on tests: the extension loaded into bpy the way Blender loads extensions.

``lmdp_ext`` (session): a temporary extension repository directory holds a symlink
``lmdp_light_transport -> <repository root>`` (so the module name never depends on the checkout
folder's name); it is registered with ``preferences.extensions.repos.new(..., source='USER')``
and the add-on is enabled with ``addon_utils.enable(..., default_set=True, handle_error=raise)``.
BLENDER_USER_RESOURCES was set to a temporary directory by tests/conftest.py before bpy was
imported.

Wheels: if ``wheels/`` exists (after ``make extension``), enabling makes Blender install the
linux wheels of the manifest into ``$BLENDER_USER_RESOURCES/extensions/.local`` as for a real
install; without it Blender skips the missing files and scipy/embreex come from the venv.

``fresh_scene``: ``read_homefile(use_empty=True, use_factory_startup=True)`` before each test
(it keeps add-ons enabled, unlike ``read_factory_settings``) and checks that the add-on still is.
"""
import importlib
import os
import sys
from pathlib import Path

import pytest

from helpers import add_material

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "scripts"
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))


class Extension:
    """The enabled extension: its module name and its submodules."""

    def __init__(self, module):
        self.module = module

    def sub(self, name):
        """Import ``<extension>.<name>``, e.g. ``ext.sub("operators.session")``."""
        return importlib.import_module(f"{self.module}.{name}")

    def __repr__(self):
        return f"Extension({self.module!r})"


@pytest.fixture(scope="session")
def lmdp_ext(tmp_path_factory):
    import bpy
    import lmdp_extension

    user_resources = os.environ["BLENDER_USER_RESOURCES"]
    assert bpy.utils.user_resource('EXTENSIONS').startswith(user_resources), \
        "bpy ignored BLENDER_USER_RESOURCES: was it imported before tests/conftest.py?"
    assert lmdp_extension.find_enabled() is None, "an LMDP extension is already enabled"

    repo_directory = tmp_path_factory.mktemp("extensions_repo")
    module, repo = lmdp_extension.register_checkout(ROOT, repo_directory, repo_module="lmdp_tests")
    assert module == "bl_ext.lmdp_tests.lmdp_light_transport"
    yield Extension(module)
    lmdp_extension.unregister_checkout(module, repo)


@pytest.fixture(scope="session")
def lmdp_module(lmdp_ext):
    """The extension's module name, ``bl_ext.<repo>.lmdp_light_transport``."""
    return lmdp_ext.module


@pytest.fixture
def fresh_scene(lmdp_ext):
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert lmdp_ext.module in bpy.context.preferences.addons, "read_homefile disabled the add-on"
    assert hasattr(bpy.types.Scene, "lmdp")
    return bpy.context.scene


@pytest.fixture
def lit_scene(fresh_scene):
    """Floor (2 x 2 m plane), Box (0.5 m cube) and Lamp (emissive 0.5 m plane), a camera.

    Returns ``{name: object}``; nothing is selected.
    """
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    floor = bpy.context.object
    floor.name = "Floor"
    floor.data.materials.append(add_material("White"))
    bpy.ops.mesh.primitive_cube_add(size=0.5, location=(0.0, 0.0, 0.25))
    box = bpy.context.object
    box.name = "Box"
    box.data.materials.append(add_material("Red", color=(0.8, 0.1, 0.1)))
    bpy.ops.mesh.primitive_plane_add(size=0.5, location=(0.0, 0.0, 1.9), rotation=(3.14159265, 0.0, 0.0))
    lamp = bpy.context.object
    lamp.name = "Lamp"
    lamp.data.materials.append(add_material("Light", emission=10.0))
    bpy.ops.object.camera_add(location=(0.0, -4.0, 1.0))
    camera = bpy.context.object
    camera.name = "Camera"
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    bpy.context.view_layer.objects.active = None
    return {"Floor": floor, "Box": box, "Lamp": lamp, "Camera": camera}


@pytest.fixture
def demo(lmdp_ext):
    """The add-on's built-in scenes (``operators.adapters.demo_scenes``) in this session's copy."""
    return lmdp_ext.sub("operators.adapters.demo_scenes")
