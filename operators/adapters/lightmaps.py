"""Baked lightmaps as Blender images and files: the add-on's own images, OpenEXR files and
``bake_stats.json``, swapped in only once everything is written.

Images: a float RGBA image of ``bake_resolution``² pixels named ``<object>_lmdp_indirect``,
colour space Non-Color (linear data, shown and saved without any view transform), alpha 1 on the
baked texels and their margin. The image carries the custom property ``lmdp_bake_object`` (the
object's name); re-baking writes only into an image with that tag, so an image of the user that
happens to have the same name is never touched (Blender then names the new one ``.001``).

:func:`write_lightmaps` first saves the new pixels as OpenEXR to temporary files in the output
folder (when one is set), and only when that worked swaps them in: the pixels go into the
add-on's own image of each object, the files replace the previous ones and
``bake_stats.json`` is written. A failure leaves every image and file as it was.
"""
import json
import os
import tempfile

import bpy

from ...lmdp_addon.bake.driver import IMAGE_SUFFIX
from ...lmdp_addon.errors import SceneError

#: Custom property naming the object an image was baked for (marks the add-on's own images).
IMAGE_TAG = "lmdp_bake_object"
STATS_FILE = "bake_stats.json"


def prepare_output_folder(output_dir):
    """``output_dir`` created (and checked writable) if set; raises ``SceneError`` otherwise."""
    if output_dir:
        try:
            os.makedirs(output_dir, exist_ok=True)
        except OSError as error:
            raise SceneError(f"Cannot create the output folder {output_dir}: {error.strerror}; "
                             "choose another Output Folder or clear it") from error
        if not os.access(output_dir, os.W_OK):
            raise SceneError(f"The output folder {output_dir} is not writable: choose another one")
    return output_dir


def own_image(object_name):
    """The add-on's image for ``object_name`` (tagged), or None."""
    wanted = object_name + IMAGE_SUFFIX
    tagged = [im for im in bpy.data.images if im.get(IMAGE_TAG) == object_name]
    for im in tagged:
        if im.name == wanted:
            return im
    return tagged[0] if tagged else None


def _new_float_image(name, resolution):
    image = bpy.data.images.new(name, resolution, resolution, alpha=True, float_buffer=True)
    image.colorspace_settings.name = 'Non-Color'
    return image


def _write_pixels(image, rgba):
    image.pixels.foreach_set(rgba.reshape(-1).astype("float32", copy=False))
    image.update()


def _temporary_file(output_dir, suffix):
    fd, path = tempfile.mkstemp(prefix=".lmdp_", suffix=suffix, dir=output_dir)
    os.close(fd)
    return path


def _write_temporary_files(result, output_dir):
    """Scratch images of the new pixels and, with ``output_dir``, their EXR files and the
    statistics as temporary files: ``(scratch images, [EXR per object], stats file or None)``.
    Raises ``SceneError`` (nothing changed) if a file cannot be written."""
    scratch, exr_files, stats_file = [], [], None
    try:
        for ob in result.objects:
            im = _new_float_image(f"LMDP scratch {ob.name}", ob.resolution)
            _write_pixels(im, ob.image)
            scratch.append(im)
            if output_dir:
                exr_files.append(_temporary_file(output_dir, ".exr"))
                im.filepath_raw = exr_files[-1]
                im.file_format = 'OPEN_EXR'
                im.save()
        if output_dir:
            stats_file = _temporary_file(output_dir, ".json")
            with open(stats_file, "w", encoding="utf-8") as fh:
                json.dump(result.stats(), fh, indent=2, default=_json_default)
    except (OSError, RuntimeError) as error:
        for im in scratch:
            bpy.data.images.remove(im)
        for path in exr_files + ([stats_file] if stats_file else []):
            if os.path.exists(path):
                os.remove(path)
        raise SceneError(f"Could not write the lightmaps to {output_dir}: {error}; nothing was "
                         "changed. Check the Output Folder") from error
    return scratch, exr_files, stats_file


def _swap_in(ob, exr_file, output_dir, warnings):
    """The add-on's image of ``ob`` showing its new pixels: the EXR moved into place and
    reloaded (with ``output_dir``), or a new packed image that takes the old one's users."""
    image = own_image(ob.name)
    if image is None:
        wanted = ob.image_name
        if wanted in bpy.data.images:
            warnings.append(f"An image named '{wanted}' that LMDP did not create exists: it is "
                            "left alone and the lightmap gets a new name")
        image = _new_float_image(wanted, ob.resolution)
        image[IMAGE_TAG] = ob.name
    if output_dir:
        final = os.path.join(output_dir, ob.image_name + ".exr")
        os.replace(exr_file, final)
        if image.packed_file is not None:
            image.unpack(method='REMOVE')
        image.source = 'FILE'
        image.filepath_raw = final
        image.file_format = 'OPEN_EXR'
        image.colorspace_settings.name = 'Non-Color'
        image.reload()
        return image
    fresh = _new_float_image(ob.image_name, ob.resolution)
    _write_pixels(fresh, ob.image)
    fresh.pack()  # generated pixels are otherwise lost when the .blend is saved
    fresh[IMAGE_TAG] = ob.name
    if image.users:
        image.user_remap(fresh)  # nodes that showed the old lightmap show the new one
    name = image.name
    bpy.data.images.remove(image)
    fresh.name = name
    return fresh


def write_lightmaps(result, output_dir, warnings):
    """Main thread: the lightmaps of ``result`` (a ``BakeResult``) into the add-on's images and,
    with ``output_dir``, its files; returns ``{object name: image}`` and appends to ``warnings``.
    Raises ``SceneError`` (nothing changed) if the files cannot be written."""
    scratch, exr_files, stats_file = _write_temporary_files(result, output_dir)
    images = {ob.name: _swap_in(ob, exr_files[i] if output_dir else None, output_dir, warnings)
              for i, ob in enumerate(result.objects)}
    if output_dir:
        os.replace(stats_file, os.path.join(output_dir, STATS_FILE))
    for im in scratch:
        bpy.data.images.remove(im)
    return images


def _json_default(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)
