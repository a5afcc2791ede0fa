"""Blender materials -> the engine's surface description (:mod:`lmdp_addon.textures`).

:class:`ShadingReader` walks a material's node tree from the Material Output's Surface through
reroutes, muted nodes and node groups (in and out of their Group Input / Group Output) and
translates it into three expressions of :mod:`lmdp_addon.textures`: the diffuse weight D
(colour), the emission E (radiance) and the transparent weight Tr (value) of the closures Cycles
would build, so that

    alpha = 1 - Tr,   albedo = D / alpha,

exactly for Diffuse BSDF, Principled BSDF (Base Color x (1 - Metallic) x (1 - Transmission),
Alpha, Emission Color x Emission Strength, all x Alpha), Emission, Transparent BSDF, Mix Shader
and Add Shader. Colour inputs may be fed by Image Texture (flat projection, UV Map / Texture
Coordinate UV / Mapping in front of the Vector), Color Attribute and Attribute nodes, RGB and
Value nodes, Mix (colour) / MixRGB, Invert, Gamma, Brightness/Contrast, Hue/Saturation/Value,
RGB Curves, Math, RGB to BW, Separate / Combine Color (RGB). Constant chains fold to constants:
untextured materials give the same numbers as before. Everything else is approximated and said
once per material in a warning that names the material and the node (the socket's own value is
used). The add-on's own hook-up nodes are transparent: the "LMDP Lightmap Multiply" node reads
as its A input.

:class:`ImageCache` (one per Blender session, :data:`IMAGE_CACHE`) keeps every image it has read
as an :class:`~lmdp_addon.textures.ImageTable` until the image changes (its name, source, file
path, size, colour space, alpha mode, packed data or generated settings, and for images edited
in memory a digest of their pixels), so an operator call does not re-read a large texture.
"""
import hashlib
import os
import threading
from collections import OrderedDict

import bpy
import numpy as np

from ...lmdp_addon import textures as tx
from .materials import NODE_MULTIPLY

#: Cycles' colour of an Image Texture without pixels (missing file, no image).
MISSING_IMAGE = (1.0, 0.0, 1.0)
#: Samples of an RGB Curves node's lookup tables on [0, 1].
CURVE_SAMPLES = 257
_BLACK3 = tx.Const([0.0, 0.0, 0.0])
_ZERO = tx.Const([0.0])
_ONE = tx.Const([1.0])


# ---- images --------------------------------------------------------------------------------

class ImageCache:
    """Blender images as :class:`~lmdp_addon.textures.ImageTable`, read once per version.

    ``table(image)`` returns the cached table while :meth:`version` of the image is unchanged;
    ``reads`` counts the pixel reads (``Image.pixels.foreach_get``) that built tables. At most
    ``max_bytes`` of tables are kept (least recently used dropped first).
    """

    def __init__(self, max_bytes=4 << 30):
        self.max_bytes = int(max_bytes)
        self.reads = 0
        self._tables = OrderedDict()     # name_full -> (version, digest, table)
        self._lock = threading.Lock()

    @staticmethod
    def version(image):
        """What identifies the pixels of ``image`` without reading them: the image datablock
        itself (``session_uid``: a new file or a new image with the same name differs), its
        source, file path and the file's modification time, size, colour space, alpha mode,
        a digest of its packed data, its generated settings and whether it is edited in memory."""
        packed = image.packed_file
        packed_digest = (hashlib.blake2b(packed.data, digest_size=16).digest()
                         if packed is not None else None)
        try:
            mtime = os.stat(bpy.path.abspath(image.filepath, library=image.library)).st_mtime_ns \
                if image.source == 'FILE' and packed is None else None
        except (OSError, ValueError):
            mtime = None
        return (getattr(image, "session_uid", None), image.source, image.filepath_raw, mtime,
                tuple(image.size), image.channels, image.is_float, image.colorspace_settings.name,
                image.alpha_mode, image.is_dirty, packed_digest, image.generated_type,
                tuple(image.generated_color), image.generated_width, image.generated_height,
                image.use_generated_float)

    def _read(self, image):
        w, h = image.size
        c = image.channels
        px = np.empty(w * h * c, dtype=np.float32)
        image.pixels.foreach_get(px)
        self.reads += 1
        return px

    def table(self, image):
        """The :class:`ImageTable` of ``image`` (None when it has no pixels)."""
        name = image.name_full
        version = self.version(image)
        with self._lock:
            cached = self._tables.get(name)
        if cached is not None and cached[0] == version and not image.is_dirty:
            with self._lock:
                self._tables.move_to_end(name)
            return cached[2]
        w, h = image.size
        if w * h == 0 or image.channels == 0:
            return None
        px = self._read(image)
        digest = hashlib.blake2b(px.tobytes(), digest_size=16).digest() if image.is_dirty else None
        if cached is not None and cached[0] == version and cached[1] == digest:
            return cached[2]
        table = _to_table(px, image)
        with self._lock:
            self._tables[name] = (version, digest, table)
            self._tables.move_to_end(name)
            while len(self._tables) > 1 and sum(t[2].pixels.nbytes for t in self._tables.values()) > self.max_bytes:
                self._tables.popitem(last=False)
        return table

    def clear(self):
        with self._lock:
            self._tables.clear()


def _to_table(px, image):
    """(H, W, 4) float32 RGBA of ``image``'s flat pixels ``px`` (row 0 at the bottom)."""
    w, h = image.size
    c = image.channels
    px = px.reshape(h, w, c)
    if c == 4:
        rgba = px                                   # the buffer read, used in place
    else:
        rgba = np.empty((h, w, 4), np.float32)
        rgba[..., :3] = px[..., :3] if c >= 3 else px[..., :1]
        rgba[..., 3] = px[..., 1] if c == 2 else 1.0
    if image.alpha_mode == 'NONE':
        rgba[..., 3] = 1.0
    srgb = (not image.is_float) and image.colorspace_settings.name == 'sRGB'
    premultiplied = c in (2, 4) and image.alpha_mode in ('STRAIGHT', 'PREMUL')
    if premultiplied and image.alpha_mode == 'STRAIGHT':
        rows = np.flatnonzero((rgba[..., 3] < 1).any(axis=1))     # only rows with alpha < 1
        if len(rows):
            part = rgba[rows]
            if image.is_float:
                part[..., :3] *= part[..., 3:]
            else:   # as Cycles associates 8-bit alpha: on the bytes, truncated (exact in float32)
                a = np.rint(part[..., 3:] * np.float32(255))
                colour = np.rint(part[..., :3] * np.float32(255))
                colour *= a
                colour /= np.float32(255)
                np.floor(colour, out=colour)
                colour /= np.float32(255)
                part[..., :3] = colour
            rgba[rows] = part
    return tx.ImageTable(rgba, srgb=srgb, name=image.name, premultiplied=premultiplied)


#: The add-on's image cache (one per Blender session; images are matched by ``name_full``).
IMAGE_CACHE = ImageCache()


# ---- the node walk -------------------------------------------------------------------------

def _links(socket):
    return [link for link in socket.links if not link.is_muted and link.is_valid]


def _group_output(tree):
    outputs = [n for n in tree.nodes if n.type == 'GROUP_OUTPUT']
    return next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)


def _by_identifier(sockets, identifier):
    return next((s for s in sockets if s.identifier == identifier), None)


def resolve(socket, stack=()):
    """What feeds the input ``socket`` of a node inside the groups ``stack`` (outermost first):
    ``(node, output socket, stack)`` of the node, or ``(None, socket, stack)`` of the unlinked
    input whose value it is; through reroutes, muted nodes, node groups and group inputs."""
    links = _links(socket)
    while links:
        link = links[0]
        node, out = link.from_node, link.from_socket
        if node.type == 'REROUTE':
            socket = node.inputs[0]
            links = _links(socket)
            continue
        if node.mute:
            through = [il.from_socket for il in node.internal_links if il.to_socket == out]
            if not through:
                return None, out, stack
            socket = through[0]
            links = _links(socket)
            continue
        if node.type == 'GROUP' and node.node_tree is not None:
            inner_out = _group_output(node.node_tree)
            inner = _by_identifier(inner_out.inputs, out.identifier) if inner_out is not None else None
            if inner is None:
                return None, out, stack
            stack = stack + (node,)
            socket = inner
            links = _links(socket)
            continue
        if node.type == 'GROUP_INPUT' and stack:
            group, stack = stack[-1], stack[:-1]
            outer = _by_identifier(group.inputs, out.identifier)
            if outer is None:
                return None, out, stack
            socket = outer
            links = _links(socket)
            continue
        return node, out, stack
    return None, socket, stack


def _default(socket, channels):
    """The socket's own value as a constant of ``channels``."""
    value = getattr(socket, "default_value", None)
    if value is None:
        return tx.Const([0.0] * channels)
    try:
        v = [float(x) for x in value][:3]
    except TypeError:
        v = [float(value)]
    c = tx.Const(v if len(v) in (1, 3) else v[:1])
    if c.channels == channels:
        return c
    if channels == 1:
        return tx.Const([float(np.dot(c.value, tx.LUMINANCE32))])
    return tx.Const([c.value[0]] * 3)


class ShadingReader:
    """Materials -> :class:`~lmdp_addon.textures.MaterialShading` and constants, with warnings.

    The images, UV maps and colour attributes the expressions read are numbered scene-wide:
    ``images`` (the :class:`ImageTable` of each), ``uv_names`` (a UV map's name; None: the
    mesh's render UV map), ``attribute_names`` (a colour attribute's name; "": the mesh's
    render colour attribute). Results are cached per material.
    """

    def __init__(self, warnings, cache=IMAGE_CACHE):
        self.warnings = warnings
        self.cache = cache
        self.images, self._image_index = [], {}
        self.uv_names, self.attribute_names = [None], []
        self._materials = {}
        self._owner = ""
        self._unsupported = []
        #: name_full -> [(node name, warning)] of the nodes LMDP could not evaluate (read as
        #: their socket's value): :meth:`flush` warns, or the caller bakes Cycles' colour.
        self.unsupported = {}
        #: name_full -> the colour (expression) a ray that passes the material carries, or None (white)
        self.tints = {}

    def warn(self, message):
        message = f"{self._owner}: {message}"
        if message not in self.warnings:
            self.warnings.append(message)

    # ---- materials ----------------------------------------------------------------------
    def material(self, mat):
        """``(albedo, emission, alpha)``: ``albedo`` and ``emission`` each a (3,) float64
        constant or an expression, ``alpha`` None (opaque) or an expression / constant."""
        if mat is None:
            return np.array((0.8, 0.8, 0.8)), np.zeros(3), None
        key = mat.name_full if hasattr(mat, "name_full") else mat.name
        if key not in self._materials:
            self._owner = f"Material '{mat.name}'"
            self._unsupported = []
            self._tint = None
            self._materials[key] = self._read(mat)
            self.unsupported[key] = self._unsupported
            self.tints[key] = self._tint
        return self._materials[key]

    def flush(self, mat):
        """Warn about the nodes of ``mat`` that read as their socket's value."""
        if mat is not None:
            for _, message in self.unsupported.get(mat.name_full, ()):
                if message not in self.warnings:
                    self.warnings.append(message)

    def add_table(self, table):
        """Index of ``table`` among :attr:`images` (added once)."""
        if id(table) not in self._image_index:
            self._image_index[id(table)] = len(self.images)
            self.images.append(table)
        return self._image_index[id(table)]

    def _read(self, mat):
        tree = mat.node_tree
        output = tree.get_output_node('CYCLES') if tree is not None else None
        if tree is None or (bpy.app.version < (5, 0, 0) and not mat.use_nodes):
            return np.array(mat.diffuse_color[:3], dtype=np.float64), np.zeros(3), None
        if output is None or resolve(output.inputs["Surface"])[0] is None:
            self.warn("has no shader connected to a Material Output: Cycles renders it black, so "
                      "LMDP uses albedo 0 (no emission)")
            return np.zeros(3), np.zeros(3), None
        D, E, Tr = self.shader(output.inputs["Surface"], ())
        alpha = tint = None
        c = tx.constant(Tr)
        if c is None or np.max(c) > 0:
            # Rays pass with probability p = the largest channel of the transparent weight Tr
            # and then carry Tr / p (1 for a grey Tr); they stop with 1 - p.
            if Tr.channels == 1 or (c is not None and np.ptp(c) == 0):
                p = Tr if Tr.channels == 1 else tx.Const(c[:1])
            else:
                p = tx.Math("MAXIMUM", tx.Math("MAXIMUM", tx.Separate(Tr, 0), tx.Separate(Tr, 1)),
                            tx.Separate(Tr, 2))
                p = tx.Math("MINIMUM", p, _ONE) if c is None else tx.Const([min(float(np.max(c)), 1.0)])
                tint = tx.quotient(Tr, p)
            alpha = tx.one_minus(p)
            D = tx.quotient(D, alpha)
        albedo = tx.constant(D)
        emission = tx.constant(E)
        if alpha is not None and (emission is None or np.any(emission > 0)):
            self.warn("emits light and is partly transparent: rays that pass it do not see its emission "
                      "(light sampling does), so its light is underestimated where alpha < 1")
        if emission is None:
            self.warn("its emission is textured: LMDP averages it over each triangle (emitters are "
                      "uniform per triangle)")
        self._tint = tint
        return (np.clip(albedo, 0.0, 1.0) if albedo is not None else D,
                np.maximum(emission, 0.0) if emission is not None else E, alpha)

    # ---- shaders: (D, E, Tr) --------------------------------------------------------------
    def shader(self, socket, stack, depth=0):
        node, out, stack = resolve(socket, stack)
        if node is None:
            return _BLACK3, _BLACK3, _ZERO
        t = node.type
        if depth > 64:
            self.warn(f"shader graph too deep at '{node.name}'; treated as black")
            return _BLACK3, _BLACK3, _ZERO
        if t == 'BSDF_DIFFUSE':
            return self.colour(node.inputs["Color"], stack), _BLACK3, _ZERO
        if t == 'BSDF_PRINCIPLED':
            return self._principled(node, stack)
        if t in ('EMISSION', 'BACKGROUND'):
            return _BLACK3, tx.product(self.colour(node.inputs["Color"], stack),
                                       self.value(node.inputs["Strength"], stack)), _ZERO
        if t == 'MIX_SHADER':
            fac = self.value(node.inputs[0], stack)
            a = self.shader(node.inputs[1], stack, depth + 1)
            b = self.shader(node.inputs[2], stack, depth + 1)
            return tuple(tx.lerp(fac, x, y) for x, y in zip(a, b))
        if t == 'ADD_SHADER':
            a = self.shader(node.inputs[0], stack, depth + 1)
            b = self.shader(node.inputs[1], stack, depth + 1)
            D = tx.total(a[0], b[0])
            c = tx.constant(D)
            if c is not None and np.any(c > 1):
                self.warn(f"Add Shader '{node.name}' sums its inputs' albedo above 1 (clipped to 1)")
            return D, tx.total(a[1], b[1]), tx.total(a[2], b[2])
        if t == 'BSDF_TRANSPARENT':
            return _BLACK3, _BLACK3, self.colour(node.inputs["Color"], stack)
        if t == 'BSDF_GLOSSY':   # no diffuse part: its reflection is a microfacet lobe (bsdf_params)
            return _BLACK3, _BLACK3, _ZERO
        if t in ('HOLDOUT', 'BSDF_REFRACTION'):
            self.warn(f"'{node.name}' ({node.bl_label}) cannot be modelled; the surface is treated as "
                      "black (absorbing)")
            return _BLACK3, _BLACK3, _ZERO
        if "Color" in node.inputs or "Base Color" in node.inputs:
            name = "Base Color" if "Base Color" in node.inputs else "Color"
            self.warn(f"'{node.name}' ({node.bl_label}) is treated as a diffuse surface with its {name} "
                      "as albedo")
            return self.colour(node.inputs[name], stack), _BLACK3, _ZERO
        self.warn(f"shader node '{node.name}' ({node.bl_label}) is not supported; using Cycles' "
                  "default grey 0.8")
        return tx.Const([0.8, 0.8, 0.8]), _BLACK3, _ZERO

    def _principled(self, node, stack):
        """Principled BSDF: D = a Base (1 - Metallic)(1 - Transmission), E = a Emission x
        Strength, Tr = 1 - a (a = Alpha)."""
        base = self.colour(node.inputs["Base Color"], stack)
        metallic = self.constant_value(node, "Metallic", stack)
        transmission = self.constant_value(node, "Transmission Weight", stack)
        if transmission > 0:   # metallic and specular: bsdf_params' microfacet lobes
            self.warn(f"Principled BSDF '{node.name}' has Transmission {transmission:g}; LMDP keeps "
                      "its diffuse, specular and metallic parts (no transmission)")
        D = tx.product(base, tx.Const([(1.0 - metallic) * (1.0 - transmission)])) \
            if (metallic or transmission) else base
        strength = self.value(node.inputs["Emission Strength"], stack)
        s = tx.constant(strength)
        E = _BLACK3 if s is not None and s[0] == 0 else tx.product(
            self.colour(node.inputs["Emission Color"], stack), strength)
        alpha = self.value(node.inputs["Alpha"], stack)
        a = tx.constant(alpha)
        if a is not None and a[0] >= 1:
            return D, E, _ZERO
        alpha = tx.Math("MINIMUM", tx.Math("MAXIMUM", alpha, _ZERO), _ONE) if a is None \
            else tx.Const([float(np.clip(a[0], 0.0, 1.0))])
        return tx.product(D, alpha), tx.product(E, alpha), tx.one_minus(alpha)

    def constant_value(self, node, name, stack):
        """A value input that LMDP only reads as a constant (warns when it is driven)."""
        socket = node.inputs[name]
        value = self.value(socket, stack)
        c = tx.constant(value)
        if c is None:
            default = float(socket.default_value)
            self.warn(f"'{node.name}' {name} is driven by a texture, which LMDP reads only as a "
                      f"constant; using the socket's default value {default:g}")
            return default
        return float(c[0])

    # ---- colours and values -------------------------------------------------------------------
    def colour(self, socket, stack):
        return self._expr(socket, stack, 3)

    def value(self, socket, stack):
        return self._expr(socket, stack, 1)

    def _expr(self, socket, stack, channels):
        node, out, inner = resolve(socket, stack)
        if node is None:
            return _default(out, channels)
        expr = self._node(node, out, inner)
        if expr is not None and tx.constant(expr) is None and not any(tx.references(expr).values()):
            expr = tx.Const(expr.evaluate(_One())[0].astype(np.float64))   # a chain of constants
        if expr is None:
            default = _default(socket, channels)
            self._unsupported.append((node.name, f"{self._owner}: '{node.name}' ({node.bl_label}) cannot be "
                                      f"evaluated by LMDP; '{socket.node.name}' {socket.name} uses its own value "
                                      f"{tuple(round(float(x), 3) for x in default.value)}"))
            return default
        if expr.channels != channels:
            c = tx.constant(expr)
            if c is not None:
                return tx.Const([float(c @ tx.LUMINANCE32)] if channels == 1 else [c[0]] * 3)
            expr = tx.Luminance(expr) if channels == 1 else tx.Combine(expr, expr, expr)
        return expr

    def _node(self, node, out, stack):
        """The expression of output ``out`` of ``node``, or None (not supported)."""
        t = node.type
        col, val = self.colour, self.value
        inputs = node.inputs
        if t == 'TEX_IMAGE':
            return self._image(node, out, stack)
        if t in ('VERTEX_COLOR', 'ATTRIBUTE'):
            return self._attribute(node, out)
        if t in ('RGB', 'VALUE'):
            return _default(out, 3 if t == 'RGB' else 1)
        if t == 'MIX' and node.name == NODE_MULTIPLY:
            return col(_by_identifier(inputs, "A_Color"), stack)    # the add-on's own hook-up
        if t == 'MIX' and node.data_type == 'RGBA' and node.blend_type in tx.MIX_BLENDS:
            fac = val(_by_identifier(inputs, "Factor_Float"), stack)
            if not node.clamp_factor:
                return None
            return self._mix(node.blend_type, fac, col(_by_identifier(inputs, "A_Color"), stack),
                             col(_by_identifier(inputs, "B_Color"), stack), node.clamp_result)
        if t == 'MIX_RGB' and node.blend_type in tx.MIX_BLENDS:
            return self._mix(node.blend_type, val(inputs["Fac"], stack), col(inputs["Color1"], stack),
                             col(inputs["Color2"], stack), node.use_clamp)
        if t == 'INVERT':
            return tx.Invert(val(inputs["Fac"], stack), col(inputs["Color"], stack))
        if t == 'GAMMA':
            return tx.Gamma(col(inputs["Color"], stack), val(inputs["Gamma"], stack))
        if t == 'BRIGHTCONTRAST':
            return tx.BrightContrast(col(inputs["Color"], stack), val(inputs["Bright"], stack),
                                     val(inputs["Contrast"], stack))
        if t == 'HUE_SAT':
            return tx.HueSaturation(val(inputs["Hue"], stack), val(inputs["Saturation"], stack),
                                    val(inputs["Value"], stack), val(inputs["Fac"], stack),
                                    col(inputs["Color"], stack))
        if t == 'CURVE_RGB':
            return self._curves(node, stack)
        if t == 'MATH' and node.operation in tx.MATH_OPERATIONS:
            return tx.Math(node.operation, val(inputs[0], stack), val(inputs[1], stack), node.use_clamp)
        if t == 'RGBTOBW':
            return tx.Luminance(col(inputs["Color"], stack))
        if t in ('SEPARATE_COLOR', 'SEPRGB') and getattr(node, "mode", 'RGB') == 'RGB':
            channel = [o.identifier for o in node.outputs].index(out.identifier)
            return tx.Separate(col(inputs[0], stack), channel)
        if t in ('COMBINE_COLOR', 'COMBRGB') and getattr(node, "mode", 'RGB') == 'RGB':
            return tx.Combine(val(inputs[0], stack), val(inputs[1], stack), val(inputs[2], stack))
        return None

    @staticmethod
    def _mix(blend, fac, a, b, clamp):
        ca, cb, ct = tx.constant(a), tx.constant(b), tx.constant(fac)
        if blend == "MIX" and not clamp:
            return tx.lerp(tx.Const([float(np.clip(ct[0], 0, 1))]) if ct is not None else fac, a, b)
        expr = tx.Mix(blend, fac, a, b, clamp)
        if ca is not None and cb is not None and ct is not None:
            return tx.Const(expr.evaluate(_One()).astype(np.float64)[0])
        return expr

    def _curves(self, node, stack):
        mapping = node.mapping
        if tuple(mapping.black_level) != (0.0, 0.0, 0.0) or tuple(mapping.white_level) != (1.0, 1.0, 1.0):
            return None
        mapping.initialize()
        x = np.linspace(0.0, 1.0, CURVE_SAMPLES)
        combined = [mapping.evaluate(mapping.curves[3], float(v)) for v in x]
        tables = np.array([[mapping.evaluate(mapping.curves[c], float(v)) for v in combined] for c in range(3)])
        return tx.Curves(tables, self.value(node.inputs["Fac"], stack), self.colour(node.inputs["Color"], stack))

    def _image(self, node, out, stack):
        image = node.image
        if out.name not in ("Color", "Alpha"):
            return None
        if image is None:
            self.warn(f"Image Texture '{node.name}' has no image: Cycles shows it magenta, and so does LMDP")
            return tx.Const(MISSING_IMAGE if out.name == "Color" else [1.0])
        if node.projection != 'FLAT' or image.source not in ('FILE', 'GENERATED'):
            self.warn(f"Image Texture '{node.name}': {node.projection.lower()} projection / "
                      f"{image.source.lower()} images are not modelled")
            return None
        uv = self._uv(node.inputs["Vector"], stack)
        if uv is None:
            return None
        table = self.cache.table(image)
        if table is None:
            self.warn(f"image '{image.name}' of '{node.name}' has no pixels (missing file?): Cycles shows "
                      "it magenta, and so does LMDP")
            return tx.Const(MISSING_IMAGE if out.name == "Color" else [1.0])
        space = image.colorspace_settings.name
        if not image.is_float and space not in ('sRGB', 'Non-Color', 'Linear Rec.709', 'Raw', 'Linear'):
            self.warn(f"image '{image.name}' has colour space '{space}', which LMDP reads as linear")
        interpolation = node.interpolation.upper()
        if interpolation == "SMART":
            interpolation = "CUBIC"          # Cycles' SVM: Smart is Cubic
        if interpolation not in tx.INTERPOLATIONS:
            self.warn(f"Image Texture '{node.name}' uses {node.interpolation} interpolation; LMDP "
                      "interpolates linearly")
            interpolation = "LINEAR"
        alpha_used = any(not link.is_muted for link in node.outputs["Alpha"].links)
        return tx.ImageTexture(self.add_table(table), uv[0], interpolation, node.extension,
                               "color" if out.name == "Color" else "alpha", uv[1], alpha_used)

    def _uv(self, socket, stack, implicit=True):
        """(UV map index, affine transform or None) of an Image Texture's Vector, or None.
        ``implicit``: an unlinked socket means the render UV map (the Image Texture's own
        Vector), else its value (a Mapping node's Vector)."""
        node, out, stack = resolve(socket, stack)
        if node is None and implicit:
            return self._uv_index(None), None
        if node is None:
            value = np.array(out.default_value[:2], dtype=np.float64)
            return self._uv_index(None), (0.0, 0.0, value[0], 0.0, 0.0, value[1])
        if node.type == 'UVMAP' and not node.from_instancer:
            return self._uv_index(node.uv_map or None), None
        if node.type == 'TEX_COORD' and out.name == "UV" and not node.from_instancer:
            return self._uv_index(None), None
        if node.type == 'MAPPING' and node.vector_type in ('POINT', 'TEXTURE'):
            inner = self._uv(node.inputs["Vector"], stack, implicit=False)
            values = [resolve(node.inputs[n], stack) for n in ("Location", "Rotation", "Scale")
                      if n in node.inputs]
            if inner is None or len(values) < 3 or any(v[0] is not None for v in values):
                return None
            loc, rot, scale = (np.array(v[1].default_value[:], dtype=np.float64) for v in values)
            if np.any(rot[:2] != 0):
                return None
            c, s = np.cos(rot[2]), np.sin(rot[2])
            m = np.array([[c * scale[0], -s * scale[1]], [s * scale[0], c * scale[1]]])
            t = loc[:2]
            if node.vector_type == 'TEXTURE':      # the inverse transform
                m = np.linalg.inv(m)
                t = -m @ t
            if inner[1] is not None:       # compose with the transform in front
                a = np.array(inner[1], dtype=np.float64).reshape(2, 3)
                t = m @ a[:, 2] + t
                m = m @ a[:, :2]
            return inner[0], (m[0, 0], m[0, 1], t[0], m[1, 0], m[1, 1], t[1])
        self.warn(f"'{node.name}' ({node.bl_label}) in front of an Image Texture's Vector cannot be "
                  "evaluated by LMDP")
        return None

    def _uv_index(self, name):
        if name not in self.uv_names:
            self.uv_names.append(name)
        return self.uv_names.index(name)

    def _attribute(self, node, out):
        if node.type == 'ATTRIBUTE':
            if node.attribute_type != 'GEOMETRY' or out.name not in ("Color", "Alpha"):
                return None
            name = node.attribute_name
        else:
            name = node.layer_name
        if out.name not in ("Color", "Alpha"):
            return None
        if name not in self.attribute_names:
            self.attribute_names.append(name)
        return tx.ColorAttribute(self.attribute_names.index(name), "color" if out.name == "Color" else "alpha")


class _One:
    """A single point, to evaluate a constant expression."""

    k = 1

    def memo(self, key, compute):
        return compute()


# ---- Cycles' own diffuse colour, for node trees LMDP cannot evaluate -------------------------------

#: Resolution of the DIFFUSE COLOR bake that stands in for a material LMDP cannot evaluate.
COLOUR_BAKE_RESOLUTION = 256


def tree_digest(tree, h=None, depth=0):
    """A digest of what a node tree computes: its nodes (type, name, mute, settings, input
    values, colour ramps and curves, images), its links, and the node groups it uses."""
    h = h if h is not None else hashlib.blake2b(digest_size=16)
    skip = {"name", "label", "location", "width", "height", "dimensions", "select", "show_options",
            "show_preview", "show_texture", "hide", "color", "use_custom_color", "warning_propagation"}
    for node in tree.nodes:
        h.update(f"\0{node.bl_idname}|{node.name}|{node.mute}".encode())
        for prop in node.bl_rna.properties:
            if prop.identifier in skip or prop.type not in ('BOOLEAN', 'INT', 'FLOAT', 'ENUM', 'STRING'):
                continue
            value = getattr(node, prop.identifier, None)
            h.update(repr(tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) else value).encode())
        for socket in node.inputs:
            value = getattr(socket, "default_value", None)
            h.update(repr(tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) else value).encode())
        ramp = getattr(node, "color_ramp", None)
        if ramp is not None:
            h.update(repr([(e.position, tuple(e.color)) for e in ramp.elements] + [ramp.interpolation]).encode())
        mapping = getattr(node, "mapping", None)
        if mapping is not None and hasattr(mapping, "curves"):
            h.update(repr([[tuple(p.location) for p in c.points] for c in mapping.curves]).encode())
        image = getattr(node, "image", None)
        if image is not None:
            h.update(repr(ImageCache.version(image)).encode())
        if node.type == 'GROUP' and node.node_tree is not None and depth < 16:
            tree_digest(node.node_tree, h, depth + 1)
    for link in tree.links:
        h.update(f"\0{link.from_node.name}|{link.from_socket.identifier}|{link.to_node.name}|"
                 f"{link.to_socket.identifier}|{link.is_muted}".encode())
    return h


class ColourBakes:
    """Cycles' DIFFUSE COLOR bakes (1 sample: the colour at each texel point, albedo x alpha) of
    objects on their render UV map, as :class:`~lmdp_addon.textures.ImageTable`; kept until the
    object's mesh, transform, UV map or materials change (``key``); ``bakes`` counts them."""

    def __init__(self, max_entries=32):
        self.max_entries = int(max_entries)
        self.bakes = 0
        self._tables = OrderedDict()

    def table(self, context, obj, key, bake=True):
        """The table of ``obj`` for ``key``; baked now if not kept (None when ``bake`` is off)."""
        if key in self._tables:
            self._tables.move_to_end(key)
            return self._tables[key]
        if not bake:
            return None
        from .demo_scenes import bake_cycles
        # The add-on's own MULTIPLY hook-up multiplies the surface colour by the lightmap: muted
        # for the bake (a muted Mix node passes its A input), so the bake sees the surface.
        hooks = [n for slot in obj.material_slots if slot.material is not None and slot.material.node_tree
                 for n in slot.material.node_tree.nodes if n.name == NODE_MULTIPLY and not n.mute]
        try:
            for node in hooks:
                node.mute = True
            px = bake_cycles(context, obj, 'DIFFUSE', ('COLOR',), COLOUR_BAKE_RESOLUTION, samples=1, margin=4)
        finally:
            for node in hooks:
                node.mute = False
        px[..., 3] = 1.0
        table = tx.ImageTable(px, name=f"{obj.name} (Cycles diffuse colour)")
        self.bakes += 1
        self._tables[key] = table
        while len(self._tables) > self.max_entries:
            self._tables.popitem(last=False)
        return table


#: The add-on's colour bakes (one per Blender session).
COLOUR_BAKES = ColourBakes()


# ---- per-mesh data ----------------------------------------------------------------------------

def uv_corners(mesh, loops, name):
    """(T, 3, 2) float32 UVs of the UV map ``name`` (None: the render UV map) at the triangles'
    corners ``loops``, or None when the mesh has no such map."""
    layers = mesh.uv_layers
    if name is None:
        layer = next((l for l in layers if l.active_render), None) or layers.active
    else:
        layer = layers.get(name)
    if layer is None:
        return None
    uv = np.empty(len(mesh.loops) * 2, dtype=np.float32)
    layer.data.foreach_get("uv", uv)
    return uv.reshape(-1, 2)[loops]


def attribute_corners(mesh, loops, verts, name):
    """(T, 3, 4) float32 linear RGBA of the colour attribute ``name`` ("": the render colour
    attribute) at the triangles' corners (``loops``, or the vertex indices ``verts`` of a
    point-domain attribute), or None when the mesh has none."""
    attrs = mesh.color_attributes
    attr = attrs.get(name) if name else (attrs[attrs.render_color_index]
                                          if 0 <= attrs.render_color_index < len(attrs) else None)
    if attr is None and not name:
        attr = attrs.active_color
    if attr is None:
        return None
    values = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", values)
    values = values.reshape(-1, 4)
    return values[loops] if attr.domain == 'CORNER' else values[verts]
