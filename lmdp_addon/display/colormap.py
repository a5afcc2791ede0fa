"""Perceptual colour maps and the colour scales of the displayed quantities (no bpy).

The desirability z spans many orders of magnitude (it falls by ``e^-λ`` per bounce in THESIS
mode, by the albedo per bounce in PHYSICAL mode), so it is shown on a logarithmic scale; the
cost-to-go ``J = -(log z)/λ`` is already logarithmic and is shown on a linear one.

Colour maps are matplotlib's *viridis* and *inferno* (van der Walt & Smith, BSD/CC0), tabulated
at 33 evenly spaced stops of the 256-entry maps and interpolated linearly (largest deviation from
the 256-entry map 0.007 in sRGB units). The tables are sRGB-encoded display values;
:func:`colormap_linear` returns scene-linear RGB, which is what Blender stores in FLOAT_COLOR
attributes and what an Emission shader emits: with the *Standard* view transform the screen then
shows exactly the perceptual map (with AgX / Filmic it is tone-mapped and no longer perceptual).

Arrays: ``t (n,)`` positions in [0, 1] on the map; colours ``(n, 3)`` or ``(n, 4)`` float32.
"""
from dataclasses import dataclass

import numpy as np

VIRIDIS_SRGB = np.array((
    (0.2670, 0.0049, 0.3294), (0.2770, 0.0502, 0.3755), (0.2823, 0.0946, 0.4170),
    (0.2829, 0.1354, 0.4530), (0.2789, 0.1749, 0.4830), (0.2708, 0.2133, 0.5066),
    (0.2593, 0.2507, 0.5244), (0.2454, 0.2867, 0.5370), (0.2302, 0.3213, 0.5455),
    (0.2148, 0.3545, 0.5510), (0.2000, 0.3864, 0.5545), (0.1861, 0.4173, 0.5567),
    (0.1733, 0.4474, 0.5579), (0.1613, 0.4770, 0.5581), (0.1497, 0.5064, 0.5573),
    (0.1384, 0.5358, 0.5551), (0.1281, 0.5651, 0.5509), (0.1209, 0.5945, 0.5442),
    (0.1203, 0.6238, 0.5343), (0.1310, 0.6529, 0.5208), (0.1554, 0.6815, 0.5032),
    (0.1930, 0.7096, 0.4812), (0.2415, 0.7366, 0.4545), (0.2986, 0.7624, 0.4230),
    (0.3629, 0.7867, 0.3866), (0.4330, 0.8091, 0.3453), (0.5081, 0.8292, 0.2992),
    (0.5873, 0.8470, 0.2489), (0.6694, 0.8622, 0.1954), (0.7529, 0.8751, 0.1427),
    (0.8359, 0.8861, 0.1025), (0.9166, 0.8961, 0.1008), (0.9932, 0.9062, 0.1439),
))
INFERNO_SRGB = np.array((
    (0.0015, 0.0005, 0.0139), (0.0139, 0.0112, 0.0716), (0.0420, 0.0280, 0.1406),
    (0.0815, 0.0432, 0.2144), (0.1285, 0.0473, 0.2896), (0.1823, 0.0405, 0.3539),
    (0.2370, 0.0366, 0.3956), (0.2894, 0.0453, 0.4182), (0.3399, 0.0618, 0.4292),
    (0.3897, 0.0803, 0.4331), (0.4393, 0.0986, 0.4317), (0.4889, 0.1164, 0.4259),
    (0.5386, 0.1339, 0.4157), (0.5882, 0.1516, 0.4011), (0.6375, 0.1704, 0.3822),
    (0.6858, 0.1910, 0.3591), (0.7328, 0.2143, 0.3321), (0.7776, 0.2414, 0.3016),
    (0.8195, 0.2728, 0.2685), (0.8578, 0.3090, 0.2333), (0.8918, 0.3500, 0.1965),
    (0.9210, 0.3954, 0.1584), (0.9451, 0.4448, 0.1188), (0.9640, 0.4974, 0.0776),
    (0.9774, 0.5526, 0.0380), (0.9855, 0.6100, 0.0245), (0.9879, 0.6692, 0.0596),
    (0.9847, 0.7296, 0.1222), (0.9759, 0.7909, 0.1973), (0.9623, 0.8522, 0.2867),
    (0.9486, 0.9109, 0.3962), (0.9518, 0.9608, 0.5247), (0.9884, 0.9984, 0.6449),
))

#: Colour maps by the identifiers the Blender layer uses.
COLOR_MAPS = {"VIRIDIS": VIRIDIS_SRGB, "INFERNO": INFERNO_SRGB}
#: Display colour (sRGB) of states / vertices without a value (z = 0 where log scale is used,
#: no state on the object): a neutral dark grey that is not on either map.
MISSING_SRGB = np.array((0.18, 0.18, 0.18))


def srgb_to_linear(c):
    """sRGB-encoded values (display) to scene-linear (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    """Scene-linear values to sRGB encoding (what the Standard view transform displays)."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, None)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def _table(name):
    try:
        return COLOR_MAPS[str(name).upper()]
    except KeyError:
        raise ValueError(f"unknown colour map {name!r}: use one of {', '.join(COLOR_MAPS)}") from None


def colormap_srgb(t, name="VIRIDIS"):
    """(n, 3) sRGB display colours of positions ``t`` (clipped to [0, 1]); NaN -> missing grey."""
    table = _table(name)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    stops = np.linspace(0.0, 1.0, len(table))
    tc = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    rgb = np.stack([np.interp(tc, stops, table[:, c]) for c in range(3)], axis=1)
    rgb[~np.isfinite(t)] = MISSING_SRGB
    return rgb


def colormap_linear(t, name="VIRIDIS", alpha=True):
    """Scene-linear colours of ``t``: (n, 4) float32 RGBA (alpha 1) for FLOAT_COLOR attributes and
    Emission shaders, or (n, 3) with ``alpha=False``. See the module docstring."""
    rgb = srgb_to_linear(colormap_srgb(t, name))
    if alpha:
        rgb = np.concatenate([rgb, np.ones((len(rgb), 1))], axis=1)
    return rgb.astype(np.float32)


@dataclass
class ColorScale:
    """Maps values of a quantity to [0, 1] on a colour map.

    lo, hi      range shown, in the scale's domain: log10 of the quantity for log scales (so a
                desirability of 1e-400, which float64 cannot hold, still has a place), the
                quantity itself for linear scales. Values outside are clipped to the map's ends.
    log         True: position = (log10 v - lo) / (hi - lo); False: (v - lo) / (hi - lo)
    label       what is shown, for legends ("z: radiance (luminance, W/sr/m²)")
    data_lo, data_hi  the smallest / largest finite data value (same domain as lo, hi); for an
                empty scale the one non-finite value every datum has (-inf: z = 0), else NaN
    empty       no datum has a place on the scale (every z is 0, every J +inf): every position
                is NaN (the missing colour), the legend shows ``note`` instead of a range
    note        why the scale is empty, for the user ("z is 0 on every state: ...")
    """

    lo: float
    hi: float
    log: bool
    label: str = ""
    data_lo: float = float("nan")
    data_hi: float = float("nan")
    empty: bool = False
    note: str = ""

    @property
    def vmin(self):
        """Lower end in the quantity's units (0.0 if it underflows float64)."""
        return float(10.0 ** self.lo) if self.log else float(self.lo)

    @property
    def vmax(self):
        return float(10.0 ** self.hi) if self.log else float(self.hi)

    @property
    def decades(self):
        """Orders of magnitude the range spans (log scales), else 0 (also for an empty scale)."""
        return float(self.hi - self.lo) if self.log and not self.empty else 0.0

    def _t(self, x):
        if self.empty:
            return np.full(np.shape(x), np.nan)
        span = self.hi - self.lo
        with np.errstate(invalid="ignore"):
            t = (x - self.lo) / span if span > 0 else np.where(np.isfinite(x), 0.5, np.nan)
        return np.where(np.isfinite(x), np.clip(t, 0.0, 1.0), np.nan)

    def position(self, values):
        """(n,) positions in [0, 1]; NaN where a value has no place on the scale (non-finite, or
        <= 0 on a log scale)."""
        v = np.asarray(values, dtype=np.float64)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where((v > 0) & np.isfinite(v), np.log10(np.where(v > 0, v, 1.0)), np.nan)
        return self._t(v)

    def position_of_log10(self, log10_values):
        """Like :meth:`position` for values given as log10 (exact where the value underflows)."""
        if not self.log:
            raise ValueError("position_of_log10 needs a log scale")
        return self._t(np.asarray(log10_values, dtype=np.float64))

    def ticks(self, count=5):
        """``count`` evenly spaced points of the scale's domain (log10 values for log scales);
        an empty scale's ticks are all its one data value (``data_lo``)."""
        if self.empty:
            return np.full(count, self.data_lo)
        return self.lo + np.linspace(0.0, 1.0, count) * (self.hi - self.lo)

    def tick_labels(self, count=5):
        return [format_log10(x) if self.log else format_value(x) for x in self.ticks(count)]

    def describe(self):
        """One line for the panel: ``label: min .. max (log, 3.2 decades)``; the note of an
        empty scale."""
        if self.empty:
            return self.note or f"{self.label}: no value to show"
        fmt = format_log10 if self.log else format_value
        kind = f"log, {self.decades:.1f} decades" if self.log else "linear"
        return f"{self.label}: {fmt(self.lo)} .. {fmt(self.hi)} ({kind})"

    def as_dict(self):
        return {"lo": self.lo, "hi": self.hi, "log": self.log, "label": self.label,
                "data_lo": self.data_lo, "data_hi": self.data_hi, "empty": self.empty, "note": self.note}


def format_value(v):
    """Compact text of a legend value: 3 significant digits, scientific when far from 1."""
    v = float(v)
    if not np.isfinite(v):
        return str(v)
    if v != 0 and (abs(v) < 1e-2 or abs(v) >= 1e4):
        return f"{v:.2e}"
    return f"{v:.3g}"


def format_log10(x):
    """Text of the value ``10**x`` for any x (also where 10**x over/underflows float64)."""
    x = float(x)
    if not np.isfinite(x):
        return "0" if x < 0 else "inf"
    if -2.0 <= x < 4.0:
        return format_value(10.0 ** x)
    e = int(np.floor(x))
    m = 10.0 ** (x - e)
    if m >= 9.995:
        m, e = 1.0, e + 1
    return f"{m:.2f}e{e:+03d}"


def _empty_scale(values, log, label, note):
    """The :class:`ColorScale` of data without a finite value (see ``ColorScale.empty``)."""
    v = values[~np.isnan(values)]
    data = float(v[0]) if v.size and np.all(v == v[0]) else float("nan")
    return ColorScale(0.0, 1.0, log, label, data, data, empty=True, note=note)


def log_scale_from_log10(log10_values, label="", low_percentile=1.0, high_percentile=99.0,
                         max_decades=None, empty_note=""):
    """Log :class:`ColorScale` for data given as log10 values (-inf for zeros).

    The range runs from the ``low_percentile`` to the ``high_percentile`` percentile of the
    finite values: a handful of extreme states (a halo right next to a light, a corner under a
    box) is clipped to the ends of the map instead of squeezing everything else into a few
    colours; ``data_lo`` / ``data_hi`` keep the full extent for the legend. With
    ``max_decades`` the range spans at most that many decades below its top. (In THESIS mode z
    falls by e^-λ per bounce, so its range can span hundreds of decades: no cap by default.)
    A constant field gets a range of half a decade around it; data without a finite value (z =
    0 everywhere) an empty scale whose legend is ``empty_note``.
    """
    x = np.asarray(log10_values, dtype=np.float64).reshape(-1)
    if not np.any(np.isfinite(x)):
        return _empty_scale(x, True, label, empty_note)
    x = x[np.isfinite(x)]
    lo, hi = (float(v) for v in np.percentile(x, [low_percentile, high_percentile]))
    if max_decades is not None:
        lo = max(lo, hi - float(max_decades))
    if hi - lo < 1e-9:
        lo, hi = hi - 0.25, hi + 0.25
    return ColorScale(lo, hi, True, label, float(x.min()), float(x.max()))


def linear_scale(values, label="", low_percentile=0.0, high_percentile=100.0, empty_note=""):
    """Linear :class:`ColorScale` from the ``low_percentile`` to the ``high_percentile``
    percentile of the finite values (a constant field gets ±0.5 around it; data without a
    finite value an empty scale whose legend is ``empty_note``)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if not np.any(np.isfinite(v)):
        return _empty_scale(v, False, label, empty_note)
    v = v[np.isfinite(v)]
    lo, hi = (float(x) for x in np.percentile(v, [low_percentile, high_percentile]))
    data = (float(v.min()), float(v.max()))
    if hi - lo <= 1e-12 * max(abs(hi), 1.0):
        lo, hi = lo - 0.5, hi + 0.5
    return ColorScale(lo, hi, False, label, *data)


def colorbar_rgba(width, height, name="VIRIDIS", vertical=False):
    """(height, width, 4) float32 scene-linear RGBA image of the map, low values left (or bottom),
    row 0 at the bottom like Blender images: for legends."""
    n = height if vertical else width
    t = (np.arange(n) + 0.5) / n
    rgba = colormap_linear(t, name)
    if vertical:
        return np.repeat(rgba[:, None, :], width, axis=1)
    return np.repeat(rgba[None, :, :], height, axis=0)
