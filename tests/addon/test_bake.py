"""lmdp.bake as a user runs it: images, files, statistics, material hook-up, bad input, cancel."""
import json
import os

import bpy
import numpy as np
import pytest

from helpers import add_material, remove_uv_maps, select


@pytest.fixture
def cornell(fresh_scene):
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    s = fresh_scene.lmdp
    s.point_count = 400
    s.rays_per_stratum = 2
    s.light_samples = 8
    s.bake_resolution = 16
    s.bake_samples = 8
    s.bake_margin = 2
    s.bake_mode = 'UNGUIDED'
    return fresh_scene


def only(*names):
    select([bpy.data.objects[n] for n in names])


def pixels(image):
    out = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(out)
    return out.reshape(image.size[1], image.size[0], 4)


def session(lmdp_ext, scene):
    return lmdp_ext.sub("operators.session").session_for(scene)


def test_unguided_bake_writes_tagged_float_images(cornell, lmdp_ext):
    only("Floor", "TallBox")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    result = session(lmdp_ext, cornell).require("bake")
    for name in ("Floor", "TallBox"):
        image = bpy.data.images[f"{name}_lmdp_indirect"]
        assert tuple(image.size) == (16, 16) and image.is_float
        assert image.colorspace_settings.name == 'Non-Color'
        assert image["lmdp_bake_object"] == name
        assert image.packed_file is not None  # kept with the .blend without an output folder
        ob = result.object(name)
        np.testing.assert_allclose(pixels(image), ob.image, rtol=1e-6, atol=1e-7)
        lit = ob.value.mean()
        assert lit > 0.01
    assert "Ceiling_lmdp_indirect" not in bpy.data.images


def test_output_folder_gets_exr_files_and_statistics(cornell, lmdp_ext, tmp_path):
    cornell.lmdp.output_dir = str(tmp_path / "bakes")
    only("Floor")
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    cornell.lmdp.bake_mode = 'GUIDED'
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    files = sorted(os.listdir(tmp_path / "bakes"))
    assert files == ["Floor_lmdp_indirect.exr", "bake_stats.json"]  # no temporary files left
    image = bpy.data.images["Floor_lmdp_indirect"]
    assert image.source == 'FILE' and image.filepath_raw.endswith("Floor_lmdp_indirect.exr")
    loaded = bpy.data.images.load(str(tmp_path / "bakes" / "Floor_lmdp_indirect.exr"))
    loaded.colorspace_settings.name = 'Non-Color'
    ob = session(lmdp_ext, cornell).require("bake").object("Floor")
    np.testing.assert_allclose(pixels(loaded), ob.image, rtol=1e-6, atol=1e-7)  # exact float EXR
    stats = json.loads((tmp_path / "bakes" / "bake_stats.json").read_text())
    assert stats["mode"] == "GUIDED" and stats["settings"]["bake_samples"] == 8
    floor = stats["objects"]["Floor"]
    assert floor["texels"] == 256 and floor["samples"] == 8 and floor["rays"] > 256 * 8
    assert set(floor["seconds"]) >= {"sample", "build", "solve", "bake"}
    assert all(v >= 0 for v in floor["seconds"].values())


def attribute_names(name):
    return sorted(a.name for a in bpy.data.objects[name].data.attributes if a.name.startswith("lmdp_"))


def test_run_all_samples_builds_solves_shows_and_bakes(cornell, lmdp_ext, tmp_path):
    """lmdp.run_pipeline is every stage: the session holds each stage's result, the meshes carry
    the z colours, the lightmaps are guided by this very solution and written to output_dir."""
    cornell.lmdp.output_dir = str(tmp_path)
    cornell.lmdp.bake_mode = 'GUIDED'
    only("Floor", "TallBox")
    assert bpy.ops.lmdp.run_pipeline() == {'FINISHED'}
    s = session(lmdp_ext, cornell)
    for stage in ("states", "dynamics", "solution", "bake", "display"):
        assert s.has(stage), stage
    for name in ("Floor", "TallBox"):
        assert {"lmdp_z", "lmdp_z_color"} <= set(attribute_names(name))
        assert s.require("bake").object(name).value.mean() > 0.01
        assert (tmp_path / f"{name}_lmdp_indirect.exr").exists()
    stats = json.loads((tmp_path / "bake_stats.json").read_text())
    assert stats["mode"] == "GUIDED" and stats["objects"]["Floor"]["seconds"]["solve"] > 0
    # The same seed through the stage operators gives the same lightmap, texel for texel.
    run_all = s.require("bake").object("Floor").value.copy()
    for op in (bpy.ops.lmdp.sample_states, bpy.ops.lmdp.build_dynamics, bpy.ops.lmdp.solve, bpy.ops.lmdp.bake):
        assert op() == {'FINISHED'}
    np.testing.assert_array_equal(s.require("bake").object("Floor").value, run_all)


def test_run_all_checks_the_bake_before_any_work(lit_scene, lmdp_ext):
    """A mesh without UV map stops Run All before sampling (nothing stored, nothing written);
    with bake=False the same selection runs."""
    floor, box = lit_scene["Floor"], lit_scene["Box"]
    remove_uv_maps(box)
    select([floor, box])
    scene = bpy.context.scene
    scene.lmdp.auto_lightmap_uvs = False          # on, the bake would give Box "LMDP Lightmap"
    before = data_snapshot()
    with pytest.raises(RuntimeError, match="No UV map on Box"):
        bpy.ops.lmdp.run_pipeline()
    assert not session(lmdp_ext, scene).has("states")
    assert data_snapshot() == before and attribute_names("Floor") == []
    assert bpy.ops.lmdp.run_pipeline(bake=False) == {'FINISHED'}
    assert session(lmdp_ext, scene).has("solution") and not session(lmdp_ext, scene).has("bake")
    assert "lmdp_z" in attribute_names("Floor")


def test_rebake_replaces_only_its_own_image(cornell, lmdp_ext):
    user = bpy.data.images.new("Floor_lmdp_indirect", 4, 4)
    user.pixels.foreach_set(np.full(64, 0.25, np.float32))
    user_pixels = pixels(user).copy()
    only("Floor")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    ours = [im for im in bpy.data.images if im.get("lmdp_bake_object") == "Floor"]
    assert len(ours) == 1 and ours[0] != user and ours[0].name.startswith("Floor_lmdp_indirect.")
    np.testing.assert_array_equal(pixels(user), user_pixels)
    first = pixels(ours[0]).copy()
    # A material node showing the lightmap keeps showing it after a re-bake (other seed).
    mat = bpy.data.objects["Floor"].material_slots[0].material
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = ours[0]
    cornell.lmdp.seed = 7
    cornell.lmdp.bake_resolution = 8
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    ours = [im for im in bpy.data.images if im.get("lmdp_bake_object") == "Floor"]
    assert len(ours) == 1 and tuple(ours[0].size) == (8, 8) and node.image == ours[0]
    assert first.shape != pixels(ours[0]).shape
    np.testing.assert_array_equal(pixels(user), user_pixels)


def data_snapshot():
    return {
        "images": sorted((im.name, tuple(im.size)) for im in bpy.data.images),
        "materials": sorted(m.name for m in bpy.data.materials),
        "nodes": {m.name: sorted(n.name for n in m.node_tree.nodes) for m in bpy.data.materials if m.node_tree},
    }


@pytest.mark.parametrize("mode", ['GUIDED', 'FINAL_GATHER', 'RESIDUAL'])
def test_first_bake_in_a_solution_mode_samples_builds_and_solves(cornell, lmdp_ext, mode):
    """A first bake on a fresh scene just works (issue 20): without a solution in the session
    the bake solves the scene itself, with states on every mesh, keeps that solution, reuses it
    for the next bake and solves again when the scene changed."""
    only("Floor")
    cornell.lmdp.bake_mode = mode
    store = session(lmdp_ext, cornell)
    assert store.result.solution is None
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    first = store.result
    assert first.solution is not None and first.states.n_points == 400
    assert {"Floor", "Ceiling", "TallBox", "LeftWall"} <= set(store.object_names)
    assert store.require("bake").mode == mode and store.require("bake").object("Floor").value.mean() > 0.01
    only("TallBox")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    assert store.result is first                              # the same scene: reused
    bpy.data.objects["ShortBox"].location.x += 0.05
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    assert store.result is not first and store.result.solution is not None


def test_a_first_residual_bake_refuses_the_thesis_cost_mode(cornell):
    only("Floor")
    cornell.lmdp.bake_mode = 'RESIDUAL'
    cornell.lmdp.cost_mode = 'THESIS'
    before = data_snapshot()
    with pytest.raises(RuntimeError, match="PHYSICAL"):
        bpy.ops.lmdp.bake()
    assert data_snapshot() == before


def test_final_gather_needs_physical_mode(cornell):
    only("Floor", "Ceiling")
    cornell.lmdp.cost_mode = 'THESIS'
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    cornell.lmdp.bake_mode = 'FINAL_GATHER'
    before = data_snapshot()
    with pytest.raises(RuntimeError, match="PHYSICAL"):
        bpy.ops.lmdp.bake()
    assert data_snapshot() == before
    cornell.lmdp.bake_mode = 'GUIDED'  # the THESIS-mode policy still guides
    assert bpy.ops.lmdp.bake() == {'FINISHED'}


def test_mesh_without_uv_map_is_named(lit_scene):
    bpy.context.scene.lmdp.bake_mode = 'UNGUIDED'
    bpy.context.scene.lmdp.auto_lightmap_uvs = False
    floor, box = lit_scene["Floor"], lit_scene["Box"]
    remove_uv_maps(box)
    select([floor, box])
    before = data_snapshot()
    with pytest.raises(RuntimeError, match=r"No UV map on Box: add one"):
        bpy.ops.lmdp.bake()
    assert data_snapshot() == before


def test_overlapping_uvs_are_refused(lit_scene):
    bpy.context.scene.lmdp.bake_mode = 'UNGUIDED'
    bpy.context.scene.lmdp.auto_lightmap_uvs = False
    box = lit_scene["Box"]
    uv = box.data.uv_layers.active.data
    square = [(0.25, 0.25), (0.75, 0.25), (0.75, 0.75), (0.25, 0.75)]
    for poly in box.data.polygons:  # every face on the same square
        for corner, loop in enumerate(poly.loop_indices):
            uv[loop].uv = square[corner]
    box.data.update()
    select([box])
    before = data_snapshot()
    with pytest.raises(RuntimeError, match="Overlapping UVs on Box"):
        bpy.ops.lmdp.bake()
    assert data_snapshot() == before


def test_scene_without_light_is_refused(lit_scene):
    bpy.context.scene.lmdp.bake_mode = 'UNGUIDED'
    lamp = lit_scene["Lamp"]
    lamp.data.materials.clear()
    lamp.data.materials.append(add_material("Grey"))
    select([lit_scene["Floor"]])
    with pytest.raises(RuntimeError, match="no light to bake"):
        bpy.ops.lmdp.bake()


def test_zero_resolution_cannot_be_set_and_is_refused_by_the_engine(cornell, lmdp_ext):
    cornell.lmdp.bake_resolution = 0
    assert cornell.lmdp.bake_resolution == 1  # the property's minimum
    bake_steps = lmdp_ext.sub("operators.bake_steps")
    settings = lmdp_ext.sub("operators.properties").settings_from_scene(cornell)
    settings.bake_resolution = 0  # a script can still pass 0 to the engine pieces
    settings.auto_lightmap_uvs = False  # its checks would rasterise at R = 0 first
    only("Floor")
    with pytest.raises(lmdp_ext.sub("lmdp_addon.errors").SceneError, match="at least 1 pixel"):
        bake_steps.bake_inputs(bpy.context, settings)


def test_unwritable_output_folder_is_refused_before_any_work(cornell, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    cornell.lmdp.output_dir = str(blocker / "bakes")
    only("Floor")
    before = data_snapshot()
    with pytest.raises(RuntimeError, match="Cannot create the output folder"):
        bpy.ops.lmdp.bake()
    assert data_snapshot() == before


def test_cancelled_bake_leaves_the_previous_image_untouched(cornell, lmdp_ext):
    only("Floor")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    previous = pixels(bpy.data.images["Floor_lmdp_indirect"]).copy()
    bake_steps = lmdp_ext.sub("operators.bake_steps")
    jobs = lmdp_ext.sub("operators.jobs")
    settings = lmdp_ext.sub("operators.properties").settings_from_scene(cornell)
    settings.bake_samples = 64
    settings.seed = 3
    inputs = bake_steps.bake_inputs(bpy.context, settings)
    runner = jobs.JobRunner(bake_steps.compute_bake, inputs, settings, name="bake test")
    runner.cancel()  # Esc before the first work unit ends
    runner.start()
    assert runner.wait(60)
    with pytest.raises(lmdp_ext.sub("lmdp_addon.errors").Cancelled):
        runner.outcome()
    np.testing.assert_array_equal(pixels(bpy.data.images["Floor_lmdp_indirect"]), previous)



def test_the_main_thread_rasterises_nothing_and_esc_stops_the_texel_checks(cornell, lmdp_ext, monkeypatch):
    """Issue 22, class 11: the texel checks (every object rasterised: seconds at 1024²) do not run
    on the main thread, where Esc cannot reach them, but first thing in the worker, where the
    progress reports them and a cancel stops them before the next object."""
    checks = lmdp_ext.sub("lmdp_addon.bake.checks")
    calls = []
    original = checks.rasterize_texels
    monkeypatch.setattr(checks, "rasterize_texels", lambda *a, **k: calls.append(1) or original(*a, **k))
    meshes = [o.name for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"]
    only(*meshes)
    bake_steps = lmdp_ext.sub("operators.bake_steps")
    jobs = lmdp_ext.sub("operators.jobs")
    settings = lmdp_ext.sub("operators.properties").settings_from_scene(cornell)
    settings.bake_resolution = 64
    settings.auto_lightmap_uvs = False          # on, it rasterises each object once (at most 256²) to find bad maps
    inputs = bake_steps.bake_inputs(bpy.context, settings)
    assert calls == []                          # prepare: every other check, no rasterisation
    runner = jobs.JobRunner(bake_steps.compute_bake, inputs, settings, name="bake test")
    runner.cancel()                             # Esc as the worker starts
    runner.start()
    assert runner.wait(60)
    with pytest.raises(lmdp_ext.sub("lmdp_addon.errors").Cancelled):
        runner.outcome()
    assert calls == []                          # stopped before the first object
    assert "Floor_lmdp_indirect" not in bpy.data.images
    settings.bake_samples = 1
    inputs = bake_steps.bake_inputs(bpy.context, settings)
    bake_steps.compute_bake(inputs, settings, lmdp_ext.sub("lmdp_addon.progress").Progress())
    assert len(calls) == len(meshes)            # once per object, in the worker


def test_multiply_hook_up_and_its_removal(cornell):
    only("Floor")
    mat = bpy.data.objects["Floor"].material_slots[0].material
    bsdf = next(n for n in mat.node_tree.nodes if n.type == 'BSDF_DIFFUSE')
    colour = tuple(bsdf.inputs["Color"].default_value)
    assert bpy.ops.lmdp.bake(hook_up='MULTIPLY') == {'FINISHED'}
    nodes = mat.node_tree.nodes
    assert "LMDP Lightmap" in nodes and "LMDP Lightmap Multiply" in nodes
    assert nodes["LMDP Lightmap"].image == bpy.data.images["Floor_lmdp_indirect"]
    link = bsdf.inputs["Color"].links[0]
    assert link.from_node.name == "LMDP Lightmap Multiply"
    a = [s for s in nodes["LMDP Lightmap Multiply"].inputs if s.type == 'RGBA'][0]
    assert tuple(a.default_value) == pytest.approx(colour)
    assert bpy.ops.lmdp.bake(hook_up='MULTIPLY') == {'FINISHED'}  # idempotent
    assert sum(n.name.startswith("LMDP Lightmap Multiply") for n in nodes) == 1
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert "LMDP Lightmap" not in nodes and "LMDP Lightmap Multiply" not in nodes
    assert not bsdf.inputs["Color"].links
    assert tuple(bsdf.inputs["Color"].default_value) == pytest.approx(colour)


def test_multiply_hook_up_keeps_a_linked_colour_and_skips_shared_materials(cornell):
    mat = bpy.data.objects["Floor"].material_slots[0].material
    tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    rgb = tree.nodes.new("ShaderNodeRGB")
    tree.links.new(rgb.outputs[0], bsdf.inputs["Color"])
    bpy.data.objects["Ceiling"].material_slots[0].material = bpy.data.objects["BackWall"].material_slots[0].material
    only("Floor", "Ceiling")
    assert bpy.ops.lmdp.bake(hook_up='MULTIPLY') == {'FINISHED'}
    mix = tree.nodes["LMDP Lightmap Multiply"]
    assert [s for s in mix.inputs if s.type == 'RGBA'][0].links[0].from_node == rgb
    shared = bpy.data.objects["Ceiling"].material_slots[0].material
    assert "LMDP Lightmap Multiply" not in shared.node_tree.nodes
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert bsdf.inputs["Color"].links[0].from_node == rgb


def test_preview_hook_up_links_at_object_level_and_is_undone(cornell):
    only("Floor")
    floor = bpy.data.objects["Floor"]
    mesh_material = floor.data.materials[0]
    assert bpy.ops.lmdp.bake(hook_up='PREVIEW') == {'FINISHED'}
    slot = floor.material_slots[0]
    assert slot.link == 'OBJECT' and slot.material.name == "Floor_lmdp_preview"
    assert floor.data.materials[0] == mesh_material  # the mesh keeps its material
    tex = slot.material.node_tree.nodes["LMDP Lightmap"]
    assert tex.image == bpy.data.images["Floor_lmdp_indirect"]
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert floor.material_slots[0].link == 'DATA' and floor.material_slots[0].material == mesh_material


def test_an_object_whose_islands_cover_no_texel_is_left_out_by_name(cornell, tmp_path):
    """Issue 18, item 7: tiny UV islands inside [0, 1] (no texel centre at this resolution) no
    longer stop the bake with "UVs outside [0, 1]": the object is named in a warning, the others
    are baked."""
    uv = bpy.data.objects["TallBox"].data.uv_layers.active.data
    coords = np.empty(2 * len(uv), np.float32)
    uv.foreach_get("uv", coords)
    coords = 0.5 + 1e-5 * (coords - 0.5)          # every island shrunk to a speck at the centre
    uv.foreach_set("uv", coords)
    cornell.lmdp.bake_mode = 'UNGUIDED'
    cornell.lmdp.bake_resolution = 16
    cornell.lmdp.bake_samples = 2
    cornell.lmdp.output_dir = str(tmp_path)
    cornell.lmdp.auto_lightmap_uvs = False       # on, TallBox would get "LMDP Lightmap" (test_lightmap_uvs)
    only("Floor", "TallBox")
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    assert "Floor_lmdp_indirect" in bpy.data.images
    assert "TallBox_lmdp_indirect" not in bpy.data.images
    stats = json.loads((tmp_path / "bake_stats.json").read_text())
    assert list(stats["objects"]) == ["Floor"]
    warning = [w for w in stats["warnings"] if "TallBox" in w]
    assert warning and "smaller than a texel" in warning[0], stats["warnings"]


@pytest.mark.parametrize("hook_up", ["MULTIPLY", "PREVIEW"])
def test_the_capture_sees_through_the_addons_own_hook_up(cornell, lmdp_ext, hook_up):
    """Issue 18: a re-bake after a hook-up captures the materials as they were: the MULTIPLY
    node's original colour (not its default grey) and the mesh's materials under PREVIEW's
    object-level emission material (not an emitter)."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    only("Floor", "TallBox")
    meshes = [bpy.data.objects["Floor"], bpy.data.objects["TallBox"]]
    before = extract.extract_scene(bpy.context, meshes)
    cornell.lmdp.bake_mode = 'UNGUIDED'
    cornell.lmdp.bake_resolution = 16
    cornell.lmdp.bake_samples = 2
    assert bpy.ops.lmdp.bake(hook_up=hook_up) == {'FINISHED'}
    after = extract.extract_scene(bpy.context, meshes)
    np.testing.assert_allclose(after.triangle_albedo, before.triangle_albedo)
    np.testing.assert_allclose(after.triangle_emission, before.triangle_emission)
    assert not any("LMDP" in w for w in after.warnings), after.warnings


def test_the_default_auto_bake_solves_only_where_unguided_paths_are_noisy(fresh_scene, lmdp_ext, tmp_path):
    """AUTO (the default): the room lit only through a hatch is noisy for unguided paths, so the
    bake solves the LMDP itself, keeps the solution in the session and traces the rest GUIDED if
    that wins; the next bake reuses it. The Cornell box is quiet: no solve."""
    assert fresh_scene.lmdp.bake_mode == 'AUTO'
    assert bpy.ops.lmdp.add_demo_scene(kind='NARROW_OPENING') == {'FINISHED'}
    s = fresh_scene.lmdp
    s.point_count, s.rays_per_stratum, s.light_samples = 400, 2, 8
    s.bake_resolution, s.bake_samples, s.bake_margin = 16, 16, 2
    s.output_dir = str(tmp_path)
    only("RoomAFloor")
    store = session(lmdp_ext, fresh_scene)
    assert bpy.ops.lmdp.bake() == {'FINISHED'}        # noisy, but 16² x 16 would not pay for the solve
    baked = store.require("bake")
    assert baked.auto.too_small and not baked.auto.solved and store.result.solution is None
    s.bake_resolution, s.bake_samples = 32, 64
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    baked = store.require("bake")
    assert baked.mode == "AUTO" and baked.auto.solved and baked.auto.relative_variance > 25
    assert sum(n for _, n in baked.auto.samples) == 64
    first = store.result
    assert first.solution is not None and baked.auto.lmdp is first      # kept for the next bake
    stats = json.loads((tmp_path / "bake_stats.json").read_text())
    assert stats["auto"]["solved"] and stats["mode"] == "AUTO"
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    assert store.result is first and store.require("bake").auto.lmdp is None   # reused, not solved again
    assert store.require("bake").object("RoomAFloor").value.mean() > 0.005

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    s = bpy.context.scene.lmdp
    s.bake_resolution, s.bake_samples, s.bake_margin = 16, 32, 2
    only("Floor")
    store = session(lmdp_ext, bpy.context.scene)
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    baked = store.require("bake")
    assert baked.mode == "AUTO" and not baked.auto.solved and baked.auto.samples == (("UNGUIDED", 32),)
    assert store.result.solution is None                                # quiet: nothing solved
