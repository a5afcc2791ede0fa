"""README.md documents every scene.lmdp property and every registered LMDP operator."""
import bpy


def readme_text(repo_root):
    return (repo_root / "README.md").read_text(encoding="utf-8")


def test_every_scene_property_is_documented(fresh_scene, repo_root):
    text = readme_text(repo_root)
    missing = [p.identifier for p in fresh_scene.lmdp.bl_rna.properties
               if p.identifier not in ("rna_type", "name") and f"`{p.identifier}`" not in text]
    assert not missing, f"document these scene.lmdp properties in README.md's scripting API: {missing}"


def test_every_registered_operator_is_documented(fresh_scene, repo_root, lmdp_ext):
    text = readme_text(repo_root)
    common = lmdp_ext.sub("operators.common")
    registered = [name for name in dir(bpy.types) if "_OT_" in name and name.startswith("LMDP_")]
    idnames = [f"lmdp.{name.split('_OT_', 1)[1]}" for name in registered]
    idnames += list(common.PIPELINE_OPERATORS)  # the public API, documented even before it lands
    missing = sorted({i for i in idnames if f"`{i}" not in text})
    assert not missing, f"document these operators in README.md's scripting API: {missing}"
