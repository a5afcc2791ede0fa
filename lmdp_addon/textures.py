"""Surface textures without bpy: diffuse colour and alpha at a point of a triangle.

The Blender layer (``operators/adapters/shading.py``) translates each material's node tree into
a small expression tree of the nodes below; :class:`SurfaceTextures` holds those trees with the
data they read (image tables, corner UVs per UV map, corner colours per colour attribute) and
evaluates them vectorised at ``(triangle, barycentrics)``, the points the tracer, the states and
the build meet. Materials whose colour and alpha are constant never get a tree: their albedo is
``SceneArrays.triangle_albedo`` and they are opaque.

Conventions are Cycles' (``kernel/svm``, ``kernel/device/cpu/image.h``):

* An image table is ``(H, W, 4)`` float32 RGBA with row 0 at the bottom (Blender's
  ``Image.pixels`` order), so texel (i, j) covers ``v ∈ [i/H, (i+1)/H)``, ``u ∈ [j/W, (j+1)/W)``.
  ``LINEAR`` interpolates the four texels around ``(u W - ½, v H - ½)``; ``CUBIC`` weighs the
  16 around it by the uniform cubic B-spline (Cycles' cubic); ``CLOSEST`` takes the texel
  containing ``(u W, v H)``. Extension ``REPEAT`` wraps, ``EXTEND`` clamps to the edge,
  ``CLIP`` reads transparent black for every texel outside the image (so a linear lookup fades
  out over the half texel beyond the border),
  ``MIRROR`` reflects at every edge.
* 8-bit sRGB images are interpolated in sRGB and converted to linear afterwards (Cycles keeps
  them compressed as sRGB bytes); float and non-colour images are used as stored.
* Images with straight alpha are stored premultiplied (8-bit: ``⌊c a / 255⌋`` on the bytes, in
  sRGB) and interpolated so; when the node's Alpha output is used the colour is then divided
  by alpha (where 0 < alpha < 1; Cycles' ``NODE_IMAGE_ALPHA_UNASSOCIATE``), and only then
  converted from sRGB. Texels outside a CLIP image have alpha 0 too.
* Mix blend modes (``svm_color_util.h``): MIX ``a + t (b - a)``, MULTIPLY ``a (1 - t + t b)``,
  ADD ``a + t b``, SUBTRACT ``a - t b``, SCREEN ``1 - (1 - t + t (1 - b)) (1 - a)``, DIVIDE
  ``(1 - t) a + t a / b`` (b ≠ 0), DIFFERENCE ``a + t (|a - b| - a)``, DARKEN
  ``a + t (min(a, b) - a)``, LIGHTEN ``max(a, t b)``; the factor clamped to [0, 1].
* A colour used as a value is its luminance (Rec.709 weights), a value used as a colour is grey.
"""
import hashlib
from dataclasses import dataclass, field

import numpy as np

EXTENSIONS = ("REPEAT", "EXTEND", "CLIP", "MIRROR")
INTERPOLATIONS = ("LINEAR", "CLOSEST", "CUBIC")
MIX_BLENDS = ("MIX", "MULTIPLY", "ADD", "SUBTRACT", "SCREEN", "DIVIDE", "DIFFERENCE", "DARKEN", "LIGHTEN")
MATH_OPERATIONS = ("ADD", "SUBTRACT", "MULTIPLY", "DIVIDE", "POWER", "MINIMUM", "MAXIMUM", "LESS_THAN",
                   "GREATER_THAN", "ABSOLUTE", "ROUND", "FLOOR")
LUMINANCE32 = np.array([0.2126, 0.7152, 0.0722], np.float32)

#: Barycentrics (weights of corners 1 and 2) of the 16 points at which :meth:`SurfaceTextures.
#: triangle_means` averages an expression over a triangle: a 4 x 4 stratified grid warped
#: uniformly onto the triangle.
_G = (np.arange(16) // 4 + 0.5) / 4.0, (np.arange(16) % 4 + 0.5) / 4.0
_MEAN_BU = (np.sqrt(_G[0]) * (1.0 - _G[1])).astype(np.float32)
_MEAN_BV = (np.sqrt(_G[0]) * _G[1]).astype(np.float32)


def srgb_to_linear(c):
    """The sRGB transfer function inverted (IEC 61966-2-1), elementwise, float32."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / np.float32(12.92),
                    ((np.maximum(c, 0.0) + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4))


@dataclass
class ImageTable:
    """An image's pixels: ``pixels (H, W, 4)`` float32 RGBA, row 0 at the bottom; ``srgb``:
    the values are sRGB-encoded (an 8-bit sRGB image) and become linear after interpolation;
    ``premultiplied``: the colours are stored multiplied by alpha (module docstring)."""

    pixels: np.ndarray
    srgb: bool = False
    name: str = ""
    premultiplied: bool = False

    def __post_init__(self):
        px = np.asarray(self.pixels, dtype=np.float32)
        if px.ndim != 3 or px.shape[2] != 4 or px.shape[0] < 1 or px.shape[1] < 1:
            raise ValueError(f"image table '{self.name}' must be (H, W, 4), not {px.shape}")
        self.pixels = np.ascontiguousarray(px)
        self._digest = None

    def digest(self):
        """bytes: digest of the table (computed once: a table is not changed after it is made)."""
        if self._digest is None:
            h = hashlib.blake2b(self.pixels.tobytes(), digest_size=16)
            h.update(bytes([self.srgb, self.premultiplied]))
            self._digest = h.digest()
        return self._digest


def _wrap(i, n, extension):
    """Texel indices ``i`` wrapped into [0, n) by ``extension`` and whether they exist (CLIP)."""
    if extension == "REPEAT":
        return np.mod(i, n), None
    if extension == "MIRROR":
        m = np.mod(np.abs(i + (i < 0)), 2 * n)
        return np.where(m >= n, 2 * n - m - 1, m), None
    inside = (i >= 0) & (i < n)
    return np.clip(i, 0, n - 1), (inside if extension == "CLIP" else None)


def _bspline(t):
    """The four uniform cubic B-spline weights at fraction ``t`` (Cycles' ``cubic_weights``)."""
    t2, t3 = t * t, t * t * t
    return ((1 - t) ** 3 / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6)


def sample_image(table, uv, interpolation="LINEAR", extension="REPEAT", unpremultiply=False):
    """(k, 4) float32 linear RGBA of ``table`` at ``uv (k, 2)`` (module docstring): the
    interpolated texels, divided by alpha where 0 < alpha < 1 when ``unpremultiply`` and the
    table is premultiplied, then converted from sRGB when the table is sRGB-encoded."""
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, not {interpolation!r}")
    if extension not in EXTENSIONS:
        raise ValueError(f"extension must be one of {EXTENSIONS}, not {extension!r}")
    px = table.pixels
    h, w = px.shape[:2]
    uv = np.asarray(uv, dtype=np.float32)
    x, y = uv[:, 0] * np.float32(w), uv[:, 1] * np.float32(h)
    if interpolation == "CLOSEST":
        ix, okx = _wrap(np.floor(x).astype(np.int64), w, extension)
        iy, oky = _wrap(np.floor(y).astype(np.int64), h, extension)
        out = px[iy, ix]
        if okx is not None:
            out = out * (okx & oky)[:, None]
    elif interpolation == "CUBIC":
        x, y = x - np.float32(0.5), y - np.float32(0.5)
        fx, fy = np.floor(x), np.floor(y)
        wx, wy = _bspline(x - fx), _bspline(y - fy)
        x0, y0 = fx.astype(np.int64), fy.astype(np.int64)
        out = np.zeros((len(uv), 4), np.float32)
        for j in range(4):                        # 4 x 4 texels, not rays
            iy, oky = _wrap(y0 + j - 1, h, extension)
            for i in range(4):
                ix, okx = _wrap(x0 + i - 1, w, extension)
                weight = wx[i] * wy[j]
                if okx is not None:
                    weight = weight * (okx & oky)
                out += weight[:, None] * px[iy, ix]
    else:
        x, y = x - np.float32(0.5), y - np.float32(0.5)
        fx, fy = np.floor(x), np.floor(y)
        tx, ty = (x - fx)[:, None], (y - fy)[:, None]
        x0, y0 = fx.astype(np.int64), fy.astype(np.int64)
        (ix0, ok0), (ix1, ok1) = _wrap(x0, w, extension), _wrap(x0 + 1, w, extension)
        (iy0, oj0), (iy1, oj1) = _wrap(y0, h, extension), _wrap(y0 + 1, h, extension)
        c00, c01, c10, c11 = px[iy0, ix0], px[iy0, ix1], px[iy1, ix0], px[iy1, ix1]
        if ok0 is not None:
            c00, c01 = c00 * (ok0 & oj0)[:, None], c01 * (ok1 & oj0)[:, None]
            c10, c11 = c10 * (ok0 & oj1)[:, None], c11 * (ok1 & oj1)[:, None]
        out = (1 - ty) * ((1 - tx) * c00 + tx * c01) + ty * ((1 - tx) * c10 + tx * c11)
    out = out.astype(np.float32, copy=False)
    if unpremultiply and table.premultiplied:
        a = out[:, 3:]
        divide = (a > 0) & (a < 1)
        out = np.concatenate([np.where(divide, out[:, :3] / np.where(divide, a, 1), out[:, :3]), a], axis=1)
    if table.srgb:
        out = np.concatenate([srgb_to_linear(out[:, :3]), out[:, 3:]], axis=1)
    return out


# ---- expressions -----------------------------------------------------------------------------
# Each node evaluates to (k, C) float32 at the points of a :class:`_Points`: C = 3 (a colour) or
# 1 (a value). ``as_channels`` converts between the two as Blender's implicit conversions do.

class _Points:
    """The points an expression is evaluated at, and the data it reads."""

    def __init__(self, surface, tri, bu, bv):
        self.surface, self.tri = surface, tri
        self.w = np.stack([1.0 - bu - bv, bu, bv], axis=1).astype(np.float32)   # (k, 3)
        self.k = len(tri)
        self._memo = {}

    def corners(self, table):
        """``table (T, 3, C)`` interpolated at the points: (k, C)."""
        return np.einsum("kj,kjc->kc", self.w, table[self.tri])

    def memo(self, key, compute):
        if key not in self._memo:
            self._memo[key] = compute()
        return self._memo[key]


def as_channels(value, channels):
    """(k, C) ``value`` as (k, ``channels``): colour -> value by luminance, value -> grey."""
    c = value.shape[1]
    if c == channels:
        return value
    if channels == 1:
        return (value[:, :3] @ LUMINANCE32)[:, None].astype(np.float32)
    return np.repeat(value[:, :1], channels, axis=1)


@dataclass
class Const:
    """A constant colour (3,) or value (1,)."""

    value: np.ndarray

    def __post_init__(self):
        self.value = np.asarray(self.value, dtype=np.float64).reshape(-1)

    @property
    def channels(self):
        return len(self.value)

    def evaluate(self, p):
        return np.broadcast_to(self.value.astype(np.float32), (p.k, self.channels))


@dataclass
class ImageTexture:
    """An Image Texture node: ``image`` index into :attr:`SurfaceTextures.images`, ``uv``
    index into :attr:`SurfaceTextures.uv_maps`, Cycles' interpolation and extension, the
    output read: ``'color'`` (3) or ``'alpha'`` (1), the UV ``transform`` and whether the
    colour is unpremultiplied (the node's Alpha output is used)."""

    image: int
    uv: int
    interpolation: str = "LINEAR"
    extension: str = "REPEAT"
    output: str = "color"
    transform: tuple = None
    unpremultiply: bool = False

    @property
    def channels(self):
        return 3 if self.output == "color" else 1

    def evaluate(self, p):
        key = ("image", self.image, self.uv, self.interpolation, self.extension, self.transform,
               self.unpremultiply)
        rgba = p.memo(key, lambda: sample_image(p.surface.images[self.image], self._uv(p),
                                                self.interpolation, self.extension, self.unpremultiply))
        return rgba[:, :3] if self.output == "color" else rgba[:, 3:]

    def _uv(self, p):
        """(k, 2) the UVs at the points, through the affine ``transform`` (a, b, c, d, e, f):
        ``u' = a u + b v + c``, ``v' = d u + e v + f`` (a Mapping node), if any."""
        uv = p.corners(p.surface.uv_maps[self.uv])
        if self.transform is None:
            return uv
        a, b, c, d, e, f = (np.float32(x) for x in self.transform)
        return np.stack([a * uv[:, 0] + b * uv[:, 1] + c, d * uv[:, 0] + e * uv[:, 1] + f], axis=1)


@dataclass
class ColorAttribute:
    """A Color Attribute node: ``attribute`` index into :attr:`SurfaceTextures.attributes`
    (corner colours, linear RGBA), output ``'color'`` or ``'alpha'``."""

    attribute: int
    output: str = "color"

    @property
    def channels(self):
        return 3 if self.output == "color" else 1

    def evaluate(self, p):
        rgba = p.memo(("attribute", self.attribute),
                      lambda: p.corners(p.surface.attributes[self.attribute]))
        return rgba[:, :3] if self.output == "color" else rgba[:, 3:]


@dataclass
class Mix:
    """A Mix (colour) node: ``blend`` of :data:`MIX_BLENDS`, factor ``fac`` (value), colours
    ``a`` and ``b``; ``clamp``: the result clamped to [0, 1]."""

    blend: str
    fac: object
    a: object
    b: object
    clamp: bool = False
    channels: int = 3

    def evaluate(self, p):
        t = np.clip(as_channels(self.fac.evaluate(p), 1), 0.0, 1.0)
        a, b = as_channels(self.a.evaluate(p), 3), as_channels(self.b.evaluate(p), 3)
        blend = self.blend
        if blend == "MIX":
            out = a + t * (b - a)
        elif blend == "MULTIPLY":
            out = a * (1 - t + t * b)
        elif blend == "ADD":
            out = a + t * b
        elif blend == "SUBTRACT":
            out = a - t * b
        elif blend == "SCREEN":
            out = 1 - (1 - t + t * (1 - b)) * (1 - a)
        elif blend == "DIVIDE":
            out = np.where(b != 0, (1 - t) * a + t * a / np.where(b != 0, b, 1), a)
        elif blend == "DIFFERENCE":
            out = a + t * (np.abs(a - b) - a)
        elif blend == "DARKEN":
            out = a + t * (np.minimum(a, b) - a)
        elif blend == "LIGHTEN":
            out = np.maximum(a, t * b)
        else:
            raise ValueError(f"unknown blend {blend!r}")
        return (np.clip(out, 0.0, 1.0) if self.clamp else out).astype(np.float32)


@dataclass
class Math:
    """A Math node on values: ``operation`` of :data:`MATH_OPERATIONS` (Cycles: DIVIDE and
    POWER give 0 where undefined; LESS_THAN / GREATER_THAN give 1 or 0, as the glTF importer's
    alpha cut-off uses them; ABSOLUTE, ROUND and FLOOR read ``a`` only), ``clamp`` to [0, 1]."""

    operation: str
    a: object
    b: object
    clamp: bool = False
    channels: int = 1

    def evaluate(self, p):
        a, b = as_channels(self.a.evaluate(p), 1), as_channels(self.b.evaluate(p), 1)
        op = self.operation
        with np.errstate(all="ignore"):
            if op == "ADD":
                out = a + b
            elif op == "SUBTRACT":
                out = a - b
            elif op == "MULTIPLY":
                out = a * b
            elif op == "DIVIDE":
                out = np.where(b != 0, a / np.where(b != 0, b, 1), 0)
            elif op == "POWER":
                out = np.where(a >= 0, np.power(np.maximum(a, 0), b), 0)
                out = np.where(np.isfinite(out), out, 0)
            elif op == "MINIMUM":
                out = np.minimum(a, b)
            elif op == "MAXIMUM":
                out = np.maximum(a, b)
            elif op == "LESS_THAN":
                out = (a < b).astype(np.float32)
            elif op == "GREATER_THAN":
                out = (a > b).astype(np.float32)
            elif op == "ABSOLUTE":
                out = np.abs(a)
            elif op == "ROUND":
                out = np.floor(a + 0.5)
            elif op == "FLOOR":
                out = np.floor(a)
            else:
                raise ValueError(f"unknown math operation {op!r}")
        return (np.clip(out, 0.0, 1.0) if self.clamp else out).astype(np.float32)


@dataclass
class Invert:
    """An Invert Color node: ``c + fac (1 - 2c)``."""

    fac: object
    color: object
    channels: int = 3

    def evaluate(self, p):
        t = as_channels(self.fac.evaluate(p), 1)
        c = as_channels(self.color.evaluate(p), 3)
        return (c + t * (1 - 2 * c)).astype(np.float32)


@dataclass
class Gamma:
    """A Gamma node: ``c^gamma`` where c > 0 (Cycles' ``svm_math_gamma_color``)."""

    color: object
    gamma: object
    channels: int = 3

    def evaluate(self, p):
        c = as_channels(self.color.evaluate(p), 3)
        g = as_channels(self.gamma.evaluate(p), 1)
        with np.errstate(all="ignore"):
            return np.where(c > 0, np.power(np.maximum(c, 0), g), c).astype(np.float32)


@dataclass
class BrightContrast:
    """A Brightness/Contrast node: ``max((1 + contrast) c + bright - contrast / 2, 0)``."""

    color: object
    bright: object
    contrast: object
    channels: int = 3

    def evaluate(self, p):
        c = as_channels(self.color.evaluate(p), 3)
        b = as_channels(self.bright.evaluate(p), 1)
        k = as_channels(self.contrast.evaluate(p), 1)
        return np.maximum((1 + k) * c + b - 0.5 * k, 0.0).astype(np.float32)


def _rgb_to_hsv(c):
    mx, mn = c.max(axis=1), c.min(axis=1)
    delta = mx - mn
    v = mx
    s = np.where(mx != 0, delta / np.where(mx != 0, mx, 1), 0)
    safe = np.where(delta != 0, delta, 1)
    r, g, b = c[:, 0], c[:, 1], c[:, 2]
    cr, cg, cb = (mx - r) / safe, (mx - g) / safe, (mx - b) / safe
    h = np.where(r == mx, cb - cg, np.where(g == mx, 2 + cr - cb, 4 + cg - cr)) / 6.0
    h = np.where(h < 0, h + 1, h)
    h = np.where(s != 0, h, 0)
    return h, s, v


def _hsv_to_rgb(h, s, v):
    h = np.where(h == 1.0, 0.0, h) * 6.0
    i = np.floor(h)
    f = h - i
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    i = i.astype(np.int64) % 6
    choices = [np.stack(x, axis=1) for x in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))]
    out = np.select([(i == j)[:, None] for j in range(6)], choices)
    return np.where((s == 0)[:, None], np.stack([v, v, v], axis=1), out)


@dataclass
class HueSaturation:
    """A Hue/Saturation/Value node (Cycles' ``svm_node_hsv``): hue shifted by ``hue - ½``,
    saturation and value scaled, mixed with the input by ``fac``, negative parts clipped."""

    hue: object
    saturation: object
    value: object
    fac: object
    color: object
    channels: int = 3

    def evaluate(self, p):
        c = as_channels(self.color.evaluate(p), 3).astype(np.float64)
        hue, sat, val, fac = (as_channels(x.evaluate(p), 1)[:, 0].astype(np.float64)
                              for x in (self.hue, self.saturation, self.value, self.fac))
        h, s, v = _rgb_to_hsv(c)
        h = np.mod(h + hue + 0.5, 1.0)
        s = np.clip(s * sat, 0.0, 1.0)
        v = v * val
        out = fac[:, None] * _hsv_to_rgb(h, s, v) + (1 - fac[:, None]) * c
        return np.maximum(out, 0.0).astype(np.float32)


@dataclass
class Curves:
    """An RGB Curves node as lookup tables: ``tables (3, N)`` the curve of each channel
    (combined curve applied) sampled at N equidistant inputs on [0, 1], linear in between and
    continued by the end slopes; mixed with the input by ``fac``."""

    tables: np.ndarray
    fac: object
    color: object
    channels: int = 3

    def evaluate(self, p):
        c = as_channels(self.color.evaluate(p), 3)
        t = as_channels(self.fac.evaluate(p), 1)
        tab = np.asarray(self.tables, dtype=np.float32)
        n = tab.shape[1]
        out = np.empty_like(c)
        for ch in range(3):                      # three channels, not rays
            x = c[:, ch] * (n - 1)
            i = np.clip(np.floor(x).astype(np.int64), 0, n - 2)
            f = x - i
            out[:, ch] = tab[ch, i] + f * (tab[ch, i + 1] - tab[ch, i])
        return (c + t * (out - c)).astype(np.float32)


@dataclass
class Separate:
    """One channel (0, 1, 2) of a colour (Separate Color, RGB mode)."""

    color: object
    channel: int
    channels: int = 1

    def evaluate(self, p):
        return as_channels(self.color.evaluate(p), 3)[:, self.channel:self.channel + 1]


@dataclass
class Combine:
    """A colour from three values (Combine Color, RGB mode)."""

    r: object
    g: object
    b: object
    channels: int = 3

    def evaluate(self, p):
        return np.concatenate([as_channels(x.evaluate(p), 1) for x in (self.r, self.g, self.b)], axis=1)


@dataclass
class Luminance:
    """The luminance of a colour as a value (RGB to BW)."""

    color: object
    channels: int = 1

    def evaluate(self, p):
        return as_channels(as_channels(self.color.evaluate(p), 3), 1)


@dataclass
class Divide:
    """A colour divided by a value, 0 where the value is 0 (the albedo given opacity)."""

    color: object
    by: object
    channels: int = 3

    def evaluate(self, p):
        c = as_channels(self.color.evaluate(p), 3)
        b = as_channels(self.by.evaluate(p), 1)
        return np.where(b > 0, c / np.where(b > 0, b, 1), 0).astype(np.float32)


# ---- building expressions, with constants folded (float64, as the constant reader did) ------

def constant(expr):
    """The (C,) float64 value of a constant expression, else None."""
    return expr.value if isinstance(expr, Const) else None


def product(a, b):
    """``a b`` elementwise (colour x colour, colour x value, value x value)."""
    ca, cb = constant(a), constant(b)
    if ca is not None and cb is not None:
        return Const(ca * cb)
    if (ca is not None and not np.any(ca)) or (cb is not None and not np.any(cb)):
        return Const(np.zeros(max(a.channels, b.channels)))
    if (ca is not None and np.all(ca == 1)) and b.channels >= a.channels:
        return b
    if (cb is not None and np.all(cb == 1)) and a.channels >= b.channels:
        return a
    if a.channels == 1 and b.channels == 1:
        return Math("MULTIPLY", a, b)
    return Mix("MULTIPLY", Const([1.0]), a, b)


def total(a, b):
    """``a + b``."""
    ca, cb = constant(a), constant(b)
    if ca is not None and cb is not None:
        return Const(ca + cb)
    if ca is not None and not np.any(ca) and b.channels >= a.channels:
        return b
    if cb is not None and not np.any(cb) and a.channels >= b.channels:
        return a
    if a.channels == 1 and b.channels == 1:
        return Math("ADD", a, b)
    return Mix("ADD", Const([1.0]), a, b)


def lerp(t, a, b):
    """``(1 - t) a + t b`` with ``t`` a value in [0, 1]."""
    ct, ca, cb = constant(t), constant(a), constant(b)
    if ca is not None and cb is not None and ca.shape == cb.shape and np.all(ca == cb):
        return a                              # the same on both sides, whatever t is
    if ct is not None and ca is not None and cb is not None:
        f = float(np.clip(ct[0], 0.0, 1.0))
        return Const((1 - f) * ca + f * cb)
    if a.channels == 1 and b.channels == 1:
        t = Math("MINIMUM", Math("MAXIMUM", t, Const([0.0])), Const([1.0]))
        return Math("ADD", Math("MULTIPLY", one_minus(t), a), Math("MULTIPLY", t, b))
    return Mix("MIX", t, a, b)


def one_minus(a):
    """``1 - a`` of a value."""
    ca = constant(a)
    if ca is not None:
        return Const(1.0 - ca[:1])
    return Math("SUBTRACT", Const([1.0]), a)


def quotient(color, by):
    """``color / by`` (a value), 0 where ``by`` is 0."""
    cc, cb = constant(color), constant(by)
    if cb is not None and cb[0] == 1:
        return color
    if cc is not None and cb is not None:
        return Const(cc / cb[0] if cb[0] > 0 else np.zeros_like(cc))
    return Divide(color, by)


def references(expr, found=None):
    """``{'uv': set, 'attribute': set}``: the UV maps and colour attributes ``expr`` reads."""
    found = found if found is not None else {"uv": set(), "attribute": set()}
    if isinstance(expr, ImageTexture):
        found["uv"].add(expr.uv)
    elif isinstance(expr, ColorAttribute):
        found["attribute"].add(expr.attribute)
    for value in getattr(expr, "__dict__", {}).values():
        if hasattr(value, "evaluate"):
            references(value, found)
    return found


@dataclass
class MaterialShading:
    """What a material shows at a point: the diffuse ``albedo`` (an expression of 3 channels:
    the diffuse reflectance where the surface is opaque) and the ``alpha`` (1 channel: the
    probability that a ray stops at the surface, 1 - the transparent closures' weight), or
    None: constant (then the triangle's ``triangle_albedo`` / opaque); ``emission`` (3
    channels, radiance) of a textured emitter, which the scene averages per triangle; ``tint``
    (3 channels): the colour a ray that passes the surface carries (the transparent weight
    divided by its largest channel), None: white."""

    albedo: object = None
    alpha: object = None
    emission: object = None
    tint: object = None


@dataclass
class SurfaceTextures:
    """The textured materials of a scene and the data they read.

    images            list of :class:`ImageTable`
    uv_maps           list of (T, 3, 2) float32 corner UVs per UV map (0 where a triangle's
                      mesh lacks the map)
    attributes        list of (T, 3, 4) float32 linear RGBA corner colours per colour attribute
    materials         list of :class:`MaterialShading`
    triangle_material (T,) int32 index into ``materials`` (-1: constant albedo, opaque)
    transparent_max_bounces  transparent surfaces a ray may pass (Cycles' setting of the name)
    """

    images: list = field(default_factory=list)
    uv_maps: list = field(default_factory=list)
    attributes: list = field(default_factory=list)
    materials: list = field(default_factory=list)
    triangle_material: np.ndarray = None
    transparent_max_bounces: int = 8

    def __post_init__(self):
        if self.triangle_material is not None:
            self.triangle_material = np.asarray(self.triangle_material, dtype=np.int32)
        self._flags = {which: np.array([getattr(m, which) is not None for m in self.materials] + [False],
                                       dtype=bool)                   # index -1: constant
                       for which in ("albedo", "alpha", "emission", "tint")}
        self._textured, self._transparent = self._flags["albedo"], self._flags["alpha"]

    def fingerprint(self):
        """bytes: digest of everything that changes what the surfaces show."""
        h = hashlib.blake2b(digest_size=16)
        for table in self.images:
            h.update(table.digest())
        for array in list(self.uv_maps) + list(self.attributes) + [self.triangle_material]:
            h.update(np.ascontiguousarray(array).tobytes())
        h.update(repr(self.materials).encode() + repr(self.transparent_max_bounces).encode())
        return h.digest()

    @property
    def has_albedo(self):
        return bool(self._textured[:-1].any())

    @property
    def has_tint(self):
        return bool(self._flags["tint"][:-1].any())

    def tint(self, tri, bu, bv):
        """(k, 3) float32 colour carried by rays that pass the surfaces at the points (1: white)."""
        out = np.ones((len(tri), 3), np.float32)
        return np.maximum(self._evaluate("tint", tri, bu, bv, out), 0.0)

    @property
    def has_alpha(self):
        return bool(self._transparent[:-1].any())

    def transparent_triangles(self):
        """(T,) bool: triangles whose material has a (non-constant-1) alpha."""
        return self._transparent[self.triangle_material]

    def _evaluate(self, which, tri, bu, bv, out):
        tri = np.asarray(tri, dtype=np.int64)
        mats = self.triangle_material[tri]
        flags = self._flags[which]
        wanted = np.flatnonzero(flags[mats])
        if len(wanted) == 0:
            return out
        bu = np.asarray(bu, dtype=np.float32)
        bv = np.asarray(bv, dtype=np.float32)
        sub = mats[wanted]
        order = np.argsort(sub, kind="stable")
        starts = np.flatnonzero(np.diff(sub[order])) + 1
        for group in np.split(order, starts):           # one pass per material, not per ray
            m = sub[group[0]]
            rows = wanted[group]
            expr = getattr(self.materials[m], which)
            points = _Points(self, tri[rows], bu[rows], bv[rows])
            out[rows] = as_channels(expr.evaluate(points), out.shape[1])
        return out

    def albedo(self, tri, bu, bv, base):
        """(k, 3) float32 diffuse albedo at barycentrics ``(bu, bv)`` (weights of corners 1
        and 2) of triangles ``tri``: ``base (T, 3)`` (the constant albedo) where the material
        is untextured, the material's expression elsewhere; clipped to [0, 1]."""
        out = np.take(base, tri, axis=0).astype(np.float32)
        return np.clip(self._evaluate("albedo", tri, bu, bv, out), 0.0, 1.0)

    def alpha(self, tri, bu, bv):
        """(k,) float32 alpha in [0, 1] at the points (1 on opaque materials)."""
        out = np.ones((len(tri), 1), np.float32)
        return np.clip(self._evaluate("alpha", tri, bu, bv, out)[:, 0], 0.0, 1.0)

    def triangle_means(self, which, triangles, base=None):
        """(n, C) mean of the albedo (``which='albedo'``, C = 3, ``base (T, 3)``), the
        emission (C = 3, 0 where constant) or the alpha (C = 1) over each of ``triangles``,
        from 16 stratified points per triangle."""
        triangles = np.asarray(triangles, dtype=np.int64)
        tri = np.repeat(triangles, 16)
        bu, bv = np.tile(_MEAN_BU, len(triangles)), np.tile(_MEAN_BV, len(triangles))
        if which == "albedo":
            v = self.albedo(tri, bu, bv, base)
        elif which == "emission":
            v = np.maximum(self._evaluate("emission", tri, bu, bv, np.zeros((len(tri), 3), np.float32)), 0.0)
        else:
            v = self.alpha(tri, bu, bv)[:, None]
        return v.reshape(len(triangles), 16, -1).mean(axis=1)
