"""Scene extraction (operators/adapters/extract.py): Blender scene -> SceneArrays, checked against the
built-in scene definitions, hand-computed values and Cycles' own bakes.

Monte Carlo tolerance of the Cycles comparisons: two bakes with different seeds give the RMS
per-texel standard error sigma = std(a - b) / 2 of their mean; see assert_matches_monte_carlo.
"""
import bpy
import numpy as np
import pytest
from scipy.spatial import cKDTree

from helpers import add_material


@pytest.fixture
def extract(lmdp_ext):
    return lmdp_ext.sub("operators.adapters.extract")


@pytest.fixture
def library(lmdp_ext):
    return lmdp_ext.sub("lmdp_addon.demo_geometry")


def match_triangles(got, ref):
    """Index into ``got`` of the triangle matching each triangle of ``ref`` (by corner sets)."""
    cg, cr = got.corners(), ref.corners()
    _, idx = cKDTree(cg.mean(axis=1)).query(cr.mean(axis=1))
    assert len(np.unique(idx)) == len(idx), "two reference triangles matched the same triangle"
    # Same corners up to their order (triangulation order / rotation).
    d = np.linalg.norm(cr[:, :, None, :] - cg[idx][:, None, :, :], axis=-1).min(axis=-1)
    assert d.max() < 1e-5
    return idx


def names_of(sa):
    return set(sa.object_names)


def assert_matches_monte_carlo(measured, expected, sigma):
    """A Cycles estimate equals ``expected`` within its noise.

    ``sigma`` is the RMS per-texel standard error (from two seeds): the texel errors must have an
    RMS of about sigma (< 1.5 sigma), their mean must be within 5 sigma / sqrt(n) of 0, and no
    texel may be off by more than 8 sigma (the noise differs between texels, so the largest
    error is not Gaussian in the global sigma; a 0.5 % model error is still > 8 sigma here).
    """
    err = np.asarray(measured, dtype=np.float64) - np.asarray(expected, dtype=np.float64)
    n = err.size
    assert np.sqrt(np.mean(err ** 2)) < 1.5 * sigma, f"RMS error {np.sqrt(np.mean(err ** 2)):.3g} vs sigma {sigma:.3g}"
    assert abs(err.mean()) < 5 * sigma / np.sqrt(n), f"mean error {err.mean():.3g} vs sigma {sigma:.3g}"
    assert np.abs(err).max() < 8 * sigma, f"max error {np.abs(err).max():.3g} vs sigma {sigma:.3g}"


def bake_twice(demo, obj, **kwargs):
    a = demo.bake_cycles(bpy.context, obj, seed=1, **kwargs)
    b = demo.bake_cycles(bpy.context, obj, seed=2, **kwargs)
    return (a + b) / 2, float(np.std(a[..., :3] - b[..., :3])) / 2 + 1e-7


@pytest.mark.parametrize("kind", ["CORNELL_BOX", "NARROW_OPENING", "PARALLEL_SQUARES", "PLANE_UNDER_SKY"])
def test_demo_scene_extracts_to_its_own_definition(fresh_scene, extract, demo, library, kind):
    carriers = demo.build_demo_scene(kind, bpy.context)
    got = extract.extract_scene(bpy.context, carriers)
    ref = library.build_scene_arrays(kind)
    assert got.warnings == []
    assert got.object_names == ref.object_names
    np.testing.assert_array_equal(got.object_carries_states, ref.object_carries_states)
    assert got.n_triangles == ref.n_triangles
    idx = match_triangles(got, ref)
    np.testing.assert_allclose(got.triangle_albedo[idx], ref.triangle_albedo, rtol=1e-6)
    np.testing.assert_allclose(got.triangle_emission[idx], ref.triangle_emission, rtol=1e-6)
    np.testing.assert_array_equal(got.triangle_emission_two_sided[idx], ref.triangle_emission_two_sided)
    assert [got.object_names[i] for i in got.triangle_object[idx]] == [ref.object_names[i] for i in ref.triangle_object]
    # UVs of matched corners agree.
    cg, cr = got.corners()[idx], ref.corners()
    order = np.linalg.norm(cr[:, :, None, :] - cg[:, None, :, :], axis=-1).argmin(axis=-1)
    uv_got = np.take_along_axis(got.triangle_uv[idx], order[..., None], axis=1)
    np.testing.assert_allclose(uv_got, ref.triangle_uv, atol=1e-6)
    np.testing.assert_allclose(got.world_radiance, ref.world_radiance, rtol=1e-6)
    assert got.object_has_uv.all()


def test_heavy_scene_extracts_fast_and_exactly(fresh_scene, extract, demo, library):
    carriers = demo.build_demo_scene("HEAVY", bpy.context)
    got = extract.extract_scene(bpy.context, carriers)
    ref = library.build_scene_arrays("HEAVY")
    assert got.n_triangles == ref.n_triangles >= 200_000
    # Same quad split and the same polygon order: triangles come out in the same order.
    np.testing.assert_allclose(got.corners(), ref.corners(), atol=1e-6)
    np.testing.assert_allclose(got.triangle_uv, ref.triangle_uv, atol=1e-6)


def test_modifiers_and_transforms_are_applied(fresh_scene, extract):
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(1.0, 2.0, 3.0), rotation=(0.0, 0.0, np.pi / 2))
    plane = bpy.context.object
    plane.scale = (2.0, 1.0, 1.0)
    array = plane.modifiers.new("Array", 'ARRAY')
    array.count = 3
    array.relative_offset_displace = (1.0, 0.0, 0.0)
    plane.modifiers.new("Triangulate", 'TRIANGULATE')
    bpy.context.view_layer.update()
    sa = extract.extract_scene(bpy.context, [plane])
    assert sa.n_triangles == 6
    # The 3 x 1 strip of unit quads, scaled 2 along local x, rotated 90 degrees about z, moved.
    v = sa.vertices[np.unique(sa.triangles)]
    np.testing.assert_allclose(v.min(axis=0), (1.0 - 0.5, 2.0 - 1.0, 3.0), atol=1e-6)
    np.testing.assert_allclose(v.max(axis=0), (1.0 + 0.5, 2.0 + 5.0, 3.0), atol=1e-6)
    normals, area = sa.triangle_geometry()
    assert area.sum() == pytest.approx(6.0)
    np.testing.assert_allclose(normals, np.tile([0, 0, 1.0], (6, 1)), atol=1e-6)
    assert sa.object_carries_states.tolist() == [True]


def test_mirrored_objects_keep_their_displayed_normals(fresh_scene, extract):
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    plane = bpy.context.object
    plane.scale = (-1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    sa = extract.extract_scene(bpy.context, [plane])
    normals, _ = sa.triangle_geometry()
    np.testing.assert_allclose(normals, np.tile([0, 0, 1.0], (2, 1)), atol=1e-6)


def test_hidden_objects_are_ignored_and_unselected_ones_only_occlude(fresh_scene, extract):
    names = ["Visible", "EyeHidden", "RenderHidden", "ViewportDisabled", "InExcluded", "Other"]
    objects = {}
    for i, name in enumerate(names):
        bpy.ops.mesh.primitive_plane_add(size=1.0, location=(2.0 * i, 0.0, 0.0))
        objects[name] = bpy.context.object
        objects[name].name = name
    objects["EyeHidden"].hide_set(True)
    objects["RenderHidden"].hide_render = True
    objects["ViewportDisabled"].hide_viewport = True
    excluded = bpy.data.collections.new("Excluded")
    bpy.context.scene.collection.children.link(excluded)
    excluded.objects.link(objects["InExcluded"])
    bpy.context.scene.collection.objects.unlink(objects["InExcluded"])
    bpy.context.view_layer.layer_collection.children["Excluded"].exclude = True
    sa = extract.extract_scene(bpy.context, [objects["Visible"], objects["RenderHidden"]])
    assert names_of(sa) == {"Visible", "Other"}
    carried = dict(zip(sa.object_names, sa.object_carries_states))
    assert carried == {"Visible": True, "Other": False}


def test_materials_without_nodes_and_without_material(fresh_scene, extract, demo):
    """Cycles renders a node tree with nothing connected black, and no material 0.8 grey."""
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    empty = bpy.context.object
    empty.name = "EmptyTree"
    mat = bpy.data.materials.new("NoNodes")
    mat.node_tree.nodes.clear()
    empty.data.materials.append(mat)
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(3, 0, 0))
    bare = bpy.context.object
    bare.name = "Bare"
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(6, 0, 0))
    slot = bpy.context.object
    slot.name = "EmptySlot"
    slot.data.materials.append(None)
    sa = extract.extract_scene(bpy.context, [empty])
    albedo = {n: sa.triangle_albedo[sa.triangle_object == i][0] for i, n in enumerate(sa.object_names)}
    np.testing.assert_allclose(albedo["EmptyTree"], 0.0)
    np.testing.assert_allclose(albedo["Bare"], extract.DEFAULT_ALBEDO)
    np.testing.assert_allclose(albedo["EmptySlot"], extract.DEFAULT_ALBEDO)
    assert any("'NoNodes'" in w and "black" in w for w in sa.warnings)
    # Cycles' own diffuse colour of the empty tree.
    colour = demo.bake_cycles(bpy.context, empty, pass_filter=('COLOR',), resolution=4, samples=1)
    np.testing.assert_allclose(colour[..., :3], 0.0, atol=1e-7)


def _image(name, pixels, float_buffer=True):
    h, w = pixels.shape[:2]
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=float_buffer)
    img.pixels.foreach_set(np.asarray(pixels, np.float32).ravel())
    return img


def _diffuse_with(name, build):
    mat = add_material(name, color=(0.1, 0.2, 0.3))
    tree = mat.node_tree
    diffuse = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    build(tree, diffuse)
    return mat


def albedo_at_uv(sa, obj, uv):
    """The scene's albedo at the point of object ``obj`` (index) whose render UV is ``uv``."""
    for t in np.flatnonzero(sa.triangle_object == obj):
        c = sa.triangle_uv[t].astype(np.float64)
        m = np.column_stack([c[1] - c[0], c[2] - c[0]])
        bu, bv = np.linalg.solve(m, np.asarray(uv, np.float64) - c[0])
        if bu >= -1e-9 and bv >= -1e-9 and bu + bv <= 1 + 1e-9:
            return sa.albedo_at(np.array([t]), np.array([bu], np.float32), np.array([bv], np.float32))[0]
    raise AssertionError(f"no triangle of object {obj} covers UV {uv}")


def test_textures_are_sampled_and_unsupported_links_are_reported(fresh_scene, extract):
    pixels = np.zeros((2, 4, 4), np.float32)
    pixels[..., 3] = 1
    pixels[0, :, :3] = (0.2, 0.4, 0.6)
    pixels[1, :, :3] = (0.6, 0.0, 0.2)
    img = _image("Checker", pixels)

    def textured(tree, diffuse):
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.name = "Albedo Map"
        tex.image = img
        tree.links.new(tex.outputs["Color"], diffuse.inputs["Color"])

    def noisy(tree, diffuse):
        noise = tree.nodes.new("ShaderNodeTexNoise")
        noise.name = "Noise Pattern"
        tree.links.new(noise.outputs["Color"], diffuse.inputs["Color"])

    for i, (name, build) in enumerate((("Textured", textured), ("Noisy", noisy))):
        bpy.ops.mesh.primitive_plane_add(size=1.0, location=(3 * i, 0, 0))
        obj = bpy.context.object
        obj.name = name
        obj.data.materials.append(_diffuse_with(name, build))
    sa = extract.extract_scene(bpy.context, [])
    albedo = {n: sa.triangle_albedo[sa.triangle_object == i][0] for i, n in enumerate(sa.object_names)}
    textured = sa.object_names.index("Textured")
    # Row 0 of the pixels is the bottom of the image (v in [0, 1/2)); linear interpolation
    # reaches the rows' own colours at their centres.
    np.testing.assert_allclose(albedo_at_uv(sa, textured, (0.3, 0.25)), (0.2, 0.4, 0.6), atol=1e-6)
    np.testing.assert_allclose(albedo_at_uv(sa, textured, (0.6, 0.75)), (0.6, 0.0, 0.2), atol=1e-6)
    np.testing.assert_allclose(albedo_at_uv(sa, textured, (0.6, 0.5)), (0.4, 0.2, 0.4), atol=1e-6)
    # The noise is beyond the reader: Cycles' own diffuse colour bake stands in for it.
    assert not np.allclose(albedo["Noisy"], (0.1, 0.2, 0.3), atol=1e-3)
    assert not any("Material 'Textured'" in w for w in sa.warnings)
    assert any("Material 'Noisy'" in w and "'Noise Pattern'" in w and "Cycles" in w for w in sa.warnings)


def test_srgb_byte_textures_are_linearised(fresh_scene, extract):
    pixels = np.ones((1, 2, 4), np.float32)
    pixels[0, :, :3] = 0.5
    img = _image("Srgb", pixels, float_buffer=False)
    assert img.colorspace_settings.name == 'sRGB' and not img.is_float

    def textured(tree, diffuse):
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.image = img
        tree.links.new(tex.outputs["Color"], diffuse.inputs["Color"])

    bpy.ops.mesh.primitive_plane_add(size=1.0)
    bpy.context.object.data.materials.append(_diffuse_with("Srgb", textured))
    sa = extract.extract_scene(bpy.context, [])
    byte = round(0.5 * 255) / 255
    np.testing.assert_allclose(sa.triangle_albedo[0], ((byte + 0.055) / 1.055) ** 2.4, atol=2e-3)


def test_principled_emission_mix_and_add_shaders(fresh_scene, extract):
    def principled(name, base, metallic=0.0, emission=(0, 0, 0), strength=0.0):
        mat = bpy.data.materials.new(name)
        node = next(n for n in mat.node_tree.nodes if n.type == 'BSDF_PRINCIPLED')
        node.inputs["Base Color"].default_value = (*base, 1)
        node.inputs["Metallic"].default_value = metallic
        node.inputs["Emission Color"].default_value = (*emission, 1)
        node.inputs["Emission Strength"].default_value = strength
        return mat

    mix = add_material("Mix", color=(1.0, 0.0, 0.0))
    tree = mix.node_tree
    red = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    output = tree.get_output_node('CYCLES')
    blue = tree.nodes.new("ShaderNodeBsdfDiffuse")
    blue.inputs["Color"].default_value = (0, 0, 1, 1)
    mixer = tree.nodes.new("ShaderNodeMixShader")
    mixer.name = "Half Half"
    mixer.inputs["Fac"].default_value = 0.25
    tree.links.new(red.outputs[0], mixer.inputs[1])
    tree.links.new(blue.outputs[0], mixer.inputs[2])
    tree.links.new(mixer.outputs[0], output.inputs["Surface"])

    glow = add_material("Glow", color=(0.5, 0.5, 0.5))
    tree = glow.node_tree
    diffuse = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (1.0, 0.5, 0.25, 1)
    emission.inputs["Strength"].default_value = 4.0
    adder = tree.nodes.new("ShaderNodeAddShader")
    tree.links.new(diffuse.outputs[0], adder.inputs[0])
    tree.links.new(emission.outputs[0], adder.inputs[1])
    tree.links.new(adder.outputs[0], tree.get_output_node('CYCLES').inputs["Surface"])

    materials = {
        "Plastic": principled("Plastic", (0.5, 0.25, 0.1)),
        "Metal": principled("Metal", (0.9, 0.9, 0.9), metallic=0.75),
        "Neon": principled("Neon", (0.2, 0.2, 0.2), emission=(0.0, 1.0, 0.5), strength=3.0),
        "Mix": mix,
        "Glow": glow,
    }
    for i, (name, mat) in enumerate(materials.items()):
        bpy.ops.mesh.primitive_plane_add(size=1.0, location=(3 * i, 0, 0))
        bpy.context.object.name = name
        bpy.context.object.data.materials.append(mat)
    sa = extract.extract_scene(bpy.context, [])
    get = {n: (sa.triangle_albedo[sa.triangle_object == i][0], sa.triangle_emission[sa.triangle_object == i][0])
           for i, n in enumerate(sa.object_names)}
    np.testing.assert_allclose(get["Plastic"][0], (0.5, 0.25, 0.1), rtol=1e-6)
    np.testing.assert_allclose(get["Plastic"][1], 0.0)
    np.testing.assert_allclose(get["Metal"][0], 0.9 * 0.25, rtol=1e-6)
    np.testing.assert_allclose(get["Neon"][1], (0.0, 3.0, 1.5), rtol=1e-6)
    np.testing.assert_allclose(get["Mix"][0], (0.75, 0.0, 0.25), rtol=1e-6)
    np.testing.assert_allclose(get["Glow"][0], 0.5, rtol=1e-6)
    np.testing.assert_allclose(get["Glow"][1], (4.0, 2.0, 1.0), rtol=1e-6)
    assert sa.triangle_emission_two_sided.all()
    # Metallic is modelled (issue 18, item 3): a conductor lobe of weight 0.75 over the specular
    # layer's 0.25, no warning
    assert not any("Metallic" in w for w in sa.warnings)
    metal = sa.materials.names.index("Metal")
    assert sa.triangle_material[sa.triangle_object == sa.object_names.index("Metal")][0] == metal
    np.testing.assert_allclose(sa.materials.weight[metal, :2, 0], (0.75, 0.25))
    assert tuple(sa.materials.kind[metal, :2]) == (2, 1)   # CONDUCTOR, DIELECTRIC
    # Mixing and adding diffuse and emission closures is exact: no warning.
    assert not any("'Half Half'" in w or "Add Shader" in w for w in sa.warnings)


def test_multiple_material_slots_per_polygon(fresh_scene, extract):
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    cube = bpy.context.object
    cube.data.materials.append(add_material("A", color=(0.1, 0.1, 0.1)))
    cube.data.materials.append(add_material("B", color=(0.9, 0.9, 0.9)))
    index = np.zeros(6, np.int32)
    index[3] = 1
    cube.data.polygons.foreach_set("material_index", index)
    cube.data.update()
    sa = extract.extract_scene(bpy.context, [cube])
    assert sa.n_triangles == 12
    assert np.isclose(sa.triangle_albedo[:, 0], 0.9).sum() == 2
    assert np.isclose(sa.triangle_albedo[:, 0], 0.1).sum() == 10


def test_active_render_uv_map_is_extracted(fresh_scene, extract):
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    plane = bpy.context.object
    first = plane.data.uv_layers[0]
    second = plane.data.uv_layers.new(name="Lightmap")
    uv = np.empty(len(plane.data.loops) * 2, np.float32)
    first.data.foreach_get("uv", uv)
    second.data.foreach_set("uv", uv * 0.5 + 0.25)
    second.active_render = True
    plane.data.uv_layers.active = first
    sa = extract.extract_scene(bpy.context, [plane])
    assert sa.triangle_uv.min() == pytest.approx(0.25) and sa.triangle_uv.max() == pytest.approx(0.75)
    assert sa.object_has_uv.tolist() == [True]
    plane.data.uv_layers.remove(plane.data.uv_layers["Lightmap"])
    plane.data.uv_layers.remove(plane.data.uv_layers[0])
    plane.data.update()
    sa = extract.extract_scene(bpy.context, [plane])
    assert sa.object_has_uv.tolist() == [False]
    assert any("no UV map" in w for w in sa.warnings)


def _area_light(name, location, shape='RECTANGLE', size=(0.5, 0.25), power=20.0, colour=(1.0, 0.5, 0.25),
                scale=(1.0, 1.0, 1.0), rotation=(0.0, 0.0, 0.0)):
    data = bpy.data.lights.new(name, 'AREA')
    data.shape = shape
    data.size, data.size_y = size
    data.energy = power
    data.color = colour
    obj = bpy.data.objects.new(name, data)
    obj.location, obj.scale, obj.rotation_euler = location, scale, rotation
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    return obj


def test_area_light_becomes_a_one_sided_lamp_with_cycles_radiance(fresh_scene, extract, demo, library, lmdp_ext):
    """Radiance P c / (π A) facing -Z (a lamp, not geometry: Cycles' lights occlude nothing),
    validated by Cycles' DIRECT bake of a floor under it."""
    texels = lmdp_ext.sub("lmdp_addon.bake.texels")
    demo.configure_cycles(bpy.context.scene)
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    floor = bpy.context.object
    floor.name = "Floor"
    floor.data.materials.append(add_material("White"))
    light = _area_light("Panel", (0.1, -0.05, 0.8), scale=(1.5, 2.0, 1.0))
    sa = extract.extract_scene(bpy.context, [floor])
    assert "Panel" not in sa.object_names and sa.lamps.names == ["Panel"]
    lamps = lmdp_ext.sub("lmdp_addon.lamps")
    assert sa.lamps.kind.tolist() == [lamps.AREA]
    np.testing.assert_allclose(sa.lamps.axis[0], [0, 0, -1.0], atol=1e-6)
    a, b = 0.5 * 1.5, 0.25 * 2.0
    assert sa.lamps.area[0] == pytest.approx(a * b)
    L = 20.0 * np.array([1.0, 0.5, 0.25]) / (np.pi * a * b)
    np.testing.assert_allclose(sa.lamps.emission[0], L, rtol=1e-6)
    normals, _ = sa.triangle_geometry()
    # Cycles: the floor's DIRECT bake is L F(texel) with the rectangle form factor.
    R = 12
    fm = sa.triangle_object == sa.object_names.index("Floor")
    ts = texels.rasterize_texels(sa.triangle_uv[fm], sa.corners()[fm], normals[fm], R)
    # Cycles averages each texel over its footprint (texels.sample_footprint): so does the reference.
    footprint = texels.sample_footprint(ts, 4000, np.random.default_rng(0))
    offset = np.array([0.1, -0.05]) - footprint.position[..., :2]
    F = library.point_to_parallel_square_form_factor(a, 0.8, offset, side_y=b).mean(axis=1)
    direct, sigma = bake_twice(demo, floor, pass_filter=('DIRECT',), resolution=R, samples=256)
    measured = direct[ts.row, ts.col, :3]
    expected = np.outer(F, L)
    assert_matches_monte_carlo(measured, expected, sigma)
    # One-sided: a floor above the light receives nothing from it.
    light.location.z = -0.8
    bpy.context.view_layer.update()
    dark = demo.bake_cycles(bpy.context, floor, pass_filter=('DIRECT',), resolution=4, samples=16)
    assert np.abs(dark[..., :3]).max() == 0.0


def test_light_options_disk_exposure_and_point_and_sun_lamps(fresh_scene, extract, lmdp_ext):
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    disk = _area_light("Disk", (0, 0, 1), shape='DISK', size=(0.4, 0.4), power=10.0, colour=(1, 1, 1))
    disk.data.exposure = 1.0
    raw = _area_light("Raw", (0, 0, 2), shape='SQUARE', size=(0.5, 0.5), power=3.0, colour=(1, 1, 1))
    raw.data.normalize = False
    point = bpy.data.objects.new("Bulb", bpy.data.lights.new("Bulb", 'POINT'))
    sun = bpy.data.objects.new("Sunlight", bpy.data.lights.new("Sunlight", 'SUN'))
    for obj in (point, sun):
        bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    sa = extract.extract_scene(bpy.context, [])
    lamps = lmdp_ext.sub("lmdp_addon.lamps")
    index = {n: i for i, n in enumerate(sa.lamps.names)}
    assert set(index) == {"Disk", "Raw", "Bulb", "Sunlight"} and sa.object_names == ["Plane"]
    disk_area = np.pi / 4 * 0.4 * 0.4
    d = index["Disk"]
    assert sa.lamps.ellipse[d] and sa.lamps.area[d] == pytest.approx(disk_area)
    np.testing.assert_allclose(sa.lamps.emission[d], 10.0 * 2.0 / (np.pi * disk_area), rtol=1e-6)
    np.testing.assert_allclose(sa.lamps.emission[index["Raw"]], 3.0 / np.pi, rtol=1e-6)
    # Cycles' conventions: a point light's radiance P / (π 4π r²) (intensity P / 4π at r = 0), a
    # sun's S / (π sin² θ) over its cone of half-angle θ
    assert sa.lamps.kind[index["Bulb"]] == lamps.POINT and sa.lamps.kind[index["Sunlight"]] == lamps.SUN
    bulb = point.data
    r = bulb.shadow_soft_size
    np.testing.assert_allclose(sa.lamps.emission[index["Bulb"]],
                               bulb.energy / (np.pi * (4 * np.pi * r * r if r > 0 else 4.0)), rtol=1e-5)
    half = sun.data.angle / 2
    np.testing.assert_allclose(sa.lamps.emission[index["Sunlight"]],
                               sun.data.energy / (np.pi * np.sin(half) ** 2), rtol=1e-4)
    assert not any("skipped" in w or "Bulb" in w or "Sunlight" in w for w in sa.warnings), sa.warnings


def test_world_background_colour_strength_and_environment_map(fresh_scene, extract):
    assert np.all(extract.extract_scene(bpy.context, []).world_radiance == 0)  # no world: black
    world = bpy.data.worlds.new("Sky")
    bpy.context.scene.world = world
    background = world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = (0.5, 0.25, 1.0, 1)
    background.inputs["Strength"].default_value = 2.0
    np.testing.assert_allclose(extract.extract_scene(bpy.context, []).world_radiance, (1.0, 0.5, 2.0), rtol=1e-6)
    # An equirectangular map (issue 19): an environment map x Strength; world_radiance is its
    # mean over the sphere (bright top half, dark bottom: half), and nothing is approximated.
    pixels = np.ones((4, 8, 4), np.float32)
    pixels[:2, :, :3] = 0.0
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = _image("Env", pixels)
    world.node_tree.links.new(env.outputs["Color"], background.inputs["Color"])
    sa = extract.extract_scene(bpy.context, [])
    np.testing.assert_allclose(sa.world_radiance, 2.0 * 0.5, rtol=1e-6)
    assert sa.environment is not None and sa.environment.radiance.shape == (4, 8, 3)
    # the centres of the top and bottom rows (between them Cycles' periodic lookup blends)
    z = np.cos(np.pi / 8)
    centres = np.array([[0.0, np.sqrt(1 - z * z), z], [0.0, np.sqrt(1 - z * z), -z]])
    np.testing.assert_allclose(sa.environment.radiance_at(centres), [[2.0] * 3, [0.0] * 3], atol=1e-5)
    assert not any("World 'Sky'" in w for w in sa.warnings), sa.warnings


def test_instances_are_extracted_in_world_space(fresh_scene, extract):
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    source = bpy.context.object
    source.name = "Tile"
    collection = bpy.data.collections.new("Tiles")
    collection.objects.link(source)
    bpy.context.scene.collection.objects.unlink(source)
    bpy.context.scene.collection.children.link(collection)
    bpy.context.view_layer.layer_collection.children["Tiles"].exclude = True
    for i in range(3):
        inst = bpy.data.objects.new(f"Copy{i}", None)
        inst.instance_type = 'COLLECTION'
        inst.instance_collection = collection
        inst.location = (2.0 * i, 0.0, 1.0)
        bpy.context.scene.collection.objects.link(inst)
    bpy.context.view_layer.update()
    sa = extract.extract_scene(bpy.context, [bpy.data.objects["Copy1"]])
    assert sorted(sa.object_names) == ["Copy0/Tile#0", "Copy1/Tile#0", "Copy2/Tile#0"]
    carried = dict(zip(sa.object_names, sa.object_carries_states))
    assert carried["Copy1/Tile#0"] and not carried["Copy0/Tile#0"]
    centres = sorted(sa.vertices[sa.triangles[sa.triangle_object == k]].reshape(-1, 3).mean(0)[0]
                     for k in range(3))
    np.testing.assert_allclose(centres, [0.0, 2.0, 4.0], atol=1e-6)
    np.testing.assert_allclose(sa.vertices[:, 2], 1.0)


def test_capture_right_after_an_object_is_removed(fresh_scene, extract):
    """A script that removes an object and captures at once: the view layer still lists the
    removed object as None until it is updated; the capture (its colour-bake pre-pass walks the
    view layer) skips it instead of failing."""
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    bpy.data.objects.remove(bpy.data.objects["Light"])
    meshes = [o for o in bpy.context.scene.objects if o.type == 'MESH']
    sa = extract.extract_scene(bpy.context, meshes)
    assert "Light" not in sa.object_names and len(sa.object_names) == len(meshes)
