"""The extension registers through Blender's extension mechanism and unregisters cleanly."""
import bpy  # first: importing bpy puts addon_utils on sys.path
import addon_utils  # noqa: E402
import pytest

PANELS = ("LMDP_PT_main", "LMDP_PT_sample", "LMDP_PT_build", "LMDP_PT_solve", "LMDP_PT_show", "LMDP_PT_bake")


def registered_lmdp_types():
    return sorted(name for name in dir(bpy.types) if name.startswith("LMDP_"))


def test_extension_module_name_is_stable(lmdp_module):
    assert lmdp_module.startswith("bl_ext.") and lmdp_module.endswith(".lmdp_light_transport")
    assert lmdp_module in bpy.context.preferences.addons


def test_every_listed_submodule_is_registered(lmdp_ext):
    operators = lmdp_ext.sub("operators")
    registered = [module.__name__.split(".operators.", 1)[1] for module in operators._registered]
    assert registered == list(operators.MODULE_NAMES)


def test_panel_is_an_lmdp_tab_in_the_viewport_sidebar(fresh_scene):
    for name in PANELS:
        panel = getattr(bpy.types, name)
        assert panel.bl_space_type == 'VIEW_3D'
        assert panel.bl_region_type == 'UI'
        assert panel.bl_category == "LMDP"
    assert bpy.types.LMDP_PT_main.poll(bpy.context)


def test_registered_operator_ids_resolve(lmdp_ext):
    common = lmdp_ext.sub("operators.common")
    for idname in common.available_operators():
        category, name = idname.split(".")
        rna = getattr(getattr(bpy.ops, category), name).get_rna_type()
        assert rna.identifier == common.operator_idname_to_type(idname)
    assert not common.operator_available("lmdp.no_such_operator")


def test_disable_removes_everything_and_enable_restores_it(fresh_scene, lmdp_ext):
    before = registered_lmdp_types()
    assert set(PANELS) <= set(before)
    try:
        addon_utils.disable(lmdp_ext.module, default_set=True)
        assert registered_lmdp_types() == []
        assert not hasattr(bpy.types.Scene, "lmdp")
    finally:
        addon_utils.enable(lmdp_ext.module, default_set=True, handle_error=_raise)
    assert registered_lmdp_types() == before
    assert bpy.context.scene.lmdp.point_count == 2048


def test_a_missing_submodule_fails_loudly_and_registers_nothing(fresh_scene, lmdp_ext):
    operators = lmdp_ext.sub("operators")
    names = operators.MODULE_NAMES
    operators.unregister()
    try:
        operators.MODULE_NAMES = names + ("no_such_module",)
        with pytest.raises(ImportError):
            operators.register()
        assert registered_lmdp_types() == []
    finally:
        operators.MODULE_NAMES = names
        operators.register()
    assert hasattr(bpy.types.Scene, "lmdp")


def _raise(error):
    raise error


def test_blender_installs_the_manifest_wheels_that_exist(lmdp_ext, repo_root):
    """Enabling the extension installs its wheels for this platform into the user's extensions
    site-packages; manifest entries without a file (no `make extension` yet) are skipped."""
    import os
    import platform
    import tomllib
    from pathlib import Path

    if not (platform.system() == "Linux" and platform.machine() == "x86_64"):
        pytest.skip("checks the linux-x64 wheels")
    with open(repo_root / "blender_manifest.toml", "rb") as fh:
        wheels = [w for w in tomllib.load(fh)["wheels"] if "manylinux" in w]
    present = {Path(w).name.split("-")[0] for w in wheels if (repo_root / w).is_file()}
    site_packages = (Path(os.environ["BLENDER_USER_RESOURCES"]) / "extensions" / ".local" / "lib"
                     / "python3.11" / "site-packages")
    installed = {name for name in ("scipy", "embreex") if (site_packages / name).is_dir()}
    assert installed == present
