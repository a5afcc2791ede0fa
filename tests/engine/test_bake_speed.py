"""The bake's cheaper per-bounce helpers compute exactly what they replace (docs/design.md, "Where
the bake's time goes"): a bake's result for a seed does not depend on them.

* ``sampling.table_index`` is numpy's ``searchsorted(side='right')`` clipped to the table,
  counted for small tables (ties, zero-probability entries, u = 0 included);
* ``sampling.stratified_first_uniforms`` is ``np.mod(·, 1)`` of the shifted points, bit for bit;
* ``sampling.set_rows`` is ``a[idx] = v`` and the tracer's ``_add_rows`` is ``L[idx] += v``, and ``_select_rows`` gathers an array passed
  twice once and hands back the arrays themselves when every path lives;
* the tracer gives the same values for float64 start points and their float32 rounding (the
  driver now writes the work unit's start points straight into float32);
* ``spherical_triangle_sample`` on a fixed set of triangles (degenerate ones included) against
  values computed by the straightforward formula (Arvo 1995) in float64.
"""
import numpy as np
import pytest

from lmdp_addon import demo_geometry as scenes
from lmdp_addon.bake.tracer import IndirectTracer, _add_rows, _select_rows
from lmdp_addon.sampling import (COUNTED_TABLE, GOLDEN, radical_inverse2, set_rows, spherical_triangle_sample,
                                 stratified_first_uniforms, table_index)


@pytest.mark.parametrize("n", [1, 2, 3, COUNTED_TABLE, COUNTED_TABLE + 1, 40])
def test_table_index_is_the_clipped_searchsorted(n):
    rng = np.random.default_rng(n)
    weight = rng.random(n)
    weight[rng.random(n) < 0.3] = 0.0           # zero-probability entries: repeated CDF values
    weight[-1] += 0.1
    cdf = np.cumsum(weight)
    cdf32 = (cdf / cdf[-1]).astype(np.float32)
    u = np.concatenate([rng.random(5000, dtype=np.float32), cdf32, np.zeros(3, np.float32),
                        np.nextafter(cdf32, np.float32(0))])
    expected = np.minimum(np.searchsorted(cdf32, u, side="right"), n - 1)
    got = table_index(cdf32, u)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)
    strided = np.stack([u, u, u], axis=1)[:, 0]   # the emitter choice reads a column of (k, 3)
    np.testing.assert_array_equal(table_index(cdf32, strided), expected)


def test_stratified_first_uniforms_are_the_fractional_parts_bit_for_bit():
    texels, n = 257, 12
    u, u_mix = stratified_first_uniforms(texels, n, np.random.default_rng(4))
    shift = np.random.default_rng(4).random((texels, 3))
    j = np.arange(n)
    base = np.stack([(j + 0.5) / n, radical_inverse2(j)], axis=1)
    np.testing.assert_array_equal(u, np.mod(base[None, :, :] + shift[:, None, :2], 1.0))
    np.testing.assert_array_equal(u_mix, np.mod(j[None, :] * GOLDEN + shift[:, 2:3], 1.0))
    assert u.min() >= 0.0 and u.max() < 1.0 and u_mix.min() >= 0.0 and u_mix.max() < 1.0


def test_add_rows_is_fancy_index_addition():
    rng = np.random.default_rng(0)
    L = rng.random((1000, 3), dtype=np.float32)
    idx = np.sort(rng.choice(1000, 600, replace=False))
    for values in (rng.random((600, 3), dtype=np.float32), rng.random((600, 3))):   # float32 and float64
        expected = L.copy()
        expected[idx] += values
        got = L.copy()
        _add_rows(got, idx, values)
        np.testing.assert_array_equal(got, expected)


def test_set_rows_is_fancy_index_assignment():
    rng = np.random.default_rng(5)
    for dtype, width in ((np.float32, 3), (np.float64, 3), (np.float32, 2)):
        a = rng.random((500, width)).astype(dtype)
        idx = np.sort(rng.choice(500, 200, replace=False))
        for values in (rng.random((200, width)).astype(np.float32), rng.random((200, width))):
            expected = a.copy()
            expected[idx] = values
            got = a.copy()
            set_rows(got, idx, values)
            np.testing.assert_array_equal(got, expected)


def test_select_rows_gathers_shared_arrays_once_and_keeps_full_selections():
    rng = np.random.default_rng(1)
    a, b = rng.random((50, 3), dtype=np.float32), rng.random(50)
    index = np.flatnonzero(rng.random(50) < 0.5)
    ta, tb, tc, none = _select_rows(index, a, b, a, None)
    assert tc is ta and none is None
    np.testing.assert_array_equal(ta, a[index])
    np.testing.assert_array_equal(tb, b[index])
    every = _select_rows(np.arange(50), a, b)
    assert every[0] is a and every[1] is b


def test_float32_start_points_trace_like_their_float64_originals():
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    tracer = IndirectTracer(scene, "UNGUIDED", max_bounces=4)
    floor = scene.object_names.index("Floor")
    tris = np.flatnonzero(scene.triangle_object == floor)
    rng = np.random.default_rng(2)
    n = 4000
    t = rng.choice(tris, n)
    c = scene.corners()[t]
    b = rng.random((n, 2))
    b = np.where(b.sum(axis=1, keepdims=True) > 1, 1 - b, b)
    points = c[:, 0] + b[:, :1] * (c[:, 1] - c[:, 0]) + b[:, 1:] * (c[:, 2] - c[:, 0])
    normals = np.tile(scene.triangle_geometry()[0][t[0]], (n, 1))
    u, u_mix = rng.random((n, 2)), rng.random(n)
    runs = [tracer.trace(p, m, np.full(n, -1), u, u_mix, np.random.default_rng(9), triangles=t)[0]
            for p, m in ((points, normals), (points.astype(np.float32), normals.astype(np.float32)))]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert runs[0].mean() > 0


def _arvo_reference(corners, u1, u2):
    """Arvo (1995) written out directly in float64, one formula per line."""
    A, B, C = (c / np.linalg.norm(c, axis=1, keepdims=True) for c in np.moveaxis(corners, 1, 0))
    n_ab = np.cross(A, B)
    n_ab /= np.linalg.norm(n_ab, axis=1, keepdims=True)
    n_ac = np.cross(A, C)
    n_ac /= np.linalg.norm(n_ac, axis=1, keepdims=True)
    cos_a = np.clip(np.sum(n_ab * n_ac, axis=1), -1, 1)
    alpha = np.arccos(cos_a)
    omega = 2 * np.arctan2(np.abs(np.sum(A * np.cross(B, C), axis=1)),
                           1 + np.sum(A * B, axis=1) + np.sum(B * C, axis=1) + np.sum(C * A, axis=1))
    s, t = np.sin(u1 * omega - alpha), np.cos(u1 * omega - alpha)
    u, v = t - cos_a, s + np.sqrt(1 - cos_a ** 2) * np.sum(A * B, axis=1)
    q = ((v * t - u * s) * cos_a - v) / ((v * s + u * t) * np.sqrt(1 - cos_a ** 2))
    perp = C - np.sum(C * A, axis=1, keepdims=True) * A
    c_hat = q[:, None] * A + np.sqrt(1 - q[:, None] ** 2) * perp / np.linalg.norm(perp, axis=1, keepdims=True)
    z = 1 - u2 * (1 - np.sum(c_hat * B, axis=1))
    perp = c_hat - np.sum(c_hat * B, axis=1, keepdims=True) * B
    return z[:, None] * B + np.sqrt(1 - z[:, None] ** 2) * perp / np.linalg.norm(perp, axis=1, keepdims=True), omega


def test_spherical_triangle_sample_is_arvos_construction():
    rng = np.random.default_rng(3)
    k = 2000
    corners = rng.normal(size=(k, 3, 3)) + np.array([0.0, 0.0, 3.0])    # in front of the viewpoint
    u1, u2 = rng.random(k).astype(np.float32), rng.random(k).astype(np.float32)
    d, omega = spherical_triangle_sample(corners, u1, u2)
    d_ref, omega_ref = _arvo_reference(corners, u1.astype(np.float64), u2.astype(np.float64))
    np.testing.assert_allclose(omega, omega_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(d, d_ref, atol=1e-6)
    degenerate = corners.copy()
    degenerate[:, 2] = degenerate[:, 1]                  # zero solid angle: towards B, Ω = 0
    with np.errstate(all="ignore"):
        d0, omega0 = spherical_triangle_sample(degenerate, u1, u2)
    assert np.all(omega0 == 0)
    B = degenerate[:, 1] / np.linalg.norm(degenerate[:, 1], axis=1, keepdims=True)
    np.testing.assert_allclose(d0, B, atol=1e-12)
