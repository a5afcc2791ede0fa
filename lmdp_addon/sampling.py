"""Shared low-discrepancy sequences and warps of the unit square, float32 for the bake's hot loop.

* sequences: :data:`GOLDEN` (Kronecker), :func:`radical_inverse2` (van der Corput), and the
  texel's first-direction uniforms :func:`stratified_first_uniforms` (shifted Hammersley);
  :func:`table_index`, the entry of a small CDF table a uniform selects;
* warps: :func:`concentric32` (Shirley–Chiu square to disk), :func:`cosine_directions`
  (cosine-weighted hemisphere), :func:`spherical_triangle_sample` (uniform in the solid angle
  of a triangle, Arvo 1995) and :func:`spherical_triangle_solid_angle`;
* frames: :func:`local_to_world` (Duff et al.'s branchless frame of a normal),
  :func:`rotate_out` / :func:`rotate_in` (given frames, rows t, b, n);
* row helpers of the wavefront loops: :func:`rows`, :func:`set_rows`, :func:`dot`, and the per-component
  :func:`unit3`, :func:`cross3`, :func:`dot3`.

The strata of the states' hemispheres are ``model/hemisphere.py``'s (float64). Contiguous (k,)
component arrays are used where the float32 loops are hot: numpy is several times faster on them
than on the strided columns of (k, 3) arrays.
"""
import numpy as np

#: 1/φ: the Kronecker sequence frac(i/φ) fills [0, 1) evenly.
GOLDEN = 0.6180339887498949
QUARTER_PI = np.pi / 4.0


# ---- sequences ---------------------------------------------------------------------------------

def radical_inverse2(j):
    """Van der Corput radical inverse in base 2 of non-negative integers ``j``."""
    j = np.asarray(j, dtype=np.uint64)
    out = np.zeros(j.shape, dtype=np.float64)
    scale = 0.5
    while np.any(j):
        out += (j & np.uint64(1)).astype(np.float64) * scale
        j = j >> np.uint64(1)
        scale *= 0.5
    return out


def stratified_first_uniforms(n_texels, n, rng):
    """``(u (n_texels, n, 2), u_mix (n_texels, n))`` for the first direction of n samples per
    texel: sample j uses the Hammersley point ``((j + ½)/n, radical_inverse₂(j))`` and the
    golden-ratio point ``frac(j/φ)``, all shifted by one random offset per texel
    (Cranley–Patterson rotation), so each texel's n samples are stratified and each one is
    uniform."""
    j = np.arange(n)
    base = np.stack([(j + 0.5) / n, radical_inverse2(j)], axis=1)
    shift = rng.random((n_texels, 3))
    # frac of non-negative sums, exactly as np.mod(·, 1) (both subtractions are exact), in place
    u = base[None, :, :] + shift[:, None, :2]
    np.subtract(u, 1.0, out=u, where=u >= 1.0)
    u_mix = j[None, :] * GOLDEN + shift[:, 2:3]
    u_mix -= np.floor(u_mix)
    return u, u_mix


#: Largest table :func:`table_index` searches by counting instead of bisecting.
COUNTED_TABLE = 16


def table_index(cdf, u):
    """``min(searchsorted(cdf, u, side='right'), n - 1)`` (k,) int64: the entry of the
    non-decreasing table ``cdf (n,)`` that each uniform ``u (k,)`` selects. Tables of at most
    :data:`COUNTED_TABLE` entries count the entries ``<= u`` instead (the same integers,
    several times faster than numpy's binary search on the few emitter triangles of a room)."""
    n = len(cdf)
    if n > COUNTED_TABLE:
        return np.minimum(np.searchsorted(cdf, u, side="right"), n - 1)
    index = np.zeros(len(u), np.int64)
    for c in cdf[:-1]:       # a loop over the table's entries, not over the samples
        index += u >= c
    return index


# ---- warps of the unit square --------------------------------------------------------------------

def concentric32(u, v):
    """Shirley–Chiu's concentric map of the unit square to the disk in float32 (as
    ``hemisphere.concentric_square_to_disk``, without its four-way select)."""
    a = 2.0 * np.asarray(u, dtype=np.float32) - 1.0
    b = 2.0 * np.asarray(v, dtype=np.float32) - 1.0
    use_a = np.abs(a) > np.abs(b)
    r = np.where(use_a, a, b)
    ratio = np.where(use_a, b, a) / np.where(r != 0, r, 1.0)
    phi = np.where(use_a, np.float32(QUARTER_PI) * ratio,
                   np.float32(2 * QUARTER_PI) - np.float32(QUARTER_PI) * ratio)
    return r * np.cos(phi), r * np.sin(phi)


def cosine_directions(normals, u, stratified=True):
    """Cosine-weighted directions (k, 3) float32 about ``normals (k, 3)`` from uniforms ``u (k, 2)``.

    ``stratified``: Shirley–Chiu's concentric map (keeps the strata of stratified ``u`` compact:
    the texel's first bounce); otherwise the cheaper polar map ``r = sqrt(u0), φ = 2π u1``
    (independent uniforms of later bounces). Both are exact cosine-weighted warps of the unit
    square, pdf cos θ / π.
    """
    u = np.asarray(u, dtype=np.float32)
    if stratified:
        x, y = concentric32(u[:, 0], u[:, 1])
        z = np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))
    else:
        r = np.sqrt(u[:, 0])
        phi = np.float32(2.0 * np.pi) * u[:, 1]
        x = r * np.cos(phi)
        y = r * np.sin(phi)
        z = np.sqrt(np.maximum(1.0 - u[:, 0], 0.0))
    return local_to_world(normals, x, y, z)


def _corner_units(corners):
    """The unit vectors towards the three corners of ``corners (k, 3, 3)``, each as three
    contiguous (k,) components (one transposing copy: numpy is faster on them than on the
    strided columns)."""
    c = np.ascontiguousarray(np.asarray(corners).transpose(1, 2, 0))    # (corner, axis, k)
    return tuple(unit3(c[i, 0], c[i, 1], c[i, 2]) for i in range(3))


def _solid_angle_of_units(A, B, C, ab=None, bc=None, ca=None):
    """Van Oosterom & Strackee (1983): tan(Ω/2) = |A·(B x C)| / (1 + A·B + B·C + C·A) (the dot
    products ``ab``, ``bc``, ``ca`` if already known)."""
    ab = dot3(A, B) if ab is None else ab
    bc = dot3(B, C) if bc is None else bc
    ca = dot3(C, A) if ca is None else ca
    return 2.0 * np.arctan2(np.abs(dot3(A, cross3(B, C))), 1.0 + ab + bc + ca)


def spherical_triangle_solid_angle(corners):
    """Solid angle (k,) of triangles ``corners (k, 3, 3)`` given relative to the viewpoint
    (Van Oosterom & Strackee 1983)."""
    return _solid_angle_of_units(*_corner_units(corners))


def spherical_triangle_sample(corners, u1, u2):
    """Directions (k, 3) uniform in the solid angle of triangles ``corners (k, 3, 3)`` (relative
    to the viewpoint) from uniforms ``u1, u2``, and the solid angles (k,) (Arvo 1995).

    The pdf of a returned direction is 1 / solid angle. Degenerate triangles get solid angle 0.
    """
    A, B, C = _corner_units(corners)
    n_ab, n_ac = unit3(*cross3(A, B)), unit3(*cross3(A, C))
    cos_a = np.clip(dot3(n_ab, n_ac), -1.0, 1.0)   # the triangle's angle α at A
    sin_a = np.sqrt(1.0 - cos_a * cos_a)
    alpha = np.arccos(cos_a)
    # Its area (solid angle) is the spherical excess α + β + γ - π; Van Oosterom's formula gives
    # the same number without the other two angles, and is the one the MIS weights use.
    ab, ca = dot3(A, B), dot3(C, A)
    omega = _solid_angle_of_units(A, B, C, ab=ab, ca=ca)
    a_hat = u1 * omega                                # the sub-triangle's area
    s, t = np.sin(a_hat - alpha), np.cos(a_hat - alpha)
    u = t - cos_a
    v = s + sin_a * ab
    den = (v * s + u * t) * sin_a
    q = np.clip(((v * t - u * s) * cos_a - v) / np.where(den != 0, den, 1e-300), -1.0, 1.0)
    perp = unit3(*(C[i] - ca * A[i] for i in range(3)))
    sq = np.sqrt(np.maximum(1.0 - q * q, 0.0))
    c_hat = tuple(q * A[i] + sq * perp[i] for i in range(3))   # the new third corner
    cb = dot3(c_hat, B)
    z = 1.0 - u2 * (1.0 - cb)                                   # uniform along the arc B..c_hat
    perp = unit3(*(c_hat[i] - cb * B[i] for i in range(3)))
    sz = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    d = np.empty((len(z), 3))
    ok = omega > 1e-12
    for i in range(3):
        d[:, i] = z * B[i] + sz * perp[i]
        ok &= np.isfinite(d[:, i])
    bad = np.flatnonzero(~ok)
    for i in range(3):       # degenerate triangles: towards the corner B
        d[bad, i] = B[i][bad]
    return d, np.where(ok, omega, 0.0)


# ---- frames ----------------------------------------------------------------------------------------

def local_to_world(n, x, y, z):
    """World directions (k, 3) float32 of local coordinates ``x, y, z (k,)`` in the frames
    (t, b, n) of unit normals ``n (k, 3)``: Duff et al.'s branchless tangent frame, formed per
    component."""
    n = np.asarray(n)
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    out = np.empty((len(n), 3), np.float32)
    out[:, 0] = (1.0 + sign * nx * nx * a) * x + b * y + nx * z
    out[:, 1] = sign * b * x + (sign + ny * ny * a) * y + ny * z
    out[:, 2] = -sign * nx * x - ny * y + nz * z
    return out


def rotate_out(frames, x, y, z):
    """World directions (k, 3) float32 of local coordinates ``x, y, z (k,)`` in ``frames (k, 3, 3)``
    (rows t, b, n): ``x t + y b + z n``, per component."""
    out = np.empty((len(frames), 3), np.float32)
    for j in range(3):
        out[:, j] = x * frames[:, 0, j] + y * frames[:, 1, j] + z * frames[:, 2, j]
    return out


def rotate_in(frames, d):
    """Local coordinates (k, 3) float32 of world directions ``d (k, 3)`` in ``frames (k, 3, 3)``."""
    out = np.empty((len(frames), 3), np.float32)
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    for i in range(3):
        out[:, i] = frames[:, i, 0] * dx + frames[:, i, 1] * dy + frames[:, i, 2] * dz
    return out


# ---- rows and components -----------------------------------------------------------------------------

def rows(a, index):
    """``a[index]`` along the first axis (``np.take``: several times faster than fancy indexing
    for the small row tables and long index arrays of the hot loop)."""
    return np.take(a, index, axis=0)


def set_rows(a, index, values):
    """``a[index] = values`` for the rows ``index`` of a C-contiguous 2-D array ``a``: the rows
    written as single items of their byte width (numpy's fancy assignment of (k, 3) rows is
    several times slower); ``values`` is cast to ``a``'s dtype first, as the assignment would."""
    item = np.dtype((np.void, a.dtype.itemsize * a.shape[1]))
    values = np.ascontiguousarray(values, dtype=a.dtype)
    a.view(item).reshape(-1)[index] = values.view(item).reshape(-1)


def dot(x, y):
    """Row-wise dot products of (k, 3) arrays, per component (faster than
    ``einsum('ij,ij->i')`` on float32 rows)."""
    return x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1] + x[:, 2] * y[:, 2]


def unit3(x, y, z):
    """Unit vectors given as three (k,) component arrays (zero vectors stay zero)."""
    n = np.sqrt(x * x + y * y + z * z)
    inv = 1.0 / np.where(n > 0, n, 1.0)
    return x * inv, y * inv, z * inv


def cross3(a, b):
    """Cross products of vectors given as three (k,) component arrays."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot3(a, b):
    """Dot products of vectors given as three (k,) component arrays."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
