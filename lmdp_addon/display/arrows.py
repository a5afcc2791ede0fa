"""Arrow geometry of the optimal policy u* (thesis eq. 2.23 / 3.2; Figure 5), without bpy.

The directional optimal policy ``u*(k | x)`` (:func:`lmdp_addon.model.policy.stratum_policy`) is the
probability that the optimal controller sends a path leaving point x through hemisphere stratum
k. It is drawn as one arrow per (point, stratum) along the stratum's central direction, with
length ``scale x u*(k|x)``: a point whose policy follows the passive dynamics shows a cosine-shaped
bouquet, a point whose policy has learnt where the light is shows one or two long arrows.

This module computes everything that is geometry, vectorised over arrows:

* which points get arrows: :func:`policy_divergence` (KL(u* || p), the control cost of the state,
  thesis eq. 2.21), :func:`most_informative` (largest divergence, spread over space),
  :func:`even_subset`;
* the arrows: :func:`stratum_arrows`, and for the probe, :func:`nearest_state` and
  :func:`next_state_targets` (the thesis's Figure 5: u*(x'|x) over the next states x');
* glossy points (one unknown per outgoing stratum): :func:`directional_policy` shows the u* of
  the unknown looking straight down on them (:func:`probe_unknowns`), its next states binned by
  the stratum of their direction (:func:`glossy_stratum_policy`; emitters at their centroids,
  lamps at their centres, the world and the void left out);
* their shapes: :func:`arrow_lines` (line segments for the viewport's GPU batch),
  :func:`arrow_mesh` (closed triangle meshes that render in Cycles / EEVEE) and
  :func:`marker_mesh` (octahedra at next states).

Arrays: ``points (m, 3)`` world metres, ``frames (m, 3, 3)`` rows t, b, n
(:func:`lmdp_addon.model.hemisphere.tangent_frame`), ``u (m, S)`` rows summing to one.
"""
from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp

from .colormap import colormap_linear
from ..lamps import SUN
from ..model.hemisphere import stratum_centers, stratum_of_local_direction, tangent_frame


@dataclass
class Arrows:
    """N arrows: ``start + length * direction``.

    starts      (N, 3) world metres
    directions  (N, 3) unit vectors
    lengths     (N,) metres
    probability (N,) the probability each arrow stands for (u*(k|x) or u*(x'|x))
    point       (N,) int64 state (point) index the arrow leaves from
    stratum     (N,) int64 stratum index (-1 for arrows to next states)
    """

    starts: np.ndarray
    directions: np.ndarray
    lengths: np.ndarray
    probability: np.ndarray
    point: np.ndarray
    stratum: np.ndarray

    @property
    def count(self):
        return len(self.lengths)

    @property
    def ends(self):
        return self.starts + self.directions * self.lengths[:, None]

    @classmethod
    def empty(cls):
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0),
                   np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))

    @classmethod
    def concatenate(cls, parts):
        parts = [p for p in parts if p is not None]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))


# -- which points ---------------------------------------------------------------------------------

def policy_divergence(u, passive):
    """KL(u*(.|x) || p(.|x)) over the strata of each point, nats (m,).

    ``passive (S,) or (m, S)``: the passive dynamics' stratum probabilities (the Lambertian
    masses ``StateSpace.stratum_weight``). This is the control cost the optimal policy pays at x
    (thesis eq. 2.21 without λ): 0 where u* follows the passive dynamics, large where it has
    learnt to aim.
    """
    u = np.asarray(u, dtype=np.float64)
    p = np.broadcast_to(np.asarray(passive, dtype=np.float64), u.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(u > 0, u * np.log(u / np.where(p > 0, p, 1e-300)), 0.0)
    return terms.sum(axis=1)


def policy_entropy(u):
    """Shannon entropy of u*(.|x) over the strata of each point, nats (m,)."""
    u = np.asarray(u, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.where(u > 0, u * np.log(np.where(u > 0, u, 1.0)), 0.0).sum(axis=1)


def most_informative(points, score, count, cell_size=None, candidates=None):
    """Indices of up to ``count`` points with the largest ``score``, spread over space.

    Points are binned into cubes of side ``cell_size`` (default: the side that gives about
    ``count`` occupied cells on the bounding box's surface area scale, see below); each cell
    keeps its best point, and the best ``count`` cells win. Without the spreading every arrow
    would crowd around the light, where the policy is sharpest. ``candidates``: restrict to these
    point indices. Returned in decreasing score.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    score = np.asarray(score, dtype=np.float64).reshape(-1)
    idx = np.arange(len(points)) if candidates is None else np.asarray(candidates, dtype=np.int64)
    count = int(count)
    if count <= 0 or idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    if idx.size <= count:
        return idx[np.argsort(-score[idx], kind="stable")]
    p = points[idx]
    if cell_size is None:
        # Points lie on surfaces: about (extent² x 6) / cell² cells are occupied; ask for ~2 count.
        extent = np.ptp(p, axis=0)
        area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[0] * extent[2])
        cell_size = np.sqrt(max(area, 1e-12) / (2.0 * count))
    cell = np.floor((p - p.min(axis=0)) / max(float(cell_size), 1e-12)).astype(np.int64)
    _, cell_id = np.unique(cell, axis=0, return_inverse=True)
    cell_id = cell_id.reshape(-1)
    # Best point per cell: sort by (cell, -score) and take the first of each cell.
    order = np.lexsort((-score[idx], cell_id))
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell_id[order][1:] != cell_id[order][:-1]
    best = order[first]
    best = best[np.argsort(-score[idx][best], kind="stable")][:count]
    if len(best) < count:  # fewer cells than wanted: fill with the next best points
        rest = np.setdiff1d(np.arange(len(idx)), best)
        rest = rest[np.argsort(-score[idx][rest], kind="stable")][:count - len(best)]
        best = np.concatenate([best, rest])
    return idx[best]


def even_subset(indices, count):
    """Up to ``count`` of ``indices`` at even strides (states are stratified along the area CDF,
    so even strides are even over the surface)."""
    indices = np.asarray(indices, dtype=np.int64)
    if len(indices) <= count:
        return indices
    pick = np.floor((np.arange(count) + 0.5) * len(indices) / count).astype(np.int64)
    return indices[pick]


# -- the arrows -----------------------------------------------------------------------------------

def stratum_directions(frames, strata_u, strata_v):
    """(m, S, 3) world central direction of every stratum of every point."""
    centers = stratum_centers(strata_u, strata_v)  # (S, 3) local
    return np.einsum("sj,mjk->msk", centers, np.asarray(frames, dtype=np.float64))


def stratum_arrows(points, frames, u, strata_u, strata_v, scale, min_probability=0.0, lift=0.0):
    """One arrow per (point, stratum) with ``u*(k|x) > min_probability``.

    The arrow leaves ``point + lift * normal`` (a small lift keeps it off the surface) along the
    stratum's central direction with length ``scale * u*(k|x)`` (so ``scale`` is the length of a
    probability-1 arrow, metres).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(frames, dtype=np.float64).reshape(-1, 3, 3)
    u = np.asarray(u, dtype=np.float64).reshape(len(points), -1)
    if u.shape[1] != strata_u * strata_v:
        raise ValueError(f"u has {u.shape[1]} strata per point, expected {strata_u} x {strata_v}")
    dirs = stratum_directions(frames, strata_u, strata_v)
    keep = (u > min_probability) & (u > 0)
    point, stratum = np.nonzero(keep)
    starts = points[point] + float(lift) * frames[point, 2]
    prob = u[point, stratum]
    return Arrows(starts, dirs[point, stratum], float(scale) * prob, prob,
                  point.astype(np.int64), stratum.astype(np.int64))


def nearest_state(points, normals, location, candidates=None, side_tolerance=1e-4):
    """Index of the state point nearest to ``location`` that has ``location`` on its front side.

    A probe placed on a thin wall must read the states of the face it was placed on, not those of
    the back face a few millimetres away: among the states with ``(location - p) · n >=
    -side_tolerance`` the nearest wins; if there is none, the nearest of all. ``candidates``
    restricts the search to those indices. Returns -1 when there are no states.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    idx = np.arange(len(points)) if candidates is None else np.asarray(candidates, dtype=np.int64)
    if idx.size == 0:
        return -1
    offset = np.asarray(location, dtype=np.float64).reshape(3) - points[idx]
    dist2 = np.einsum("ij,ij->i", offset, offset)
    front = np.einsum("ij,ij->i", offset, normals[idx]) >= -float(side_tolerance)
    if front.any():
        dist2 = np.where(front, dist2, np.inf)
    return int(idx[np.argmin(dist2)])


def next_state_targets(policy_row_indices, policy_row_values, n_points, count=None, point_of=None):
    """The next states x' of one state's u*(x'|x) that are surface points, largest first.

    ``policy_row_*``: the CSR row of :func:`lmdp_addon.model.policy.optimal_policy` (column indices and
    probabilities; columns >= n_points are terminals, ``n_points`` then counting the unknowns).
    ``point_of (N,)``: the point of each unknown (``UnknownMap.point``) where glossy points carry
    several; their probabilities are summed per point. Returns ``(points (K,), probability (K,),
    terminal_probability)``: the surface next states (at most ``count``), and the total
    probability of the terminal states (lights, world, void) which have no position.
    """
    cols = np.asarray(policy_row_indices, dtype=np.int64)
    vals = np.asarray(policy_row_values, dtype=np.float64)
    surface = (cols < n_points) & (vals > 0)
    terminal = float(vals[cols >= n_points].sum())
    cols, vals = cols[surface], vals[surface]
    if point_of is not None:
        cols, inverse = np.unique(np.asarray(point_of)[cols], return_inverse=True)
        vals = np.bincount(inverse.reshape(-1), weights=vals, minlength=len(cols))
    order = np.argsort(-vals, kind="stable")
    if count is not None:
        order = order[:int(count)]
    return cols[order], vals[order], terminal


def arrows_between(starts, ends, probability, point, shorten=0.0):
    """Arrows from ``starts`` to ``ends`` (each shortened by ``shorten`` metres at the tip)."""
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    d = ends - starts
    length = np.linalg.norm(d, axis=1)
    direction = np.where(length[:, None] > 0, d / np.where(length > 0, length, 1.0)[:, None], 0.0)
    length = np.maximum(length - float(shorten), 0.0)
    n = len(starts)
    return Arrows(starts, direction, length, np.asarray(probability, dtype=np.float64).reshape(n),
                  np.broadcast_to(np.asarray(point, dtype=np.int64), (n,)).copy(),
                  np.full(n, -1, dtype=np.int64))


# -- shapes ---------------------------------------------------------------------------------------

def _perpendiculars(directions):
    """Two unit vectors perpendicular to each direction and to each other: (N, 3), (N, 3)."""
    frames = tangent_frame(directions)
    return frames[:, 0], frames[:, 1]


def arrow_lines(arrows, head_fraction=0.3, head_width=0.35):
    """Line segments of the arrows for a 'LINES' GPU batch.

    Each arrow is its shaft plus four barbs from the tip, ``head_fraction`` of its length long and
    ``head_width`` of the head length wide, around the shaft (readable from every view).
    Returns ``(vertices (10 N, 3) float32, arrow (10 N,) int64)``: consecutive pairs are segments.
    """
    n = arrows.count
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    tip = arrows.ends
    d = arrows.directions
    a, b = _perpendiculars(d)
    head = (float(head_fraction) * arrows.lengths)[:, None]
    back = tip - d * head
    w = float(head_width) * head
    barbs = [back + a * w, back - a * w, back + b * w, back - b * w]
    segments = [arrows.starts, tip]
    for barb in barbs:
        segments += [tip, barb]
    verts = np.stack(segments, axis=1).reshape(-1, 3)
    return verts.astype(np.float32), np.repeat(np.arange(n), 10)


def arrow_mesh(arrows, shaft_radius, head_radius=None, head_length=None, sides=6):
    """Closed triangle meshes of the arrows: a ``sides``-gon prism shaft and a pyramid head
    (joined by an annulus, so each arrow is a closed, outward-facing 2-manifold).

    ``shaft_radius``: metres, scalar or (N,); ``head_radius`` defaults to 2.5 x the shaft radius
    and ``head_length`` to min(6 x shaft radius, 0.45 x length): short arrows keep a visible head.
    Returns ``(vertices (N*V, 3) float32, triangles (N*F, 3) int64, arrow (N*V,) int64)`` with
    V = 3 sides + 1 and F = 6 sides - 2 triangles per arrow, outward-facing.
    """
    n = arrows.count
    sides = int(sides)
    if sides < 3:
        raise ValueError("an arrow needs at least 3 sides")
    per_v, per_f = 3 * sides + 1, 6 * sides - 2
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    r = np.broadcast_to(np.asarray(shaft_radius, dtype=np.float64), (n,))
    hr = 2.5 * r if head_radius is None else np.broadcast_to(np.asarray(head_radius, np.float64), (n,))
    L = arrows.lengths
    hl = np.minimum(6.0 * r, 0.45 * L) if head_length is None else \
        np.minimum(np.broadcast_to(np.asarray(head_length, np.float64), (n,)), L)
    d = arrows.directions
    a, b = _perpendiculars(d)
    angle = 2.0 * np.pi * np.arange(sides) / sides
    ring = np.cos(angle)[None, :, None] * a[:, None, :] + np.sin(angle)[None, :, None] * b[:, None, :]
    start = arrows.starts
    neck = start + d * (L - hl)[:, None]
    tip = start + d * L[:, None]
    verts = np.concatenate([
        start[:, None, :] + r[:, None, None] * ring,    # 0 .. s-1   shaft bottom ring
        neck[:, None, :] + r[:, None, None] * ring,     # s .. 2s-1  shaft top ring
        neck[:, None, :] + hr[:, None, None] * ring,    # 2s .. 3s-1 head base ring
        tip[:, None, :],                                # 3s         tip
    ], axis=1)
    s = np.arange(sides)
    s1 = (s + 1) % sides
    faces = np.concatenate([
        np.stack([s, s1, sides + s1], axis=1), np.stack([s, sides + s1, sides + s], axis=1),  # shaft
        np.stack([np.zeros(sides - 2, int), np.arange(2, sides), np.arange(1, sides - 1)], axis=1),
        np.stack([sides + s, sides + s1, 2 * sides + s1], axis=1),  # annulus under the head
        np.stack([sides + s, 2 * sides + s1, 2 * sides + s], axis=1),
        np.stack([2 * sides + s, 2 * sides + s1, np.full(sides, 3 * sides)], axis=1),  # head cone
    ])
    assert len(faces) == per_f
    triangles = faces[None, :, :] + (np.arange(n) * per_v)[:, None, None]
    return (verts.reshape(-1, 3).astype(np.float32), triangles.reshape(-1, 3).astype(np.int64),
            np.repeat(np.arange(n), per_v))


def marker_mesh(centers, radii):
    """Octahedra (6 vertices, 8 outward triangles each) at ``centers (K, 3)`` with ``radii``.

    Returns ``(vertices (6K, 3) float32, triangles (8K, 3) int64, marker (6K,) int64)``.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    k = len(centers)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (k,))
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    verts = centers[:, None, :] + r[:, None, None] * axes[None]
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    triangles = faces[None] + (np.arange(k) * 6)[:, None, None]
    return (verts.reshape(-1, 3).astype(np.float32), triangles.reshape(-1, 3).astype(np.int64),
            np.repeat(np.arange(k), 6))


# -- what the viewport draws ----------------------------------------------------------------------

#: Colour map of the arrows, and where on it the least probable arrow starts: arrows stay visible
#: (never black) and differ from the desirability's viridis.
ARROW_COLORMAP = "INFERNO"
ARROW_COLOR_FLOOR = 0.35


def arrow_colors(probability, vmax=None, colormap=ARROW_COLORMAP, floor=ARROW_COLOR_FLOOR):
    """(N, 4) scene-linear RGBA of arrows by probability: ``floor + (1 - floor) p / vmax`` on the
    map (vmax: the largest probability shown, default the largest of ``probability``)."""
    p = np.asarray(probability, dtype=np.float64).reshape(-1)
    if vmax is None:
        vmax = float(p.max()) if p.size else 1.0
    t = floor + (1.0 - floor) * np.clip(p / max(float(vmax), 1e-300), 0.0, 1.0)
    return colormap_linear(t, colormap)


@dataclass
class Probe:
    """The optimal policy of one state, as in the thesis's Figure 5.

    state          index of the probed state (point)
    location       (3,) where the probe was placed
    arrows         :class:`Arrows` of u*(k|x) over the strata of the state
    targets        (K,) surface next states x' with the largest u*(x'|x), largest first
    target_probability (K,)
    terminal_probability  total u* of the terminal next states (lights, world, void)
    target_points  (K, 3) positions of the targets
    """

    state: int
    location: np.ndarray
    arrows: Arrows
    targets: np.ndarray
    target_probability: np.ndarray
    terminal_probability: float
    target_points: np.ndarray

    def links(self, shorten=0.0):
        """:class:`Arrows` from the probed state to each target x' (probability u*(x'|x))."""
        start = self.arrows.starts[:1] if self.arrows.count else self.target_points[:0]
        starts = np.repeat(start, len(self.targets), axis=0)
        return arrows_between(starts, self.target_points, self.target_probability, self.state, shorten)


@dataclass
class PolicyView:
    """Everything the viewport overlay draws for the optimal policy (one session result).

    arrows   :class:`Arrows` of the chosen subset of states (may be empty)
    subset   'ACTIVE_OBJECT', 'MOST_INFORMATIVE' or '' (probe only)
    points   (P,) the states that got arrows
    probe    :class:`Probe` or None
    """

    arrows: Arrows
    subset: str = ""
    points: np.ndarray = None
    probe: Probe = None

    def summary(self):
        parts = []
        if self.arrows.count:
            parts.append(f"{self.arrows.count} arrows on {len(np.unique(self.arrows.point))} states")
        if self.probe is not None:
            parts.append(f"probe at state {self.probe.state}")
        return ", ".join(parts) if parts else "no arrows"

    def lines(self, head_fraction=0.3):
        """``(vertices (2L, 3) float32, colours (2L, 4) float32)`` of every segment to draw: the
        subset's arrows, the probe's arrows, and for each probe target a cross and a line from
        the probed state, coloured by probability (:func:`arrow_colors`, each group on its own
        scale)."""
        verts, colors = [], []
        for arrows in (self.arrows, self.probe.arrows if self.probe is not None else None):
            if arrows is None or arrows.count == 0:
                continue
            v, which = arrow_lines(arrows, head_fraction=head_fraction)
            verts.append(v)
            colors.append(arrow_colors(arrows.probability)[which])
        if self.probe is not None and len(self.probe.targets):
            v, which = target_crosses(self.probe.target_points, self._cross_size())
            verts.append(v)
            colors.append(arrow_colors(self.probe.target_probability)[which])
            links = self.probe.links()
            v, which = arrow_lines(links, head_fraction=0.0)
            keep = (np.arange(len(v)) % 10) < 2          # the shafts only
            verts.append(v[keep])
            colors.append(arrow_colors(links.probability)[which][keep])
        if not verts:
            return np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32)
        return np.concatenate(verts).astype(np.float32), np.concatenate(colors).astype(np.float32)

    def _cross_size(self):
        a = self.probe.arrows
        return 0.25 * float(a.lengths.max()) if a.count else 0.01


def target_crosses(centers, size):
    """Three axis-aligned segments of length ``2 size`` through each centre (a 3D cross), for
    the viewport; returns ``(vertices (6K, 3) float32, marker (6K,) int64)``."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    axes = np.eye(3) * float(size)
    v = np.stack([centers - axes[0], centers + axes[0], centers - axes[1], centers + axes[1],
                  centers - axes[2], centers + axes[2]], axis=1)
    return v.reshape(-1, 3).astype(np.float32), np.repeat(np.arange(len(centers)), 6)


# -- from a solved LMDP to what is drawn --------------------------------------------------------------

SUBSETS = ("ACTIVE_OBJECT", "MOST_INFORMATIVE")


def choose_points(states, u, subset, max_points, candidates):
    """The states that get arrows: ``candidates`` (point indices, e.g. those of the active
    object) thinned to ``max_points`` at even strides for ACTIVE_OBJECT, or the ``max_points``
    candidates of largest KL(u* || p), spread over space, for MOST_INFORMATIVE."""
    if subset not in SUBSETS:
        raise ValueError(f"subset must be one of {', '.join(SUBSETS)}, not {subset!r}")
    candidates = np.asarray(candidates, dtype=np.int64)
    if subset == "ACTIVE_OBJECT":
        return even_subset(candidates, int(max_points))
    score = policy_divergence(u[candidates], states.stratum_weight)
    full = np.zeros(states.n_points)
    full[candidates] = score
    return most_informative(states.points, full, int(max_points), candidates=candidates)


def default_min_probability(n_strata):
    """Arrows below a quarter of the uniform probability 1/S are not drawn (clutter)."""
    return 0.25 / max(int(n_strata), 1)


def policy_view(states, u, subset, max_points, scale, candidates, min_probability=None, probe=None):
    """:class:`PolicyView` of the chosen states' stratum arrows (see :func:`choose_points`)."""
    points = choose_points(states, u, subset, max_points, candidates)
    if min_probability is None:
        min_probability = default_min_probability(states.n_strata)
    arrows = stratum_arrows(states.points[points], states.frames[points], u[points], states.strata_u,
                            states.strata_v, scale, min_probability, lift=0.01 * float(scale))
    arrows.point = points[arrows.point]
    return PolicyView(arrows=arrows, subset=subset, points=points, probe=probe)


def terminal_positions(scene, dynamics):
    """(nT, 3) where each terminal of ``dynamics`` lies: an emitter's area-weighted centroid, a
    point / spot / area lamp's centre; NaN for the world, the void and suns (no position)."""
    out = np.full((dynamics.n_terminals, 3), np.nan)
    E = dynamics.n_emitters
    if E:
        tri_emitter = scene.emitter_groups()[0]
        corners = scene.corners()
        areas = scene.triangle_geometry()[1]
        on = np.flatnonzero(tri_emitter >= 0)
        w = areas[on]
        c = corners[on].mean(axis=1)
        total = np.bincount(tri_emitter[on], weights=w, minlength=E)
        for i in range(3):
            out[:E, i] = np.bincount(tri_emitter[on], weights=w * c[:, i], minlength=E) / np.maximum(total, 1e-300)
    lamps = getattr(scene, "lamps", None)
    if dynamics.n_lamps and lamps is not None and lamps.position is not None:
        first = E + dynamics.n_world + 1
        position = np.asarray(lamps.position, dtype=np.float64).reshape(-1, 3)
        sun = np.asarray(lamps.kind) == SUN
        out[first:first + len(position)] = np.where(sun[:, None], np.nan, position)
    return out


def glossy_stratum_policy(states, policy, points, targets):
    """u*(k_in | x, k) (len(points), S) of the glossy points ``points`` for the unknown the
    probe shows (:func:`probe_unknown`): the optimal policy's next states binned by the stratum
    of the direction from x to them (``targets (N + nT, 3)``: the unknowns' points and the
    terminals' positions, :func:`terminal_positions`; columns without a position, the world and
    the void, left out). The unknowns' own next states, rather than the cosine stratum rows the
    guide reads (``policy.stratum_policy``)."""
    points = np.asarray(points, dtype=np.int64)
    S = states.n_strata
    rows = sp.csr_matrix(policy)[probe_unknowns(states, points)].tocoo()
    x = points[rows.row]
    d = targets[rows.col] - states.points[x]
    ok = np.flatnonzero(np.all(np.isfinite(d), axis=1) & (rows.data > 0))
    local = np.einsum("kij,kj->ki", states.frames[x[ok]], d[ok])
    k = stratum_of_local_direction(local, states.strata_u, states.strata_v)
    up = k >= 0
    out = np.bincount(rows.row[ok][up] * S + k[up], weights=rows.data[ok][up],
                      minlength=len(points) * S).reshape(len(points), S)
    sums = out.sum(axis=1, keepdims=True)
    return np.where(sums > 0, out / np.where(sums > 0, sums, 1.0), 0.0)


def directional_policy(scene, states, dynamics, u, policy, points=None):
    """``u (m, S)`` (``policy.stratum_policy``) with the rows of glossy points (among ``points``,
    default all) replaced by :func:`glossy_stratum_policy` of their shown unknown, so that the
    arrows of a glossy point show where the optimal policy of that direction goes."""
    unknowns = states.unknowns
    if unknowns.identity:
        return u
    points = np.arange(states.n_points) if points is None else np.asarray(points, dtype=np.int64)
    g = points[unknowns.glossy[points]]
    if len(g) == 0:
        return u
    targets = np.vstack([states.points[unknowns.point], terminal_positions(scene, dynamics)])
    out = np.array(u, dtype=np.float64)
    out[g] = glossy_stratum_policy(states, policy, g, targets)
    return out


def probe_unknowns(states, points):
    """(k,) the unknown the policy display shows for each of ``points``: its only one, or on a
    glossy point the one of the outgoing stratum whose centre is nearest the normal (u*(x'|x, k)
    of the view straight down on it)."""
    unknowns = states.unknowns
    points = np.asarray(points, dtype=np.int64)
    k = int(np.argmax(stratum_centers(states.strata_u, states.strata_v)[:, 2]))
    return unknowns.first[points] + np.where(unknowns.glossy[points], k, 0)


def probe_unknown(states, point):
    """:func:`probe_unknowns` of one point (an int)."""
    return int(probe_unknowns(states, [point])[0])


def probe(states, u, policy_row, location, scale, next_states=24, candidates=None, longest=False):
    """:class:`Probe` of the state nearest to ``location`` (:func:`nearest_state`).

    ``u (m, S)`` directional policy; ``policy_row``: a callable ``i -> (columns, values)`` giving
    the row of u*(x'|x) over the next states (:func:`lmdp_addon.model.policy.optimal_policy`).
    Every stratum arrow is drawn (the whole distribution, as in Figure 5), with length
    ``scale x u*(k|x)``; with ``longest=True`` the most probable stratum's arrow is ``scale``
    long instead (a single state's distribution is easier to read at a fixed size).
    ``policy_row(i)`` takes the point's unknown (:func:`probe_unknown`: on a glossy point the
    one of its outgoing stratum nearest the normal), whose next states are summed per point.
    """
    i = nearest_state(states.points, states.normals, location, candidates)
    if i < 0:
        raise ValueError("there are no states to probe")
    if longest:
        scale = float(scale) / max(float(u[i].max()), 1e-12)
    arrows = stratum_arrows(states.points[i:i + 1], states.frames[i:i + 1], u[i:i + 1], states.strata_u,
                            states.strata_v, scale, 0.0, lift=0.01 * float(scale))
    arrows.point[:] = i
    cols, vals = policy_row(probe_unknown(states, i))
    unknowns = states.unknowns
    targets, probability, terminal = next_state_targets(
        cols, vals, unknowns.n_unknowns, next_states, None if unknowns.identity else unknowns.point)
    return Probe(state=i, location=np.asarray(location, dtype=np.float64).reshape(3), arrows=arrows,
                 targets=targets, target_probability=probability, terminal_probability=terminal,
                 target_points=states.points[targets] + 0.01 * float(scale) * states.normals[targets])
