"""The guide: the optimal policy of the solved states as the bake's direction-sampling density.

At a path vertex with shading normal n and nearest compatible state s (same object, facing the
same side), GUIDED bakes draw ω from a one-sample mixture of the optimal policy and cosine
sampling,

    p(ω) = α g_s(ω) + (1 - α) max(cos θ, 0) / π,
    g_s(ω) = u*(k(ω) | s) · S / (2π)   for ω in stratum k of s's hemisphere, 0 below it,

where u*(k|s) is s's directional optimal policy (thesis eq. 2.23 per stratum,
``policy.stratum_policy``) and the S strata of s's Shirley–Chiu grid have solid angle 2π/S each
(equal-area map), so g_s is a normalised piecewise-constant density. A guide sample picks
stratum k by u*(·|s), then a uniform point of the stratum's cell of the unit square (uniform in
solid angle within the stratum). Directions below the shading point's own horizon get weight 0
while the pdf stays exact, so the estimator is unbiased for every α < 1 (α = 1 leaves strata
with u* = 0 unsampled). Vertices without a compatible state use cosine sampling (the choice
depends only on the vertex, so the pdf stays consistent). The texel's own vertex uses u* over
the surface states only (``columns='points'``: the light wanted there arrives after a bounce);
later vertices use ``'points+world'`` (emitters are covered by next-event estimation, the world
by escaping rays).

* :class:`StateGuide`: g_s as a table: ``sample`` and ``density`` (and the state lookup of
  surface points and ray hits);
* :func:`neighbour_average`: the rows of u* averaged over neighbouring states (denoising);
* :func:`build_guide`: the :class:`StateGuide` of a solved pipeline for a traced scene;
* :class:`CosineDirections` / :class:`GuidedDirections`: the tracer's direction sampling,
  ``sample(...) -> (ω, w = cos θ / (π p(ω)), cos θ)``, unguided or the mixture above.

The bake reuses the build's :class:`~lmdp_addon.model.locator.StateLocator` when the scene is
the one the states were sampled on (the same states, the same triangles).
"""
from dataclasses import dataclass, field

import numpy as np

from ..model.hemisphere import stratum_of_local_direction
from ..model.locator import StateLocator
from ..model.policy import stratum_policy
from ..sampling import concentric32, cosine_directions, dot, rotate_in, rotate_out, rows
from .checks import scene_fingerprint

INV_PI = 1.0 / np.pi
#: States whose optimal policies are averaged into each point's guide (:func:`neighbour_average`):
#: enough to average out the noise of the rays' estimates, few enough to stay local.
GUIDE_NEIGHBOURS = 16
#: Largest angle (degrees) between the normals of states whose guide rows are averaged
#: (:func:`neighbour_average`): curved and bumpy surfaces gain from mixing nearly equal normals,
#: flat ones are unaffected (their normals are equal).
NEIGHBOUR_MAX_ANGLE = 15.0


@dataclass
class StateGuide:
    """The optimal policy of the states as a sampling density g_s (module docstring).

    locator          :class:`~lmdp_addon.model.locator.StateLocator` of the states (nearest
                     compatible state point)
    frames           (m, 3, 3) float64 tangent frames of the states (rows t, b, n)
    first, later     (m, S) u*(k|s) for the texel vertex (columns 'points') and later vertices
                     ('points+world'); each row sums to 1
    strata_u, strata_v  the hemisphere grid of the states
    same_scene       True when the traced scene is the one the states were sampled on (then
                     triangle indices agree and front hits use the fast tabulated lookup)
    object_map       (O_traced,) int: the states' object index of each traced object (-1: none),
                     used when ``same_scene`` is False (objects matched by name)
    """

    locator: object
    frames: np.ndarray
    first: np.ndarray
    later: np.ndarray
    strata_u: int
    strata_v: int
    same_scene: bool = True
    object_map: np.ndarray = None
    cdf_first: np.ndarray = field(init=False, repr=False)
    cdf_later: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.frames = np.asarray(self.frames, dtype=np.float64)
        self.frames32 = self.frames.astype(np.float32)
        self.first = _normalised_rows(self.first)
        self.later = _normalised_rows(self.later)
        self.cdf_first = _row_cdf(self.first)
        self.cdf_later = _row_cdf(self.later)
        if self.n_strata > 32:   # fine tables: cut points of every row (:meth:`_fine_strata`)
            self.cut_first = _cut_points(self.cdf_first)
            self.cut_later = _cut_points(self.cdf_later)

    @property
    def n_strata(self):
        return self.strata_u * self.strata_v

    def states_at(self, positions, side_normals, objects):
        """Nearest compatible state of arbitrary surface points (exact tree query); -1 if none."""
        return locate_points(self.locator, self.object_map, positions, side_normals, objects)

    def states_at_hits(self, tri, bu, bv, positions, side_normals, front, objects):
        """Nearest compatible state of ray hits (-1: none): :func:`locate_hits`."""
        return locate_hits(self.locator, self.same_scene, self.object_map, tri, bu, bv, positions, side_normals,
                           front, objects)

    def sample(self, states, u, first, return_density=False):
        """World directions drawn from g_s for ``states (k,)`` with uniforms ``u (k, 2)``
        (and, with ``return_density``, g_s at them: u*(k|s) S / 2π of the chosen stratum)."""
        prob = self.first if first else self.later
        cdf = self.cdf_first if first else self.cdf_later
        S = self.n_strata
        if S <= 32:  # the stratum is the count of row entries <= u: one row gather, S compares
            k = np.minimum(np.count_nonzero(np.take(cdf, states, axis=0) <= u[:, 0:1], axis=1), S - 1)
        else:
            k = self._fine_strata(cdf, self.cut_first if first else self.cut_later, states, u[:, 0])
        flat = states * S + k
        lo = np.where(k > 0, np.take(cdf, flat - 1), 0.0)
        p = np.take(prob, flat)
        t = np.clip((u[:, 0] - lo) / np.where(p > 0, p, 1.0), 0.0, 1.0 - 1e-7)
        su = (k // self.strata_v + t) / self.strata_u
        sv = (k % self.strata_v + u[:, 1]) / self.strata_v
        x, y = concentric32(su, sv)
        r2 = x * x + y * y
        lift = np.sqrt(np.maximum(2.0 - r2, 0.0))
        # Equal-area lift of the disk to the hemisphere (hemisphere.py), then into s's frame.
        d = rotate_out(rows(self.frames32, states), x * lift, y * lift, 1.0 - r2)
        if return_density:
            return d, p * (S / (2.0 * np.pi))
        return d

    @staticmethod
    def _fine_strata(cdf, cut, states, u):
        """The first k with ``cdf[s, k] > u`` (the stratum of u under row s) for long rows, by the
        cut-point method (Chen & Asau): ``cut[s, j]`` is a k at or before the answer for every u
        in [j/S, (j+1)/S), and the search steps forward from there (about one step on average;
        a loop over steps, not rays)."""
        S = cdf.shape[1]
        flat_cdf = cdf.reshape(-1)
        base = states * S
        j = np.minimum((u * S).astype(np.int64), S - 1)
        k = np.take(cut, base + j).astype(np.int64)
        live = np.flatnonzero(np.take(flat_cdf, base + k) <= u)
        while len(live):
            k[live] += 1
            live = live[np.take(flat_cdf, base[live] + k[live]) <= u[live]]
        return np.minimum(k, S - 1)

    def density(self, states, directions, first):
        """g_s(ω) (k,) for world directions ``(k, 3)``: u*(k|s) S / 2π, 0 below s's horizon."""
        prob = self.first if first else self.later
        local = rotate_in(rows(self.frames32, states), np.asarray(directions, dtype=np.float32))
        k = stratum_of_local_direction(local, self.strata_u, self.strata_v)
        g = np.take(prob, states * self.n_strata + np.maximum(k, 0)) * (self.n_strata / (2.0 * np.pi))
        return np.where(k >= 0, g, 0.0)


def _normalised_rows(p):
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, None)
    s = p.sum(axis=1, keepdims=True)
    return np.where(s > 0, p / np.where(s > 0, s, 1.0), 1.0 / p.shape[1])


def _row_cdf(p):
    cdf = np.cumsum(p, axis=1)
    cdf[:, -1] = 1.0
    return cdf


def _cut_points(cdf):
    """(m, S) int32: per row s and bin j the number of CDF entries at or below j/S - 1e-9, a
    stratum at or before the one of every u in [j/S, (j+1)/S) (``StateGuide._fine_strata``);
    the rows shifted by s form one increasing array, so one binary search serves all rows."""
    m, S = cdf.shape
    shift = np.arange(m, dtype=np.float64)[:, None]
    offset = (cdf + shift).ravel()
    target = (np.arange(S) / S - 1e-9)[None, :] + shift
    return (np.searchsorted(offset, target.ravel(), side="right").reshape(m, S)
            - np.arange(m)[:, None] * S).clip(0, S - 1).astype(np.int32)


def locate_points(locator, object_map, positions, side_normals, objects):
    """Nearest compatible state of arbitrary surface points (exact tree query of ``locator``;
    ``object_map``: the states' object of each traced object, None: the same objects); -1 if none."""
    objects = np.asarray(objects)
    if len(objects) == 0:
        return np.zeros(0, dtype=np.int64)
    if object_map is not None:
        objects = np.where(objects >= 0, object_map[np.maximum(objects, 0)], -1)
    return locator.locate(np.asarray(positions, dtype=np.float64),
                          np.asarray(side_normals, dtype=np.float64), objects, workers=1)


def locate_hits(locator, same_scene, object_map, tri, bu, bv, positions, side_normals, front, objects):
    """Nearest compatible state of ray hits (-1: none).

    On the scene the states were sampled on (``same_scene``), only front hits on state-carrying
    triangles have one (the tabulated ``locate_front``): back faces and other geometry carry no
    states. On another scene every hit is looked up exactly (objects matched by name).
    """
    out = np.full(len(tri), -1, dtype=np.int64)
    if len(tri) == 0:
        return out
    if same_scene:
        carrier = front & (locator.gu[tri] > 0) if not locator.exact else front
        carrier = np.flatnonzero(carrier)
        if len(carrier):
            exact_positions = (rows(positions, carrier).astype(np.float64) if locator.exact else None)
            out[carrier] = locator.locate_front(tri[carrier], bu[carrier], bv[carrier], exact_positions, workers=1)
        return out
    return locate_points(locator, object_map, positions, side_normals, objects)


def neighbour_average(rows, locator, normals, neighbours, max_angle=None):
    """Mean of the per-stratum distributions ``rows (m, S)`` (or several side by side, (m, n S):
    the mean is taken per column) over each point's ``neighbours`` nearest points (``locator``'s
    6-D distance, same object) whose normal is within ``max_angle`` degrees of its own
    (default :data:`NEIGHBOUR_MAX_ANGLE`) and on the same side of the horizontal (below).

    u*(k|x) comes from ``R`` rays per stratum (thesis eq. 3.1), so a point's row is a Monte Carlo
    estimate whose noise easily exceeds the differences between neighbouring points. Points with
    the same normal have the same tangent frame (``hemisphere.tangent_frame``), hence the same
    strata, and the mean of their rows is again a distribution over those strata: a guide
    estimated from ``neighbours`` x as many rays. Points whose normals differ by a few degrees
    (curved or bumpy surfaces) have strata turned by about as much; their mean is a slightly
    blurred guide. The frame jumps where a normal's z changes sign (Duff et al.'s branch), so
    points on either side are never mixed. Any rows keep the guided estimator unbiased (the pdf
    is evaluated from the same table it is sampled from); only its variance changes. Points with
    no such neighbour keep their row.
    """
    rows = np.asarray(rows, dtype=np.float64)
    out = rows.copy()
    for ids, near, w in neighbour_weights(locator, normals, neighbours, max_angle):
        out[ids] = np.einsum("ik,iks->is", w, rows[near])
    return out


def neighbour_weights(locator, normals, neighbours, max_angle=None):
    """The averaging of :func:`neighbour_average`, one object at a time: ``(ids (n_o,),
    near (n_o, k), w (n_o, k))``, the mean of point ``ids[i]``'s row being
    ``Σ_j w[i, j] row[near[i, j]]`` (objects whose points keep their rows are left out)."""
    if neighbours <= 1:
        return
    cos_max = np.cos(np.radians(NEIGHBOUR_MAX_ANGLE if max_angle is None else max_angle))
    for o, tree in locator.trees.items():  # loop over objects, not points
        ids = locator.index[o]
        k = min(int(neighbours), len(ids))
        if k <= 1:
            continue
        _, nn = tree.query(tree.data, k=k, workers=1)
        near = ids[nn]                                                   # (n_o, k)
        close = np.einsum("ij,ikj->ik", normals[ids], normals[near]) >= cos_max
        branch = (normals[ids, 2] >= 0.0)[:, None] == (normals[near, 2] >= 0.0)
        same = close & branch
        yield ids, near, same / same.sum(axis=1, keepdims=True)          # self is always in


def guide_frame(scene, lmdp):
    """``(locator, object_map, same_scene)`` of a guide of ``lmdp``'s states for tracing ``scene``
    (:func:`build_guide`)."""
    same = scene_fingerprint(scene) == scene_fingerprint(lmdp.scene)
    locator = lmdp.dynamics.locator
    if locator is None:
        locator = StateLocator(lmdp.scene, lmdp.states)
    object_map = None
    if not same:
        lookup = {n: i for i, n in enumerate(lmdp.scene.object_names)}
        object_map = np.array([lookup.get(n, -1) for n in scene.object_names], dtype=np.int64)
    return locator, object_map, same


def build_guide(scene, lmdp, fine=False, seed=0, paths=None, table_rays=None):
    """:class:`StateGuide` of the solved states for tracing ``scene``.

    ``lmdp``: anything with ``scene``, ``states``, ``dynamics``, ``solution``. The build's
    locator (``dynamics.locator``) serves when it has one: the same states on the same scene;
    otherwise the states get a locator of their own. On another scene than the states' one,
    objects are matched by name (``object_map``). ``fine`` (GUIDED bakes) with a PHYSICAL
    solution: the fine guide of :mod:`~lmdp_addon.bake.fine_guide` (G x G cells of the light
    arriving at each state, traced with ``seed``, G from the bake's ``paths`` and ``table_rays``
    per path); otherwise
    u*(k|s) over the solve's strata.
    """
    if fine and lmdp.solution.cost_mode == "PHYSICAL":
        from .fine_guide import build_fine_guide     # it builds on this module's StateGuide
        return build_fine_guide(scene, lmdp, seed=seed, paths=paths, rays_per_path=table_rays)
    locator, object_map, same = guide_frame(scene, lmdp)
    # Both policies side by side: one neighbour search averages them (the mean is per column).
    S = lmdp.states.n_strata
    both = neighbour_average(np.hstack([stratum_policy(lmdp.dynamics, lmdp.solution, "points"),
                                        stratum_policy(lmdp.dynamics, lmdp.solution, "points+world")]),
                             locator, lmdp.states.normals, GUIDE_NEIGHBOURS)
    return StateGuide(locator=locator, frames=lmdp.states.frames, first=both[:, :S], later=both[:, S:],
                      strata_u=lmdp.states.strata_u, strata_v=lmdp.states.strata_v, same_scene=same,
                      object_map=object_map)


# ---- the tracer's direction sampling ----------------------------------------------------------------

class CosineDirections:
    """UNGUIDED direction sampling: ``p(ω) = cos θ / π``, so ``w = 1``."""

    guide = None

    def sample(self, normals, states, u, u_mix, first):
        """Directions ``d (k, 3)`` float32, weights ``w = cos θ / (π p(d)) (k,)`` and ``cos θ``
        about ``normals (k, 3)`` float32 (``states``, ``u_mix`` unused). ``first``: the texel's
        stratified first bounce (concentric map), otherwise the polar map."""
        d = cosine_directions(normals, u, stratified=first)
        return d, np.ones(len(normals), np.float32), dot(normals, d)

    def density(self, normals, states, directions, first):
        """p(ω) = max(cos θ, 0) / π (k,) of :meth:`sample` for ``directions (k, 3)``."""
        return np.maximum(dot(normals, directions).astype(np.float64), 0.0) * INV_PI


class GuidedDirections:
    """GUIDED direction sampling: the one-sample mixture ``p = α g_s + (1 - α) cos/π`` of the
    guide ``guide`` (:class:`StateGuide`) and cosine sampling, α = ``fraction`` (module
    docstring); vertices with no state (``states < 0``) sample the cosine lobe alone."""

    def __init__(self, guide, fraction):
        self.guide = guide
        self.fraction = fraction

    def sample(self, normals, states, u, u_mix, first):
        """Directions ``d (k, 3)`` float32, weights ``w = cos θ / (π p(d))`` (k,) float32 and
        ``cos θ`` (k,) float64 at vertices with normals ``normals (k, 3)`` float32 and nearest
        states ``states (k,)`` (-1: none); ``u (k, 2)`` the direction's uniforms, ``u_mix (k,)``
        the choice between guide and cosine, ``first``: the texel's vertex (u* over 'points')."""
        has = states >= 0
        guided = has & (u_mix < self.fraction)
        use_guide = np.flatnonzero(guided)
        cos_sel = np.flatnonzero(~guided)
        d = np.empty((len(normals), 3), np.float32)
        g = np.zeros(len(normals))
        if len(cos_sel):
            d[cos_sel] = cosine_directions(rows(normals, cos_sel), rows(u, cos_sel), stratified=first)
        if len(use_guide):
            d[use_guide], g[use_guide] = self.guide.sample(states[use_guide], rows(u, use_guide), first,
                                                           return_density=True)
        # g_s of the cosine-drawn directions needs their stratum in s's frame; the guide-drawn
        # ones know theirs. The mixture pdf of every direction: α g + (1 - α) cos/π.
        other = np.flatnonzero(has & ~guided)
        if len(other):
            g[other] = self.guide.density(states[other], rows(d, other), first)
        cos = dot(normals, d).astype(np.float64)
        pdf = self._mixture(has, g, cos)
        w = np.where((cos > 0) & (pdf > 0), cos * INV_PI / np.where(pdf > 0, pdf, 1.0), 0.0)
        return d, w.astype(np.float32), cos

    def _mixture(self, has, g, cos):
        """α g + (1 - α) max(cos, 0) / π where a vertex has a state (``has``), else the cosine
        density alone."""
        c = np.maximum(cos, 0.0) * INV_PI
        return np.where(has, self.fraction * g + (1.0 - self.fraction) * c, c)

    def density(self, normals, states, directions, first):
        """The mixture's p(ω) (k,) of :meth:`sample` for ``directions (k, 3)`` at vertices with
        normals ``normals`` and states ``states`` (-1: the cosine lobe alone)."""
        has = states >= 0
        g = np.zeros(len(normals))
        h = np.flatnonzero(has)
        if len(h):
            g[h] = self.guide.density(states[h], rows(directions, h), first)
        return self._mixture(has, g, dot(normals, directions).astype(np.float64))
