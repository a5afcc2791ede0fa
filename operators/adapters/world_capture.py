"""bpy world -> the engine's world: a uniform radiance or an :class:`~lmdp_addon.world.EnvironmentMap`.

:func:`capture_world` reads the shader connected to the World Output (Cycles' target):

* no node tree (Blender < 5.0 with nodes off): the world colour, uniform;
* Background: Color x Strength, uniform when Color is a value;
* Background whose Color is an **Environment Texture** (equirectangular projection, packed or
  file image): the image's pixels once, as float32 radiance x Strength (8-bit sRGB images
  decoded to linear), with the node's interpolation (Linear, Closest; Cubic / Smart as Linear,
  with a warning). Its Vector may come from a Texture Coordinate node (Generated / Object
  without an object: the direction itself) through a Mapping node: a rotation (with a uniform
  scale and no location, which do not change a direction) becomes the map's rotation, exactly;
  any other mapping is evaluated for every direction of an equirectangular table of the image's
  size (bilinear), with a warning naming the node;
* anything else (Sky Texture, gradients, Mix shaders, a Mirror Ball projection, ...): the world is
  rendered once into an equirectangular map by Cycles (:func:`render_world`: a panoramic camera
  looking along +x, which Cycles aligns with the Environment Texture's convention; small bright
  features such as a sun disc rendered again with more samples, :func:`refined_render`) with a
  warning naming the world and the node; Light Path tricks see the camera rays of that render.

A world whose Ray Visibility excludes diffuse rays lights nothing in a diffuse bake: black, with
a warning. The uniform case returns the same radiance as before, so its bakes do not change.
"""
import os
import tempfile

import bpy
import numpy as np

from ...lmdp_addon.world import EnvironmentMap

_BLACK = np.zeros(3)
_NODES_OPTIONAL = bpy.app.version < (5, 0, 0)
#: Size and samples of the equirectangular render of a world tree the capture cannot read.
RENDER_SIZE = (256, 128)
RENDER_SAMPLES = 16
#: Small bright features of the render (a sun disc) are rendered again with HOT_SAMPLES: pixels
#: above HOT_FACTOR x the median luminance, HOT_MARGIN pixels around them, if their box covers
#: at most HOT_MAX_SHARE of the map.
HOT_SAMPLES = 4096
HOT_FACTOR = 100.0
HOT_MARGIN = 2
HOT_MAX_SHARE = 0.01
_INTERPOLATION = {'Linear': "LINEAR", 'Closest': "CLOSEST", 'Cubic': "LINEAR", 'Smart': "LINEAR"}
_DIRECTION_COORDINATES = {'Generated', 'Object'}


def srgb_to_linear(c):
    """The sRGB transfer function inverted, elementwise (float64 in, float64 out)."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def socket_source(socket):
    """(node, output socket) feeding ``socket``, through reroutes and muted nodes; or None."""
    links = [link for link in socket.links if not link.is_muted and link.is_valid]
    while links:
        link = links[0]
        node, out = link.from_node, link.from_socket
        if node.type == 'REROUTE':
            links = [l for l in node.inputs[0].links if not l.is_muted and l.is_valid]
            continue
        if node.mute:
            through = [il.from_socket for il in node.internal_links if il.to_socket == out]
            links = [l for s in through for l in s.links if not l.is_muted and l.is_valid]
            continue
        return node, out
    return None


def image_radiance(image):
    """(H, W, 3) float32 linear RGB of ``image`` (row 0 at the bottom), or None without pixels."""
    w, h = image.size
    if w * h == 0:
        return None
    c = image.channels
    px = np.empty(w * h * c, dtype=np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, c)
    rgb = px[..., :3] if c >= 3 else np.repeat(px[..., :1], 3, axis=-1)
    if not image.is_float and image.colorspace_settings.name == 'sRGB':
        rgb = srgb_to_linear(rgb.astype(np.float64))
    return np.ascontiguousarray(rgb, dtype=np.float32)


def euler_xyz(rotation):
    """Blender's XYZ Euler rotation matrix ``Rz Ry Rx`` of ``rotation`` (3,) radians."""
    x, y, z = (float(a) for a in rotation)
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _mapping_function(node):
    """The vector a Mapping node makes of a direction, as Cycles' ``svm_mapping`` does:
    ``(rotation or None, function)``: the rotation R with ``map direction = R ω`` when the node
    only turns directions (uniform positive scale, no location where it applies), else None;
    the function maps (k, 3) directions to (k, 3) vectors in every case."""
    loc = np.array(node.inputs["Location"].default_value[:3], dtype=np.float64) \
        if "Location" in node.inputs else np.zeros(3)
    rot = euler_xyz(node.inputs["Rotation"].default_value[:3])
    scale = np.array(node.inputs["Scale"].default_value[:3], dtype=np.float64)
    kind = node.vector_type
    uniform = bool(np.all(scale > 0) and np.ptp(scale) <= 1e-9 * np.abs(scale).max())
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_scale = np.where(scale != 0, 1.0 / scale, 0.0)
    if kind == 'POINT':
        fn = lambda d: (d * scale) @ rot.T + loc                              # noqa: E731
        exact = rot if uniform and not np.any(loc) else None
    elif kind == 'TEXTURE':
        fn = lambda d: ((d - loc) @ rot) * inv_scale                          # noqa: E731
        exact = rot.T if uniform and not np.any(loc) else None
    elif kind == 'VECTOR':
        fn = lambda d: (d * scale) @ rot.T                                    # noqa: E731
        exact = rot if uniform else None
    else:   # NORMAL
        fn = lambda d: (d * inv_scale) @ rot.T                                # noqa: E731
        exact = rot if uniform else None
    return exact, fn


class WorldReader:
    """Reads a world into ``(world_radiance (3,), environment or None)``, with warnings."""

    def __init__(self, warnings):
        self.warnings = warnings

    def warn(self, message):
        if message not in self.warnings:
            self.warnings.append(message)

    def capture(self, world):
        if world is None:
            return _BLACK, None
        owner = f"World '{world.name}'"
        visibility = getattr(world, "cycles_visibility", None)
        if visibility is not None and not visibility.diffuse:
            self.warn(f"{owner} is invisible to diffuse rays (World > Ray Visibility > Diffuse is off): "
                      "it lights nothing in a diffuse bake, so LMDP treats it as black")
            return _BLACK, None
        tree = world.node_tree
        if tree is None or (_NODES_OPTIONAL and not world.use_nodes):
            return np.array(world.color[:3], dtype=np.float64), None
        output = tree.get_output_node('CYCLES')
        if output is None:
            return _BLACK, None
        source = socket_source(output.inputs["Surface"])
        if source is None:
            return _BLACK, None
        node = source[0]
        if node.type == 'BACKGROUND' and socket_source(node.inputs["Strength"]) is None:
            strength = float(node.inputs["Strength"].default_value)
            colour = socket_source(node.inputs["Color"])
            if colour is None:
                return np.maximum(np.array(node.inputs["Color"].default_value[:3], dtype=np.float64)
                                  * strength, 0.0), None
            env = self._environment_texture(owner, colour[0], strength)
            if env is not None:
                return self._result(env)
            culprit = colour[0]
        else:
            culprit = node
        return self._rendered(world, owner, culprit)

    @staticmethod
    def _result(env):
        return np.maximum(env.mean_radiance(), 0.0), (env if env.lit else None)

    def _environment_texture(self, owner, tex, strength):
        """The :class:`EnvironmentMap` of an Environment Texture node read directly, or None
        when only a render of the world can evaluate it."""
        if tex.type != 'TEX_ENVIRONMENT' or tex.image is None or tex.projection != 'EQUIRECTANGULAR':
            return None
        vector = socket_source(tex.inputs["Vector"])
        rotation, warp = np.eye(3), None
        if vector is not None:
            node = vector[0]
            if node.type == 'MAPPING':
                if any(socket_source(s) is not None for s in node.inputs if s.name != "Vector"):
                    return None
                inner = socket_source(node.inputs["Vector"])
                if inner is not None and not _is_direction(inner):
                    return None
                rotation, warp = _mapping_function(node)
                if rotation is not None:
                    warp = None
            elif not _is_direction(vector):
                return None
        pixels = image_radiance(tex.image)
        if pixels is None:
            self.warn(f"{owner}: image '{tex.image.name}' of Environment Texture '{tex.name}' has no pixels "
                      "(a missing file? Cycles shows it magenta): LMDP treats the world as black; fix the "
                      "image's path or pack it")
            return EnvironmentMap(np.zeros((1, 1, 3), np.float32), name=owner)
        bad = int(np.count_nonzero(~np.isfinite(pixels).all(axis=2)))
        if bad:
            self.warn(f"{owner}: image '{tex.image.name}' has {bad} pixel{'s' if bad > 1 else ''} that are "
                      "not finite numbers (Inf or NaN); LMDP treats them as black")
        interpolation = _INTERPOLATION.get(tex.interpolation, "LINEAR")
        if tex.interpolation not in ('Linear', 'Closest'):
            self.warn(f"{owner}: Environment Texture '{tex.name}' uses {tex.interpolation} interpolation; "
                      "LMDP interpolates it linearly")
        env = EnvironmentMap(pixels * np.float32(strength), rotation=rotation if rotation is not None
                             else np.eye(3), interpolation=interpolation, name=f"{owner} / image '{tex.image.name}'")
        if warp is not None:
            mapping = vector[0]
            self.warn(f"{owner}: Mapping '{mapping.name}' does more than turn directions (a location, or "
                      "a scale that is not uniform): LMDP evaluates it for every direction of an "
                      f"equirectangular table of {env.width} x {env.height} (bilinear)")
            env = EnvironmentMap(_resampled(env, warp), interpolation="LINEAR", name=env.name)
        return env

    def _rendered(self, world, owner, node):
        """The world rendered into an equirectangular map by Cycles (module docstring)."""
        w, h = RENDER_SIZE
        self.warn(f"{owner}: '{node.name}' ({node.bl_label}) is not read directly; LMDP renders the "
                  f"world once into a {w} x {h} equirectangular map with Cycles ({RENDER_SAMPLES} "
                  "samples per pixel; Light Path nodes see that render's camera rays)")
        paths = [n.name for n in world.node_tree.nodes if n.type == 'LIGHT_PATH' and not n.mute]
        if paths:
            self.warn(f"{owner} uses Light Path {', '.join(repr(n) for n in paths)}: the rendered map shows "
                      "what camera rays see, while Cycles' bake sees the world through diffuse rays; if the "
                      "tree switches on the ray type (e.g. Is Camera Ray), connect the lighting branch to "
                      "the World Output for the bake")
        try:
            pixels = refined_render(world, w, h, RENDER_SAMPLES)
        except Exception as exc:      # any failure of the render: the capture goes on without it
            self.warn(f"{owner}: the render of the world failed ({exc}); LMDP treats the world as black")
            return _BLACK, None
        return self._result(EnvironmentMap(pixels, interpolation="LINEAR", name=f"{owner} (rendered)"))


def _is_direction(source):
    """True for the Texture Coordinate outputs that are the world direction itself."""
    node, out = source
    return node.type == 'TEX_COORD' and out.name in _DIRECTION_COORDINATES and \
        (out.name != 'Object' or getattr(node, "object", None) is None)


def _resampled(env, warp):
    """(H, W, 3) float32 table of ``env`` looked up along ``warp(ω)`` for the pixel-centre
    directions ω of an equirectangular table of the same size (Cycles' convention)."""
    H, W = env.height, env.width
    u, v = np.meshgrid((np.arange(W) + 0.5) / W, (np.arange(H) + 0.5) / H)
    theta, phi = np.pi * (1.0 - v.ravel()), np.pi - 2.0 * np.pi * u.ravel()
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    m = warp(d)
    norm = np.linalg.norm(m, axis=1, keepdims=True)
    m = np.where(norm > 0, m / np.where(norm > 0, norm, 1.0), 0.0)
    return env.radiance_at(m).reshape(H, W, 3)


def refined_render(world, width, height, samples):
    """:func:`render_world` at ``samples``, then the small bright features (a sun disc covers a
    fraction of a pixel, and ``samples`` samples find it a few times) rendered again with
    :data:`HOT_SAMPLES`: the pixels brighter than :data:`HOT_FACTOR` x the map's median
    luminance, dilated by :data:`HOT_MARGIN` pixels, when their bounding box is small (a render
    border); each pixel of either render is an unbiased estimate of its mean radiance."""
    pixels = render_world(world, width, height, samples)
    lum = pixels.max(axis=2)
    hot = lum > HOT_FACTOR * max(float(np.median(lum)), 1e-12)
    if not hot.any():
        return pixels
    rows, cols = np.nonzero(hot)
    r0, r1 = max(rows.min() - HOT_MARGIN, 0), min(rows.max() + HOT_MARGIN + 1, height)
    c0, c1 = max(cols.min() - HOT_MARGIN, 0), min(cols.max() + HOT_MARGIN + 1, width)
    if (r1 - r0) * (c1 - c0) > HOT_MAX_SHARE * width * height:
        return pixels
    fine = render_world(world, width, height, HOT_SAMPLES, border=(c0 / width, c1 / width, r0 / height, r1 / height))
    pixels[r0:r1, c0:c1] = fine[r0:r1, c0:c1]
    return pixels


def render_world(world, width, height, samples, border=None):
    """(height, width, 3) float32 radiance of ``world`` rendered by Cycles with an
    equirectangular panoramic camera looking along +x (Cycles turns panoramic cameras so that
    one pointed along +x sees the Environment Texture's centre: the table is in the map
    convention of ``lmdp_addon.world``), a 1-pixel box filter (each pixel the mean over its
    solid angle) and ``samples`` samples; ``border (x0, x1, y0, y1)`` (fractions of the image,
    y from the bottom) renders only that region (the rest is black). A scratch scene, camera and image are removed
    afterwards; the user's scenes are not touched. Raises RuntimeError when the render fails."""
    scene = bpy.data.scenes.new("LMDP world capture")
    cam_data = bpy.data.cameras.new("LMDP world capture")
    cam = bpy.data.objects.new("LMDP world capture", cam_data)
    path = os.path.join(tempfile.mkdtemp(prefix="lmdp_world_"), "world.exr")
    image = None
    try:
        scene.world = world
        scene.collection.objects.link(cam)
        scene.camera = cam
        cam_data.type = 'PANO'
        if hasattr(cam_data, "panorama_type"):
            cam_data.panorama_type = 'EQUIRECTANGULAR'
        else:
            cam_data.cycles.panorama_type = 'EQUIRECTANGULAR'
        cam.rotation_euler = (np.pi / 2, 0.0, -np.pi / 2)      # looking along +x, up +z
        render = scene.render
        render.engine = 'CYCLES'
        render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
        render.film_transparent = False
        render.image_settings.file_format = 'OPEN_EXR'
        render.image_settings.color_depth = '32'
        render.filepath = path
        cycles = scene.cycles
        cycles.device = 'CPU'
        cycles.samples = int(samples)
        cycles.use_adaptive_sampling = False
        cycles.use_denoising = False
        cycles.pixel_filter_type = 'BOX'
        cycles.filter_width = 1.0
        cycles.seed = 0
        if border is not None:
            render.use_border, render.use_crop_to_border = True, False
            render.border_min_x, render.border_max_x, render.border_min_y, render.border_max_y = border
        with bpy.context.temp_override(scene=scene):
            result = bpy.ops.render.render(write_still=True, scene=scene.name)
        if result != {'FINISHED'} or not os.path.exists(path):
            raise RuntimeError(f"Cycles render returned {result}")
        image = bpy.data.images.load(path)
        pixels = image_radiance(image)
        if pixels is None:
            raise RuntimeError("the render has no pixels")
        return pixels
    finally:
        if image is not None:
            bpy.data.images.remove(image)
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        bpy.data.scenes.remove(scene)
        try:
            os.remove(path)
            os.rmdir(os.path.dirname(path))
        except OSError:
            pass
