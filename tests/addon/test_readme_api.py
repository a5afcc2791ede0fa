"""README.md's scripting-API tables document every scene.lmdp property and every registered LMDP
operator: each must be named in the first column of a table of that section."""
import re

import bpy

SECTION = "## Scripting API"


def readme_text(repo_root):
    return (repo_root / "README.md").read_text(encoding="utf-8")


def api_table_names(text):
    """Names in backticks in the first column of the tables of the scripting-API section
    (``lmdp.bake(hook_up='NONE')`` -> ``lmdp.bake``; a cell may name several)."""
    assert SECTION in text, f"README.md has no '{SECTION}' section"
    body = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    names = set()
    for line in body.splitlines():
        if line.startswith("|"):
            names.update(code.split("(", 1)[0] for code in re.findall(r"`([^`]+)`", line.split("|")[1]))
    return names


def test_every_scene_property_is_documented(fresh_scene, repo_root):
    names = api_table_names(readme_text(repo_root))
    missing = [p.identifier for p in fresh_scene.lmdp.bl_rna.properties
               if p.identifier not in ("rna_type", "name") and p.identifier not in names]
    assert not missing, f"document these scene.lmdp properties in README.md's scripting API: {missing}"


def test_every_registered_operator_is_documented(fresh_scene, repo_root, lmdp_ext):
    names = api_table_names(readme_text(repo_root))
    common = lmdp_ext.sub("operators.common")
    registered = [name for name in dir(bpy.types) if "_OT_" in name and name.startswith("LMDP_")]
    idnames = [f"lmdp.{name.split('_OT_', 1)[1]}" for name in registered]
    idnames += list(common.PIPELINE_OPERATORS)  # the public API, documented even before it lands
    missing = sorted({i for i in idnames if i not in names})
    assert not missing, f"document these operators in README.md's scripting API: {missing}"
