"""World portals: the environment map's light samples sent where the baked surfaces see the world.

Under an HDRI every path vertex y samples the world by the map's radiance (``world``: a pixel
with probability ∝ L sin θ, a shadow ray to infinity). Inside a room lit through its openings
most of those directions end on a wall, so the world's light at y is a rare success times a
large weight (docs/design.md, "World portals", has the measurements). The openings are where
the world is seen from; this module learns them and samples the map there (issue 20, "openings
as portals"), with no geometry given by the user:

* the map is cut into blocks of pixels (:func:`block_shape`: up to :data:`BLOCKS_U` x
  :data:`BLOCKS_V`, equal in u and v);
* a **probe** (:class:`PortalProbe`) of a few thousand unguided paths from the baked texels records
  each world sample of its vertices: the block b it fell in, the object of the vertex (its region
  r) and the sample's estimate ``y = β L cos θ / (π p)`` (0 when the shadow ray is blocked; β the
  path's throughput, so vertices weigh by what they carry to the texels);
* the bake then draws a block with

      P_r(b) = (1 − δ) P(b) √M_r(b) / Σ_b' P(b') √M_r(b') + δ P(b),                   (1)

  and a pixel within it by the map as before, so its density is

      p_r(ω) = p(ω) P_r(b(ω)) / P(b(ω)).                                             (2)

  P(b) is the map's own probability of block b and M_r(b) the mean of y² over the probe's
  samples in b from region r (shrunk towards the all-vertex mean with :data:`PRIOR` samples'
  weight; regions with fewer than :data:`MIN_REGION_SAMPLES` samples use that mean). For a
  one-sample estimate the choice P_r(b) ∝ P(b) √M_r(b) minimises its second moment over the
  blocks' probabilities (Lagrange: Σ_b M_r(b) P(b)² / P_r(b) under Σ P_r = 1); blocks the
  vertices never see drop to the defensive share δ = :data:`DEFENSIVE`.

Every direction the map can draw keeps p_r >= δ p, so the bake is unbiased whatever the probe
saw, and the world sample's second moment is at most 1/δ the map's. The tracer evaluates (2)
for the rays its BSDF sampling sends to the world too (the balance heuristic's partner,
``world.escape_weight``), with the region of the vertex each ray left. The probe draws its own
random numbers (a seed of its own), so the bake is as deterministic for a seed as before.
"""
import threading
from dataclasses import dataclass, field

import numpy as np

#: Blocks of the map along u (azimuth) and v (elevation): a 1024 x 512 map gets 32 x 32 pixels
#: per block (side bench, sun + HDRI, 1024 probe paths: 16 x 8 / 32 x 16 / 64 x 32 blocks gave
#: variance per path 0.246 / 0.241 / 0.237 against the map's 0.304).
BLOCKS_U = 32
BLOCKS_V = 16
#: δ of eq. 1: the map's own share of every block (0.1 / 0.2 gave 0.236 / 0.241 in that bench).
DEFENSIVE = 0.2
#: Weight, in samples, of the all-vertex mean a region's block mean is shrunk towards.
PRIOR = 8.0
#: Fewest probe samples from one object for it to get block probabilities of its own.
MIN_REGION_SAMPLES = 256
#: Fewest probe samples that saw the world for any portals at all: a small window seen by 1 % of
#: the map's samples left 20 of 2143 (a room lit by a constant map through a 0.3 m window), and
#: the tables learned from them raised the variance per path from 72 to 86 (77 with 5288 samples,
#: 71 with 10 824): too few to tell the window's blocks from the rest.
MIN_VISIBLE = 256
#: Paths of a probe (a bake that is not AUTO runs one; AUTO's unguided pilot is its probe):
#: every k-th texel of the baked objects, :data:`PROBE_SAMPLES` samples each.
PROBE_PATHS = 2048
PROBE_SAMPLES = 4


def triangle_groups(scene):
    """``(groups (T,) int64, n)``: the group of each scene triangle, its object and the axis
    nearest to its normal (±x, ±y, ±z): the vertices of one group see the world through about
    the same openings (the walls of one room mesh face different ways)."""
    normals = scene.triangle_geometry()[0]
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.take_along_axis(normals, axis[:, None], axis=1)[:, 0] < 0
    groups = scene.triangle_object.astype(np.int64) * 6 + axis * 2 + sign
    return groups, 6 * len(scene.object_names)


def block_shape(height, width):
    """``(B_v, B_u)``: the blocks of a ``height`` x ``width`` map."""
    return min(BLOCKS_V, int(height)), min(BLOCKS_U, int(width))


def pixel_blocks(height, width):
    """(H W,) int64 block of each row-major pixel: ``(i B_v // H) B_u + j B_u // W``."""
    bv, bu = block_shape(height, width)
    row = np.arange(height, dtype=np.int64) * bv // height
    col = np.arange(width, dtype=np.int64) * bu // width
    return (row[:, None] * bu + col[None, :]).ravel()


class PortalProbe:
    """Sums of the probe's world samples: ``squares (1 + groups, blocks)`` of y² and
    ``counts`` (row 0 all vertices, row 1 + g those on triangles of group g,
    :func:`triangle_groups`). Thread-safe; the tracer hands :meth:`recorder` to
    ``world.next_event``."""

    def __init__(self, scene):
        environment = scene.environment
        self.environment = environment
        self.blocks = pixel_blocks(environment.height, environment.width)
        self.n_blocks = int(np.prod(block_shape(environment.height, environment.width)))
        self.groups, self.n_groups = triangle_groups(scene)
        self.squares = np.zeros((1 + self.n_groups, self.n_blocks))
        self.counts = np.zeros((1 + self.n_groups, self.n_blocks))
        self.visible = 0
        self._lock = threading.Lock()

    def recorder(self, triangles, beta_luminance):
        """``record(rows, directions, values)`` for ``world.next_event`` at vertices on
        ``triangles`` (k,) with throughput luminances ``beta_luminance`` (k,)."""
        def record(rows, directions, values):
            env = self.environment
            u, v = env.map_uv(directions)
            block = self.blocks[env.pixel_of_uv(u, v)]
            y2 = np.square(np.take(beta_luminance, rows).astype(np.float64) * values)
            at = np.take(self.groups, np.take(triangles, rows)) + 1
            size = self.counts.size
            flat = np.concatenate([block, at * self.n_blocks + block])
            s = np.bincount(flat, weights=np.concatenate([y2, y2]), minlength=size)
            c = np.bincount(flat, minlength=size)
            seen = int(np.count_nonzero(values))
            with self._lock:
                self.squares += s.reshape(self.squares.shape)
                self.counts += c.reshape(self.counts.shape)
                self.visible += seen
        return record

    @property
    def samples(self):
        return int(self.counts[0].sum())


@dataclass
class Portals:
    """What a probe learned (small and plain, so a bake farm's workers get it with the recipe):
    ``table (R, blocks)`` eq. 1's block probabilities per region (row 0 all vertices) and
    ``region_of_group (groups,)`` the row of each :func:`triangle_groups` group."""

    table: np.ndarray
    region_of_group: np.ndarray
    info: dict = field(default_factory=dict)
    _samplers: dict = field(default_factory=dict, repr=False, compare=False)

    def sampler(self, environment):
        """The :class:`PortalSampler` of ``environment`` with these tables (made once)."""
        key = id(environment)
        if key not in self._samplers:
            self._samplers[key] = PortalSampler(environment, self.table)
        return self._samplers[key]

    def regions(self, scene):
        """(T,) int64 the table row of each triangle of ``scene`` (None: one row for all)."""
        if len(self.table) == 1:
            return None
        return np.take(self.region_of_group, triangle_groups(scene)[0])

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_samplers"] = {}
        return state


def learn(probe):
    """:class:`Portals` of a :class:`PortalProbe` (eq. 1), or None when fewer than
    :data:`MIN_VISIBLE` of its samples saw the world."""
    env = probe.environment
    mass = np.bincount(probe.blocks, weights=env.pixel_prob, minlength=probe.n_blocks)
    S, N = probe.squares, probe.counts
    if probe.visible < MIN_VISIBLE or S[0].sum() <= 0:
        return None
    overall = np.where(N[0] > 0, S[0] / np.maximum(N[0], 1), 0.0)
    enough = N[1:].sum(axis=1) >= MIN_REGION_SAMPLES
    region_of_group = np.zeros(probe.n_groups, np.int64)
    region_of_group[enough] = 1 + np.arange(int(enough.sum()))
    rows = [overall] + [(S[1 + o] + PRIOR * overall) / (N[1 + o] + PRIOR) for o in np.flatnonzero(enough)]
    table = np.empty((len(rows), probe.n_blocks))
    for r, m in enumerate(rows):
        score = mass * np.sqrt(m)
        total = score.sum()
        table[r] = ((1.0 - DEFENSIVE) * score / total + DEFENSIVE * mass) if total > 0 else mass
    info = {"probe_samples": int(N[0].sum()), "probe_visible": probe.visible / float(N[0].sum()),
            "regions": int(len(rows)), "blocks": int(probe.n_blocks)}
    return Portals(table=table, region_of_group=region_of_group, info=info)


class PortalSampler:
    """The environment map's light drawn with per-region block probabilities ``table (R, B)``
    (eq. 1-2): ``sample(r, regions)`` and ``pdf(directions, regions)`` as
    :meth:`~lmdp_addon.world.EnvironmentMap.sample` / ``pdf`` (``regions`` (k,) rows of the
    table, None: row 0), ``radiance_at`` the map's own."""

    def __init__(self, environment, table):
        env = self.environment = environment
        self.lit = environment.lit
        self.radiance_at = environment.radiance_at
        blocks = self.blocks = pixel_blocks(env.height, env.width)
        nb = int(np.prod(block_shape(env.height, env.width)))
        self.n_blocks = nb
        self.order = np.argsort(blocks, kind="stable")           # pixels block by block
        self.cumulative = np.cumsum(env.pixel_prob[self.order])
        self.mass = np.bincount(blocks, weights=env.pixel_prob, minlength=nb)
        self.first = np.concatenate([[0], np.cumsum(np.bincount(blocks, minlength=nb))])
        self.start = np.concatenate([[0.0], np.cumsum(self.mass)])[:-1]
        table = np.where(self.mass[None, :] > 0, np.asarray(table, dtype=np.float64), 0.0)
        table /= np.maximum(table.sum(axis=1, keepdims=True), 1e-300)
        self.table = table
        self.ratio = np.where(self.mass > 0, table / np.maximum(self.mass, 1e-300), 0.0).astype(np.float32)
        cdf = np.cumsum(table, axis=1)
        cdf[:, -1] = 1.0
        self.cdf = cdf
        self.flat_cdf = (cdf + np.arange(len(table))[:, None]).ravel()

    def sample(self, r, regions=None):
        """``(directions (k, 3) float32, pdf (k,) float32, radiance (k, 3) float32)`` of
        uniforms ``r (k, 3)``: r[:, 0] chooses the block (eq. 1) and, rescaled within the
        block's share, the pixel in it by the map; r[:, 1:] the point in the pixel."""
        r = np.asarray(r)
        k = len(r)
        if not self.lit or k == 0:
            return np.zeros((k, 3), np.float32), np.zeros(k, np.float32), np.zeros((k, 3), np.float32)
        nb = self.n_blocks
        reg = np.zeros(k, np.int64) if regions is None else np.asarray(regions, dtype=np.int64)
        u0 = r[:, 0].astype(np.float64)
        b = np.clip(np.searchsorted(self.flat_cdf, reg + u0, side="right") - reg * nb, 0, nb - 1)
        below = np.where(b > 0, self.cdf[reg, np.maximum(b - 1, 0)], 0.0)
        share = self.table[reg, b]
        within = np.clip((u0 - below) / np.maximum(share, 1e-300), 0.0, 1.0)
        target = self.start[b] + within * self.mass[b]
        order = np.argsort(target)     # searched in increasing order: the searches share cache lines
        at = np.empty(k, np.int64)
        at[order] = np.searchsorted(self.cumulative, target[order], side="right")
        at = np.clip(at, self.first[b], self.first[b + 1] - 1)
        d, p, L, _ = self.environment.pixel_directions(self.order[at], r[:, 1], r[:, 2])
        return d, (p * self.ratio[reg, b]).astype(np.float32), L

    def pdf(self, directions, regions=None):
        """(k,) float32 density per steradian of :meth:`sample` at world ``directions (k, 3)``
        from vertices of ``regions`` (eq. 2)."""
        env = self.environment
        u, v = env.map_uv(directions)
        pixel = env.pixel_of_uv(u, v)
        reg = 0 if regions is None else np.asarray(regions, dtype=np.int64)
        return (env._pdf_uv(u, v, pixel) * self.ratio[reg, self.blocks[pixel]]).astype(np.float32)
