"""The panel's buttons are greyed out by their operators' poll until the session holds their
inputs (drawing itself needs a GPU window, which headless Blender does not have; the poll
functions are what Blender greys the buttons with)."""
import bpy

from helpers import select


def can_run(idname):
    """What Blender asks before it enables a button: the operator's poll in this context."""
    category, name = idname.split(".")
    return getattr(getattr(bpy.ops, category), name).poll()


def test_sections_become_ready_as_the_session_fills(lit_scene, lmdp_ext):
    store = lmdp_ext.sub("operators.session")
    context = bpy.context
    select([])
    assert not can_run("lmdp.sample_states")
    select([lit_scene["Floor"]])
    assert can_run("lmdp.sample_states")
    assert not can_run("lmdp.build_dynamics")
    assert not can_run("lmdp.solve")
    assert not can_run("lmdp.show_desirability")

    session = store.session_for(context.scene)
    session.store("scene", object())
    session.store("states", object())
    assert can_run("lmdp.build_dynamics") and not can_run("lmdp.solve")
    session.store("dynamics", object())
    assert can_run("lmdp.solve") and not can_run("lmdp.show_desirability")
    context.scene.lmdp.bake_mode = 'GUIDED'
    assert can_run("lmdp.bake")          # without a solution it samples, builds and solves first
    session.store("solution", object())
    assert can_run("lmdp.show_desirability") and can_run("lmdp.bake")

    session.store("states", object())  # re-sampling invalidates the dynamics and the solution
    assert not can_run("lmdp.solve") and not can_run("lmdp.show_desirability")


def test_unguided_bake_needs_only_a_mesh_selection(lit_scene, lmdp_ext):
    bpy.context.scene.lmdp.bake_mode = 'UNGUIDED'
    select([lit_scene["Camera"]])
    assert not can_run("lmdp.bake")
    select([lit_scene["Box"]])
    assert can_run("lmdp.bake")


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


# -- drawing -------------------------------------------------------------------------------------------
# A UILayout exists only inside a drawing window region; headless Blender has none. A recorder with
# the UILayout methods the panel uses stands in for it, so the real draw code runs end to end.

class Recorder:
    def __init__(self, log=None):
        self.log = [] if log is None else log
        self.enabled = self.active = True
        self.scale_y = 1.0
        self.use_property_split = self.use_property_decorate = False

    def _child(self, kind):
        self.log.append((kind,))
        return Recorder(self.log)

    def row(self, align=False):
        return self._child("row")

    def column(self, align=False):
        return self._child("column")

    def box(self):
        return self._child("box")

    def separator(self):
        self.log.append(("separator",))

    def label(self, text="", icon='NONE', icon_value=0):
        self.log.append(("label", text, icon, icon_value))

    def prop(self, data, name, text=None, **kwargs):
        assert hasattr(data, name), name
        self.log.append(("prop", name))

    def operator(self, idname, text=None, icon='NONE'):
        assert hasattr(bpy.types, "LMDP_OT_" + idname.split(".")[1]), idname
        props = type("OperatorProperties", (), {})()
        self.log.append(("operator", idname, text, props))
        return props

    def labels(self):
        return [entry[1] for entry in self.log if entry[0] == "label"]

    def operators(self):
        return [entry[1] for entry in self.log if entry[0] == "operator"]


def draw_all(panel, context):
    layouts = {}
    for cls in (panel.LMDP_PT_sample, panel.LMDP_PT_build, panel.LMDP_PT_solve, panel.LMDP_PT_show,
                panel.LMDP_PT_bake):
        layout = Recorder()
        cls.draw_section(None, context, layout, context.scene.lmdp)
        layouts[cls.bl_label] = layout
    return layouts


def test_sections_draw_status_legend_and_tools(lit_scene, lmdp_ext):
    panel = lmdp_ext.sub("operators.ui.panel")
    common = lmdp_ext.sub("operators.common")
    context = bpy.context
    select([lit_scene["Floor"], lit_scene["Box"]])
    empty = draw_all(panel, context)                      # nothing computed yet: still draws
    assert "lmdp.sample_states" in empty["Sample"].operators()
    assert not any("states" in text for text in empty["Sample"].labels())
    context.scene.lmdp.point_count = 300
    context.scene.lmdp.rays_per_stratum = 2
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    assert bpy.ops.lmdp.show_desirability() == {'FINISHED'}
    assert bpy.ops.lmdp.show_policy() == {'FINISHED'}
    layouts = draw_all(panel, context)
    assert any("300 points x 16 strata = 4,800 states" in t for t in layouts["Sample"].labels())
    assert any(t.startswith("P: 300 x") and "nnz" in t and "iB" in t for t in layouts["Build"].labels())
    solve = layouts["Solve"].labels()
    assert any("converged" in t for t in solve) and any(t.startswith("Relative residual") for t in solve)
    show = layouts["Show"]
    record = lmdp_ext.sub("operators.session").session_for(context.scene).require("display")
    texts = show.labels()
    assert record.scale.label in texts
    for tick in record.scale.tick_labels(panel.LEGEND_STEPS):
        assert any(t.startswith(tick) for t in texts), tick
    assert any(t.startswith("Viridis, log scale") for t in texts)
    assert any("arrows on" in t for t in texts)
    for idname in ("lmdp.show_desirability", "lmdp.view_desirability", "lmdp.show_policy",
                   "lmdp.probe_policy", "lmdp.clear_display"):
        assert idname in show.operators()
    bake = layouts["Bake"]
    if common.operator_available("lmdp.bake"):
        assert "lmdp.bake" in bake.operators()
    else:  # the bake module is not registered in this build: the panel says so instead
        assert any("not part of this build" in t for t in bake.labels())


def test_run_all_button_carries_the_show_and_bake_toggles(lit_scene, lmdp_ext):
    """The main panel's Run All passes scene.lmdp.run_all_show / run_all_bake to the operator."""
    from types import SimpleNamespace
    panel = lmdp_ext.sub("operators.ui.panel")
    context = bpy.context
    select([lit_scene["Floor"]])
    context.scene.lmdp.run_all_bake = False
    fake = SimpleNamespace(layout=Recorder())
    panel.LMDP_PT_main.draw(fake, context)
    runs = [entry for entry in fake.layout.log if entry[0] == "operator" and entry[1] == "lmdp.run_pipeline"]
    assert len(runs) == 1 and runs[0][2] == "Run All"
    props = runs[0][3]
    assert props.show is True and props.bake is False
    assert ("prop", "run_all_show") in fake.layout.log and ("prop", "run_all_bake") in fake.layout.log
