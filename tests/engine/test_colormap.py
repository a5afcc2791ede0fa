"""Colour maps and scales of the displayed quantities (lmdp_addon.display.colormap)."""
import numpy as np
import pytest

from lmdp_addon.display import colormap as C


@pytest.mark.parametrize("name", ["viridis", "inferno"])
def test_tables_match_matplotlib(name):
    """Our 33-stop tables reproduce matplotlib's 256-entry maps to 0.007 (sRGB units)."""
    matplotlib = pytest.importorskip("matplotlib")
    reference = np.asarray(matplotlib.colormaps[name].colors)
    t = np.linspace(0.0, 1.0, 4001)
    expected = np.stack([np.interp(t * 255, np.arange(256), reference[:, c]) for c in range(3)], axis=1)
    assert np.abs(C.colormap_srgb(t, name.upper()) - expected).max() < 0.007


@pytest.mark.parametrize("name", ["VIRIDIS", "INFERNO"])
def test_maps_are_perceptually_ordered(name):
    """Lightness (CIE L* of the sRGB colour) increases monotonically along both maps."""
    lin = C.srgb_to_linear(C.colormap_srgb(np.linspace(0, 1, 200), name))
    Y = lin @ np.array([0.2126, 0.7152, 0.0722])
    L = np.where(Y > 216 / 24389, 116 * np.cbrt(Y) - 16, Y * 24389 / 27)
    assert np.all(np.diff(L) > 0)


def test_linear_colours_display_as_the_map_under_the_standard_transform():
    t = np.linspace(0, 1, 50)
    rgba = C.colormap_linear(t, "VIRIDIS")
    assert rgba.shape == (50, 4) and rgba.dtype == np.float32 and np.all(rgba[:, 3] == 1)
    assert np.allclose(C.linear_to_srgb(rgba[:, :3]), C.colormap_srgb(t), atol=1e-5)


def test_missing_values_are_grey_and_positions_are_clipped():
    rgb = C.colormap_srgb(np.array([np.nan, -1.0, 2.0]))
    assert np.allclose(rgb[0], C.MISSING_SRGB)
    assert np.allclose(rgb[1], C.VIRIDIS_SRGB[0]) and np.allclose(rgb[2], C.VIRIDIS_SRGB[-1])
    with pytest.raises(ValueError, match="unknown colour map"):
        C.colormap_srgb([0.5], "JET")


def test_log_scale_positions():
    scale = C.ColorScale(-3.0, 1.0, True, "z")
    t = scale.position([1e-3, 1e-2, 10.0, 1e3, 1e-9, 0.0, np.inf])
    assert np.allclose(t[:5], [0.0, 0.25, 1.0, 1.0, 0.0])
    assert np.isnan(t[5]) and np.isnan(t[6])  # zero and inf have no place on a log scale
    assert scale.decades == pytest.approx(4.0)
    assert (scale.vmin, scale.vmax) == pytest.approx((1e-3, 10.0))
    assert np.allclose(scale.position_of_log10([-3.0, -1.0, -np.inf]), [0.0, 0.5, np.nan], equal_nan=True)
    assert np.allclose(scale.ticks(5), [-3, -2, -1, 0, 1])
    assert scale.tick_labels(3) == ["1.00e-03", "0.1", "10"]
    assert "4.0 decades" in scale.describe() and "1.00e-03" in scale.describe()


def test_log_scales_hold_values_beyond_float_range():
    scale = C.ColorScale(-420.0, -400.0, True, "z")
    assert scale.vmax == 0.0                      # 1e-400 underflows ...
    assert np.allclose(scale.position_of_log10([-410.0]), 0.5)   # ... its log does not
    assert C.format_log10(-400.3) == "5.01e-401" and C.format_log10(500.0) == "1.00e+500"
    assert C.format_log10(-np.inf) == "0" and C.format_log10(0.5) == "3.16"
    assert "5.01e-401" in C.ColorScale(-410.0, -400.3, True, "z").describe()


def test_log_scale_from_data_clips_the_extremes_and_remembers_them():
    rng = np.random.default_rng(0)
    x = rng.uniform(-6.0, 1.0, 1000)
    x[:3] = -np.inf                      # z = 0 states
    x[3] = -300.0                        # one state that is nearly unreachable
    x[4] = 5.0                           # one state in the halo of a light
    scale = C.log_scale_from_log10(x, "z")
    finite = x[np.isfinite(x)]
    assert scale.hi == pytest.approx(np.percentile(finite, 99)) and 0.8 < scale.hi < 1.0
    assert -6.0 < scale.lo < -5.8        # the 1st percentile, not the outlier
    assert (scale.data_lo, scale.data_hi) == (-300.0, 5.0)
    assert np.allclose(scale.position_of_log10([5.0, -300.0]), [1.0, 0.0])
    wide = C.log_scale_from_log10(np.array([-300.0, 0.0]), low_percentile=0.0, high_percentile=100.0)
    assert wide.decades == pytest.approx(300.0)   # THESIS-mode z spans hundreds of decades
    capped = C.log_scale_from_log10(np.array([-300.0, 0.0]), "", 0.0, 100.0, max_decades=12)
    assert capped.decades == pytest.approx(12.0)
    flat = C.log_scale_from_log10(np.full(10, 2.0))
    assert flat.vmin < 100.0 < flat.vmax and np.allclose(flat.position([100.0]), 0.5)


def test_linear_scale():
    s = C.linear_scale(np.array([1.0, 3.0, np.inf, np.nan]), "J")
    assert (s.lo, s.hi, s.log) == (1.0, 3.0, False)
    robust = C.linear_scale(np.r_[np.linspace(0, 1, 101), 50.0], "J", 0.0, 99.0)
    assert robust.hi < 1.5 and robust.data_hi == 50.0
    assert np.allclose(s.position([1.0, 2.0, 3.0, 5.0]), [0.0, 0.5, 1.0, 1.0])
    flat = C.linear_scale(np.array([2.0, 2.0]))
    assert np.allclose(flat.position([2.0]), 0.5)
    assert s.tick_labels(3) == ["1", "2", "3"]


def test_colorbar_image():
    img = C.colorbar_rgba(64, 4, "INFERNO")
    assert img.shape == (4, 64, 4)
    assert np.allclose(img[0], img[3])
    srgb = C.linear_to_srgb(img[0, :, :3])
    assert np.allclose(srgb[0], C.colormap_srgb([0.5 / 64], "INFERNO")[0], atol=1e-5)
    assert C.colorbar_rgba(4, 32, vertical=True).shape == (32, 4, 4)
