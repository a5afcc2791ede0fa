"""Panel sections are greyed out until the session holds their inputs (drawing itself needs a GPU
window, which headless Blender does not have; the readiness rules are what the draw code uses)."""
import bpy

from helpers import select


def test_sections_become_ready_as_the_session_fills(lit_scene, lmdp_ext):
    panel = lmdp_ext.sub("operators.panel")
    store = lmdp_ext.sub("operators.session")
    context = bpy.context
    select([])
    assert not panel.LMDP_PT_sample.ready(context)
    select([lit_scene["Floor"]])
    assert panel.LMDP_PT_sample.ready(context)
    assert not panel.LMDP_PT_build.ready(context)
    assert not panel.LMDP_PT_solve.ready(context)
    assert not panel.LMDP_PT_show.ready(context)

    session = store.session_for(context.scene)
    session.store("scene_arrays", object())
    session.store("states", object())
    assert panel.LMDP_PT_build.ready(context) and not panel.LMDP_PT_solve.ready(context)
    session.store("dynamics", object())
    assert panel.LMDP_PT_solve.ready(context) and not panel.LMDP_PT_show.ready(context)
    context.scene.lmdp.bake_mode = 'GUIDED'
    assert not panel.LMDP_PT_bake.ready(context)
    session.store("solution", object())
    assert panel.LMDP_PT_show.ready(context) and panel.LMDP_PT_bake.ready(context)

    session.store("states", object())  # re-sampling invalidates the dynamics and the solution
    assert not panel.LMDP_PT_solve.ready(context) and not panel.LMDP_PT_show.ready(context)


def test_unguided_bake_needs_only_a_mesh_selection(lit_scene, lmdp_ext):
    panel = lmdp_ext.sub("operators.panel")
    bpy.context.scene.lmdp.bake_mode = 'UNGUIDED'
    select([lit_scene["Camera"]])
    assert not panel.LMDP_PT_bake.ready(bpy.context)
    select([lit_scene["Box"]])
    assert panel.LMDP_PT_bake.ready(bpy.context)


def test_operator_availability_follows_registration(lmdp_ext):
    common = lmdp_ext.sub("operators.common")

    class LMDP_OT_test_probe(bpy.types.Operator):
        bl_idname = "lmdp.test_probe"
        bl_label = "Probe"

        def execute(self, context):
            return {'FINISHED'}

    assert not common.operator_available("lmdp.test_probe")
    bpy.utils.register_class(LMDP_OT_test_probe)
    try:
        assert common.operator_available("lmdp.test_probe")
        assert "lmdp.test_probe" in common.available_operators(("lmdp.test_probe", "lmdp.no_such_operator"))
        assert common.call_operator("lmdp.test_probe") == {'FINISHED'}
    finally:
        bpy.utils.unregister_class(LMDP_OT_test_probe)
    assert not common.operator_available("lmdp.test_probe")
