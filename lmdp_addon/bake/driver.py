"""Texture baking: indirect diffuse light of the selected meshes into lightmaps, texel for texel
like Cycles' ``bake(type='DIFFUSE', pass_filter={'INDIRECT'})``.

For every baked object: its texels at ``bake_resolution`` (``texels.rasterize_texels``: Cycles'
mapping of its UV map), ``bake_samples`` paths per texel started at points of the texel's
footprint (``texels.sample_footprint``: sample 0 the texel point, the others jittered in Cycles'
half-pixel box), each traced by :class:`~lmdp_addon.bake.tracer.IndirectTracer`, averaged, and the
``bake_margin`` filled by ``texels.dilate`` (Cycles' EXTEND margin).

The samples of a texel are split into B independent *batches* (B = the largest divisor of the
sample count up to 8). Inside a batch the first direction is stratified: sample j of n uses the
Hammersley point ``((j + ½)/n, radical_inverse₂(j))`` of the unit square shifted by a random
offset per texel and batch (Cranley–Patterson rotation), and ``frac(j/φ + s)`` chooses between
guide and cosine sampling. Every batch mean is therefore an unbiased estimate on its own, the B
batch means are independent, and their spread gives each texel's standard error
(``ObjectBake.standard_error``) without assuming anything about the estimator's variance.

Work is cut into equal units of at most about :data:`PATHS_PER_UNIT` paths (bounded memory): a
unit is a range of texels in one batch or, when a whole batch of all texels is smaller than that,
several whole batches (:func:`work_units`). Unit u of object o whose first batch is b draws its
random numbers from ``default_rng([seed, o, b, u])``, so a bake is deterministic for a seed
whatever the thread scheduling. Units run on a small thread pool
(embree and numpy release the GIL); ``progress.update`` between units raises ``Cancelled`` when
the user asked to stop, and nothing is returned.
"""
import hashlib
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np

from ..model.locator import StateLocator
from ..errors import SceneError, StageOrderError
from ..model.policy import stratum_policy
from ..progress import Progress
from ..raycast import RayCaster
from ..settings import BAKE_MODES
from ..model.states import GOLDEN
from .texels import dilate, rasterize_texels, sample_footprint
from .tracer import GatherField, IndirectTracer, StateGuide, TraceStats, neighbour_average

#: Most paths traced by one work unit (memory: ~0.5 KiB per path in flight, so ~64 MiB per
#: unit). Larger units amortise the per-bounce Python overhead of the wavefront loop (measured on
#: 2 cores, 64 samples: 2^17 paths per unit bakes the narrow opening's floor ~20 % faster than
#: 2^16, the Cornell floor ~5 %).
PATHS_PER_UNIT = 1 << 17
#: Work units in flight (the machine's cores; embree and numpy release the GIL).
BAKE_THREADS = 2
#: Most independent batches per texel (for the standard error).
MAX_BATCHES = 8
#: States whose optimal policies are averaged into each point's guide (``tracer.neighbour_average``):
#: measured on the Cornell box floor (2048 points, 64 samples, 6 seeds), GUIDED's variance per
#: sample relative to UNGUIDED's is 1.11 with 1, 0.99 with 16, 0.98 with 32 and 1.11 with 128.
GUIDE_NEIGHBOURS = 16
#: Most texels (summed over objects) whose rasterisation ``check_bake_inputs`` keeps for the bake
#: (120 B each, 120 MiB at the limit); objects beyond it are rasterised again in turn.
TEXEL_CACHE_LIMIT = 1 << 20
#: Suffix of the images the add-on writes.
IMAGE_SUFFIX = "_lmdp_indirect"


@dataclass
class ObjectBake:
    """The lightmap of one object.

    name            object name; the image is ``name + IMAGE_SUFFIX``
    texels          :class:`~lmdp_addon.bake.texels.TexelSet` (covered texels, Cycles' mapping)
    triangles       (T_o,) the scene triangle of each of the object's local triangle indices
    value           (n, 3) float32 estimate of E_ind/π per covered texel (W / sr m²)
    standard_error  (n, 3) float32 standard error of ``value`` from the batch means (NaN for 1 batch)
    image           (R, R, 4) float32 RGBA, margin filled, alpha 1 where filled; row 0 = bottom
    samples         paths per texel; batches: independent batches they were split into
    stats           :class:`~lmdp_addon.bake.tracer.TraceStats`
    seconds         wall time of this object's bake
    """

    name: str
    texels: object
    triangles: np.ndarray
    value: np.ndarray
    standard_error: np.ndarray
    image: np.ndarray
    samples: int
    batches: int
    stats: TraceStats
    seconds: float

    @property
    def image_name(self):
        return self.name + IMAGE_SUFFIX

    @property
    def n_texels(self):
        return len(self.texels)

    @property
    def resolution(self):
        return self.texels.resolution


@dataclass
class BakeResult:
    """Lightmaps of the baked objects plus what produced them (``bake_stats.json``)."""

    mode: str
    objects: list
    settings: dict
    seconds: dict = field(default_factory=dict)   #: stage -> wall time: sample, build, solve, bake
    warnings: list = field(default_factory=list)
    guide_info: dict = field(default_factory=dict)

    @property
    def n_texels(self):
        return sum(o.n_texels for o in self.objects)

    def object(self, name):
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(name)

    def summary(self):
        rays = sum(o.stats.total_rays for o in self.objects)
        secs = sum(o.seconds for o in self.objects)
        return (f"{self.mode} bake of {len(self.objects)} object(s), {self.n_texels} texels x "
                f"{self.settings.get('bake_samples')} samples, {rays} rays in {secs:.2f} s")

    def stats(self):
        """Plain dict for ``bake_stats.json``."""
        objects = {}
        for o in self.objects:
            rays = o.stats.total_rays
            objects[o.name] = {
                "image": o.image_name,
                "resolution": o.resolution,
                "texels": o.n_texels,
                "samples": o.samples,
                "batches": o.batches,
                "paths": o.stats.paths,
                "rays": rays,
                "closest_hit_rays": o.stats.rays,
                "shadow_rays": o.stats.shadow_rays,
                "rays_per_second": rays / o.seconds if o.seconds > 0 else None,
                "trace": o.stats.as_dict(),
                "mean": [float(x) for x in o.value.mean(axis=0)] if o.n_texels else [0.0, 0.0, 0.0],
                "mean_relative_standard_error": _relative_error(o),
                "seconds": {**{k: v for k, v in self.seconds.items() if k != "bake"}, "bake": o.seconds},
            }
        return {
            "mode": self.mode,
            "settings": dict(self.settings),
            "seconds": dict(self.seconds),
            "guide": dict(self.guide_info),
            "objects": objects,
            "warnings": list(self.warnings),
        }


def _relative_error(o):
    """RMS standard error over the texels divided by the mean value (luminance-free: all channels)."""
    if o.n_texels == 0 or not np.all(np.isfinite(o.standard_error)):
        return None
    mean = float(o.value.mean())
    return float(np.sqrt(np.mean(o.standard_error.astype(np.float64) ** 2)) / mean) if mean > 0 else None


# -- texels and input checks ---------------------------------------------------------------------

def object_index(scene, name):
    try:
        return scene.object_names.index(name)
    except ValueError:
        raise SceneError(f"Object '{name}' is not part of the captured scene (is it hidden?)") from None


def object_texels(scene, index, resolution, reverse=False):
    """Texels of object ``index`` at ``resolution``: ``(TexelSet, triangles (T_o,))``.

    ``triangles`` maps the TexelSet's local triangle indices to the scene's triangles. With
    ``reverse`` the triangles are rasterised in reverse order (used to detect overlaps).
    """
    tris = np.flatnonzero(scene.triangle_object == index)
    if reverse:
        tris = tris[::-1]
    normals, _ = scene.triangle_geometry()
    ts = rasterize_texels(scene.triangle_uv[tris], scene.corners()[tris], normals[tris], resolution)
    return ts, tris


def uv_overlaps(scene, index, resolution, forward=None):
    """Texels whose centre two or more of the object's UV triangles cover: ``(count, (row, col))``.

    Rasterising in both triangle orders (the last triangle wins a texel, like Blender) gives a
    different triangle exactly where several cover the same texel centre; shared edges cover a
    centre once, so adjacent triangles never count. ``forward``: ``object_texels(scene, index,
    resolution)`` if the caller has it already.
    """
    a, ta = forward if forward is not None else object_texels(scene, index, resolution)
    b, tb = object_texels(scene, index, resolution, reverse=True)
    differs = ta[a.triangle] != tb[b.triangle]
    count = int(np.count_nonzero(differs))
    example = (int(a.row[differs][0]), int(a.col[differs][0])) if count else None
    return count, example


def scene_fingerprint(scene):
    """Hash of the geometry, materials, world and object names of a SceneArrays (not the selection)."""
    h = hashlib.blake2b(digest_size=16)
    for array in (scene.vertices, scene.triangles, scene.triangle_object, scene.triangle_albedo,
                  scene.triangle_emission, scene.triangle_emission_two_sided, scene.world_radiance):
        h.update(np.ascontiguousarray(array).tobytes())
    h.update("\0".join(scene.object_names).encode())
    return h.hexdigest()


def check_bake_inputs(scene, names, settings, lmdp=None, will_solve=False, texels=None):
    """Raise :class:`SceneError` / :class:`StageOrderError` (user messages) before any work.

    Checks: resolution and samples >= 1, the mode, every object has a UV map, covers at least one
    texel and has no overlapping UVs, the scene has light, GUIDED / FINAL_GATHER have a solution
    and FINAL_GATHER a PHYSICAL one of this very scene. ``will_solve``: the caller solves this
    scene with ``settings`` before baking (Run All), so only the cost mode is checked. Returns the
    warnings to show. ``texels``: a dict that receives the checked objects' ``object_texels``
    under ``(index, resolution)``, up to ``TEXEL_CACHE_LIMIT`` texels in all (the bake reuses
    them instead of rasterising again).
    """
    warnings = []
    mode = settings.bake_mode
    if mode not in BAKE_MODES:
        raise SceneError(f"Unknown bake mode {mode!r}: use one of {', '.join(BAKE_MODES)}")
    R = int(settings.bake_resolution)
    if R < 1:
        raise SceneError(f"Bake resolution must be at least 1 pixel (got {R}): set LMDP > Bake > Resolution")
    if int(settings.bake_samples) < 1:
        raise SceneError(f"Bake samples must be at least 1 (got {settings.bake_samples}): set LMDP > Bake > Samples")
    if int(settings.max_bounces) < 1:
        raise SceneError(f"Max bounces must be at least 1 for indirect light (got {settings.max_bounces})")
    if not names:
        raise SceneError("Select at least one mesh object to bake")
    indices = [object_index(scene, n) for n in names]
    no_uv = [n for n, i in zip(names, indices) if not scene.object_has_uv[i]]
    if no_uv:
        raise SceneError(f"No UV map on {', '.join(no_uv)}: add one (UV > Smart UV Project or "
                         "Lightmap Pack) or deselect them; the lightmap is laid out by the UV map")
    empty, overlapping = [], []
    for n, i in zip(names, indices):
        forward = object_texels(scene, i, R)
        if texels is not None and (sum(len(t) for t, _ in texels.values()) + len(forward[0])
                                   <= TEXEL_CACHE_LIMIT):
            texels[(i, R)] = forward
        count, example = uv_overlaps(scene, i, R, forward)
        ts, _ = forward
        if len(ts) == 0:
            empty.append(n)
        elif count:
            overlapping.append(f"{n} ({count} texels, e.g. column {example[1]}, row {example[0]})")
    if empty:
        raise SceneError(f"The UV map of {', '.join(empty)} covers no texel centre of a {R} x {R} "
                         "image (UVs outside [0, 1] or degenerate): unwrap into the unit square")
    if overlapping:
        raise SceneError(f"Overlapping UVs on {'; '.join(overlapping)}: several faces share these "
                         f"texels of the {R} x {R} lightmap. Give each face its own area "
                         "(UV > Lightmap Pack, or Smart UV Project) and bake again")
    if not scene.has_light():
        raise SceneError("The scene has no light to bake: add an emissive material (Emission "
                         "shader or Principled emission), an area light, or a non-black world")
    if will_solve:
        if mode == "FINAL_GATHER" and settings.cost_mode != "PHYSICAL":
            raise SceneError("Final Gather reads the outgoing radiance z of the PHYSICAL cost mode: "
                             f"set Cost Mode to Physical (it is {settings.cost_mode}), or bake with "
                             "Guided or Unguided")
    elif mode in ("GUIDED", "FINAL_GATHER"):
        if lmdp is None or lmdp.solution is None:
            raise StageOrderError(f"Solve first (LMDP panel > Solve): {mode} bakes are guided by "
                                  "the optimal policy of the solved states; or use bake mode Unguided")
        same = scene_fingerprint(scene) == scene_fingerprint(lmdp.scene)
        if mode == "FINAL_GATHER":
            if lmdp.solution.cost_mode != "PHYSICAL":
                raise SceneError("Final Gather reads the outgoing radiance z of the PHYSICAL cost "
                                 f"mode, but the solution was computed in {lmdp.solution.cost_mode} "
                                 "mode: set Cost Mode to Physical and run the pipeline again")
            if not same:
                raise SceneError("The scene changed since the states were sampled: Final Gather would "
                                 "read the old solution at the new surfaces. Run the pipeline again "
                                 "(LMDP > Run All), or bake with Guided or Unguided")
        elif not same:
            warnings.append("The scene changed since the states were sampled: the bake traces the "
                            "current scene, guided by the old optimal policy (still unbiased, but "
                            "less effective). Run the pipeline again for the best guide")
        carried = set(np.asarray(lmdp.scene.object_names)[lmdp.states.point_object].tolist())
        unguided = [n for n in names if n not in carried]
        if unguided:
            warnings.append(f"No states on {', '.join(unguided)}: their texels start with cosine "
                            "sampling (select them when sampling to guide them too)")
    if mode == "GUIDED" and float(settings.guide_fraction) >= 1.0:
        warnings.append("Guide fraction 1 never samples the cosine lobe: the bake is biased where "
                        "the optimal policy is zero; a value below 1 keeps it unbiased")
    return warnings


# -- guide ------------------------------------------------------------------------------------

def build_guide(scene, lmdp):
    """:class:`StateGuide` of the solved states for tracing ``scene`` (see ``tracer``)."""
    same = scene_fingerprint(scene) == scene_fingerprint(lmdp.scene)
    locator = getattr(lmdp.dynamics, "locator", None)  # the build's own (same states, same scene)
    if locator is None:
        locator = StateLocator(lmdp.scene, lmdp.states)
    object_map = None
    if not same:
        lookup = {n: i for i, n in enumerate(lmdp.scene.object_names)}
        object_map = np.array([lookup.get(n, -1) for n in scene.object_names], dtype=np.int64)
    # Both policies side by side: one neighbour search averages them (the mean is per column).
    S = lmdp.states.n_strata
    both = neighbour_average(np.hstack([stratum_policy(lmdp.dynamics, lmdp.solution, "points"),
                                        stratum_policy(lmdp.dynamics, lmdp.solution, "points+world")]),
                             locator, lmdp.states.normals, GUIDE_NEIGHBOURS)
    guide = StateGuide(
        locator=locator,
        frames=lmdp.states.frames,
        first=both[:, :S],
        later=both[:, S:],
        strata_u=lmdp.states.strata_u,
        strata_v=lmdp.states.strata_v,
        same_scene=same,
        object_map=object_map,
    )
    return guide


#: Rays per state point of :func:`direct_after_one_bounce`: ``GATHER_RAY_BUDGET`` rays in all,
#: between ``GATHER_RAYS_MIN`` and ``GATHER_RAYS_MAX`` per point (squares: a stratified grid).
GATHER_RAY_BUDGET = 1 << 18
GATHER_RAYS_MIN = 9
GATHER_RAYS_MAX = 64


def gather_rays_per_point(n_points):
    """Rays per point of :func:`direct_after_one_bounce`: a square, about the budget / points."""
    side = int(np.sqrt(max(GATHER_RAY_BUDGET // max(int(n_points), 1), 1)))
    return int(np.clip(side, np.sqrt(GATHER_RAYS_MIN), np.sqrt(GATHER_RAYS_MAX))) ** 2


def direct_after_one_bounce(lmdp, rays_per_point, seed=0, points=None):
    """b (m, 3): the direct light that reaches each state point after one reflection,

        b(x) = ∫ ρ(h) D_e(h) cos θ / π dω,     h the surface that x sees in direction ω,

    estimated with ``rays_per_point`` cosine-distributed rays per point (a jittered square
    grid through the concentric map) and one light sample at each hit (``D_e`` as the tracer
    samples it). Rays that escape or meet an emitter or the back of a face give 0 (the direct
    light of x itself and the void of the passive dynamics). Hidden (buried) points get 0, and
    so do the points not in ``points`` (indices; default all)."""
    states, dynamics = lmdp.states, lmdp.dynamics
    scene = lmdp.scene
    caster = getattr(dynamics, "caster", None) or RayCaster(scene)
    m = states.n_points
    b = np.zeros((m, 3))
    if m == 0:
        return b
    light = IndirectTracer(scene, "UNGUIDED", caster=caster)
    targets = getattr(dynamics.locator, "targets", None)
    live = np.arange(m) if points is None else np.unique(np.asarray(points, dtype=np.int64))
    if targets is not None:
        live = live[targets[live]]
    n = int(round(np.sqrt(rays_per_point)))
    R = n * n
    rng = np.random.default_rng([int(seed), 0xD1EC7])
    cell = np.arange(R)
    face_normals = light.face_normals
    reflects = (light.albedo.max(axis=1) > 0) & ~scene.is_emissive()
    lifted = states.points + caster.offset() * states.normals
    per_chunk = max(1, GATHER_RAY_BUDGET // R)
    for start in range(0, len(live), per_chunk):
        ids = live[start:start + per_chunk]
        k = len(ids)
        u = np.empty((k * R, 2))
        u[:, 0] = (np.tile(cell // n, k) + rng.random(k * R)) / n
        u[:, 1] = (np.tile(cell % n, k) + rng.random(k * R)) / n
        owner = np.repeat(ids, R)
        d = IndirectTracer._cosine_directions(states.normals[owner].astype(np.float32), u, stratified=True)
        origin = lifted[owner].astype(np.float32)
        tri, dist = caster.intersect(origin, d)
        hit = np.flatnonzero(tri >= 0)
        t = tri[hit]
        ng = face_normals[t]
        keep = (np.einsum("ij,ij->i", ng, d[hit]) < 0) & reflects[t]
        hit, t, ng = hit[keep], t[keep], ng[keep]
        pos = origin[hit] + d[hit] * dist[hit, None]
        value = light.albedo[t] * light.direct_light(pos, ng, rng)
        for c in range(3):
            b[:, c] += np.bincount(owner[hit], weights=value[:, c], minlength=m)
    return b / R


def build_gather(guide, lmdp, max_bounces=None, seed=0):
    """:class:`GatherField` of the PHYSICAL solution: the *indirect* irradiance/π ẑ of every state
    point, the light that reaches it after at least one reflection,

        ẑ = b + w + P_NN (q ⊙ ẑ),       b = :func:`direct_after_one_bounce`,  w = P_NW z_W,

    eq. 2.22 for the light *arriving* at the states, with the direct part of every reflection
    evaluated where the ray lands rather than at the nearest state (the tracer adds the direct
    light of the gather point itself, also by light sampling). Direct light changes within
    millimetres near an emitter: the states at the edge of the 5 mm gap between a two-sided light
    and the ceiling see the light's back at point-blank range, and the rays that land on the
    ceiling beside the light (which hardly sees it) would read their z. With 2048 points that
    moved the Cornell floor's FINAL_GATHER bias between -1.8 and +5.0 % with the seed; with b,
    between -0.6 and +0.7 % (``bench/bias_map.py``, seeds 0, 1, 2, 100, 101; 128 px, 64 samples).

    With ``max_bounces`` = N the recursion runs from ẑ = w for N - 1 steps: the gather point is
    the path's first vertex, so the light it reads has at most N - 1 more vertices, as the
    tracer's and Cycles' paths of N bounces (the converged ẑ would add the light of every
    longer path: at N = 8, +1 % on the Cornell floor and +10 % in the room the narrow opening
    lights). ``max_bounces=None``: the converged solution.
    """
    problem = lmdp.lmdp
    E = len(lmdp.dynamics.emitter_radiance)
    P_NN = problem.P_NN
    q = np.asarray(problem.q, dtype=np.float64)
    w = np.asarray(problem.P_NT[:, E:] @ problem.z_terminal[E:], dtype=np.float64)   # world (void: 0)
    z_hat = w.copy()
    steps = 100_000 if max_bounces is None else int(max_bounces) - 1
    if steps > 0:
        source = direct_after_one_bounce(lmdp, gather_rays_per_point(lmdp.states.n_points), seed) + w
        for _ in range(steps):
            new = source + np.asarray(P_NN @ (q * z_hat))
            converged = np.max(np.abs(new - z_hat)) <= 1e-12 * max(np.max(np.abs(new)), 1e-300)
            z_hat = new
            if converged:
                break
    return GatherField(locator=guide.locator, irradiance=np.maximum(z_hat, 0.0), same_scene=guide.same_scene,
                       object_map=guide.object_map)


# -- sampling helpers ----------------------------------------------------------------------------

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
    texel: a shifted Hammersley set and a shifted golden-ratio sequence (module docstring)."""
    j = np.arange(n)
    base = np.stack([(j + 0.5) / n, radical_inverse2(j)], axis=1)
    shift = rng.random((n_texels, 3))
    u = np.mod(base[None, :, :] + shift[:, None, :2], 1.0)
    u_mix = np.mod(j[None, :] * GOLDEN + shift[:, 2:3], 1.0)
    return u, u_mix


def batch_count(samples):
    """Largest divisor of ``samples`` that is at most :data:`MAX_BATCHES`."""
    samples = int(samples)
    return max(b for b in range(1, min(MAX_BATCHES, samples) + 1) if samples % b == 0)


def work_units(n_texels, batches, per_batch):
    """``(group, units)``: the work units of a bake, each ``(first batch, first texel, end
    texel)`` covering ``group`` whole batches of those texels.

    A unit holds at most about :data:`PATHS_PER_UNIT` paths. Where a batch of all texels is
    smaller than that (few samples per batch), whole batches share a unit: a wavefront of
    2^15 paths costs about as much Python overhead per bounce as one of 2^17, and threads
    overlap better on long numpy calls (measured on 2 cores, 128 x 128 texels, 16 samples:
    units of 2^15 paths bake the Cornell floor 18 % and the narrow opening 36 % slower than
    units of 2^17). There are at least :data:`BAKE_THREADS` units where the texels allow it
    (whatever the number of threads a bake runs on, so that its result does not depend on it).
    """
    threads = BAKE_THREADS
    per_batch_paths = max(1, n_texels * per_batch)
    n_chunks = max(1, -(-per_batch_paths // PATHS_PER_UNIT))
    group = 1
    if n_chunks == 1:
        fit = max(1, PATHS_PER_UNIT // per_batch_paths)
        group = max(g for g in range(1, batches + 1)
                    if batches % g == 0 and g <= fit and (g == 1 or batches // g >= threads))
        if batches // group < threads:     # too few units for the threads: split the texels too
            n_chunks = max(1, min(n_texels, -(-threads // (batches // group))))
    chunk = max(1, -(-n_texels // n_chunks))
    return group, [(b, lo, min(lo + chunk, n_texels)) for b in range(0, batches, group)
                   for lo in range(0, n_texels, chunk)]


def _texel_subset(ts, sel):
    """A TexelSet view of the texels ``sel`` (for footprint sampling of a chunk)."""
    from .texels import TexelSet
    return TexelSet(ts.resolution, ts.row[sel], ts.col[sel], ts.triangle[sel], ts.barycentric[sel],
                    ts.position[sel], ts.normal[sel], ts.pixel_barycentric_derivatives[sel],
                    ts.triangle_corners, ts.triangle_normals)


# -- the bake ---------------------------------------------------------------------------------

def bake_object(tracer, scene, name, settings, object_number=0, guide=None, progress=None,
                threads=BAKE_THREADS, texels=None):
    """Bake one object's lightmap with ``tracer``; returns :class:`ObjectBake`. ``texels``: the
    dict ``check_bake_inputs`` filled (optional)."""
    t0 = time.perf_counter()
    progress = progress if progress is not None else Progress()
    index = object_index(scene, name)
    R = int(settings.bake_resolution)
    N = int(settings.bake_samples)
    cached = texels.pop((index, R), None) if texels is not None else None
    ts, tris = cached if cached is not None else object_texels(scene, index, R)
    n_tex = len(ts)
    B = batch_count(N)
    per_batch = N // B
    states = np.full(n_tex, -1, dtype=np.int64)
    if guide is not None and n_tex:
        states = guide.states_at(ts.position, ts.normal, np.full(n_tex, index))
    # Texel chunks of equal size (no small remainder unit: every unit carries the fixed cost of
    # a wavefront's Python loop), or groups of whole batches.
    group, units = work_units(n_tex, B, per_batch)
    # Running sums of the batch means and their squares: memory O(texels), not O(batches x texels).
    acc = np.zeros((n_tex, 3), np.float64)
    acc2 = np.zeros((n_tex, 3), np.float64)
    stats = TraceStats()
    seed = int(settings.seed)

    def run(unit_id):
        b0, lo, hi = units[unit_id]
        rng = np.random.default_rng([seed, object_number, b0, unit_id])
        sub = _texel_subset(ts, np.arange(lo, hi))
        k = (hi - lo) * per_batch
        parts = []
        for b in range(b0, b0 + group):     # the batches' starting points, one after another
            fp = sample_footprint(sub, per_batch, rng, include_center=(b == 0))
            u, u_mix = stratified_first_uniforms(hi - lo, per_batch, rng)
            parts.append((fp.position.reshape(k, 3), fp.normal.reshape(k, 3), u.reshape(k, 2),
                          u_mix.reshape(k)))
        position, normal, u, u_mix = (np.concatenate(p) if group > 1 else p[0] for p in zip(*parts))
        values, st = tracer.trace(position, normal, np.tile(np.repeat(states[lo:hi], per_batch), group),
                                  u, u_mix, rng)
        return unit_id, values.reshape(group, hi - lo, per_batch, 3).sum(axis=2, dtype=np.float64), st

    total = len(units)
    progress.update(0.0, f"{name}: {n_tex} texels x {N} samples")

    pending = {}
    order = [0]  # next unit to add: sums are formed in unit order, so bakes are bit-identical
                 # whatever order the threads finish in

    def collect(done, outcome):
        unit_id, part, st = outcome
        pending[unit_id] = part
        while order[0] in pending:
            _, lo, hi = units[order[0]]
            for mean in pending.pop(order[0]) / per_batch:    # the unit's batches in turn
                acc[lo:hi] += mean
                acc2[lo:hi] += mean * mean
            order[0] += 1
        stats.add(st)
        progress.update(done / total, f"{name}: {done}/{total} work units")

    if int(threads) <= 1:
        for done, unit_id in enumerate(range(total), start=1):
            collect(done, run(unit_id))
    else:
        with ThreadPoolExecutor(max_workers=int(threads)) as pool:
            futures = [pool.submit(run, u) for u in range(total)]
            try:
                for done, future in enumerate(as_completed(futures), start=1):
                    collect(done, future.result())
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    value = acc / B
    if B > 1:
        stderr = np.sqrt(np.maximum(acc2 - B * value * value, 0.0) / (B - 1) / B)
    else:
        stderr = np.full_like(value, np.nan)
    image = np.zeros((R, R, 4), np.float32)
    if n_tex:
        rgb = ts.to_image(value.astype(np.float32))
        filled_rgb, filled = dilate(rgb, ts.covered_mask(), int(settings.bake_margin), return_mask=True)
        image[..., :3] = filled_rgb
        image[..., 3] = filled.astype(np.float32)
    return ObjectBake(name=name, texels=ts, triangles=tris, value=value.astype(np.float32),
                      standard_error=stderr.astype(np.float32), image=image, samples=N, batches=B,
                      stats=stats, seconds=time.perf_counter() - t0)


def make_tracer(scene, settings, lmdp=None, caster=None):
    """The :class:`IndirectTracer` (and guide) of ``settings.bake_mode`` for ``scene``."""
    mode = settings.bake_mode
    guide = gather = None
    info = {}
    if mode in ("GUIDED", "FINAL_GATHER"):
        guide = build_guide(scene, lmdp)
        info = {"same_scene": bool(guide.same_scene), "points": int(lmdp.states.n_points),
                "strata": int(lmdp.states.n_strata), "cost_mode": lmdp.solution.cost_mode}
        if mode == "FINAL_GATHER":
            gather = build_gather(guide, lmdp, settings.max_bounces, seed=settings.seed)
        if caster is None and guide.same_scene:  # same geometry: the build's BVH serves
            caster = getattr(lmdp.dynamics, "caster", None)
    tracer = IndirectTracer(scene, mode, max_bounces=settings.max_bounces, guide=guide, gather=gather,
                            guide_fraction=settings.guide_fraction, caster=caster)
    return tracer, guide, info


def bake(scene, names, settings, lmdp=None, progress=None, precompute_seconds=None, threads=BAKE_THREADS):
    """Bake the lightmaps of the objects ``names`` of ``scene`` (module docstring).

    scene     :class:`~lmdp_addon.scene_arrays.SceneArrays` to trace (with UVs)
    names     object names to bake
    settings  :class:`~lmdp_addon.settings.Settings` (bake_mode, bake_resolution, bake_samples,
              bake_margin, guide_fraction, max_bounces, seed)
    lmdp      anything with ``scene``, ``states``, ``dynamics``, ``solution`` (e.g.
              ``pipeline.LMDPResult``): required by GUIDED and FINAL_GATHER
    precompute_seconds  {'sample', 'build', 'solve'} wall times to report with the bake
    Returns :class:`BakeResult`. Raises the errors of :func:`check_bake_inputs`, or ``Cancelled``.
    """
    with scene.held():
        return _bake(scene, names, settings, lmdp, progress, precompute_seconds, threads)


def _bake(scene, names, settings, lmdp, progress, precompute_seconds, threads):
    """:func:`bake` with the scene's derived geometry held."""
    progress = progress if progress is not None else Progress()
    texels = {}
    warnings = check_bake_inputs(scene, list(names), settings, lmdp, texels=texels)
    t0 = time.perf_counter()
    tracer, guide, info = make_tracer(scene, settings, lmdp)
    setup = time.perf_counter() - t0
    objects = []
    for number, name in enumerate(names):
        progress.begin(f"bake {name}")
        ob = bake_object(tracer, scene, name, settings, object_number=number, guide=guide,
                         progress=progress, threads=threads, texels=texels)
        progress.end(f"{ob.n_texels} texels, {ob.stats.total_rays} rays in {ob.seconds:.2f} s "
                     f"({ob.stats.total_rays / max(ob.seconds, 1e-9) / 1e6:.2f} Mrays/s)")
        objects.append(ob)
    seconds = dict(precompute_seconds or {})
    seconds["bake_setup"] = setup
    seconds["bake"] = time.perf_counter() - t0
    return BakeResult(mode=settings.bake_mode, objects=objects, settings=settings.as_dict(),
                      seconds=seconds, warnings=warnings, guide_info=info)
