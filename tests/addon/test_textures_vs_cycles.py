"""Textured colour, colour attributes, alpha and emission chains against Cycles (issue 18, items
2, 4, 5).

* The diffuse colour at every texel is compared with Cycles' own DIFFUSE COLOR bake of the same
  texels with one sample: Cycles' sample 0 shades exactly the texel point (``bake/texels.py``),
  so the engine's ``SceneArrays.albedo_at`` there (times alpha: the colour pass holds the
  diffuse closure's weight) must agree to float precision, whatever the image's wrap mode,
  interpolation, colour space and the chain of nodes in front of Base Color.
* The indirect light of a textured box in a lit room and of a floor under an alpha-cut-out leaf
  plane is compared with Cycles' DIFFUSE INDIRECT bake of the same texels (clamping off, the
  same bounces), as in ``test_bake_vs_cycles``: mean within 2 % and 5 standard errors of both.
"""
import os

import bpy
import numpy as np
import pytest

from helpers import select
from test_bake_vs_cycles import K, assert_means_agree, build, compare, lmdp_bake, reference

RESOLUTION = 24


def image(name, pixels, float_buffer=False, colorspace=None):
    h, w = pixels.shape[:2]
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=float_buffer)
    if colorspace:   # before the pixels: changing it regenerates a generated image
        img.colorspace_settings.name = colorspace
    img.pixels.foreach_set(np.asarray(pixels, np.float32).ravel())
    img.pack()
    return img


def checker(n, rng, alpha=None):
    px = np.ones((n, n, 4), np.float32)
    px[..., :3] = rng.random((n, n, 3)) * 0.8 + 0.1
    if alpha is not None:
        px[..., 3] = alpha
    return px


def principled_material(name):
    """A Principled BSDF without its specular layer (IOR Level 0: Cycles' diffuse colour is then
    Base Color; the specular layer is another subsystem's)."""
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == 'BSDF_PRINCIPLED')
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    return mat, tree, bsdf


def image_node(tree, img, interpolation='Linear', extension='REPEAT'):
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    tex.interpolation = interpolation
    tex.extension = extension
    return tex


def plane(name, location, mat):
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=location)
    obj = bpy.context.object
    obj.name = name
    obj.data.materials.append(mat)
    return obj


def mapped(tree, tex, scale=(2.0, 1.5, 1.0), rotation=0.3, location=(-0.4, 0.2, 0.0), uv_map=None):
    mapping = tree.nodes.new("ShaderNodeMapping")
    mapping.inputs["Scale"].default_value = scale
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, rotation)
    mapping.inputs["Location"].default_value = location
    if uv_map:
        source = tree.nodes.new("ShaderNodeUVMap")
        source.uv_map = uv_map
        tree.links.new(source.outputs["UV"], mapping.inputs["Vector"])
    else:
        source = tree.nodes.new("ShaderNodeTexCoord")
        tree.links.new(source.outputs["UV"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])


def textured_planes(rng):
    """Planes whose materials exercise every supported path into Base Color."""
    made = []
    # sRGB bytes, linear, repeat, through a Mapping node.
    mat, tree, bsdf = principled_material("Repeat")
    tex = image_node(tree, image("RepeatImage", checker(8, rng)))
    mapped(tree, tex)
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    made.append(plane("Repeat", (0, 0, 0), mat))
    # float image, closest, mirror, on a second UV map.
    mat, tree, bsdf = principled_material("Mirror")
    tex = image_node(tree, image("MirrorImage", checker(5, rng), float_buffer=True), 'Closest', 'MIRROR')
    mapped(tree, tex, scale=(1.3, 1.7, 1.0), rotation=0.0, location=(-0.2, -0.3, 0.0), uv_map="Second")
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    made.append(plane("Mirror", (2, 0, 0), mat))
    second = made[-1].data.uv_layers.new(name="Second")
    uv = np.empty(2 * len(made[-1].data.loops), np.float32)
    second.data.foreach_get("uv", uv)
    second.data.foreach_set("uv", uv * 2.0 - 0.5)
    made[-1].data.uv_layers.active_index = 0
    # extend and clip, non-colour data, a chain of colour nodes inside a node group.
    mat, tree, bsdf = principled_material("Chain")
    group = bpy.data.node_groups.new("Grade", 'ShaderNodeTree')
    group.interface.new_socket("Color", in_out='INPUT', socket_type='NodeSocketColor')
    group.interface.new_socket("Color", in_out='OUTPUT', socket_type='NodeSocketColor')
    g_in, g_out = group.nodes.new("NodeGroupInput"), group.nodes.new("NodeGroupOutput")
    hsv = group.nodes.new("ShaderNodeHueSaturation")
    hsv.inputs["Hue"].default_value = 0.6
    hsv.inputs["Saturation"].default_value = 0.7
    hsv.inputs["Value"].default_value = 1.1
    invert = group.nodes.new("ShaderNodeInvert")
    invert.inputs["Fac"].default_value = 0.3
    gamma = group.nodes.new("ShaderNodeGamma")
    gamma.inputs["Gamma"].default_value = 1.5
    bright = group.nodes.new("ShaderNodeBrightContrast")
    bright.inputs["Bright"].default_value = 0.05
    bright.inputs["Contrast"].default_value = 0.2
    group.links.new(g_in.outputs[0], hsv.inputs["Color"])
    group.links.new(hsv.outputs[0], invert.inputs["Color"])
    group.links.new(invert.outputs[0], gamma.inputs["Color"])
    group.links.new(gamma.outputs[0], bright.inputs["Color"])
    group.links.new(bright.outputs[0], g_out.inputs[0])
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    a = image_node(tree, image("ExtendImage", checker(6, rng), colorspace='Non-Color'), 'Linear', 'EXTEND')
    mapped(tree, a, scale=(1.6, 1.6, 1.0), rotation=0.2, location=(-0.3, -0.3, 0.0))
    b = image_node(tree, image("ClipImage", checker(4, rng)), 'Linear', 'CLIP')
    mapped(tree, b, scale=(1.4, 1.2, 1.0), rotation=-0.1, location=(-0.2, -0.1, 0.0))
    mix = tree.nodes.new("ShaderNodeMix")
    mix.data_type = 'RGBA'
    mix.blend_type = 'MULTIPLY'
    mix.inputs["Factor"].default_value = 0.7
    tree.links.new(a.outputs["Color"], mix.inputs["A"])
    tree.links.new(b.outputs["Color"], mix.inputs["B"])
    tree.links.new(mix.outputs["Result"], node.inputs[0])
    tree.links.new(node.outputs[0], bsdf.inputs["Base Color"])
    made.append(plane("Chain", (4, 0, 0), mat))
    # colour attribute (corners) screened over an image, with RGB curves.
    mat, tree, bsdf = principled_material("Attribute")
    attribute = tree.nodes.new("ShaderNodeVertexColor")
    attribute.layer_name = "Paint"
    tex = image_node(tree, image("AttrImage", checker(3, rng)))
    mix = tree.nodes.new("ShaderNodeMix")
    mix.data_type = 'RGBA'
    mix.blend_type = 'SCREEN'
    mix.inputs["Factor"].default_value = 0.6
    curves = tree.nodes.new("ShaderNodeRGBCurve")
    point = curves.mapping.curves[3].points
    point[1].location = (1.0, 0.8)
    point.new(0.5, 0.6)
    curves.mapping.update()
    tree.links.new(attribute.outputs["Color"], mix.inputs["A"])
    tree.links.new(tex.outputs["Color"], mix.inputs["B"])
    tree.links.new(mix.outputs["Result"], curves.inputs["Color"])
    tree.links.new(curves.outputs["Color"], bsdf.inputs["Base Color"])
    made.append(plane("Attribute", (6, 0, 0), mat))
    mesh = made[-1].data
    paint = mesh.color_attributes.new("Paint", 'FLOAT_COLOR', 'CORNER')
    colours = np.ones((len(mesh.loops), 4), np.float32)
    colours[:, :3] = rng.random((len(mesh.loops), 3))
    paint.data.foreach_set("color", colours.ravel())
    # cubic and smart interpolation (Cycles: the cubic B-spline), repeat and clip.
    for name, interpolation, extension in (("Cubic", 'Cubic', 'REPEAT'), ("Smart", 'Smart', 'CLIP')):
        mat, tree, bsdf = principled_material(name)
        tex = image_node(tree, image(f"{name}Image", checker(5, rng)), interpolation, extension)
        mapped(tree, tex, scale=(1.3, 1.4, 1.0), rotation=0.4, location=(-0.2, -0.25, 0.0))
        tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
        made.append(plane(name, (12 + 2 * len(made), 0, 0), mat))
    # Principled Alpha from the image's alpha channel.
    mat, tree, bsdf = principled_material("Alpha")
    tex = image_node(tree, image("AlphaImage", checker(4, rng, alpha=rng.random((4, 4)))))
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    tree.links.new(tex.outputs["Alpha"], bsdf.inputs["Alpha"])
    made.append(plane("Alpha", (8, 0, 0), mat))
    return made


def test_albedo_at_texels_matches_cycles_diffuse_color(fresh_scene, lmdp_ext, demo):
    """Cycles' DIFFUSE COLOR bake (1 sample: the texel point itself) against the engine's
    albedo x alpha at the same texels, per material: within 2e-3 (8-bit images, float32)."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    texels = lmdp_ext.sub("lmdp_addon.bake.texels")
    objects = textured_planes(np.random.default_rng(3))
    bpy.context.scene.render.engine = 'CYCLES'
    sa = extract.extract_scene(bpy.context, objects)
    assert sa.surface is not None
    normals, _ = sa.triangle_geometry()
    for index, obj in enumerate(objects):
        o = sa.object_names.index(obj.name)
        tris = np.flatnonzero(sa.triangle_object == o)
        ts = texels.rasterize_texels(sa.triangle_uv[tris], sa.corners()[tris], normals[tris], RESOLUTION)
        t = tris[ts.triangle]
        bu, bv = ts.barycentric[:, 1].astype(np.float32), ts.barycentric[:, 2].astype(np.float32)
        ours = sa.albedo_at(t, bu, bv) * sa.surface.alpha(t, bu, bv)[:, None]
        cycles = demo.bake_cycles(bpy.context, obj, 'DIFFUSE', ('COLOR',), RESOLUTION, samples=1)
        cyc = cycles[ts.row, ts.col, :3]
        error = np.abs(ours - cyc).max()
        print(f"{obj.name}: {len(t)} texels, max |ours - Cycles| = {error:.2e}, mean {cyc.mean(0)}")
        assert error < 2e-3, (obj.name, error)
    assert not any(f"Material '{obj.name}'" in w for obj in objects for w in sa.warnings), sa.warnings


# -- the indirect light against Cycles' DIFFUSE INDIRECT bake -----------------------------------

def check_indirect(lmdp_ext, demo, name, samples=512, ref_samples=1024, mode="UNGUIDED"):
    """lmdp.bake (``mode``) of ``name`` against Cycles (two seeds): the mean within 2 % and 5
    standard errors of both, the per-texel squared differences as the variances predict."""
    refs = reference(lmdp_ext, demo, name, RESOLUTION, ref_samples)
    ob = lmdp_bake(lmdp_ext, name, mode, RESOLUTION, samples)
    ours, cyc, var_o, var_c = compare(ob, refs)
    rel, rel_sigma = assert_means_agree(ours, cyc, var_o, var_c)
    excess = ((ours - cyc) ** 2 - var_o - var_c).sum(axis=1)
    print(f"{name}: {len(ours)} texels, mean ours {ours.mean(axis=0)} Cycles {cyc.mean(axis=0)}: "
          f"{np.round(rel * 100, 2)} % ± {np.round(rel_sigma * 100, 2)} % (1 s.e.), per-texel excess "
          f"{excess.mean():.3g} ± {excess.std() / np.sqrt(len(excess)):.3g}")
    assert np.all(np.abs(rel) < 0.02), rel
    assert abs(excess.mean()) <= K * excess.std() / np.sqrt(len(excess)), excess.mean()
    return rel


def texel_image(lmdp_ext, obj, size, colour_of):
    """An (size, size, 4) image whose pixels on ``obj``'s render UV islands have the colour
    ``colour_of(positions (n, 3)) -> (n, 3)`` of the surface point each stands for (others: the
    mean), so a texture's colour follows the object's geometry."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    texels = lmdp_ext.sub("lmdp_addon.bake.texels")
    sa = extract.extract_scene(bpy.context, [obj])
    tris = np.flatnonzero(sa.triangle_object == sa.object_names.index(obj.name))
    normals, _ = sa.triangle_geometry()
    ts = texels.rasterize_texels(sa.triangle_uv[tris], sa.corners()[tris], normals[tris], size)
    rgb = colour_of(ts.position)
    px = np.ones((size, size, 4), np.float32)
    px[..., :3] = rgb.mean(axis=0)
    px[ts.row, ts.col, :3] = rgb
    return px


def textured_box(lmdp_ext):
    """The Cornell box's tall box with an sRGB Image Texture whose colour goes from orange at the
    bottom to blue at the top, with a checker, through a Mix (Multiply, factor 0.8) by a warm
    RGB, into a Diffuse BSDF."""
    box = bpy.data.objects["TallBox"]

    def colour(p):
        t = np.clip(p[:, 2:3] / 0.6, 0, 1)
        gradient = (1 - t) * np.array([0.95, 0.55, 0.15]) + t * np.array([0.15, 0.3, 0.9])
        check = (np.floor(p[:, 0] * 10) + np.floor(p[:, 1] * 10) + np.floor(p[:, 2] * 10)) % 2
        return gradient * (0.55 + 0.45 * check[:, None])

    img = image("BoxTexture", texel_image(lmdp_ext, box, 32, colour))
    mat = box.data.materials[0]
    tree = mat.node_tree
    diffuse = next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE')
    tex = image_node(tree, img)
    rgb = tree.nodes.new("ShaderNodeRGB")
    rgb.outputs[0].default_value = (0.9, 0.85, 0.8, 1.0)
    mix = tree.nodes.new("ShaderNodeMix")
    mix.data_type = 'RGBA'
    mix.blend_type = 'MULTIPLY'
    mix.inputs["Factor"].default_value = 0.8
    tree.links.new(tex.outputs["Color"], mix.inputs[6])
    tree.links.new(rgb.outputs[0], mix.inputs[7])
    tree.links.new(mix.outputs[2], diffuse.inputs["Color"])
    return box


@pytest.mark.parametrize("name", ["Floor", "TallBox"])
def test_textured_box_in_a_lit_room_matches_cycles(fresh_scene, lmdp_ext, demo, name):
    build("CORNELL_BOX", lmdp_ext)
    textured_box(lmdp_ext)
    check_indirect(lmdp_ext, demo, name)


def leaf_plane():
    """A 0.5 m plane 0.75 m above the Cornell floor (above both boxes: a plane coplanar with a
    box's top would make the comparison meaningless) with a Principled BSDF whose Base Color and
    Alpha come from an image: a leaf-green disc with holes (alpha 1) on alpha 0."""
    n = 32
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n - 0.5
    inside = (x ** 2 + (y / 0.7) ** 2 < 0.2) & ~(((x * 6) % 1 < 0.3) & ((y * 6) % 1 < 0.3))
    px = np.zeros((n, n, 4), np.float32)
    px[..., :3] = (0.15, 0.6, 0.1)
    px[..., 3] = inside
    mat, tree, bsdf = principled_material("Leaf")
    tex = image_node(tree, image("LeafImage", px))
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    tree.links.new(tex.outputs["Alpha"], bsdf.inputs["Alpha"])
    leaf = plane("Leaf", (0.1, -0.15, 0.75), mat)
    leaf.scale = (0.5, 0.5, 1.0)
    bpy.context.view_layer.update()
    return leaf


def test_alpha_cut_out_leaf_over_a_floor_matches_cycles(fresh_scene, lmdp_ext, demo):
    """Rays and shadow rays pass the leaf's cut-out parts as in Cycles: the floor under it."""
    build("CORNELL_BOX", lmdp_ext)
    leaf_plane()
    extract = lmdp_ext.sub("operators.adapters.extract")
    sa = extract.extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert sa.surface.has_alpha
    check_indirect(lmdp_ext, demo, "Floor")


@pytest.mark.parametrize("scene, mode", [("leaf", "GUIDED"), ("box", "FINAL_GATHER")])
def test_solved_modes_see_textures_and_alpha(fresh_scene, lmdp_ext, demo, scene, mode):
    """The LMDP's states take the albedo at their points and its rays pass the leaf: GUIDED
    (unbiased) and FINAL_GATHER (biased by the discretisation, measured +0.6 %) on the floor."""
    build("CORNELL_BOX", lmdp_ext)
    if scene == "box":
        textured_box(lmdp_ext)
    else:
        leaf_plane()
    fresh_scene.lmdp.point_count = 2048
    fresh_scene.lmdp.cost_mode = 'PHYSICAL'
    select([o for o in bpy.data.objects if o.type == 'MESH' and o.name != "Light"])
    assert bpy.ops.lmdp.run_pipeline(show=False, bake=False) == {'FINISHED'}
    check_indirect(lmdp_ext, demo, "Floor", mode=mode)


def test_tinted_transparent_leaf_over_a_floor_matches_cycles(fresh_scene, lmdp_ext, demo):
    """A Mix Shader of a Diffuse BSDF and an orange Transparent BSDF (factor from the leaf image's
    alpha, so the cut-out parts are fully transparent): rays that pass carry the colour."""
    build("CORNELL_BOX", lmdp_ext)
    leaf = leaf_plane()
    tree = leaf.data.materials[0].node_tree
    tex = next(n for n in tree.nodes if n.type == 'TEX_IMAGE')
    output = tree.get_output_node('CYCLES')
    diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (0.2, 0.7, 0.2, 1.0)
    clear = tree.nodes.new("ShaderNodeBsdfTransparent")
    clear.inputs["Color"].default_value = (0.95, 0.45, 0.1, 1.0)
    invert = tree.nodes.new("ShaderNodeMath")
    invert.operation = 'SUBTRACT'
    invert.inputs[0].default_value = 1.0
    tree.links.new(tex.outputs["Alpha"], invert.inputs[1])
    mix = tree.nodes.new("ShaderNodeMixShader")
    tree.links.new(invert.outputs[0], mix.inputs["Fac"])
    tree.links.new(diffuse.outputs[0], mix.inputs[1])
    tree.links.new(clear.outputs[0], mix.inputs[2])
    tree.links.new(mix.outputs[0], output.inputs["Surface"])
    extract = lmdp_ext.sub("operators.adapters.extract")
    sa = extract.extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert sa.surface.has_tint and not any("Leaf" in w for w in sa.warnings), sa.warnings
    check_indirect(lmdp_ext, demo, "Floor")


# -- the image cache ------------------------------------------------------------------------------

def test_images_are_read_once_until_they_change(fresh_scene, lmdp_ext, tmp_path):
    """A file image is read on the first extraction only; editing its pixels (the image becomes
    dirty), replacing it by another image of the same name and size, or changing its colour
    space make the next extraction read it again and see the change."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    shading = lmdp_ext.sub("operators.adapters.shading")
    px = np.ones((64, 64, 4), np.float32)
    px[..., :3] = 0.5
    img = bpy.data.images.new("Cached", 64, 64, alpha=True)
    img.pixels.foreach_set(px.ravel())
    img.filepath_raw = str(tmp_path / "cached.png")
    img.file_format = 'PNG'
    img.save()
    img.reload()
    mat = bpy.data.materials.new("Cached")
    bsdf = next(n for n in mat.node_tree.nodes if n.type == 'BSDF_PRINCIPLED')
    tex = image_node(mat.node_tree, img)
    mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    obj = plane("CachedPlane", (0, 0, 0), mat)

    def albedo():
        return extract.extract_scene(bpy.context, [obj]).triangle_albedo[0, 0]

    reads = shading.IMAGE_CACHE.reads
    first = albedo()
    assert shading.IMAGE_CACHE.reads == reads + 1
    assert albedo() == first and albedo() == first
    assert shading.IMAGE_CACHE.reads == reads + 1               # no read on later calls
    px[..., :3] = 0.25
    img.pixels.foreach_set(px.ravel())                          # edited in memory: dirty
    assert img.is_dirty
    edited = albedo()
    assert edited < first and shading.IMAGE_CACHE.reads == reads + 2
    img.colorspace_settings.name = 'Non-Color'
    assert albedo() != edited
    bpy.data.images.remove(img)
    other = bpy.data.images.new("Cached", 64, 64, alpha=True)   # same name and size
    other.pixels.foreach_set(np.full(64 * 64 * 4, 1.0, np.float32))
    tex.image = other
    assert albedo() == pytest.approx(1.0)


# -- emission ----------------------------------------------------------------------------------

def test_emission_in_node_groups_with_strength_chains_and_textures(fresh_scene, lmdp_ext, demo):
    """An Emission shader inside a node group whose Strength is Value x Math (Multiply) outside
    it: the radiance Cycles' EMIT bake gives (1 sample, the texel points); a Principled BSDF
    whose Emission Color is an image: averaged per triangle, with a warning naming the material."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    group = bpy.data.node_groups.new("Glow Group", 'ShaderNodeTree')
    group.interface.new_socket("Strength", in_out='INPUT', socket_type='NodeSocketFloat')
    group.interface.new_socket("Shader", in_out='OUTPUT', socket_type='NodeSocketShader')
    g_in, g_out = group.nodes.new("NodeGroupInput"), group.nodes.new("NodeGroupOutput")
    emission = group.nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (1.0, 0.5, 0.25, 1.0)
    group.links.new(g_in.outputs[0], emission.inputs["Strength"])
    group.links.new(emission.outputs[0], g_out.inputs[0])
    mat = bpy.data.materials.new("Grouped Glow")
    tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    value = tree.nodes.new("ShaderNodeValue")
    value.outputs[0].default_value = 2.0
    math = tree.nodes.new("ShaderNodeMath")
    math.operation = 'MULTIPLY'
    math.inputs[1].default_value = 1.5
    tree.links.new(value.outputs[0], math.inputs[0])
    tree.links.new(math.outputs[0], node.inputs[0])
    tree.links.new(node.outputs[0], out.inputs["Surface"])
    glow = plane("Glow", (0, 0, 0), mat)

    tex_mat, tex_tree, bsdf = principled_material("Screen")
    px = np.ones((8, 8, 4), np.float32)
    px[:, :4, :3] = 0.0                    # left half black, right half white
    tex = image_node(tex_tree, image("ScreenImage", px, float_buffer=True))
    tex_tree.links.new(tex.outputs["Color"], bsdf.inputs["Emission Color"])
    bsdf.inputs["Emission Strength"].default_value = 4.0
    plane("Screen", (3, 0, 0), tex_mat)

    sa = extract.extract_scene(bpy.context, [])
    assert sa.has_light()
    emitted = {n: sa.triangle_emission[sa.triangle_object == i] for i, n in enumerate(sa.object_names)}
    np.testing.assert_allclose(emitted["Glow"], [[3.0, 1.5, 0.75]] * 2, rtol=1e-6)
    cycles = demo.bake_cycles(bpy.context, glow, 'EMIT', (), 8, samples=1)[..., :3]
    np.testing.assert_allclose(cycles.reshape(-1, 3), [[3.0, 1.5, 0.75]] * 64, rtol=1e-5)
    # The screen's two triangles each cover half black, half white: 4 x 1/2 on average.
    np.testing.assert_allclose(emitted["Screen"].mean(), 2.0, rtol=0.05)
    assert any("Material 'Screen'" in w and "emission is textured" in w for w in sa.warnings)
    assert not any("Grouped Glow" in w for w in sa.warnings), sa.warnings


# -- a glTF scene as a new user would bake it ------------------------------------------------------

GLTF = "/work/fp/gltf/04_common_materials/04_common_materials.gltf"


def gltf_scene():
    """glTF-Sample-style "common materials" (a crate with an image texture on a plane, a red
    sphere) imported with Blender's glTF importer, a 3 m area light 8 m up, and a lightmap UV
    map (Smart UV Project, active for rendering) on each mesh; the crate's texture keeps its own
    UV map through a UV Map node. The Principled BSDFs' specular layer is switched off (IOR
    Level 0): it is not this subsystem's (issue 18, item 3)."""
    assert bpy.ops.import_scene.gltf(filepath=GLTF) == {'FINISHED'}
    crate = bpy.data.materials["Crate"].node_tree
    uv = crate.nodes.new("ShaderNodeUVMap")
    uv.uv_map = "UVMap"
    crate.links.new(uv.outputs["UV"], crate.nodes["Image Texture"].inputs["Vector"])
    for mat in bpy.data.materials:
        for node in (mat.node_tree.nodes if mat.node_tree else ()):
            if node.type == 'BSDF_PRINCIPLED':
                node.inputs["Specular IOR Level"].default_value = 0.0
    for name in ("Cube", "Plane", "Sphere"):
        obj = bpy.data.objects[name]
        layer = obj.data.uv_layers.new(name="Lightmap")
        layer.active_render = True
        obj.data.uv_layers.active = layer
        select([obj])
        bpy.ops.object.mode_set(mode='EDIT')
        bpy.ops.mesh.select_all(action='SELECT')
        bpy.ops.uv.smart_project(island_margin=0.05)
        bpy.ops.object.mode_set(mode='OBJECT')
    light = bpy.data.lights.new("Area", 'AREA')
    light.energy, light.size = 3000.0, 3.0
    lamp = bpy.data.objects.new("Area", light)
    lamp.location = (1.0, -1.0, 8.0)
    bpy.context.scene.collection.objects.link(lamp)
    cycles = bpy.context.scene.cycles
    cycles.sample_clamp_indirect = 0.0
    cycles.max_bounces = cycles.diffuse_bounces = 8      # the bake follows the scene's Light Paths
    bpy.context.view_layer.update()


@pytest.mark.skipif(not os.path.exists(GLTF), reason="the glTF sample is not on this machine")
@pytest.mark.parametrize("name", ["Cube", "Sphere"])
def test_gltf_scene_matches_cycles_per_receiver(fresh_scene, lmdp_ext, demo, name):
    """The textured crate and the red sphere (albedo 0 in green and blue: Cycles' pass division
    gives those channels the red one's value, and so does the bake)."""
    gltf_scene()
    check_indirect(lmdp_ext, demo, name)


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(GLTF), reason="the glTF sample is not on this machine")
def test_gltf_floor_matches_cycles(fresh_scene, lmdp_ext, demo):
    """The 20 m floor, lit only indirectly by what the crate and the sphere reflect (dark and
    noisy: more samples)."""
    gltf_scene()
    check_indirect(lmdp_ext, demo, "Plane", samples=16384, ref_samples=16384)


def test_colour_attribute_box_in_a_lit_room_matches_cycles(fresh_scene, lmdp_ext, demo):
    """The short box coloured by a Color Attribute (byte colours per face corner, saturated:
    some channels 0) into its Diffuse BSDF: the floor and the box itself."""
    build("CORNELL_BOX", lmdp_ext)
    box = bpy.data.objects["ShortBox"]
    mesh = box.data
    paint = mesh.color_attributes.new("Paint", 'BYTE_COLOR', 'CORNER')
    rng = np.random.default_rng(5)
    colours = np.ones((len(mesh.loops), 4), np.float32)
    colours[:, :3] = rng.choice([0.0, 0.3, 0.9], size=(len(mesh.loops), 3))
    paint.data.foreach_set("color", colours.ravel())
    tree = box.data.materials[0].node_tree
    node = tree.nodes.new("ShaderNodeVertexColor")
    node.layer_name = "Paint"
    tree.links.new(node.outputs["Color"], next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE').inputs["Color"])
    for name in ("Floor", "ShortBox"):
        check_indirect(lmdp_ext, demo, name)


GLTF_MASK = "/work/fp/gltf/01_alpha_mask/01_alpha_mask.gltf"


@pytest.mark.skipif(not os.path.exists(GLTF_MASK), reason="the glTF sample is not on this machine")
def test_gltf_alpha_mask_over_a_floor_matches_cycles(fresh_scene, lmdp_ext, demo):
    """glTF's alphaMode MASK as Blender's importer builds it (image alpha < cut-off, through Math
    nodes, into Principled Alpha), as a leaf 0.75 m over the Cornell floor (Metallic and the
    specular layer off: issue 18, item 3)."""
    build("CORNELL_BOX", lmdp_ext)
    assert bpy.ops.import_scene.gltf(filepath=GLTF_MASK) == {'FINISHED'}
    leaf = bpy.data.objects["Alpha_Mask"]
    for node in leaf.data.materials[0].node_tree.nodes:
        if node.type == 'BSDF_PRINCIPLED':   # glTF's default metal and specular: not this subsystem's
            node.inputs["Specular IOR Level"].default_value = 0.0
            node.inputs["Metallic"].default_value = 0.0
    corners = np.array([leaf.matrix_world @ v.co for v in leaf.data.vertices])
    size = float(np.ptp(corners, axis=0).max())
    leaf.scale = leaf.scale * (0.5 / size)
    bpy.context.view_layer.update()
    centre = np.array([leaf.matrix_world @ v.co for v in leaf.data.vertices]).mean(axis=0)
    leaf.location = np.array(leaf.location) + np.array([0.1, -0.15, 0.75]) - centre
    bpy.context.view_layer.update()
    extract = lmdp_ext.sub("operators.adapters.extract")
    sa = extract.extract_scene(bpy.context, [bpy.data.objects["Floor"]])
    assert sa.surface.has_alpha and not any("Alpha_Mask" in w for w in sa.warnings), sa.warnings
    check_indirect(lmdp_ext, demo, "Floor")


# -- node trees beyond the reader: Cycles' own diffuse colour -------------------------------------

def noisy_box():
    """The tall box's Diffuse BSDF fed by Noise Texture -> Color Ramp (orange to blue), which the
    reader cannot evaluate."""
    tree = bpy.data.objects["TallBox"].data.materials[0].node_tree
    noise = tree.nodes.new("ShaderNodeTexNoise")
    noise.name = "Grain"
    noise.inputs["Scale"].default_value = 3.0
    ramp = tree.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.9, 0.4, 0.1, 1.0)
    ramp.color_ramp.elements[1].color = (0.1, 0.3, 0.9, 1.0)
    tree.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    tree.links.new(ramp.outputs["Color"], next(n for n in tree.nodes if n.type == 'BSDF_DIFFUSE').inputs["Color"])
    return ramp


def test_unsupported_nodes_take_cycles_diffuse_colour(fresh_scene, lmdp_ext, demo):
    """Noise Texture -> Color Ramp: the albedo at the texels is Cycles' 1-sample DIFFUSE COLOR of
    them up to the interpolation of the 256² stand-in (mean |error| < 0.005), the bake of the
    floor and the box matches Cycles' DIFFUSE INDIRECT; the stand-in is baked once until the
    material changes."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    texels = lmdp_ext.sub("lmdp_addon.bake.texels")
    shading = lmdp_ext.sub("operators.adapters.shading")
    build("CORNELL_BOX", lmdp_ext)
    ramp = noisy_box()
    box = bpy.data.objects["TallBox"]
    bakes = shading.COLOUR_BAKES.bakes
    sa = extract.extract_scene(bpy.context, [box])
    assert shading.COLOUR_BAKES.bakes == bakes + 1
    assert any("'Color Ramp'" in w and "Cycles' own DIFFUSE COLOR" in w for w in sa.warnings), sa.warnings
    tris = np.flatnonzero(sa.triangle_object == sa.object_names.index("TallBox"))
    normals, _ = sa.triangle_geometry()
    ts = texels.rasterize_texels(sa.triangle_uv[tris], sa.corners()[tris], normals[tris], RESOLUTION)
    ours = sa.albedo_at(tris[ts.triangle], ts.barycentric[:, 1].astype(np.float32),
                        ts.barycentric[:, 2].astype(np.float32))
    cycles = demo.bake_cycles(bpy.context, box, 'DIFFUSE', ('COLOR',), RESOLUTION, samples=1)[ts.row, ts.col, :3]
    error = np.abs(ours - cycles)
    print(f"noise stand-in: mean |ours - Cycles| {error.mean():.2e}, max {error.max():.2e}, "
          f"spread of the colour {cycles.std(axis=0)}")
    assert error.mean() < 0.005
    extract.extract_scene(bpy.context, [box])
    assert shading.COLOUR_BAKES.bakes == bakes + 1                      # kept
    for name in ("Floor", "TallBox"):
        check_indirect(lmdp_ext, demo, name)
    # The add-on's MULTIPLY hook-up (lightmap x surface colour) stays invisible to the stand-in.
    select([box])
    assert bpy.ops.lmdp.bake(hook_up='MULTIPLY') == {'FINISHED'}
    hooked = extract.extract_scene(bpy.context, [box])
    again = hooked.albedo_at(tris[ts.triangle], ts.barycentric[:, 1].astype(np.float32),
                             ts.barycentric[:, 2].astype(np.float32))
    np.testing.assert_allclose(again, ours, atol=1e-6)
    # Under the PREVIEW hook-up Cycles would bake the preview: the kept bake serves, else a warning.
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    assert bpy.ops.lmdp.bake(hook_up='PREVIEW') == {'FINISHED'}
    previewed = extract.extract_scene(bpy.context, [box])
    np.testing.assert_allclose(previewed.albedo_at(tris[ts.triangle], ts.barycentric[:, 1].astype(np.float32),
                                                   ts.barycentric[:, 2].astype(np.float32)), ours, atol=1e-6)
    shading.COLOUR_BAKES._tables.clear()
    assert any("TallBox" in w and "preview" in w for w in extract.extract_scene(bpy.context, [box]).warnings)
    assert bpy.ops.lmdp.remove_bake_hookup() == {'FINISHED'}
    ramp.color_ramp.elements[1].color = (0.9, 0.9, 0.2, 1.0)
    extract.extract_scene(bpy.context, [box])
    assert shading.COLOUR_BAKES.bakes > bakes + 1                       # the material changed


GLTF_EMISSION = "/work/fp/gltf/14_emission_strength/14_emission_strength.gltf"


@pytest.mark.skipif(not os.path.exists(GLTF_EMISSION), reason="the glTF sample is not on this machine")
def test_gltf_emission_strength_matches_cycles(fresh_scene, lmdp_ext, demo):
    """glTF emissive factors, KHR_materials_emissive_strength and the spec-gloss node groups as
    Blender's importer builds them: the radiance of every constant emitter is Cycles' EMIT bake
    at its texels (to 1e-5); textured ones are their per-triangle mean (within 10 % of Cycles'
    texel mean) with a warning."""
    extract = lmdp_ext.sub("operators.adapters.extract")
    texels = lmdp_ext.sub("lmdp_addon.bake.texels")
    assert bpy.ops.import_scene.gltf(filepath=GLTF_EMISSION) == {'FINISHED'}
    objects = [o for o in bpy.data.objects if o.type == 'MESH']
    sa = extract.extract_scene(bpy.context, objects)
    normals, _ = sa.triangle_geometry()
    for obj in objects:
        tris = np.flatnonzero(sa.triangle_object == sa.object_names.index(obj.name))
        ts = texels.rasterize_texels(sa.triangle_uv[tris], sa.corners()[tris], normals[tris], 8)
        ours = sa.triangle_emission[tris[ts.triangle]].astype(np.float64)
        cycles = demo.bake_cycles(bpy.context, obj, 'EMIT', (), 8, samples=1)[ts.row, ts.col, :3]
        textured = any(f"Material '{obj.data.materials[0].name}': its emission is textured" in w for w in sa.warnings)
        print(f"{obj.name}: ours {ours.mean(axis=0)} Cycles {cycles.mean(axis=0)} textured {textured}")
        if textured:
            np.testing.assert_allclose(ours.mean(axis=0), cycles.mean(axis=0), rtol=0.1, atol=1e-6)
        else:
            np.testing.assert_allclose(ours, cycles, rtol=1e-5, atol=1e-6)
