"""Desirability on mesh vertices: the state quantity to show, and its interpolation (no bpy).

States are points on the surfaces (thesis 3.1.1), vertices are wherever the modeller put them:
a Cornell-box wall is one quad with four vertices and hundreds of states, a sculpted mesh has
millions of vertices and a few thousand states. This module turns per-state values into values
at arbitrary sample points (mesh vertices, or the nodes of a finer display lattice):

* :func:`interpolation_weights`: a sparse (V, m) matrix of Gaussian kernel weights over the ``k``
  nearest states **on the same object** whose normal is **compatible** with the sample's normal
  (``dot > min_cos``), so light never bleeds through a thin wall or around a box edge. The
  kernel width is ``smoothing x`` the local state spacing (``sqrt`` of the area a state stands
  for): a light low-pass over the Monte Carlo noise of z. A sample with no compatible state among
  its neighbours takes the nearest state of its object. One cKDTree per object; everything else is
  vectorised over samples.
* :func:`interpolate`: applies the weights, ignoring non-finite values (z = 0 on a log scale,
  J = +inf) and renormalising over the finite ones.
* :func:`state_quantity` / :func:`vertex_field`: the quantity the user chose (z, the cost-to-go
  J = -(log z)/λ, or the per-state residual) on the states, its colour scale, and its values and
  colours at the samples. Log-scaled quantities are interpolated in log10 (geometric mean of the
  neighbours, exact where z underflows float64); PHYSICAL-mode radiance is interpolated linearly
  per RGB channel (radiance is additive) and ``z`` is its Rec.709 luminance.
* :func:`triangle_lattice`, :func:`subdivision_level`: the regular subdivision of triangles
  used to show a faithful field on coarse meshes (see ``operators/ops/display.py``).

Arrays: ``points (n, 3)`` world metres, ``normals (n, 3)`` unit, ``objects (n,)`` int object
indices (those of ``SceneArrays.object_names``), ``values (m, C)``.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .colormap import colormap_linear, linear_scale, log_scale_from_log10
from ..model.costs import scalar_desirability
from ..scene_arrays import luminance

#: Neighbouring states considered per sample.
NEIGHBOURS = 12
#: Smallest cosine between a sample's normal and a state's normal for the state to count.
MIN_COS = 0.5
#: Kernel width in units of the local state spacing.
SMOOTHING = 0.75
#: Residuals below this are shown as this (an exact state has residual 0; log10(0) = -inf).
RESIDUAL_FLOOR = 1e-16
QUANTITIES = ("Z", "COST_TO_GO", "RESIDUAL")
#: The legend of a quantity that no state has a finite value of.
NO_LIGHT_NOTE = ("{} on every state: no light reaches them (an emitter facing away, or "
                 "blocked?); shown in the missing colour (grey)")


@dataclass
class FieldWeights:
    """Interpolation from m states to V samples.

    matrix    CSR (V, m) float32, rows sum to 1 (all-zero rows: no state on the sample's object);
              rows may hold explicit zeros
    nearest   (V,) int64: the nearest state counted for each sample (-1: none)
    fallback  (V,) bool: no compatible state among the neighbours; the nearest state of the
              object was used
    """

    matrix: sp.csr_matrix
    nearest: np.ndarray
    fallback: np.ndarray

    @property
    def n_samples(self):
        return self.matrix.shape[0]

    @property
    def empty(self):
        """(V,) bool: samples whose object carries no state."""
        return self.nearest < 0


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


def interpolation_weights(sample_points, sample_normals, sample_objects, state_points, state_normals,
                          state_objects, state_spacing, k=NEIGHBOURS, min_cos=MIN_COS,
                          smoothing=SMOOTHING, workers=-1):
    """Gaussian weights over the ``k`` nearest compatible states of the same object.

    ``state_spacing (m,)``: distance between neighbouring states around each state (metres),
    e.g. ``sqrt(StateSpace.point_area)``. A state j counts for sample i when both are on the same
    object and ``n_i · n_j > min_cos`` (a sample with a zero normal accepts every state). Weights
    ``exp(-(d_ij² - d_i0²) / (2 h_i²))`` with ``d_i0`` the nearest counted state and
    ``h_i = smoothing x spacing`` of that state: the shift by ``d_i0`` keeps far samples from
    underflowing. Returns :class:`FieldWeights`.
    """
    P = np.asarray(sample_points, dtype=np.float64).reshape(-1, 3)
    N = _unit(np.asarray(sample_normals, dtype=np.float64).reshape(-1, 3))
    O = np.asarray(sample_objects).reshape(-1)
    S = np.asarray(state_points, dtype=np.float64).reshape(-1, 3)
    SN = _unit(np.asarray(state_normals, dtype=np.float64).reshape(-1, 3)).astype(np.float32)
    SO = np.asarray(state_objects).reshape(-1)
    spacing = np.asarray(state_spacing, dtype=np.float64).reshape(-1)
    V, m = len(P), len(S)
    kmax = int(max(1, min(k, m)))
    # Dense (V, k) neighbour lists, wrapped into CSR at the end without sorting (rows may hold
    # explicit zeros: padding for objects with fewer than k states, incompatible neighbours).
    all_idx = np.zeros((V, kmax), dtype=np.int32)
    all_w = np.zeros((V, kmax), dtype=np.float32)
    nearest = np.full(V, -1, dtype=np.int64)
    fallback = np.zeros(V, dtype=bool)
    for obj in np.unique(O):  # a loop over objects (few), vectorised over their samples
        samples = np.flatnonzero(O == obj)
        owned = np.flatnonzero(SO == obj)
        if owned.size == 0:
            continue
        tree = cKDTree(S[owned], leafsize=8)
        kk = int(min(kmax, owned.size))
        dist, idx, ok = _compatible_neighbours(tree, owned, P[samples], N[samples], SN, kk, min_cos, workers)
        retry = np.flatnonzero(~ok.any(axis=1))
        if retry.size and owned.size > kk:
            # Few compatible states nearby (a thin wall, a sharp crease): look further before
            # giving up, but only for those samples.
            k2 = int(min(8 * k, owned.size))
            d2, i2, ok2 = _compatible_neighbours(tree, owned, P[samples[retry]], N[samples[retry]], SN,
                                                 k2, min_cos, workers)
            found = ok2.any(axis=1)
            # Keep the kk nearest compatible of the wider search (compatible first, by distance).
            order = np.argsort(~ok2, axis=1, kind="stable")[:, :kk]
            rows_ = retry[found]
            dist[rows_] = np.take_along_axis(d2, order, axis=1)[found]
            idx[rows_] = np.take_along_axis(i2, order, axis=1)[found]
            ok[rows_] = np.take_along_axis(ok2, order, axis=1)[found]
        none = ~ok.any(axis=1)
        if none.any():  # the nearest state of the object, whatever its normal (column 0)
            ok[none] = False
            ok[none, 0] = True
        fallback[samples[none]] = True
        ar = np.arange(len(samples))
        first = np.argmax(ok, axis=1)  # nearest counted neighbour (distances are sorted)
        d0 = dist[ar, first]
        h = np.maximum(smoothing * spacing[idx[ar, first]], 1e-12).astype(np.float32)
        w = np.exp(-(dist * dist - (d0 * d0)[:, None]) / (2.0 * h * h)[:, None])
        w[~ok] = 0.0
        w /= w.sum(axis=1, keepdims=True)
        nearest[samples] = idx[ar, first]
        all_idx[samples, :kk] = idx
        all_w[samples, :kk] = w
    matrix = sp.csr_matrix((all_w.ravel(), all_idx.ravel(), np.arange(0, V * kmax + 1, kmax)), shape=(V, m))
    return FieldWeights(matrix, nearest, fallback)


def _compatible_neighbours(tree, owned, points, normals, state_normals, k, min_cos, workers):
    """The ``k`` nearest states (distances, state indices, compatibility mask), each (n, k)."""
    dist, local = tree.query(points, k=k, workers=workers)
    dist = np.asarray(dist, dtype=np.float32).reshape(len(points), k)
    idx = owned[np.asarray(local).reshape(len(points), k)].astype(np.int32)
    cos = np.einsum("sj,skj->sk", normals.astype(np.float32), state_normals[idx])
    no_normal = ~np.any(normals != 0, axis=1)
    return dist, idx, (cos > min_cos) | no_normal[:, None]


def interpolate(weights, values):
    """(V, C) values at the samples from ``values (m,) or (m, C)`` at the states.

    Non-finite state values are left out and the weights renormalised over the finite ones; a
    sample whose weighted states are all non-finite takes its nearest state's value, and a sample
    without states gets NaN.
    """
    values = np.asarray(values, dtype=np.float64)
    flat = values.ndim == 1
    vals = values.reshape(len(values), -1)
    finite = np.isfinite(vals)
    W = weights.matrix
    num = np.asarray(W @ np.where(finite, vals, 0.0))
    den = np.asarray(W @ finite.astype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), np.nan)
    has_state = weights.nearest >= 0
    fill = (den <= 1e-12) & has_state[:, None]
    if fill.any():
        nearest_vals = vals[np.maximum(weights.nearest, 0)]
        out = np.where(fill, nearest_vals, out)
    out[~has_state] = np.nan
    return out[:, 0] if flat else out


# -- the quantity shown ---------------------------------------------------------------------------

@dataclass
class StateQuantity:
    """The displayed quantity on the states, in the domain it is interpolated in.

    quantity   'Z', 'COST_TO_GO' or 'RESIDUAL'
    log10_z    (m,) log10 of the scalar desirability (luminance in PHYSICAL mode); -inf where z = 0
    z_rgb      (m, 3) PHYSICAL-mode radiance per channel, else None
    value      (m,) what the colour shows, interpolated as is: log10 z, J, or log10 residual
    scale      :class:`~lmdp_addon.display.colormap.ColorScale` of the quantity (in its own units)
    lambda_    λ of the solution (J = -(ln z)/λ)
    """

    quantity: str
    log10_z: np.ndarray
    z_rgb: np.ndarray
    value: np.ndarray
    scale: object
    lambda_: float

    @property
    def log_value(self):
        """True when :attr:`value` holds log10 of the quantity."""
        return self.quantity in ("Z", "RESIDUAL")


def state_quantity(solution, quantity="Z", residuals=None, states=None):
    """The :class:`StateQuantity` of ``solution`` for ``quantity``, one value per state point.

    ``states``: the :class:`~lmdp_addon.model.states.StateSpace` of the solution; where glossy
    points carry directional unknowns a glossy point shows the cosine-weighted mean of its
    directions' z, Σ_k w_k z(x, k) (its radiosity-equivalent B/π, what a Lambertian point's z
    is), and the largest residual of its unknowns. Without glossy points it changes nothing.

    Z: desirability (PHYSICAL: outgoing radiance; its Rec.709 luminance is the scalar z), log
    scale over the 1st-99th percentile of the states. COST_TO_GO: J = -(ln z)/λ of the scalar z
    (design.md's convention), linear scale over the 1st-99th percentile. RESIDUAL:
    ``residuals (m,)`` from :func:`lmdp_addon.model.solvers.state_residuals` (relative |z - QPz|/z per
    state), log scale over the full range, floored at 1e-16. Where no state has a finite value
    (z = 0 everywhere) the scale is empty (``ColorScale.empty``): every colour is the missing
    one and the legend says why (:data:`NO_LIGHT_NOTE`).
    """
    if quantity not in QUANTITIES:
        raise ValueError(f"quantity must be one of {', '.join(QUANTITIES)}, not {quantity!r}")
    physical = solution.cost_mode == "PHYSICAL"
    log_z = np.asarray(solution.log_z, dtype=np.float64)  # (N, C), exact where z underflows
    unknowns = None if states is None or states.unknowns.identity else states.unknowns
    if unknowns is not None:
        log_z = unknowns.point_log_values(log_z, states.stratum_weight)        # (m, C)
        if residuals is not None:
            residuals = unknowns.point_max(residuals)
    if log_z.shape[1] == 1:
        ln_scalar = log_z[:, 0]
        z_rgb = None
    else:
        z_rgb = (np.asarray(solution.z, dtype=np.float64) if unknowns is None
                 else unknowns.point_values(solution.z, states.stratum_weight))
        with np.errstate(divide="ignore"):
            ln_scalar = np.log(scalar_desirability(z_rgb))
    log10_z = ln_scalar / np.log(10.0)
    lam = float(solution.lambda_)
    if quantity == "Z":
        label = "z: radiance (luminance, W/sr/m²)" if physical else "z: desirability"
        value = log10_z
        scale = log_scale_from_log10(value, label, empty_note=NO_LIGHT_NOTE.format("z is 0"))
    elif quantity == "COST_TO_GO":
        value = -ln_scalar / lam
        scale = linear_scale(value, f"J = -(ln z)/λ (λ = {lam:.4g})", 1.0, 99.0,
                             empty_note=NO_LIGHT_NOTE.format("J is +inf (z = 0)"))
    else:
        if residuals is None:
            raise ValueError("the RESIDUAL quantity needs the per-state residuals")
        res = np.maximum(np.asarray(residuals, dtype=np.float64).reshape(-1), RESIDUAL_FLOOR)
        value = np.log10(res)
        scale = log_scale_from_log10(value, "relative residual |z - QPz|/z", 0.0, 100.0)
    return StateQuantity(quantity, log10_z, z_rgb, value, scale, lam)


@dataclass
class VertexField:
    """The quantity at V samples, ready to be written as attributes.

    z         (V,) float64 desirability (luminance in PHYSICAL mode); 0 where it underflows
    log10_z   (V,) log10 of z, exact where z underflows (-inf where z = 0)
    z_rgb     (V, 3) PHYSICAL radiance, else None
    quantity  (V,) the displayed quantity in its own units (z, J or the residual)
    color     (V, 4) float32 scene-linear RGBA on the colour map
    position  (V,) position on the colour map in [0, 1] (NaN: no value)
    """

    z: np.ndarray
    log10_z: np.ndarray
    z_rgb: np.ndarray
    quantity: np.ndarray
    color: np.ndarray
    position: np.ndarray


def vertex_field(weights, sq, colormap="VIRIDIS"):
    """Interpolate :class:`StateQuantity` ``sq`` with ``weights``; returns a :class:`VertexField`."""
    if sq.z_rgb is not None:
        # Radiance is additive: interpolate it linearly, z is its luminance.
        z_rgb = np.maximum(interpolate(weights, sq.z_rgb), 0.0)
        z = luminance(np.nan_to_num(z_rgb, nan=0.0))
        z = np.where(np.isnan(z_rgb[:, 0]), np.nan, z)
        with np.errstate(divide="ignore", invalid="ignore"):
            log10_z = np.where(z > 0, np.log10(np.where(z > 0, z, 1.0)), -np.inf)
        log10_z = np.where(np.isnan(z), np.nan, log10_z)
    else:
        z_rgb = None
        log10_z = interpolate(weights, sq.log10_z)
        with np.errstate(over="ignore", under="ignore"):
            z = np.power(10.0, log10_z)
    if sq.quantity == "Z":
        position = sq.scale.position_of_log10(log10_z)
        quantity = z
    elif sq.quantity == "COST_TO_GO":
        quantity = interpolate(weights, sq.value)
        position = sq.scale.position(quantity)
    else:
        log_res = interpolate(weights, sq.value)
        position = sq.scale.position_of_log10(log_res)
        quantity = np.power(10.0, log_res)
    color = colormap_linear(position, colormap)
    return VertexField(z=z, log10_z=log10_z, z_rgb=z_rgb, quantity=quantity, color=color, position=position)


# -- display lattices for coarse meshes ----------------------------------------------------------------

def lattice_template(n):
    """Barycentric lattice of one triangle split into n² similar triangles.

    Returns ``(ij (N, 2) int, triangles (n², 3) int)``: node (i, j) is ``a + (b-a) i/n + (c-a) j/n``
    for ``i + j <= n``; N = (n+1)(n+2)/2.
    """
    n = int(n)
    if n < 1:
        raise ValueError("lattice resolution must be at least 1")
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    ij = np.stack([i[keep], j[keep]], axis=1)
    index = np.full((n + 2, n + 2), -1, dtype=np.int64)
    index[ij[:, 0], ij[:, 1]] = np.arange(len(ij))
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = a + b <= n - 1
    down = a + b <= n - 2
    tri_up = np.stack([index[a[up], b[up]], index[a[up] + 1, b[up]], index[a[up], b[up] + 1]], axis=1)
    tri_down = np.stack([index[a[down] + 1, b[down]], index[a[down] + 1, b[down] + 1],
                         index[a[down], b[down] + 1]], axis=1)
    return ij, np.concatenate([tri_up, tri_down])


def triangle_lattice(corners, n):
    """Subdivide triangles ``corners (T, 3, 3)`` into n² sub-triangles each.

    Returns ``(points (T*N, 3), triangles (T*n², 3), source (T*N,))`` where ``source`` is the
    triangle each node came from. Nodes on shared edges are repeated per triangle (each keeps its
    own triangle's normal), which is what a display lattice wants at creases.
    For a planar parallelogram quad split into (a, b, c), (a, c, d) the nodes are exactly the
    bilinear grid of Blender's simple subdivision with ``n = 2^level`` cuts.
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 3, 3)
    ij, tris = lattice_template(n)
    s = ij / float(n)
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    points = (a[:, None, :] + (b - a)[:, None, :] * s[None, :, :1] + (c - a)[:, None, :] * s[None, :, 1:])
    T, N = len(corners), len(ij)
    triangles = (tris[None, :, :] + (np.arange(T) * N)[:, None, None]).reshape(-1, 3)
    source = np.repeat(np.arange(T), N)
    return points.reshape(-1, 3), triangles, source


def subdivision_level(edge_length, spacing, max_level=6):
    """Smallest level L (0..max_level) with ``edge_length / 2^L <= spacing / 2``: every display
    edge is at most half the distance between neighbouring states."""
    edge_length = float(edge_length)
    spacing = float(spacing)
    if not (edge_length > 0 and spacing > 0):
        return 0
    level = int(np.ceil(np.log2(max(edge_length / (0.5 * spacing), 1.0))))
    return int(min(max(level, 0), max_level))


def state_spacing(point_area):
    """(m,) distance between neighbouring states: ``sqrt`` of the area each state stands for."""
    return np.sqrt(np.maximum(np.asarray(point_area, dtype=np.float64), 0.0))

