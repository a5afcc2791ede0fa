"""Lightmap files (issue 21, item 6): each ``output_format`` and 8-bit copy reads back, with
Blender's own image reader, as the baked pixels to the format's precision; RGBM round trip; the
add-on's image loads from the file; a companion name held by a user's file is never replaced.
"""
import json
import os

import bpy
import numpy as np
import pytest

from helpers import select


@pytest.fixture
def baked_floor(fresh_scene, tmp_path):
    """The Cornell floor at 16 px, 16 samples (the ceiling light makes values above 1 near it
    on the walls; the floor's are below), written to ``tmp_path``."""
    assert bpy.ops.lmdp.add_demo_scene(kind='CORNELL_BOX') == {'FINISHED'}
    s = fresh_scene.lmdp
    s.bake_mode, s.bake_resolution, s.bake_samples, s.bake_margin = 'UNGUIDED', 16, 16, 2
    s.bake_content = 'DIRECT_INDIRECT'
    s.output_dir = str(tmp_path)
    return fresh_scene


def bake(lmdp_ext, name="Floor", **settings):
    for key, value in settings.items():
        setattr(bpy.context.scene.lmdp, key, value)
    select([bpy.data.objects[name]])
    assert bpy.ops.lmdp.bake() == {'FINISHED'}
    return lmdp_ext.sub("operators.session").session_for(bpy.context.scene).require("bake").object(name)


def read(path, colorspace='Non-Color'):
    image = bpy.data.images.load(str(path))
    try:
        image.colorspace_settings.name = colorspace
        px = np.empty(image.size[0] * image.size[1] * 4, np.float32)
        image.pixels.foreach_get(px)
        return px.reshape(image.size[1], image.size[0], 4)
    finally:
        bpy.data.images.remove(image)


def exr_channel_type(path):
    """OpenEXR pixel type of the first channel: 1 half, 2 float."""
    header = open(path, "rb").read(4096)
    start = header.index(b"chlist\x00") + len(b"chlist\x00") + 4
    name_end = header.index(b"\x00", start)
    return int.from_bytes(header[name_end + 1:name_end + 5], "little")


def stats(folder):
    with open(os.path.join(folder, "bake_stats.json"), encoding="utf-8") as fh:
        return json.load(fh)


def test_exr_float_is_exact_and_the_image_loads_from_it(baked_floor, lmdp_ext, tmp_path):
    ob = bake(lmdp_ext, output_format='EXR_FLOAT')
    path = tmp_path / "Floor_lmdp_indirect.exr"
    assert exr_channel_type(path) == 2
    np.testing.assert_array_equal(read(path), ob.image)
    image = bpy.data.images[ob.image_name]
    assert bpy.path.abspath(image.filepath_raw) == str(path) and image.file_format == 'OPEN_EXR'
    assert stats(tmp_path)["output"]["format"] == "EXR_FLOAT"


def test_exr_half_holds_half_floats(baked_floor, lmdp_ext, tmp_path):
    ob = bake(lmdp_ext, output_format='EXR_HALF')
    path = tmp_path / "Floor_lmdp_indirect.exr"
    assert exr_channel_type(path) == 1
    back = read(path)
    np.testing.assert_array_equal(back, ob.image.astype(np.float16).astype(np.float32))
    assert np.abs(back - ob.image).max() > 0       # really rounded: not the float file


def test_radiance_hdr_keeps_8_bits_of_the_brightest_channel(baked_floor, lmdp_ext, tmp_path):
    """RGBE: a shared exponent per texel, so every channel is within one mantissa step (at most
    1/128 of the texel's brightest channel) of the baked value."""
    ob = bake(lmdp_ext, output_format='HDR')
    path = tmp_path / "Floor_lmdp_indirect.hdr"
    assert not (tmp_path / "Floor_lmdp_indirect.exr").exists()
    back = read(path)[..., :3]
    rgb = ob.image[..., :3]
    peak = rgb.max(axis=-1, keepdims=True)
    assert np.all(np.abs(back - rgb) <= peak / 128 + 1e-7)
    assert np.abs(back - rgb).max() > 0
    assert bpy.data.images[ob.image_name].file_format == 'HDR'
    np.testing.assert_array_equal(read(bpy.path.abspath(bpy.data.images[ob.image_name].filepath_raw))[..., :3],
                                  back)


def test_png_goes_through_the_view_transform(baked_floor, lmdp_ext, tmp_path):
    """Standard view, exposure +1: the bytes are the sRGB encoding of 2 x the value, clipped at 1."""
    view = bpy.context.scene.view_settings
    view.view_transform, view.look, view.exposure, view.gamma = 'Standard', 'None', 1.0, 1.0
    ob = bake(lmdp_ext, output_8bit='PNG')
    back = read(tmp_path / "Floor_lmdp_indirect_srgb.png")[..., :3]
    v = np.clip(ob.image[..., :3].astype(np.float64) * 2.0, 0.0, 1.0)
    srgb = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    assert np.abs(back - srgb).max() <= 1.5 / 255
    assert (tmp_path / "Floor_lmdp_indirect.exr").exists()
    assert stats(tmp_path)["objects"]["Floor"]["png_file"] == "Floor_lmdp_indirect_srgb.png"


def test_rgbm_png_round_trip(baked_floor, lmdp_ext, tmp_path):
    """RGBM bytes decode (rgb x m x RGBM_RANGE) to the baked value within half a byte step of
    m x range, and values above the range are clipped to it."""
    encoding = lmdp_ext.sub("lmdp_addon.bake.encoding")
    ob = bake(lmdp_ext, output_8bit='RGBM')
    raw = np.rint(read(tmp_path / "Floor_lmdp_indirect_rgbm.png") * 255).astype(np.uint8)
    decoded = encoding.rgbm_decode(raw)
    rgb = ob.image[..., :3]
    bound = (rgb.max(axis=-1, keepdims=True) + encoding.RGBM_RANGE / 255) / 510 + 1e-6
    assert np.all(np.abs(decoded - rgb) <= bound)
    rel = np.abs(decoded - rgb).max(axis=-1) / np.maximum(rgb.max(axis=-1), 1e-6)
    print(f"RGBM round trip: max error {np.abs(decoded - rgb).max():.2e}, median relative "
          f"{np.median(rel[rgb.max(axis=-1) > 0.05]):.2e}")
    assert stats(tmp_path)["output"]["rgbm_range"] == encoding.RGBM_RANGE
    assert ob.image[..., :3].max() < encoding.RGBM_RANGE      # the floor's light: nothing clipped
    big = np.array([[0.0, 0.5, 3.0], [10.0, 1.0, 0.0], [1e-4, 2e-4, 0.0]], np.float32)
    back = encoding.rgbm_decode(encoding.rgbm_encode(big))
    np.testing.assert_allclose(back[0], big[0], atol=(3.0 + 7 / 255) / 510)
    assert back[1, 0] == pytest.approx(encoding.RGBM_RANGE, rel=1e-6)    # clipped to the range


def test_a_users_file_with_a_companion_name_is_left_alone(baked_floor, lmdp_ext, tmp_path):
    mine = tmp_path / "Floor_lmdp_indirect_srgb.png"
    mine.write_bytes(b"not a lightmap")
    bake(lmdp_ext, output_8bit='PNG')
    assert mine.read_bytes() == b"not a lightmap"
    assert (tmp_path / "Floor_lmdp_indirect.exr").exists()
    assert "png_file" not in stats(tmp_path)["objects"]["Floor"]
    # a second bake reuses its own files, no '.001'
    bake(lmdp_ext, output_8bit='RGBM')
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([
        "Floor_lmdp_indirect.exr", "Floor_lmdp_indirect_srgb.png", "Floor_lmdp_indirect_rgbm.png", "bake_stats.json"])


def test_a_denoised_bake_keeps_the_raw_lightmap_as_image_and_file(baked_floor, lmdp_ext, tmp_path):
    ob = bake(lmdp_ext, denoise=True, output_format='EXR_HALF')
    main, raw = tmp_path / "Floor_lmdp_indirect.exr", tmp_path / "Floor_lmdp_indirect_raw.exr"
    np.testing.assert_array_equal(read(main), ob.image.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(read(raw), ob.raw_image.astype(np.float16).astype(np.float32))
    assert np.abs(ob.image - ob.raw_image).max() > 0
    image = bpy.data.images[ob.raw_image_name]
    assert image["lmdp_raw_of"] == "Floor" and bpy.path.abspath(image.filepath_raw) == str(raw)
    assert stats(tmp_path)["objects"]["Floor"]["raw_file"] == raw.name
    assert stats(tmp_path)["objects"]["Floor"]["denoised"] is True
    # denoise off again: the raw file stays LMDP's (listed), the main file is the path tracer's
    ob = bake(lmdp_ext, denoise=False, output_format='EXR_FLOAT')
    np.testing.assert_array_equal(read(main), ob.image)
    assert raw.name in stats(tmp_path)["files"] and raw.exists()
    assert ob.raw_image_name not in bpy.data.images     # no stale raw image in the file


def test_rgbm_of_a_surface_brighter_than_its_range_warns(baked_floor, lmdp_ext, tmp_path):
    """The ceiling around the lamp (5 mm above it) is far brighter than 7."""
    ob = bake(lmdp_ext, name="Ceiling", output_8bit='RGBM')
    assert ob.image[..., :3].max() > 7
    warnings = stats(tmp_path)["warnings"]
    assert any("RGBM copies of Ceiling clip values above 7" in w for w in warnings), warnings
