"""Install a built extension zip the way a user does and run the pipeline on it.

    python install_zip.py EXTENSION.zip USER_RESOURCES_DIR

Run in a fresh process (BLENDER_USER_RESOURCES must be set before bpy is imported). scipy and
embreex are made importable only from the wheels Blender extracted for the extension (the
venv's own copies are hidden), so this proves the zip's bundled wheels work. Prints
"INSTALLED-AND-RAN" and exits 0 on success.
"""
import importlib.abc
import importlib.machinery
import os
import sys

zip_path, user_dir = sys.argv[1], sys.argv[2]
os.environ["BLENDER_USER_RESOURCES"] = user_dir
BUNDLED = ("scipy", "embreex")


class OnlyExtensionWheels(importlib.abc.MetaPathFinder):
    """scipy / embreex from Blender's extension site-packages only."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] not in BUNDLED or "." in name:
            return None
        paths = [p for p in sys.path if os.path.join("extensions", ".local") in p]
        spec = importlib.machinery.PathFinder.find_spec(name, paths)
        if spec is None:
            raise ImportError(f"{name} is not in the extension's bundled wheels ({paths})")
        return spec


sys.meta_path.insert(0, OnlyExtensionWheels())
import bpy  # noqa: E402

result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
assert result == {'FINISHED'}, result
import scipy  # noqa: E402
import embreex  # noqa: E402
for module in (scipy, embreex):
    assert os.path.join("extensions", ".local") in module.__file__, module.__file__
assert hasattr(bpy.types.Scene, "lmdp"), "the installed extension did not register"
bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
settings = bpy.context.scene.lmdp
settings.point_count, settings.bake_resolution, settings.bake_samples = 300, 8, 4
assert bpy.ops.lmdp.run_pipeline() == {'FINISHED'}
assert any(image.get("lmdp_bake_object") for image in bpy.data.images)
print("INSTALLED-AND-RAN", scipy.__version__, embreex.__file__)
