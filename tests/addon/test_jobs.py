"""Engine operators: the synchronous execute path through a real operator, and the worker-thread
runner (the modal UI path cannot run headless, so its runner is tested directly)."""
import io
import threading
import time

import bpy
import numpy as np
import pytest
from bpy.props import BoolProperty

from helpers import select

OPERATOR_ID = "lmdp.test_surface_area"


def mesh_world_triangles(obj, depsgraph):
    """(T, 3, 3) world-space corners of the evaluated mesh's triangles."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        vertices = np.empty(len(mesh.vertices) * 3, np.float64)
        mesh.vertices.foreach_get("co", vertices)
        triangles = np.empty(len(mesh.loop_triangles) * 3, np.int64)
        mesh.loop_triangles.foreach_get("vertices", triangles)
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array(obj.matrix_world)
    vertices = vertices.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    return vertices[triangles.reshape(-1, 3)]


@pytest.fixture
def area_operator(lmdp_ext):
    """A real engine operator: total world-space area of each selected mesh."""
    jobs = lmdp_ext.sub("operators.jobs")
    common = lmdp_ext.sub("operators.common")
    session = lmdp_ext.sub("operators.session")
    errors = lmdp_ext.sub("lmdp_addon.errors")

    class LMDP_OT_test_surface_area(jobs.EngineJob, bpy.types.Operator):
        bl_idname = OPERATOR_ID
        bl_label = "Surface Area"
        bl_options = {'REGISTER', 'UNDO'}
        stage = "area"

        fail_in_compute: BoolProperty(default=False)

        def prepare(self, context):
            meshes = common.selected_meshes(context)
            depsgraph = context.evaluated_depsgraph_get()
            return {"names": [obj.name for obj in meshes],
                    "corners": [mesh_world_triangles(obj, depsgraph) for obj in meshes],
                    "fail": self.fail_in_compute}

        def compute(self, inputs, settings, progress):
            areas = {}
            for i, (name, corners) in enumerate(zip(inputs["names"], inputs["corners"])):
                progress.update(i / len(inputs["names"]), name)
                cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
                areas[name] = 0.5 * float(np.linalg.norm(cross, axis=1).sum())
            if inputs["fail"]:
                raise errors.SceneError("Test failure raised by compute()")
            return areas

        def apply(self, context, result):
            for name, area in result.items():
                context.scene[f"lmdp_test_area_{name}"] = area
            session.session_for(context.scene).store("scene", result, seconds=self.compute_seconds)
            return f"Measured {len(result)} meshes"

    bpy.utils.register_class(LMDP_OT_test_surface_area)
    yield LMDP_OT_test_surface_area
    bpy.utils.unregister_class(LMDP_OT_test_surface_area)


def written_areas(scene):
    return {key: scene[key] for key in scene.keys() if key.startswith("lmdp_test_area_")}


def test_execute_runs_prepare_compute_apply(lit_scene, area_operator, lmdp_ext, capfd):
    select([lit_scene["Floor"], lit_scene["Box"], lit_scene["Camera"]])
    assert bpy.ops.lmdp.test_surface_area() == {'FINISHED'}
    scene = bpy.context.scene
    assert written_areas(scene) == pytest.approx({"lmdp_test_area_Floor": 4.0, "lmdp_test_area_Box": 1.5})
    session = lmdp_ext.sub("operators.session").peek(scene)
    assert session.get("scene") == pytest.approx({"Floor": 4.0, "Box": 1.5})
    assert session.timings["scene"] >= 0.0
    assert session.last_message == "Measured 2 meshes"
    err = capfd.readouterr().err
    assert "[LMDP] area:   0.0% started" in err and "[LMDP] area: 100.0% done in" in err


def test_nothing_selected_is_refused_and_changes_nothing(lit_scene, area_operator, lmdp_ext):
    select([])
    with pytest.raises(RuntimeError, match="Select at least one mesh object: nothing is selected"):
        bpy.ops.lmdp.test_surface_area()
    select([lit_scene["Camera"]])
    with pytest.raises(RuntimeError, match=r"Select at least one mesh object: the selection \(Camera\) has no mesh"):
        bpy.ops.lmdp.test_surface_area()
    assert written_areas(bpy.context.scene) == {}
    assert lmdp_ext.sub("operators.session").peek(bpy.context.scene) is None


def test_engine_error_is_reported_and_nothing_is_applied(lit_scene, area_operator, lmdp_ext):
    select([lit_scene["Floor"]])
    with pytest.raises(RuntimeError, match="Test failure raised by compute"):
        bpy.ops.lmdp.test_surface_area(fail_in_compute=True)
    assert written_areas(bpy.context.scene) == {}
    assert lmdp_ext.sub("operators.session").peek(bpy.context.scene) is None


def test_execute_refuses_while_a_ui_job_runs(lit_scene, area_operator, lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    release = threading.Event()
    runner = jobs.JobRunner(lambda inputs, settings, progress: release.wait(10), None, None).start()
    jobs._active["runner"], jobs._active["label"] = runner, "Blocking Job"
    try:
        select([lit_scene["Floor"]])
        with pytest.raises(RuntimeError, match=r"Another LMDP job is running \(Blocking Job\)"):
            bpy.ops.lmdp.test_surface_area()
    finally:
        release.set()
        runner.wait(10)
        jobs._active["runner"], jobs._active["label"] = None, ""
    assert bpy.ops.lmdp.test_surface_area() == {'FINISHED'}


# -- the worker-thread runner --------------------------------------------------------------------
def endless_engine_stage(inputs, settings, progress):
    """Engine-style loop: reports progress between batches until cancelled."""
    progress.begin("endless")
    batch = 0
    while True:
        batch += 1
        inputs["batches"] = batch
        progress.update((batch % 100) / 100.0, f"batch {batch}")
        time.sleep(0.001)


def test_runner_returns_the_result(lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    runner = jobs.JobRunner(lambda inputs, settings, progress: inputs * 2, 21, None).start()
    assert runner.wait(10)
    assert runner.outcome() == 42
    assert runner.seconds >= 0.0 and not runner.cancelled


def test_cancel_stops_the_engine_at_its_next_progress_update(lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    errors = lmdp_ext.sub("lmdp_addon.errors")
    progress_module = lmdp_ext.sub("lmdp_addon.progress")
    inputs = {"batches": 0}
    runner = jobs.JobRunner(endless_engine_stage, inputs, None).start()
    assert isinstance(runner.progress, progress_module.Progress)
    deadline = time.time() + 10
    while inputs["batches"] < 5 and time.time() < deadline:
        time.sleep(0.01)
    stage, fraction, message = runner.snapshot()
    assert stage == "endless" and message.startswith("batch ")
    assert not runner.done
    runner.cancel()
    assert runner.wait(10), "the worker did not stop after cancel()"
    with pytest.raises(errors.Cancelled, match="Cancelled during endless"):
        runner.outcome()
    assert isinstance(runner.error, errors.Cancelled)
    assert runner.result is None


def test_a_job_cancelled_after_it_finished_is_still_cancelled(lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    errors = lmdp_ext.sub("lmdp_addon.errors")
    runner = jobs.JobRunner(lambda inputs, settings, progress: "done", None, None).start()
    runner.wait(10)
    runner.cancel()
    with pytest.raises(errors.Cancelled):
        runner.outcome()


def test_engine_errors_reach_the_main_thread(lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    errors = lmdp_ext.sub("lmdp_addon.errors")

    def failing(inputs, settings, progress):
        raise errors.SceneError("The scene has no light")

    runner = jobs.JobRunner(failing, None, None).start()
    runner.wait(10)
    with pytest.raises(errors.SceneError, match="no light"):
        runner.outcome()


def test_staged_compute_logs_one_line_per_stage(lmdp_ext):
    jobs = lmdp_ext.sub("operators.jobs")
    progress_module = lmdp_ext.sub("lmdp_addon.progress")
    stream = io.StringIO()
    log = progress_module.LogProgress(stream=stream)
    result = jobs.staged_compute(lambda inputs, settings, progress: inputs + 1, "solve")(1, None, log)
    assert result == 2
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("[LMDP] solve:   0.0%") and lines[1].startswith("[LMDP] solve: 100.0% done in")
