"""scene.lmdp mirrors lmdp_addon.settings.Settings one to one (names, types, defaults, enums)."""
import dataclasses

import bpy
import pytest

ENGINE_ENUMS = {"cost_mode": "COST_MODES", "solver": "SOLVERS", "bake_mode": "BAKE_MODES",
                "bake_content": "BAKE_CONTENTS", "output_format": "OUTPUT_FORMATS", "output_8bit": "OUTPUT_8BIT",
                "resolution_mode": "RESOLUTION_MODES"}
DISPLAY_ENUMS = {"display_quantity": ("Z", "COST_TO_GO", "RESIDUAL"),
                 "policy_subset": ("ACTIVE_OBJECT", "MOST_INFORMATIVE")}


def rna_properties():
    rna = bpy.context.scene.lmdp.bl_rna.properties
    return {p.identifier: p for p in rna if p.identifier not in ("rna_type", "name")}


def test_every_settings_field_has_a_property_with_its_type_and_default(fresh_scene, lmdp_ext):
    settings_module = lmdp_ext.sub("lmdp_addon.settings")
    props = rna_properties()
    for field in dataclasses.fields(settings_module.Settings):
        if field.metadata.get("light_paths") or field.metadata.get("auto"):   # set from the scene's
            # Cycles Light Paths or by AUTO, not by the user
            assert field.name not in props
            continue
        assert field.name in props, f"scene.lmdp has no property for Settings.{field.name}"
        prop = props[field.name]
        default = field.default
        if field.name in ENGINE_ENUMS:
            assert prop.type == 'ENUM'
            identifiers = tuple(item.identifier for item in prop.enum_items)
            assert identifiers == tuple(getattr(settings_module, ENGINE_ENUMS[field.name]))
            assert prop.default == default
        elif isinstance(default, bool):
            assert prop.type == 'BOOLEAN' and prop.default == default
        elif isinstance(default, int):
            assert prop.type == 'INT' and prop.default == default
        elif isinstance(default, float):
            assert prop.type == 'FLOAT'
            assert prop.default == pytest.approx(default, rel=1e-6)
        else:
            assert prop.type == 'STRING' and prop.default == default


def test_properties_have_descriptions_and_sane_limits(fresh_scene):
    for name, prop in rna_properties().items():
        assert len(prop.description) > 15, f"scene.lmdp.{name} needs a user-facing description"
        if prop.type in ('INT', 'FLOAT') and name != "seed":
            assert prop.hard_min <= prop.default <= prop.hard_max, name
            assert prop.hard_min > -1e30 and prop.hard_max < 1e30, f"{name} has no limits"
    assert rna_properties()["output_dir"].subtype == 'DIR_PATH'


def test_display_properties(fresh_scene):
    props = rna_properties()
    for name, identifiers in DISPLAY_ENUMS.items():
        assert tuple(item.identifier for item in props[name].enum_items) == identifiers
    assert props["policy_max_points"].type == 'INT'
    assert props["policy_arrow_scale"].type == 'FLOAT'


def test_settings_from_scene_defaults_equal_engine_defaults(fresh_scene, lmdp_ext):
    Settings = lmdp_ext.sub("lmdp_addon.settings").Settings
    settings = lmdp_ext.sub("operators.properties").settings_from_scene(fresh_scene)
    assert settings == Settings()  # floats come back exactly (1e-8 stays 1e-8)


def test_settings_from_scene_reads_what_the_user_set(fresh_scene, lmdp_ext, tmp_path):
    props = fresh_scene.lmdp
    props.point_count = 123
    props.cost_mode = 'THESIS'
    props.solver = 'DIRECT'
    props.tolerance = 3e-7
    props.bake_mode = 'FINAL_GATHER'
    props.output_dir = "//bakes/"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    settings = lmdp_ext.sub("operators.properties").settings_from_scene(bpy.context.scene)
    assert settings.point_count == 123
    assert settings.cost_mode == "THESIS" and settings.solver == "DIRECT"
    assert settings.bake_mode == "FINAL_GATHER"
    assert settings.tolerance == 3e-7
    assert settings.output_dir.rstrip("/\\") == str(tmp_path / "bakes")


def test_limits_reject_nonsense(fresh_scene):
    props = fresh_scene.lmdp
    props.point_count = -5
    assert props.point_count >= 1
    with pytest.raises(TypeError):
        props.cost_mode = 'NOT_A_MODE'
