"""Baked lightmaps as Blender images and files: the add-on's own images, OpenEXR files and
``bake_stats.json``, swapped in only once everything is written.

Images: a float RGBA image of ``bake_resolution``² pixels named ``<object>_lmdp_indirect``,
colour space Non-Color (linear data, shown and saved without any view transform), alpha 1 on the
baked texels and their margin, with a fake user so that saving the .blend keeps it whatever uses
it. The image carries the custom property ``lmdp_bake_object``, the object's key (its name, or
``name_full`` such as ``"Floor [library.blend]"`` for a linked object); re-baking writes only into
the local image with that tag, so an image of the user's that happens to have the same name is
never touched (Blender then names the new one ``.001``).

Files (with an output folder): the object's name made safe for every file system (no path
separators or reserved characters, no leading dots, at most :data:`MAX_STEM_BYTES` bytes) plus
``_lmdp_indirect.exr``, unique in the folder. ``bake_stats.json`` lists under ``"files"`` every
file the add-on wrote there and for which object; a file that is neither in that list nor the
file of one of the add-on's images was not written by LMDP and is never replaced (the lightmap
gets the next free name, ``.001``, and a warning says so). A ``bake_stats.json`` the add-on did
not write stops the bake before any work.

Formats (``Settings.output_format``): 32-bit float OpenEXR (the default), half float OpenEXR
(``save_render`` with a scratch scene's file settings), Radiance HDR (RGBE: a shared exponent
per texel, so a channel keeps 8 bits relative to the texel's brightest one). Optional 8-bit
copies next to each file (``Settings.output_8bit``): ``<stem>_srgb.png``, sRGB through the scene's
view transform, look and exposure (what a render of the same linear values shows; curves are not
copied), or ``<stem>_rgbm.png`` (``lmdp_addon.bake.encoding``). A denoised bake also keeps the raw
lightmap: the image ``<image>_raw`` (tagged :data:`RAW_TAG`) and the file ``<stem>_raw<ext>``.

:func:`write_lightmaps` first saves the new pixels to temporary files in the output
folder, then moves them all into place (all or nothing: a failure puts back every file it had
replaced), and only then swaps the pixels into the images. A failure leaves every image and file
as it was, with no temporary file or scratch image behind.
"""
import json
import os
import tempfile

import bpy
import numpy as np

from ...lmdp_addon.bake.driver import IMAGE_SUFFIX
from ...lmdp_addon.bake.encoding import RGBM_RANGE, rgbm_encode
from ...lmdp_addon.errors import SceneError

#: Custom property naming the object an image was baked for (marks the add-on's own images).
IMAGE_TAG = "lmdp_bake_object"
#: Custom property of the raw (not denoised) lightmap a denoised bake keeps, "<image>_raw".
RAW_TAG = "lmdp_raw_of"
#: File extension and Blender file format of each ``Settings.output_format``.
FORMATS = {"EXR_FLOAT": (".exr", 'OPEN_EXR'), "EXR_HALF": (".exr", 'OPEN_EXR'), "HDR": (".hdr", 'HDR')}
#: What is added to a lightmap file's name (without its extension) for its companions.
RAW_PART, PNG_PART, RGBM_PART = "_raw", "_srgb", "_rgbm"
STATS_FILE = "bake_stats.json"
#: Prefix of the temporary files written next to the outputs (hidden, removed in every case).
TEMP_PREFIX = ".lmdp_"
#: Longest object-name part of a lightmap file name, in UTF-8 bytes (file systems take 255).
MAX_STEM_BYTES = 120
#: Characters no file name may hold on some file system (Windows' list; '/' everywhere).
_RESERVED = frozenset('<>:"/\\|?*')
_STATS_KEYS = frozenset({"mode", "settings", "objects"})


# ---- The output folder ------------------------------------------------------------------------------

def resolve_output_folder(output_dir, setting="Output Folder"):
    """``output_dir`` as an absolute path ('' stays ''): ``//`` is the folder of the saved .blend
    file, ``~`` the home folder. Raises ``SceneError`` for ``//`` in a file that was never saved
    and for any other relative path (it would land wherever Blender was started from)."""
    if not output_dir:
        return ""
    if output_dir.startswith("//"):
        if not bpy.data.filepath:
            raise SceneError(f"The {setting} '{output_dir}' is relative to the .blend file, which "
                             "has not been saved: save the .blend first or use an absolute path")
        output_dir = bpy.path.abspath(output_dir)
    path = os.path.expanduser(output_dir)
    if not os.path.isabs(path):
        raise SceneError(f"The {setting} '{output_dir}' is a relative path (it would be written "
                         "wherever Blender was started from): use an absolute path, or "
                         f"'//{output_dir}' for a folder next to the saved .blend file")
    return os.path.normpath(path)


def prepare_output_folder(output_dir):
    """The absolute output folder (see :func:`resolve_output_folder`), created and checked
    writable, or '' when none is set; raises ``SceneError`` if it cannot be used or holds a
    ``bake_stats.json`` that LMDP did not write."""
    folder = resolve_output_folder(output_dir)
    if folder:
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as error:
            raise SceneError(f"Cannot create the output folder {folder}: {error.strerror}; "
                             "choose another Output Folder or clear it") from error
        if not os.access(folder, os.W_OK):
            raise SceneError(f"The output folder {folder} is not writable: choose another one")
        read_stats(folder)
    return folder


def read_stats(folder):
    """The ``bake_stats.json`` of ``folder`` as a dict ({} if there is none); raises
    ``SceneError`` when the file there was not written by LMDP (it is never replaced)."""
    path = os.path.join(folder, STATS_FILE)
    if not os.path.lexists(path):
        return {}
    try:
        with open(path, encoding="utf-8") as fh:
            stats = json.load(fh)
    except (OSError, ValueError):
        stats = None
    if not isinstance(stats, dict) or not _STATS_KEYS <= stats.keys():
        raise SceneError(f"{path} was not written by LMDP and would be replaced by the bake's "
                         "statistics: move it away or choose another Output Folder")
    return stats


# ---- File names ---------------------------------------------------------------------------------------

def safe_file_stem(name):
    """``name`` as the start of a file name on any file system: reserved characters and control
    characters become '_', leading and trailing dots and spaces go, at most
    :data:`MAX_STEM_BYTES` UTF-8 bytes; "object" if nothing is left."""
    stem = "".join("_" if c in _RESERVED or ord(c) < 32 or ord(c) == 127 else c for c in name)
    stem = stem.strip(" .")
    encoded = stem.encode("utf-8")
    if len(encoded) > MAX_STEM_BYTES:
        stem = encoded[:MAX_STEM_BYTES].decode("utf-8", "ignore").rstrip(" .")
    return stem or "object"


def _plain_file_name(name):
    return (isinstance(name, str) and name not in ("", ".", "..") and os.path.basename(name) == name
            and "/" not in name and "\\" not in name and not name.startswith(TEMP_PREFIX))


def _same_path(a, b):
    return os.path.normcase(os.path.normpath(a)) == os.path.normcase(os.path.normpath(b))


def owned_files(folder, stats):
    """{file name in ``folder``: object key} of the files LMDP wrote there: the ``"files"`` of its
    statistics (or, for statistics written before that list, each object's image name + .exr)
    and the files the add-on's images are loaded from."""
    owned = {}
    objects, files = stats.get("objects"), stats.get("files")
    for name, entry in (objects.items() if isinstance(objects, dict) else ()):
        if isinstance(entry, dict):
            owned[entry.get("file") or f"{entry.get('image') or name + IMAGE_SUFFIX}.exr"] = name
    owned.update(files if isinstance(files, dict) else {})
    for image in _tagged_images():
        if image.source == 'FILE' and image.filepath_raw:
            path = bpy.path.abspath(image.filepath_raw)
            if _same_path(os.path.dirname(path), folder):
                owned[os.path.basename(path)] = image[IMAGE_TAG]
    return {f: k for f, k in owned.items() if _plain_file_name(f) and isinstance(k, str)}


def assign_files(objects, key_of, folder, owned, warnings, extension=".exr"):
    """{object name: file name in ``folder``} for the ``objects`` (``ObjectBake``) being baked:
    the file LMDP wrote for the same object before, else the first free name of
    ``<safe name>_lmdp_indirect[.NNN]<extension>`` that no other object's file and no file of the
    user's holds (names compared case-insensitively). Objects whose names are already safe pick
    first; a file of the same object in another format is not reused."""
    previous = {}
    for name, key in owned.items():
        previous.setdefault(key, name)
    owned_lower = {f.lower(): k for f, k in owned.items()}
    used, files = set(), {}
    for ob in sorted(objects, key=lambda ob: safe_file_stem(ob.name) != ob.name):
        key = key_of(ob)
        mine = previous.get(key)
        if mine is not None and mine.lower() not in used and mine.lower().endswith(extension) \
                and _main_file(mine, extension):
            files[ob.name] = mine
            used.add(mine.lower())
            continue
        base, skipped = safe_file_stem(ob.name) + IMAGE_SUFFIX, None
        for n in range(1000):
            candidate = f"{base}.{n:03d}{extension}" if n else f"{base}{extension}"
            low = candidate.lower()
            if low in used or owned_lower.get(low, key) != key:
                continue
            if low not in owned_lower and os.path.lexists(os.path.join(folder, candidate)):
                skipped = skipped or candidate
                continue
            break
        else:
            raise SceneError(f"No free file name for the lightmap of '{ob.name}' in {folder}: "
                             "clear the folder or choose another Output Folder")
        if skipped:
            warnings.append(f"{os.path.join(folder, skipped)} was not written by LMDP: it is left "
                            f"alone and the lightmap of '{ob.name}' is saved as {candidate}")
        files[ob.name] = candidate
        used.add(low)
    return files


def _main_file(name, extension):
    """``name`` is a lightmap file, not one of its companions (raw, PNG, RGBM)."""
    stem = name[:-len(extension)]
    return not (stem.endswith(RAW_PART) or stem.endswith(RGBM_PART) or stem.endswith(PNG_PART))


def companion_files(folder, main, owned, extension, parts, warnings):
    """{part: file name} of the companions of the lightmap file ``main`` (``<stem><part><ext>``
    for each ``(part, ext)`` of ``parts``); one that exists and that LMDP did not write is left
    alone and left out, with a warning."""
    stem = main[:-len(extension)]
    owned_lower = {f.lower() for f in owned}
    out = {}
    for part, ext in parts:
        name = f"{stem}{part}{ext}"
        if name.lower() not in owned_lower and os.path.lexists(os.path.join(folder, name)):
            warnings.append(f"{os.path.join(folder, name)} was not written by LMDP: it is left alone "
                            f"and not replaced by the lightmap's {part.strip('_') or 'PNG'} copy")
            continue
        out[part + ext] = name
    return out


# ---- Images -------------------------------------------------------------------------------------------

def _tagged_images(tag=IMAGE_TAG):
    """The add-on's images: local (not linked, not overrides) and tagged."""
    return [im for im in bpy.data.images if im.library is None
            and getattr(im, "override_library", None) is None and isinstance(im.get(tag), str)]


def own_image(key, image_name=None, tag=IMAGE_TAG):
    """The add-on's local image for the object ``key`` (its name, or ``name_full`` when linked),
    or None; the one named ``image_name`` (default ``key + IMAGE_SUFFIX``) if there are several.
    ``tag``: :data:`RAW_TAG` for the raw lightmap of a denoised bake."""
    wanted = image_name or key + IMAGE_SUFFIX
    tagged = [im for im in _tagged_images(tag) if im[tag] == key]
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


def _temporary_file(folder, suffix):
    fd, path = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=suffix, dir=folder)
    os.close(fd)
    return path


def _swap_in(key, image_name, resolution, pixels, final, warnings, tag=IMAGE_TAG):
    """The add-on's image ``image_name`` (tagged ``tag`` = ``key``) showing ``pixels`` (R, R, 4):
    reloaded from ``final`` (its file, now in place) or, without a file, a new packed image that
    takes the old one's users."""
    image = own_image(key, image_name, tag)
    if image is None:
        existing = bpy.data.images.get(image_name)
        if existing is not None and not isinstance(existing.get(tag), str):
            warnings.append(f"An image named '{image_name}' that LMDP did not create exists: it "
                            "is left alone and the lightmap gets a new name")
        image = _new_float_image(image_name, resolution)
        image[tag] = key
    if final:
        if image.packed_file is not None:
            image.unpack(method='REMOVE')
        image.source = 'FILE'
        image.filepath_raw = final
        image.file_format = 'HDR' if final.lower().endswith(".hdr") else 'OPEN_EXR'
        image.colorspace_settings.name = 'Non-Color'
        image.reload()
        image.use_fake_user = True  # kept on save even when nothing shows it
        return image
    fresh = _new_float_image(image_name, resolution)
    _write_pixels(fresh, pixels)
    fresh.pack()  # generated pixels are otherwise lost when the .blend is saved
    fresh[tag] = key
    fresh.use_fake_user = True
    if image.users:
        image.user_remap(fresh)  # nodes that showed the old lightmap show the new one
    name = image.name
    bpy.data.images.remove(image)
    fresh.name = name
    return fresh


# ---- Saving one file ----------------------------------------------------------------------------------

class _Saver:
    """Writes (R, R, 4) float pixels in the formats of :data:`FORMATS` and the 8-bit copies;
    scratch images and a scratch scene (the file settings of ``save_render``) are removed by
    :meth:`close`. ``view_scene``: the scene whose view transform the plain PNG goes through."""

    def __init__(self, view_scene=None):
        self.view_scene = view_scene
        self.images, self.scene = [], None

    def _image(self, pixels, float_buffer=True, colorspace='Non-Color'):
        R = pixels.shape[1]
        im = bpy.data.images.new(f"LMDP scratch {len(self.images)}", R, pixels.shape[0], alpha=True,
                                 float_buffer=float_buffer)
        self.images.append(im)
        im.colorspace_settings.name = colorspace
        _write_pixels(im, pixels)
        return im

    def _render_settings(self):
        if self.scene is None:
            self.scene = bpy.data.scenes.new("LMDP scratch output")
            source = self.view_scene
            if source is not None:
                view, src = self.scene.view_settings, source.view_settings
                self.scene.display_settings.display_device = source.display_settings.display_device
                view.view_transform = src.view_transform
                view.look = src.look
                view.exposure, view.gamma = src.exposure, src.gamma
        return self.scene.render.image_settings

    def save(self, pixels, path, kind):
        """``kind``: an :data:`FORMATS` key, 'PNG' (8-bit sRGB through the view transform) or
        'RGBM' (:func:`~lmdp_addon.bake.encoding.rgbm_encode`, raw bytes)."""
        pixels = np.asarray(pixels, dtype=np.float32)
        if kind in ("EXR_FLOAT", "HDR"):
            im = self._image(pixels)
            im.filepath_raw = path
            im.file_format = FORMATS[kind][1]
            im.save()
        elif kind == "EXR_HALF":
            settings = self._render_settings()
            settings.file_format, settings.color_depth, settings.color_mode = 'OPEN_EXR', '16', 'RGBA'
            settings.exr_codec = 'ZIP'
            self._image(pixels).save_render(path, scene=self.scene)
        elif kind == "PNG":
            settings = self._render_settings()
            settings.file_format, settings.color_depth, settings.color_mode = 'PNG', '8', 'RGB'
            self._image(pixels, colorspace='Linear Rec.709').save_render(path, scene=self.scene)
        elif kind == "RGBM":
            im = self._image(rgbm_encode(pixels[..., :3]).astype(np.float32) / 255.0, float_buffer=False)
            im.filepath_raw = path
            im.file_format = 'PNG'
            im.save()
        else:
            raise ValueError(f"unknown lightmap file kind {kind!r}")

    def close(self):
        for im in self.images:
            bpy.data.images.remove(im)
        if self.scene is not None:
            bpy.data.scenes.remove(self.scene)
        self.images, self.scene = [], None


# ---- Writing ------------------------------------------------------------------------------------------

def _move_into_place(moves):
    """Rename each ``(temporary, final)`` file of ``moves``, all or nothing: a file already at
    ``final`` is first renamed to a hidden backup; on a failure every step is undone and the
    error raised. The backups are removed once every file is in place."""
    done = []  # [final, backup or None, moved]
    try:
        for temporary, final in moves:
            backup = None
            if os.path.lexists(final):
                backup = _temporary_file(os.path.dirname(final), ".old")
                os.replace(final, backup)
            done.append([final, backup, False])
            os.replace(temporary, final)
            done[-1][2] = True
    except OSError:
        for final, backup, moved in reversed(done):
            try:
                if backup is not None:
                    os.replace(backup, final)
                elif moved:
                    os.remove(final)
            except OSError:
                pass
        raise
    for _, backup, _ in done:
        if backup is not None:
            _remove_quietly(backup)


def _remove_quietly(path):
    try:
        if os.path.lexists(path):
            os.remove(path)
    except OSError:
        pass


def _stats_payload(result, files, companions, key_of, owned, folder, output_format, output_8bit):
    stats = result.stats()
    written = {}
    for ob in result.objects:
        entry = stats["objects"][ob.name]
        out = result.output_of(ob.name)
        entry["file"] = files[out]
        for part, name in companions.get(out, {}).items():
            entry[{"raw": "raw_file", "png": "png_file", "rgbm": "rgbm_file"}[_part_kind(part)]] = name
    for atlas in result.atlases:
        stats["atlases"][atlas.name]["file"] = files[atlas.name]
    for ob in result.outputs():
        written[files[ob.name]] = key_of(ob)
        for name in companions.get(ob.name, {}).values():
            written[name] = key_of(ob)
    kept = {f: k for f, k in owned.items() if os.path.lexists(os.path.join(folder, f))}
    stats["files"] = {**kept, **written}
    stats["output"] = {"format": output_format, "8bit": output_8bit,
                       "rgbm_range": RGBM_RANGE if output_8bit == "RGBM" else None}
    return stats


def _part_kind(part):
    """'raw', 'png' or 'rgbm' for a companion key ``<part><ext>``."""
    if part.startswith(RAW_PART):
        return "raw"
    return "rgbm" if part.startswith(RGBM_PART) else "png"


def write_lightmaps(result, output_dir, warnings, keys=None, output_format="EXR_FLOAT", output_8bit="NONE",
                    view_scene=None):
    """Main thread: the lightmaps of ``result`` (a ``BakeResult``) into the add-on's images and,
    with ``output_dir`` (absolute, from :func:`prepare_output_folder`), its files; ``keys`` maps
    an object name to the object's key (default: the name; an atlas's key is its name). One image
    per output (``BakeResult.outputs``: an object's own lightmap, or an atlas shared by its
    objects). Returns ``{output name: image}`` and appends to ``warnings``. Raises
    ``SceneError`` (nothing changed) if the files cannot be written.

    ``output_format`` (:data:`FORMATS`): the file each image is loaded from. ``output_8bit``:
    'PNG' also writes ``<stem>_srgb.png`` through ``view_scene``'s view transform (the scene's Color
    Management), 'RGBM' ``<stem>_rgbm.png`` (``lmdp_addon.bake.encoding``, range
    ``RGBM_RANGE``). A denoised object's raw lightmap becomes the image ``<image>_raw`` and, with
    a folder, the file ``<stem>_raw<ext>``."""
    keys = keys or {}

    def key_of(ob):
        return keys.get(ob.name, ob.name)

    if output_format not in FORMATS:
        raise SceneError(f"Unknown Output Format {output_format!r}: use one of {', '.join(FORMATS)}")
    extension = FORMATS[output_format][0]
    files, companions, stats = {}, {}, None
    outputs = result.outputs()
    if output_dir:
        owned = owned_files(output_dir, read_stats(output_dir))
        files = assign_files(outputs, key_of, output_dir, owned, warnings, extension)
        for ob in outputs:
            parts = [(RAW_PART, extension)] if _raw(ob) is not None else []
            parts += {"PNG": [(PNG_PART, ".png")], "RGBM": [(RGBM_PART, ".png")]}.get(output_8bit, [])
            companions[ob.name] = companion_files(output_dir, files[ob.name], owned, extension, parts, warnings)
        stats = _stats_payload(result, files, companions, key_of, owned, output_dir, output_format, output_8bit)
        if output_8bit == "RGBM":
            clipped = [ob.name for ob in outputs if ob.image[..., :3].max(initial=0.0) > RGBM_RANGE]
            if clipped:
                warnings.append(f"The RGBM copies of {', '.join(clipped)} clip values above {RGBM_RANGE:g} "
                                "(the lightmap files keep them)")
                stats["warnings"].append(warnings[-1])
    finals = {name: os.path.join(output_dir, f) for name, f in files.items()}
    saver, moves = _Saver(view_scene), []
    try:
        if output_dir:
            for ob in outputs:
                jobs = [(ob.image, finals[ob.name], output_format)]
                for part, name in companions[ob.name].items():
                    kind = _part_kind(part)
                    pixels = _raw(ob) if kind == "raw" else ob.image
                    jobs.append((pixels, os.path.join(output_dir, name),
                                 output_format if kind == "raw" else kind.upper()))
                for pixels, final, kind in jobs:
                    moves.append((_temporary_file(output_dir, os.path.splitext(final)[1]), final))
                    saver.save(pixels, moves[-1][0], kind)
            moves.append((_temporary_file(output_dir, ".json"), os.path.join(output_dir, STATS_FILE)))
            with open(moves[-1][0], "w", encoding="utf-8") as fh:
                json.dump(stats, fh, indent=2, default=_json_default)
            _move_into_place(moves)
    except (OSError, RuntimeError) as error:
        raise SceneError(f"Could not write the lightmaps to {output_dir}: {error}; nothing was "
                         "changed. Check the Output Folder") from error
    finally:
        saver.close()
        for temporary, _ in moves:
            _remove_quietly(temporary)
    images = {}
    for ob in outputs:
        images[ob.name] = _swap_in(key_of(ob), ob.image_name, ob.resolution, ob.image, finals.get(ob.name),
                                   warnings)
        if not hasattr(ob, "raw_image"):    # an atlas: no raw image of its own
            continue
        if ob.raw_image is not None:
            raw = companions.get(ob.name, {}).get(RAW_PART + extension)
            _swap_in(key_of(ob), ob.raw_image_name, ob.resolution, ob.raw_image,
                     os.path.join(output_dir, raw) if raw else None, warnings, tag=RAW_TAG)
        else:   # not denoised: a raw image of an earlier bake would be stale
            stale = own_image(key_of(ob), ob.raw_image_name, RAW_TAG)
            if stale is not None and not stale.users - int(stale.use_fake_user):
                bpy.data.images.remove(stale)
    return images


def _raw(output):
    """The raw (not denoised) pixels of an output, or None (not denoised, or an atlas)."""
    return getattr(output, "raw_image", None)


def _json_default(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)
