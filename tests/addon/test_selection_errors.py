"""Every pipeline operator that exists refuses an empty / mesh-less selection and changes nothing."""
import bpy
import pytest

from helpers import select


def snapshot(scene, session_module):
    """Everything a refused operator must leave untouched."""
    data = {
        "objects": sorted(o.name for o in bpy.data.objects),
        "meshes": sorted(m.name for m in bpy.data.meshes),
        "attributes": {m.name: sorted(a.name for a in m.attributes) for m in bpy.data.meshes},
        "color_attributes": {m.name: sorted(a.name for a in m.color_attributes) for m in bpy.data.meshes},
        "images": sorted(i.name for i in bpy.data.images),
        "materials": sorted(m.name for m in bpy.data.materials),
        "settings": {p.identifier: getattr(scene.lmdp, p.identifier)
                     for p in scene.lmdp.bl_rna.properties if p.identifier != "rna_type"},
    }
    session = session_module.peek(scene)
    data["session"] = sorted(session.results) if session is not None else None
    return data


def test_operators_refuse_nothing_selected_and_no_mesh_selected(lit_scene, lmdp_ext):
    common = lmdp_ext.sub("operators.common")
    session_module = lmdp_ext.sub("operators.session")
    operators = common.available_operators(common.SELECTION_OPERATORS)
    if not operators:
        pytest.skip("no pipeline operator is registered yet")
    scene = bpy.context.scene
    for selection in ([], [lit_scene["Camera"]]):
        select(selection)
        before = snapshot(scene, session_module)
        for idname in operators:
            with pytest.raises(RuntimeError, match="Select at least one mesh object") as info:
                result = common.call_operator(idname)
                pytest.fail(f"{idname} returned {result} with selection {[o.name for o in selection]}")
            assert snapshot(scene, session_module) == before, f"{idname} changed data: {info.value}"
