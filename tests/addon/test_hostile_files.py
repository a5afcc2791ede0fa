"""Issue 22, files, images, materials and linked data: what a hostile-but-realistic user does to
the bake's outputs and the export, and what must come out of it (a clear refusal, nothing of the
user's lost or half-written).

Classes: 3 (file names from object names), 4 (lightmaps lost on save), 5 (a user's own file in the
output folder), 6 (hook-up removal after MULTIPLY then PREVIEW), 7 (linked library data),
8 (export to an unwritable path), 9 (``//`` paths in an unsaved file).
"""
import json
import os

import bpy
import numpy as np
import pytest

from helpers import add_material, select

SUFFIX = "_lmdp_indirect"
PREVIEW_SAVED = "lmdp_preview_saved_slots"


@pytest.fixture
def scene(lit_scene):
    """lit_scene with a bake that takes a fraction of a second (8 px, 4 samples, unguided)."""
    s = bpy.context.scene.lmdp
    s.bake_resolution = 8
    s.bake_samples = 4
    s.bake_margin = 1
    s.bake_mode = 'UNGUIDED'
    s.point_count = 64
    s.rays_per_stratum = 1
    s.light_samples = 2
    return lit_scene


def pixels(image):
    out = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(out)
    return out


def ours(key):
    """The add-on's images for the object ``key`` (its ``name_full``)."""
    return [im for im in bpy.data.images if im.get("lmdp_bake_object") == key]


def own_image(obj):
    found = ours(obj.name_full)
    assert len(found) == 1, (obj.name_full, [im.name for im in bpy.data.images])
    return found[0]


def files_under(folder):
    return sorted(os.path.relpath(os.path.join(d, f), folder) for d, _, fs in os.walk(folder) for f in fs)


def folder_bytes(folder):
    return {f: open(os.path.join(folder, f), "rb").read() for f in files_under(folder)}


def bake(**kwargs):
    return bpy.ops.lmdp.bake(**kwargs)


def add_plane(name, location=(0.0, 0.0, 0.0), size=0.3):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location)
    obj = bpy.context.object
    obj.name = name
    obj.data.materials.append(add_material(f"{name[:40]} material"))
    return obj


def lmdp_nodes():
    """{material: names of the LMDP nodes in it} for every material but the preview ones."""
    return {m.name: sorted(n.name for n in m.node_tree.nodes if n.name.startswith("LMDP"))
            for m in bpy.data.materials
            if m.node_tree is not None and "lmdp_preview_material" not in m}


# -- class 3: file names come from object names ------------------------------------------------------

def test_object_names_give_safe_unique_files_inside_the_output_folder(scene, tmp_path, lmdp_ext):
    """'/', '..', a name that another one becomes once made safe, a 250-character name, a long
    non-ASCII one, characters Windows refuses, two names that differ only in case: each object
    gets its own file, inside output_dir, with a name every file system takes."""
    out = tmp_path / "bakes"
    bpy.context.scene.lmdp.output_dir = str(out)
    scene["Floor"].name = "Wall/North"
    scene["Box"].name = "../escaped"
    others = [add_plane("Wall_North", (0.6, 0.6, 0.01)), add_plane("L" * 250, (-0.6, 0.6, 0.01)),
              add_plane("Ünïcødé " * 20, (0.6, -0.6, 0.01)), add_plane("..", (-0.6, -0.6, 0.01)),
              add_plane('Tab\there: "quoted" <1|2>?*', (0.0, 0.7, 0.01)), add_plane("wall_NORTH", (0.0, -0.7, 0.01))]
    objects = [scene["Floor"], scene["Box"], *others]
    select(objects)
    assert bake() == {'FINISHED'}
    assert files_under(tmp_path) == [os.path.join("bakes", f) for f in files_under(out)]
    exr = [f for f in files_under(out) if f.endswith(".exr")]
    assert len(exr) == len(objects) and sorted(exr + ["bake_stats.json"]) == files_under(out)
    assert all(len(f.encode()) <= 255 and not f.startswith(".") for f in exr)
    assert len({f.lower() for f in exr}) == len(exr)
    stats = json.loads((out / "bake_stats.json").read_text())
    for obj in objects:
        image = own_image(obj)
        path = bpy.path.abspath(image.filepath_raw)
        assert os.path.dirname(path) == str(out) and os.path.basename(path) in exr
        assert stats["objects"][obj.name]["file"] == os.path.basename(path)
        baked = lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake")
        np.testing.assert_array_equal(pixels(image), baked.object(obj.name).image.reshape(-1))
    assert len({bpy.path.abspath(own_image(o).filepath_raw) for o in objects}) == len(objects)
    assert not [im.name for im in bpy.data.images if im.name.startswith("LMDP scratch")]
    # A re-bake writes the same files again (nothing new next to them).
    before = files_under(out)
    bpy.context.scene.lmdp.seed = 5
    assert bake() == {'FINISHED'}
    assert files_under(out) == before


def test_a_failure_half_way_through_the_swap_changes_nothing(scene, tmp_path, monkeypatch):
    """The second file cannot be moved into place: the first one is put back, no temporary file
    or scratch image is left, the images keep their pixels, the statistics their content."""
    out = tmp_path / "bakes"
    bpy.context.scene.lmdp.output_dir = str(out)
    select([scene["Floor"], scene["Box"]])
    assert bake() == {'FINISHED'}
    files = folder_bytes(out)
    images = {name: pixels(own_image(scene[name])) for name in ("Floor", "Box")}
    names = sorted(im.name for im in bpy.data.images)
    real_replace = os.replace
    failed = []

    def replace(src, dst, *args, **kwargs):
        if os.path.basename(dst) == f"Floor{SUFFIX}.exr" and not failed:
            failed.append(dst)
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    bpy.context.scene.lmdp.seed = 9
    with pytest.raises(RuntimeError, match="nothing was changed"):
        bake()
    monkeypatch.undo()
    assert failed
    assert folder_bytes(out) == files
    assert sorted(im.name for im in bpy.data.images) == names
    for name, before in images.items():
        np.testing.assert_array_equal(pixels(own_image(scene[name])), before)


# -- class 4: lightmaps lost on save ------------------------------------------------------------------

@pytest.mark.parametrize("folder", [False, True], ids=["packed", "output_dir"])
@pytest.mark.parametrize("hook_up", ["NONE", "MULTIPLY", "PREVIEW"])
def test_lightmaps_survive_save_and_reload(scene, tmp_path, hook_up, folder):
    if folder:
        bpy.context.scene.lmdp.output_dir = str(tmp_path / "bakes")
    select([scene["Floor"]])
    assert bake(hook_up=hook_up) == {'FINISHED'}
    baked = pixels(own_image(scene["Floor"]))
    path = tmp_path / "baked.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    floor = bpy.data.objects["Floor"]
    image = own_image(floor)
    assert image.name == f"Floor{SUFFIX}" and image.colorspace_settings.name == 'Non-Color'
    np.testing.assert_array_equal(pixels(image), baked)
    if hook_up == "MULTIPLY":
        assert floor.data.materials[0].node_tree.nodes["LMDP Lightmap"].image == image
    if hook_up == "PREVIEW":
        assert floor.material_slots[0].material.node_tree.nodes["LMDP Lightmap"].image == image
    # The hook-up can still be removed after the reload, and the lightmap stays.
    select([floor])
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert lmdp_nodes() == {m.name: [] for m in bpy.data.materials
                            if m.node_tree is not None and "lmdp_preview_material" not in m}
    assert floor.material_slots[0].link == 'DATA'
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    np.testing.assert_array_equal(pixels(own_image(bpy.data.objects["Floor"])), baked)


# -- class 5: a user's own file in output_dir ---------------------------------------------------------

def test_a_file_lmdp_did_not_write_is_never_overwritten(scene, tmp_path):
    """The user's image of the lightmap's name, and its file in output_dir: both are left alone,
    the lightmap goes to a file of its own (named in a warning), and re-bakes reuse that file."""
    out = tmp_path / "bakes"
    out.mkdir()
    user_file = out / f"Floor{SUFFIX}.exr"
    user_file.write_bytes(b"the user's own bake")
    user_image = bpy.data.images.load(str(user_file), check_existing=False)
    user_image.name = f"Floor{SUFFIX}"
    bpy.context.scene.lmdp.output_dir = str(out)
    select([scene["Floor"]])
    assert bake() == {'FINISHED'}
    assert user_file.read_bytes() == b"the user's own bake"
    assert user_image.filepath_raw == str(user_file) and "lmdp_bake_object" not in user_image
    image = own_image(scene["Floor"])
    ours_file = bpy.path.abspath(image.filepath_raw)
    assert os.path.dirname(ours_file) == str(out) and ours_file != str(user_file)
    assert os.path.exists(ours_file)
    files = files_under(out)
    bpy.context.scene.lmdp.seed = 4
    assert bake() == {'FINISHED'}
    assert files_under(out) == files and user_file.read_bytes() == b"the user's own bake"
    assert bpy.path.abspath(own_image(scene["Floor"]).filepath_raw) == ours_file


def test_a_statistics_file_lmdp_did_not_write_is_refused_before_any_work(scene, tmp_path):
    out = tmp_path / "bakes"
    out.mkdir()
    (out / "bake_stats.json").write_text("my notes")
    bpy.context.scene.lmdp.output_dir = str(out)
    select([scene["Floor"]])
    images = sorted(im.name for im in bpy.data.images)
    with pytest.raises(RuntimeError, match="bake_stats.json.*not written by LMDP"):
        bake()
    assert files_under(out) == ["bake_stats.json"] and (out / "bake_stats.json").read_text() == "my notes"
    assert sorted(im.name for im in bpy.data.images) == images


def test_a_hand_edited_statistics_file_cannot_point_outside_the_folder(scene, tmp_path):
    """bake_stats.json's list of files is only trusted for plain file names in the folder."""
    out = tmp_path / "bakes"
    out.mkdir()
    victim = tmp_path / "victim.exr"
    victim.write_bytes(b"keep me")
    stats = {"mode": "UNGUIDED", "settings": {}, "objects": [1, 2],
             "files": {"../victim.exr": "Floor", "/etc/hosts": "Floor", "x": 5}}
    (out / "bake_stats.json").write_text(json.dumps(stats))
    bpy.context.scene.lmdp.output_dir = str(out)
    select([scene["Floor"]])
    assert bake() == {'FINISHED'}
    assert victim.read_bytes() == b"keep me"
    assert files_under(out) == [f"Floor{SUFFIX}.exr", "bake_stats.json"]
    assert json.loads((out / "bake_stats.json").read_text())["files"] == {f"Floor{SUFFIX}.exr": "Floor"}


# -- class 6: hook-up removal after MULTIPLY then PREVIEW ---------------------------------------------

def slot_state(obj):
    return [(s.link, s.material.name if s.material else None) for s in obj.material_slots]


def test_remove_hookup_after_multiply_then_preview_restores_everything(scene):
    """Also the object-level material the user keeps behind a slot linked to the mesh's data."""
    floor = scene["Floor"]
    hidden = add_material("Object-level, hidden")
    floor.material_slots[0].link = 'OBJECT'
    floor.material_slots[0].material = hidden
    floor.material_slots[0].link = 'DATA'
    material = floor.data.materials[0]
    bsdf = next(n for n in material.node_tree.nodes if n.type == 'BSDF_DIFFUSE')
    colour = tuple(bsdf.inputs["Color"].default_value)
    slots = slot_state(floor)
    nodes = lmdp_nodes()
    select([floor])
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    assert bake(hook_up='PREVIEW') == {'FINISHED'}
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert lmdp_nodes() == nodes and slot_state(floor) == slots
    assert not bsdf.inputs["Color"].links and tuple(bsdf.inputs["Color"].default_value) == pytest.approx(colour)
    floor.material_slots[0].link = 'OBJECT'
    assert floor.material_slots[0].material == hidden


def test_hook_ups_whose_nodes_the_user_deleted_are_remade_and_removed(scene):
    """The user deleted the lightmap's image node (MULTIPLY, PREVIEW) or the Mix node (MULTIPLY):
    a re-bake makes the hook-up whole again, and its removal leaves no node behind."""
    floor = scene["Floor"]
    nodes = floor.data.materials[0].node_tree.nodes
    select([floor])
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    nodes.remove(nodes["LMDP Lightmap"])
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    assert nodes["LMDP Lightmap"].image == own_image(floor)
    b = [s for s in nodes["LMDP Lightmap Multiply"].inputs if s.type == 'RGBA'][1]
    assert b.links[0].from_node == nodes["LMDP Lightmap"]
    nodes.remove(nodes["LMDP Lightmap Multiply"])
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    assert sorted(n.name for n in nodes if n.name.startswith("LMDP")) == ["LMDP Lightmap", "LMDP Lightmap Multiply"]
    assert bake(hook_up='PREVIEW') == {'FINISHED'}
    preview = floor.material_slots[0].material.node_tree.nodes
    preview.remove(preview["LMDP Lightmap"])
    assert bake(hook_up='PREVIEW') == {'FINISHED'}
    emission = next(n for n in floor.material_slots[0].material.node_tree.nodes if n.type == 'EMISSION')
    assert emission.inputs["Color"].links[0].from_node.image == own_image(floor)
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert not any(lmdp_nodes().values()) and slot_state(floor) == [('DATA', floor.data.materials[0].name)]


def test_multiply_after_preview_hooks_the_objects_own_materials(scene):
    """PREVIEW hides the mesh's materials behind the object-level preview: MULTIPLY still
    hooks the mesh's material (not the preview), and a slot added in between is restored too."""
    floor = scene["Floor"]
    material = floor.data.materials[0]
    select([floor])
    assert bake(hook_up='PREVIEW') == {'FINISHED'}
    floor.data.materials.append(add_material("Added later"))
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    assert "LMDP Lightmap Multiply" in material.node_tree.nodes
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert not any(lmdp_nodes().values())
    assert slot_state(floor) == [('DATA', material.name), ('DATA', "Added later")]


# -- class 7: linked library data ---------------------------------------------------------------------

def add_multiply_nodes(material, image):
    """The nodes of a MULTIPLY hook-up, made by hand (as a library file made with LMDP has them)."""
    tree = material.node_tree
    bsdf = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.name = "LMDP Lightmap"
    tex.image = image
    mix = tree.nodes.new("ShaderNodeMix")
    mix.name = "LMDP Lightmap Multiply"
    mix.data_type = 'RGBA'
    mix.blend_type = 'MULTIPLY'
    a, b = [s for s in mix.inputs if s.type == 'RGBA'][:2]
    tree.links.new(tex.outputs["Color"], b)
    tree.links.new(next(s for s in mix.outputs if s.type == 'RGBA'), bsdf.inputs["Color"])


@pytest.fixture
def linked(scene, tmp_path):
    """A library .blend holding a plane "Floor" (its material already hooked up with MULTIPLY in
    the library), a plane "LibPanel" and a material "LibOnly material", linked into the scene
    next to the local Floor."""
    library = tmp_path / "library.blend"
    local_floor = scene["Floor"]
    local_floor.name = "Local for now"
    made = [add_plane("Floor", (0.0, 0.0, 1.0), 0.4), add_plane("LibPanel", (0.0, 0.8, 0.5), 0.4)]
    image = bpy.data.images.new("LibLightmap", 4, 4)
    add_multiply_nodes(made[0].data.materials[0], image)
    alone = add_material("LibOnly material")
    bpy.data.libraries.write(str(library), set(made) | {alone}, fake_user=True)
    bpy.data.materials.remove(alone)
    for obj in made:
        mesh, mat = obj.data, obj.data.materials[0]
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(mesh)
        bpy.data.materials.remove(mat)
    bpy.data.images.remove(image)
    local_floor.name = "Floor"
    with bpy.data.libraries.load(str(library), link=True) as (_, dst):
        dst.objects = ["Floor", "LibPanel"]
        dst.materials = ["LibOnly material"]
    for obj in dst.objects:
        bpy.context.scene.collection.objects.link(obj)
    lib = {o.name: o for o in dst.objects}
    assert all(o.library is not None for o in lib.values()) and local_floor.library is None
    return {**scene, "local": local_floor, "Floor": lib["Floor"], "LibPanel": lib["LibPanel"],
            "material": dst.materials[0]}


def library_state(linked):
    """What the library's data looks like in this session (must never change)."""
    return {o.name_full: (slot_state(o), sorted(o.keys()),
                          {s.material.name_full: sorted(n.name for n in s.material.node_tree.nodes)
                           for s in o.material_slots if s.material})
            for o in (linked["Floor"], linked["LibPanel"])} | {
        "material": sorted(n.name for n in linked["material"].node_tree.nodes)}


def test_a_linked_object_never_writes_into_its_local_namesakes_lightmap(linked, tmp_path):
    out = tmp_path / "bakes"
    bpy.context.scene.lmdp.output_dir = str(out)
    local, lib_floor = linked["local"], linked["Floor"]
    lib_floor.hide_set(True)
    select([local])
    assert bake() == {'FINISHED'}
    local_image = own_image(local)
    local_pixels = pixels(local_image)
    local_files = folder_bytes(out)
    # Both visible: the capture cannot tell two objects named Floor apart, so it refuses.
    lib_floor.hide_set(False)
    select([lib_floor])
    with pytest.raises(RuntimeError, match="Floor.*linked from.*library.blend.*rename"):
        bake()
    # The local one hidden: the linked Floor is baked into an image and a file of its own.
    local.hide_set(True)
    select([lib_floor])
    assert bake() == {'FINISHED'}
    assert own_image(local) == local_image and local_image["lmdp_bake_object"] == "Floor"
    np.testing.assert_array_equal(pixels(local_image), local_pixels)
    lib_image = own_image(lib_floor)
    assert lib_image != local_image and lib_image.library is None
    for name, data in local_files.items():
        if name.endswith(".exr"):
            assert (out / name).read_bytes() == data
    assert bpy.path.abspath(lib_image.filepath_raw) != bpy.path.abspath(local_image.filepath_raw)


def test_hook_ups_that_would_edit_library_data_are_refused_before_any_work(linked):
    panel, box = linked["LibPanel"], linked["Box"]
    state = library_state(linked)
    images = sorted(im.name_full for im in bpy.data.images)
    select([panel])
    for hook_up in ('PREVIEW', 'MULTIPLY'):
        with pytest.raises(RuntimeError, match="LibPanel.*linked from.*library.blend"):
            bake(hook_up=hook_up)
    # A local object whose material comes from the library: MULTIPLY would edit that material.
    box.data.materials[0] = linked["material"]
    box_nodes = sorted(n.name for n in box.data.materials[0].node_tree.nodes)
    select([box])
    with pytest.raises(RuntimeError, match="Material 'LibOnly material' of 'Box'.*linked from.*library.blend"):
        bake(hook_up='MULTIPLY')
    assert sorted(im.name_full for im in bpy.data.images) == images
    # Shared with a linked object too: not hooked up (a warning says so), nothing edited.
    box.data.materials[0] = panel.material_slots[0].material
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    box.data.materials[0] = linked["material"]
    assert sorted(n.name for n in box.data.materials[0].node_tree.nodes) == box_nodes
    assert library_state(linked) == state
    # PREVIEW touches only the local object's slots and a local material: allowed.
    assert bake(hook_up='PREVIEW') == {'FINISHED'}
    assert box.material_slots[0].material.library is None
    assert library_state(linked) == state


def test_hook_ups_of_a_library_override_are_refused(linked):
    """A library override is local in name only: its mesh and materials stay in the library and
    its own edits outside the overridable properties are reset when the file is reloaded."""
    state = library_state(linked)
    override = linked["LibPanel"].override_create(remap_local_usages=True)
    assert override.library is None and override.override_library is not None
    select([override])
    with pytest.raises(RuntimeError, match="'LibPanel' is a library override of .*library.blend"):
        bake(hook_up='PREVIEW')
    # Its material is the library's, still used by the linked original: not hooked up.
    assert bake(hook_up='MULTIPLY') == {'FINISHED'}
    assert own_image(override).library is None
    assert library_state(linked) == state and PREVIEW_SAVED not in override


def test_remove_hookup_leaves_library_data_alone(linked):
    """The library's own Floor carries a MULTIPLY hook-up made in the library: removing hook-ups
    of a selection that holds it changes nothing there, and says so."""
    state = library_state(linked)
    linked["local"].name = "Local Floor"
    select([linked["Floor"], linked["LibPanel"]])
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert library_state(linked) == state
    assert "LMDP Lightmap Multiply" in linked["Floor"].material_slots[0].material.node_tree.nodes


# -- class 8: export to an unwritable path ------------------------------------------------------------

@pytest.fixture
def solved(scene):
    select([scene["Floor"], scene["Box"]])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    return scene


@pytest.mark.parametrize("where", ["sys", "proc", "too_long", "read_only", "folder_is_a_file"])
def test_export_to_an_unwritable_path_is_a_clear_error(solved, tmp_path, where):
    read_only = tmp_path / "kept.npz"
    read_only.write_bytes(b"earlier export")
    read_only.chmod(0o444)
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    path = {"sys": "/sys/lmdp.npz", "proc": "/proc/lmdp.npz", "too_long": str(tmp_path / ("x" * 300 + ".npz")),
            "read_only": str(read_only), "folder_is_a_file": str(blocker / "lmdp.npz")}[where]
    with pytest.raises(RuntimeError) as error:
        bpy.ops.lmdp.export_npz(filepath=path)
    message = str(error.value)
    assert "Internal error" not in message and "file path" in message.lower(), message
    assert read_only.read_bytes() == b"earlier export" and blocker.read_text() == "not a folder"
    assert sorted(os.listdir(tmp_path)) == ["file", "kept.npz"]


def test_a_failed_export_keeps_the_previous_file(solved, tmp_path, monkeypatch):
    path = tmp_path / "lmdp.npz"
    assert bpy.ops.lmdp.export_npz(filepath=str(path)) == {'FINISHED'}
    previous = path.read_bytes()

    def full_disk(file, *args, **kwargs):
        (file.write if hasattr(file, "write") else open(file, "wb").write)(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", full_disk)
    with pytest.raises(RuntimeError, match="No space left on device"):
        bpy.ops.lmdp.export_npz(filepath=str(path))
    monkeypatch.undo()
    assert path.read_bytes() == previous and os.listdir(tmp_path) == ["lmdp.npz"]


# -- class 9: relative paths in an unsaved file -------------------------------------------------------

@pytest.mark.parametrize("output_dir", ["//bakes/", "bakes/"])
def test_relative_output_folder_needs_a_saved_file_or_an_absolute_path(solved, tmp_path, monkeypatch, output_dir):
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    assert bpy.data.filepath == ""
    bpy.context.scene.lmdp.output_dir = output_dir
    select([solved["Floor"]])
    images = sorted(im.name for im in bpy.data.images)
    wanted = "save the .blend first or use an absolute path" if output_dir.startswith("//") else "absolute path"
    with pytest.raises(RuntimeError, match=f"Output Folder.*{wanted}"):
        bake()
    with pytest.raises(RuntimeError, match=f"Output Folder.*{wanted}"):
        bpy.ops.lmdp.export_npz()
    with pytest.raises(RuntimeError, match="save the .blend first or use an absolute path"):
        bpy.ops.lmdp.export_npz(filepath="//lmdp.npz")
    assert os.listdir(work) == [] and sorted(im.name for im in bpy.data.images) == images
    # Saved, '//bakes/' is the folder next to the .blend file.
    if output_dir.startswith("//"):
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
        assert bake() == {'FINISHED'}
        assert bpy.ops.lmdp.export_npz() == {'FINISHED'}
        assert sorted(os.listdir(tmp_path / "bakes")) == [f"Floor{SUFFIX}.exr", "bake_stats.json", "lmdp.npz"]
        assert os.listdir(work) == []


def test_a_home_relative_output_folder_is_expanded(scene, tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    bpy.context.scene.lmdp.output_dir = "~/bakes"
    select([scene["Floor"]])
    assert bake() == {'FINISHED'}
    assert sorted(os.listdir(tmp_path / "bakes")) == [f"Floor{SUFFIX}.exr", "bake_stats.json"]
    assert not (tmp_path / "~").exists()
