"""scripts/lmdp_headless.py called wrongly (issue 22, class 13): every bad argument exits 2 with
one line on stderr that names it, no traceback, and (when --output is usable) a summary.json
whose "error" says what happened; a failing pipeline exits 1 with "error" set; the default
selection leaves out the meshes that cannot carry states or be baked, and says which.

Most cases call the script's ``main`` in this process (fast: no second Blender start-up); a few
run it as a user does, in a subprocess."""
import json
import os
import subprocess
import sys

import bpy
import pytest

from helpers import add_material, remove_uv_maps

SCRIPT_ERROR = "lmdp_headless.py: error: "
FAST = ["--set", "point_count=64", "--set", "rays_per_stratum=1", "--set", "light_samples=4"]
SMALL_BAKE = ["--set", "bake_resolution=16", "--set", "bake_samples=2", "--set", "bake_margin=1"]


@pytest.fixture
def headless(fresh_scene):
    import lmdp_headless
    return lmdp_headless


@pytest.fixture
def checks(headless):
    import lmdp_headless_checks
    return lmdp_headless_checks


class Outcome:
    def __init__(self, status, out, err, output):
        self.status, self.out, self.output = status, out, output
        self.err = [line for line in err.splitlines() if line.strip()]
        path = os.path.join(output, "summary.json") if output else None
        self.summary = json.load(open(path, encoding="utf-8")) if path and os.path.isfile(path) else None

    def refused(self, status, *words):
        """Exit ``status``, exactly one stderr line naming ``words``, no traceback."""
        assert self.status == status, (self.status, self.err)
        assert len(self.err) == 1 and self.err[0].startswith(SCRIPT_ERROR), self.err
        assert "Traceback" not in self.err[0]
        for word in words:
            assert word in self.err[0], (word, self.err[0])
        return self.err[0][len(SCRIPT_ERROR):]


@pytest.fixture
def call(headless, capfd, tmp_path):
    """``call(*args, output=...)``: the script's main in-process; ``output=None`` omits --output."""
    def run(*args, output="out"):
        capfd.readouterr()
        path = None if output is None else str(tmp_path / output)
        argv = ["lmdp_headless.py", *args] + ([] if path is None else ["--output", path])
        status = headless.main(argv)
        captured = capfd.readouterr()
        return Outcome(status, captured.out, captured.err, path)
    return run


def save(path):
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return str(path)


@pytest.fixture
def lit_file(lit_scene, tmp_path):
    bpy.context.scene.camera = lit_scene["Camera"]
    return save(tmp_path / "lit.blend")


def add_plane(name, location, size=0.3):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location)
    obj = bpy.context.object
    obj.name = name
    obj.data.materials.append(add_material(name + "Grey"))
    return obj


def mesh_without_faces(name):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(0, 0, 0), (1, 0, 0)], [(0, 1)], [])
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.collection.objects.link(obj)
    return obj


@pytest.fixture
def mixed_file(lit_scene, tmp_path):
    """The lit scene plus meshes that cannot carry states or be baked, and hidden ones."""
    remove_uv_maps(add_plane("NoUV", (0.6, 0.6, 0.01)))
    mesh_without_faces("EdgesOnly")
    empty = bpy.data.meshes.new("EmptyMesh")
    bpy.context.collection.objects.link(bpy.data.objects.new("EmptyMesh", empty))
    add_plane("Hidden", (-0.6, 0.6, 0.01)).hide_set(True)
    add_plane("NotRendered", (-0.6, -0.6, 0.01)).hide_render = True
    triangle = bpy.data.meshes.new("Triangle")
    triangle.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    bpy.data.scenes.new("Other").collection.objects.link(bpy.data.objects.new("Elsewhere", triangle))
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    return save(tmp_path / "mixed.blend")


# -- the .blend file --------------------------------------------------------------------------------
@pytest.mark.parametrize("kind, words", [
    ("missing", ["no such file"]),
    ("folder", ["is a folder"]),
    ("empty", ["is empty (0 bytes)"]),
    ("random", ["is not a .blend file"]),
    ("text", ["is not a .blend file"]),
    ("truncated", ["Blender cannot open it", "give a complete .blend file"]),
])
def test_a_bad_blend_file_is_refused_with_its_name(call, lit_file, tmp_path, kind, words):
    path = tmp_path / f"{kind}.blend"
    if kind == "folder":
        path.mkdir()
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "random":
        path.write_bytes(bytes(range(256)) * 20)
    elif kind == "text":
        path.write_text("not a scene\n")
    elif kind == "truncated":
        path.write_bytes(open(lit_file, "rb").read()[:40000])
    outcome = call(str(path), "--dry-run")
    message = outcome.refused(2, str(path), *words)
    assert outcome.summary["error"] == message and outcome.summary["exit_status"] == 2


def test_a_compressed_blend_file_is_read(call, lit_scene, tmp_path):
    path = str(tmp_path / "compressed.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path, copy=True, compress=True)
    outcome = call(path, "--dry-run")
    assert outcome.status == 0, outcome.err
    assert outcome.summary["objects"] == ["Box", "Floor"]


def test_an_unreadable_blend_file_is_refused(call, checks, lit_file, monkeypatch):
    def no_permission(*args, **kwargs):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(checks, "open", no_permission, raising=False)
    outcome = call(lit_file, "--dry-run")
    outcome.refused(2, lit_file, "cannot read the file (Permission denied)")
    assert "Permission denied" in outcome.summary["error"]


# -- --output -------------------------------------------------------------------------------------
def test_an_unusable_output_is_refused_without_a_traceback(call, checks, lit_file, tmp_path, monkeypatch):
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    cases = [
        (str(afile), ["--output", "is a file, not a folder"]),
        (str(afile / "sub" / "deeper"), ["--output", f"{afile} is a file, so no folder can be made"]),
        ("/proc/lmdp_cannot_be_made", ["--output", "cannot create or write the folder"]),
        ("//bakes", ["--output //bakes", "'//' is Blender's prefix"]),
        ("", ["--output is empty"]),
    ]
    for output, words in cases:
        outcome = call(lit_file, "--dry-run", "--output", output, output=None)
        outcome.refused(2, *words)
    assert afile.read_text() == "mine\n"
    assert not os.path.exists("/bakes") and not os.path.exists(os.path.join(os.getcwd(), "bakes"))

    (tmp_path / "taken" / "summary.json").mkdir(parents=True)
    call(lit_file, "--dry-run", output="taken").refused(2, "summary.json in it is a folder")
    (tmp_path / "result" / "lit_lmdp.blend").mkdir(parents=True)
    outcome = call(lit_file, *FAST, output="result")
    outcome.refused(2, "lit_lmdp.blend in it is a folder")
    assert outcome.summary["steps"] == []  # refused before the work, not after it

    def read_only(*args, **kwargs):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(checks.tempfile, "mkstemp", read_only)
    call(lit_file, "--dry-run", output="locked").refused(2, "--output", "(Permission denied)")


def test_a_missing_output_is_one_line(call, lit_file):
    call(lit_file, output=None).refused(2, "the following arguments are required: --output", "--help")


def test_blender_form_without_double_dash_says_where_the_arguments_go(call, lit_file):
    # sys.argv of `blender lit.blend --background --python scripts/lmdp_headless.py --output DIR`
    outcome = call(lit_file, "--background", "--python", "scripts/lmdp_headless.py")
    outcome.refused(2, "put the script's arguments after `--`")
    assert outcome.summary["error"].startswith("inside Blender")


# -- --objects -------------------------------------------------------------------------------------
@pytest.mark.parametrize("objects, words", [
    (",,,", ["--objects ',,,' names no object"]),
    ("  ", ["names no object"]),
    ("", ["names no object"]),
    ("Flor", ["no object named 'Flor'", "did you mean 'Floor'"]),
    ("Camera", ["'Camera' is a camera, not a mesh"]),
    ("Hidden", ["'Hidden' is hidden (eye icon): unhide it"]),
    ("NotRendered", ["'NotRendered' is disabled in renders"]),
    ("Elsewhere", ["'Elsewhere' is not in scene 'Scene'"]),
    ("EmptyMesh", ["'EmptyMesh' has no faces"]),
    ("EdgesOnly,Floor", ["'EdgesOnly' has no faces"]),
    ("Lamp", ["'Lamp' emits light on every face"]),
])
def test_objects_that_cannot_carry_states_are_refused(call, mixed_file, objects, words):
    outcome = call(mixed_file, "--objects", objects, "--dry-run")
    message = outcome.refused(2, *words)
    assert outcome.summary["error"] == message


def test_objects_whose_names_contain_commas_can_be_named(call, lit_scene, tmp_path):
    lit_scene["Box"].name = "Wall, North"
    path = save(tmp_path / "comma.blend")
    for text in ("Wall, North", "Floor,Wall, North", " Wall, North ,Floor,Floor"):
        outcome = call(path, "--objects", text, "--dry-run")
        assert outcome.status == 0, outcome.err
        assert outcome.summary["objects"] == (["Wall, North"] if text == "Wall, North" else ["Floor", "Wall, North"])


def test_bake_refuses_named_meshes_without_uv_map_before_any_work(call, mixed_file):
    outcome = call(mixed_file, "--objects", "NoUV,Floor", "--bake", "--set", "auto_lightmap_uvs=false", *FAST)
    outcome.refused(2, "--bake: NoUV has no UV map", "--no-bake")
    assert outcome.summary["steps"] == []


# -- --set -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("item, words", [
    ("pointcount=64", ["unknown setting 'pointcount'", "did you mean point_count"]),
    ("session_id=x", ["unknown setting 'session_id'"]),
    ("point_count=many", ["--set point_count=many: expected a whole number"]),
    ("point_count=64.5", ["expected a whole number"]),
    ("point_count=-5", ["--set point_count=-5: out of range", "from 1 to 10000000"]),
    ("point_count=99999999999", ["out of range"]),
    ("tolerance=nan", ["--set tolerance=nan: expected a finite number"]),
    ("lambda_scale=inf", ["expected a finite number"]),
    ("tolerance=1e-16", ["out of range", "1e-15 to 0.1"]),
    ("guide_fraction=1.5", ["out of range", "0 to 1"]),
    ("display_subdivide=maybe", ["expected true or false"]),
    ("cost_mode=NONSENSE", ["expected one of THESIS, PHYSICAL"]),
    ("output_dir=/tmp/elsewhere", ["--set output_dir: the output folder is --output"]),
    ("run_all_bake=false", ["--bake / --no-bake"]),
    ("point_count", ["--set expects KEY=VALUE"]),
    ("=5", ["--set expects KEY=VALUE"]),
])
def test_bad_settings_are_refused_not_clamped(call, lit_file, item, words):
    outcome = call(lit_file, "--set", item, "--dry-run")
    message = outcome.refused(2, *words)
    assert outcome.summary["error"] == message


def test_good_settings_pass_at_their_limits(call, lit_file):
    outcome = call(lit_file, "--dry-run", "--set", "tolerance=1e-15", "--set", "solver=direct",
                   "--set", "display_subdivide=Yes", "--set", "point_count=64", "--set", "point_count=64")
    assert outcome.status == 0, outcome.err
    settings = outcome.summary["settings"]
    assert settings["tolerance"] == 1e-15 and settings["solver"] == "DIRECT" and settings["point_count"] == 64


def test_a_setting_given_twice_is_a_conflict(call, lit_file):
    outcome = call(lit_file, "--set", "point_count=64", "--set", "point_count=128", "--dry-run")
    outcome.refused(2, "--set point_count is given twice (64 and 128)")


# -- --demo and conflicting options ----------------------------------------------------------------
def test_an_unknown_demo_is_one_line_with_a_summary(call):
    outcome = call("--demo", "nope")
    message = outcome.refused(2, "argument --demo: invalid choice: 'nope'", "cornell")
    assert outcome.summary["error"] == message


@pytest.mark.parametrize("args, words", [
    (["LIT", "--demo", "cornell"], ["give either a .blend file or --demo, not both"]),
    (["LIT", "--dry-run", "--bake"], ["--dry-run runs nothing, so --bake"]),
    (["LIT", "--dry-run", "--pictures"], ["--dry-run runs nothing, so --pictures"]),
    (["LIT", "--frobnicate"], ["unrecognized arguments: --frobnicate"]),
    (["LIT", "LIT"], ["unrecognized arguments"]),
])
def test_conflicting_options_are_refused(call, lit_file, args, words):
    outcome = call(*[lit_file if a == "LIT" else a for a in args])
    message = outcome.refused(2, *words)
    assert outcome.summary["error"] == message


def test_blender_form_with_a_loaded_file_refuses_another_scene(call, lit_file, tmp_path):
    other = save(tmp_path / "other.blend")
    bpy.ops.wm.open_mainfile(filepath=lit_file)  # as `blender lit.blend --python ...` does
    call("--", other, "--dry-run").refused(2, f"Blender has loaded {lit_file}", other)
    bpy.ops.wm.open_mainfile(filepath=lit_file)
    call("--", "--demo", "cornell", "--dry-run").refused(2, "and --demo cornell: give one scene")
    bpy.ops.wm.open_mainfile(filepath=lit_file)
    outcome = call("--", "--dry-run")
    assert outcome.status == 0 and outcome.summary["blend"] == lit_file


def test_pictures_without_a_camera_are_refused_before_the_work(call, lit_scene, tmp_path):
    path = save(tmp_path / "no_camera.blend")  # the lit scene's camera is not the scene camera
    outcome = call(path, "--pictures", *FAST)
    outcome.refused(2, "--pictures: scene 'Scene' has no active camera")
    assert outcome.summary["steps"] == []


# -- failures of the pipeline and of the script itself ---------------------------------------------
def test_a_scene_without_light_exits_1_with_the_error(call, lit_scene, tmp_path):
    bpy.data.objects.remove(lit_scene["Lamp"])
    outcome = call(save(tmp_path / "dark.blend"), "--no-bake", *FAST)
    message = outcome.refused(1, "lmdp.run_pipeline failed: The scene has no light")
    assert outcome.summary["error"] == message and outcome.summary["exit_status"] == 1
    assert outcome.summary["steps"][0]["status"] == "FAILED"


def test_an_internal_error_exits_1_with_its_traceback_in_the_summary(call, headless, lit_file, monkeypatch):
    def broken(objects):
        raise ValueError("a bug")
    monkeypatch.setattr(headless, "select_only", broken)
    outcome = call(lit_file, "--dry-run")
    outcome.refused(1, "internal error: ValueError: a bug", "summary.json")
    assert outcome.summary["error"] == "internal error: ValueError: a bug"
    assert "Traceback" in outcome.summary["traceback"] and "broken" in outcome.summary["traceback"]


def test_ctrl_c_exits_130_and_says_so(call, headless, lit_file, monkeypatch):
    def interrupted(objects):
        raise KeyboardInterrupt
    monkeypatch.setattr(headless, "select_only", interrupted)
    outcome = call(lit_file, "--dry-run")
    outcome.refused(130, "interrupted (Ctrl+C)")
    assert outcome.summary["exit_status"] == 130


# -- the default selection -------------------------------------------------------------------------
def test_default_selection_leaves_out_what_cannot_be_baked_and_says_why(call, mixed_file, tmp_path):
    outcome = call(mixed_file, "--set", "auto_lightmap_uvs=false", *FAST, *SMALL_BAKE)
    assert outcome.status == 0, outcome.err
    summary = outcome.summary
    assert summary["objects"] == ["Box", "Floor"] and summary["bake"] is True
    left_out = summary["left_out"]
    assert set(left_out) == {"EdgesOnly", "EmptyMesh", "Lamp", "NoUV", "Hidden", "NotRendered"}
    assert "no faces" in left_out["EmptyMesh"] and "emits light" in left_out["Lamp"]
    assert "no UV map" in left_out["NoUV"] and "disabled in renders" in left_out["NotRendered"]
    assert "[LMDP] left out NoUV: it has no UV map" in outcome.out
    for name in ("Box", "Floor"):
        assert (tmp_path / "out" / f"{name}_lmdp_indirect.exr").is_file()


def test_default_selection_bakes_meshes_without_uv_map_with_auto_lightmap_uvs(call, mixed_file, tmp_path):
    """Issue 21, item 7: with the default auto_lightmap_uvs the mesh without UV map is baked (it
    gets "LMDP Lightmap"); what cannot be baked is still left out, by name and why."""
    outcome = call(mixed_file, *FAST, *SMALL_BAKE)
    assert outcome.status == 0, outcome.err
    summary = outcome.summary
    assert summary["objects"] == ["Box", "Floor", "NoUV"] and summary["bake"] is True
    assert set(summary["left_out"]) == {"EdgesOnly", "EmptyMesh", "Lamp", "Hidden", "NotRendered"}
    assert "NoUV: no UV map, the bake gives it 'LMDP Lightmap'" in outcome.out
    for name in ("Box", "Floor", "NoUV"):
        assert (tmp_path / "out" / f"{name}_lmdp_indirect.exr").is_file()


def test_default_selection_with_no_bake_puts_states_on_meshes_without_uv_map(call, mixed_file):
    outcome = call(mixed_file, "--no-bake", "--dry-run")
    assert outcome.status == 0, outcome.err
    assert outcome.summary["objects"] == ["Box", "Floor", "NoUV"] and outcome.summary["bake"] is False


def test_a_scene_with_no_mesh_that_can_carry_states_exits_1(call, fresh_scene, tmp_path):
    mesh_without_faces("EdgesOnly")
    outcome = call(save(tmp_path / "edges.blend"), "--dry-run")
    outcome.refused(1, "no mesh can carry the states", "EdgesOnly has no faces")


def test_an_emitter_in_edit_mode_still_lights_the_scene(call, lit_scene, tmp_path):
    lamp = lit_scene["Lamp"]
    bpy.context.view_layer.objects.active = lamp
    lamp.select_set(True)
    bpy.ops.object.mode_set(mode='EDIT')
    path = save(tmp_path / "lamp_in_edit_mode.blend")
    bpy.ops.object.mode_set(mode='OBJECT')
    outcome = call(path, "--no-bake", *FAST)
    assert outcome.status == 0, outcome.err
    assert outcome.summary["mode_switched"] == ["Lamp"]
    assert "Lamp: switched to Object Mode" in outcome.out


# -- as a user runs it -----------------------------------------------------------------------------
def run_script(repo_root, tmp_path, *args):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender_user"))
    return subprocess.run([sys.executable, str(repo_root / "scripts" / "lmdp_headless.py"), *args],
                          capture_output=True, text=True, env=env, timeout=600)


def test_as_a_user_runs_it_a_corrupt_file_and_a_file_as_output(repo_root, tmp_path):
    corrupt = tmp_path / "corrupt.blend"
    corrupt.write_bytes(b"\0" * 4096)
    run = run_script(repo_root, tmp_path, str(corrupt), "--output", str(tmp_path / "out"))
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "Traceback" not in run.stderr
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["error"].startswith(str(corrupt))
    run = run_script(repo_root, tmp_path, str(corrupt), "--output", str(corrupt))
    assert run.returncode == 2 and run.stderr == (f"{SCRIPT_ERROR}--output {corrupt} is a file, not a "
                                                  "folder: give a folder (it is created if missing)\n")


def test_help_documents_the_exit_statuses_and_the_default_selection(repo_root, tmp_path):
    run = run_script(repo_root, tmp_path, "--help")
    assert run.returncode == 0
    text = " ".join(run.stdout.split())
    for words in ("exit status:", "0 success", "1 the pipeline failed", "2 bad arguments",
                  "130 interrupted", "meshes without faces and meshes that emit light on every face "
                  "are left out", "meshes without a UV map"):
        assert words in text, words
