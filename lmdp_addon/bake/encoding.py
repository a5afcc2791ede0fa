"""8-bit encodings of HDR lightmaps for engines that cannot read float images.

RGBM (linear, no gamma): a value ``v = (r, g, b) >= 0`` is stored as four bytes
``(R, G, B, M)`` with ``v ≈ (R, G, B) / 255 · M / 255 · RGBM_RANGE``. ``M`` is the smallest
multiple of 1/255 with ``max(v) ≤ M · RANGE`` (at least 1/255), so values up to ``RGBM_RANGE``
are kept; brighter ones are clipped to it. Decoders: three.js ``RGBMLoader`` with
``setMaxRange(RGBM_RANGE)`` (the default 7), or ``rgb * a * 7`` on the raw (non-sRGB) bytes.
The round-trip error of a channel is at most half a step of its byte, ``M·RANGE / 510``, which
is at most ``(max(v) + RANGE/255) / 510``: 0.2 % of the texel's brightest channel plus 5.4e-5.
"""
import numpy as np

#: Largest value an RGBM texel holds (linear radiance units of the lightmap).
RGBM_RANGE = 7.0


def rgbm_encode(rgb):
    """(..., 3) float linear values -> (..., 4) uint8 RGBM."""
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, RGBM_RANGE)
    peak = rgb.max(axis=-1)
    m = np.clip(np.ceil(peak / RGBM_RANGE * 255.0), 1, 255)
    scale = (m / 255.0 * RGBM_RANGE)[..., None]
    out = np.empty(rgb.shape[:-1] + (4,), np.uint8)
    out[..., :3] = np.clip(np.rint(rgb / scale * 255.0), 0, 255)
    out[..., 3] = m
    return out


def rgbm_decode(rgbm):
    """(..., 4) uint8 RGBM -> (..., 3) float32 linear values."""
    rgbm = np.asarray(rgbm, dtype=np.float64)
    return (rgbm[..., :3] / 255.0 * (rgbm[..., 3:] / 255.0) * RGBM_RANGE).astype(np.float32)
