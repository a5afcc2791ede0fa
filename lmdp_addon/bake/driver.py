"""The bake: indirect diffuse light of the selected meshes into lightmaps, texel for texel like
Cycles' ``bake(type='DIFFUSE', pass_filter={'INDIRECT'})`` (or, with ``Settings.bake_content`` /
``multiply_color``, {'DIRECT', 'INDIRECT'} and 'COLOR': :mod:`~lmdp_addon.bake.content`).

For every baked object: its texels at ``bake_resolution`` (``texels.rasterize_texels``: Cycles'
mapping of its UV map), ``bake_samples`` paths per texel started at points of the texel's
footprint (``texels.sample_footprint``: sample 0 the texel point, the others jittered in Cycles'
half-pixel box), each traced by :class:`~lmdp_addon.bake.tracer.IndirectTracer`, averaged, and the
``bake_margin`` filled by ``texels.dilate`` (Cycles' EXTEND margin).

The samples of a texel are split into B independent *batches* (B = the largest divisor of the
sample count up to :data:`MAX_BATCHES`). Inside a batch the first direction is stratified
(``sampling.stratified_first_uniforms``: a shifted Hammersley set, and ``frac(j/φ + s)``
choosing between guide and cosine sampling). Every batch mean is therefore an unbiased estimate
on its own, the B batch means are independent, and their spread gives each texel's standard
error (``ObjectBake.standard_error``) without assuming anything about the estimator's variance.

Work is cut into equal units of at most about :data:`PATHS_PER_UNIT` paths (bounded memory): a
unit is a range of texels in one batch or, when a whole batch of all texels is smaller than that,
several whole batches (:func:`work_units`). Unit u of object o whose first batch is b draws its
random numbers from ``default_rng([seed, o, b, u])``, so a bake is deterministic for a seed
whatever the thread scheduling. Units run on a small thread pool (embree and numpy release the
GIL); ``progress.update`` between units raises ``Cancelled`` when the user asked to stop, and
nothing is returned.
The same units can run on a bake farm's workers instead (``bake(..., farm=)`` or the farm in use,
``lmdp_addon.farm``): :func:`trace_unit` is the unit's body on both paths, and the reduction in
unit order makes the result byte-identical.

Walk of one bake: :func:`bake` -> ``checks.check_bake`` (unless given its plan) ->
:func:`make_tracer` (``guide.build_guide``, ``gather.build_gather``) -> :func:`bake_object` per
object (:func:`work_units`, ``IndirectTracer.trace`` per unit) -> ``results.BakeResult``.
"""
import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import closing, nullcontext
from dataclasses import dataclass, replace

import numpy as np

from ..farm import session as farm_session
from ..progress import Progress
from ..sampling import stratified_first_uniforms
from . import auto, portals as world_portals, reuse
from .checks import check_bake, check_texels, object_index, object_texels
from .clamp import SampleClamp
from .content import BakeContent
from .gather import build_gather
from .memory import MAX_BATCHES, batch_count, batch_means_bytes   # the batches (memory counts them)
from .guide import build_guide
from .residual import ControlVariate
from .splitting import SplitField
from .results import ATLAS_NAME, IMAGE_SUFFIX, AtlasBake, BakeResult, ObjectBake
from .texels import dilate, sample_footprint
from .tracer import IndirectTracer, TraceStats

# The operators read BakeResult, ObjectBake and IMAGE_SUFFIX here.
__all__ = ["bake", "bake_object", "compose_atlas", "make_tracer", "work_units", "trace_unit", "UnitJob", "batch_count",
           "bake_threads", "PATHS_PER_UNIT", "BAKE_THREADS", "MIN_UNITS", "MAX_BATCHES", "BakeResult", "ObjectBake",
           "IMAGE_SUFFIX"]

#: Most paths traced by one work unit (memory: ~0.5 KiB per path in flight, so ~64 MiB per
#: unit). Larger units amortise the per-bounce Python overhead of the wavefront loop.
PATHS_PER_UNIT = 1 << 17
#: Fewest work units a bake is cut into where the texels allow it (:func:`work_units`). A
#: constant, not the thread count: the units, hence the result, do not depend on the machine.
MIN_UNITS = 2


#: Environment variable that caps the bake's threads (a positive integer; unset: every core).
THREADS_VARIABLE = "LMDP_BAKE_THREADS"


def bake_threads(cap=None):
    """Work units in flight: the machine's cores (``os.cpu_count()``, or the CPUs this process
    may run on where the system says; embree and numpy release the GIL), at most ``cap`` when it
    is positive; ``cap=None`` reads :data:`THREADS_VARIABLE` (unset, empty or not a positive
    integer: no cap)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cores = max(1, int(cores or 1))
    if cap is None:
        value = os.environ.get(THREADS_VARIABLE, "").strip()
        cap = int(value) if value.isdigit() else 0
    return min(cores, int(cap)) if int(cap) > 0 else cores


#: Work units in flight by default (every core).
BAKE_THREADS = bake_threads()
#: Texels whose nearest states are looked up at once.
STATE_LOOKUP_CHUNK = 1 << 18


def work_units(n_texels, batches, per_batch, min_units=MIN_UNITS):
    """``(group, units)``: the work units of a bake, each ``(first batch, first texel, end
    texel)`` covering ``group`` whole batches of those texels.

    A unit holds at most about :data:`PATHS_PER_UNIT` paths. Where a batch of all texels is
    smaller than that (few samples per batch), whole batches share a unit: a small wavefront
    costs about as much Python overhead per bounce as a large one, and threads overlap better on
    long numpy calls. Texel chunks are of equal size (no small remainder unit). There are at
    least :data:`MIN_UNITS` units where the texels allow it (whatever the number of threads a
    bake runs on, so that its result does not depend on it).
    """
    threads = int(min_units)
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


# ---- the bake of one object -------------------------------------------------------------------------

def bake_object(tracer, scene, name, settings, object_number=0, guide=None, progress=None,
                threads=None, texels=None, resolution=None, runner=None, min_units=MIN_UNITS, image=True):
    """Bake one object's lightmap with ``tracer``; returns :class:`ObjectBake`. ``resolution``:
    its lightmap side R (default ``settings.bake_resolution``; ``BakePlan.resolution_of``);
    ``texels``: its ``(TexelSet, triangles)`` at R if the caller has them (``BakePlan.texels``),
    else they are rasterised here. ``threads``: default :func:`bake_threads`. ``runner``: a
    farm's unit runner (``Farm.bake_units``), None: local threads. ``image=False``: the texels'
    values and standard errors only (a pilot or probe), its ``image`` None."""
    t0 = time.perf_counter()
    progress = progress if progress is not None else Progress()
    index = object_index(scene, name)
    R = int(resolution if resolution is not None else settings.bake_resolution)
    N = int(settings.bake_samples)
    ts, tris = texels if texels is not None else object_texels(scene, index, R)
    threads = bake_threads() if threads is None else int(threads)
    n_tex = len(ts)
    B = batch_count(N)
    states = np.full(n_tex, -1, dtype=np.int64)
    if guide is not None:
        for lo in range(0, n_tex, STATE_LOOKUP_CHUNK):    # bounded temporaries (positions, normals)
            sub = ts.subset(slice(lo, lo + STATE_LOOKUP_CHUNK))
            states[lo:lo + len(sub)] = guide.states_at(sub.position, sub.normal, np.full(len(sub), index))
    progress.update(0.0, f"{name}: {n_tex} texels x {N} samples")
    means = np.zeros((B, n_tex, 3), np.float32) if batch_means_bytes(n_tex, B) else None
    acc, acc2, stats = _trace_batches(tracer, ts, tris[ts.triangle], states, B, N // B, int(settings.seed),
                                      object_number, name, progress, threads, runner, min_units, means)
    del states
    value, stderr = _batch_statistics(acc, acc2, B)
    del acc, acc2
    return ObjectBake(name=name, texels=ts, triangles=tris, value=value, standard_error=stderr,
                      image=object_image(ts, value, R, settings.bake_margin) if image else None,
                      samples=N, batches=B, stats=stats, seconds=time.perf_counter() - t0, batch_means=means)


def object_image(ts, value, R, margin):
    """(R, R, 4) float32 lightmap of the texels ``ts`` with ``value`` (n, 3): alpha 1 where
    covered, the ``margin`` filled around the islands (``texels.dilate``)."""
    image = np.zeros((R, R, 4), np.float32)
    if len(ts):
        rgb = ts.to_image(value)
        filled_rgb, filled = dilate(rgb, ts.covered_mask(), int(margin), return_mask=True)
        del rgb
        image[..., :3] = filled_rgb
        image[..., 3] = filled.astype(np.float32)
    return image


def _batch_statistics(acc, acc2, B):
    """``(value, standard error)`` (n, 3) float32 of the texels from the sums of their B batch
    means ``acc`` and of their squares ``acc2`` (float64; both are overwritten):
    value = acc / B, standard error = sqrt(max(acc2 - B value², 0) / (B - 1) / B), NaN for
    B = 1."""
    acc /= B
    value = acc.astype(np.float32)
    if B == 1:
        return value, np.full_like(value, np.nan)
    square = np.multiply(acc, B)
    square *= acc
    acc2 -= square
    del square
    np.maximum(acc2, 0.0, out=acc2)
    acc2 /= B - 1
    acc2 /= B
    return value, np.sqrt(acc2, out=acc2).astype(np.float32)


@dataclass
class UnitJob:
    """The work units of one object's bake, as :func:`trace_unit` needs them (plain arrays, so a
    farm sends them once per object: ``lmdp_addon.farm``).

    texels          :class:`~lmdp_addon.bake.texels.TexelSet` of the object (n texels)
    triangles       (n,) int64 each texel's scene triangle (its rays' offset)
    states          (n,) int64 each texel's nearest state (-1: none)
    units           :func:`work_units` ``(first batch, first texel, end texel)``
    group           whole batches per unit
    per_batch       paths per texel and batch
    seed, object_number  the random streams' keys
    """

    texels: object
    triangles: np.ndarray
    states: np.ndarray
    units: list
    group: int
    per_batch: int
    seed: int
    object_number: int


def trace_unit(tracer, job, unit_id):
    """``(unit_id, sums, TraceStats)`` of work unit ``unit_id`` of ``job`` traced with ``tracer``:
    ``sums`` (group, texels of the unit, 3) float64 the sums of each batch's path values. Its
    random numbers come from ``default_rng([seed, object_number, first batch, unit_id])`` only,
    so the result does not depend on where or when the unit runs."""
    units, group, per_batch = job.units, job.group, job.per_batch
    states, triangles = job.states, job.triangles
    b0, lo, hi = units[unit_id]
    rng = np.random.default_rng([job.seed, job.object_number, b0, unit_id])
    sub = job.texels.subset(slice(lo, hi))
    k = (hi - lo) * per_batch
    # The batches' starting points, one after another, written straight into the tracer's
    # float32 rows (the same rounding as converting the float64 footprint afterwards).
    position = np.empty((k * group, 3), np.float32)
    normal = np.empty((k * group, 3), np.float32)
    u = np.empty((k * group, 2))
    u_mix = np.empty(k * group)
    for i, b in enumerate(range(b0, b0 + group)):
        rows = slice(i * k, (i + 1) * k)
        fp = sample_footprint(sub, per_batch, rng, include_center=(b == 0))
        position[rows] = fp.position.reshape(k, 3)
        normal[rows] = fp.normal.reshape(k, 3)
        del fp
        first, choice = stratified_first_uniforms(hi - lo, per_batch, rng)
        u[rows], u_mix[rows] = first.reshape(k, 2), choice.reshape(k)
    control = np.zeros((k * group, 3), np.float32) if tracer.control is not None else None
    tiles = None
    if tracer.path_reuse > 1 and control is None:     # path reuse: the tile of every path (bake/reuse)
        texel = np.tile(np.repeat(np.arange(lo, hi), per_batch), group)
        batch = b0 + np.arange(k * group) // k                      # each path's batch and sample in it
        sample = batch * per_batch + np.tile(np.arange(per_batch), (hi - lo) * group)
        tiles = reuse.groups(job.texels.row[texel], job.texels.col[texel], sample, tracer.path_reuse)
    values, st = tracer.trace(position, normal, np.tile(np.repeat(states[lo:hi], per_batch), group),
                              u, u_mix, rng, triangles=np.tile(np.repeat(triangles[lo:hi], per_batch), group),
                              control_out=control, reuse_groups=tiles)
    if control is not None:              # RESIDUAL: the paths estimate f - g (residual.py)
        values -= control
    sums = values.reshape(group, hi - lo, per_batch, 3).sum(axis=2, dtype=np.float64)
    if control is not None:              # ... and the control samples E[g], ratio x as many
        ratio = tracer.control.ratio
        for i, b in enumerate(range(b0, b0 + group)):
            g, cst = tracer.control.samples(tracer, sub, triangles[lo:hi], per_batch, b == 0, rng)
            sums[i] += g / ratio
            st.add(cst)
    return unit_id, sums, st


def _trace_batches(tracer, ts, triangles, states, B, per_batch, seed, object_number, name, progress, threads,
                   runner=None, min_units=MIN_UNITS, means=None):
    """``(Σ_b mean_b, Σ_b mean_b², TraceStats)`` over the B batches of ``per_batch`` paths of
    every texel of ``ts`` (``triangles``: each texel's scene triangle, for its rays' offset;
    ``states``: each texel's nearest state, -1: none), traced as the
    :func:`work_units` on ``threads`` threads, or by ``runner(job, unit_ids)`` (a farm's: it
    yields :func:`trace_unit`'s outcomes in any order). Running sums keep memory O(texels), not
    O(batches x texels); they are formed in unit order, so bakes are bit-identical whatever
    order the units finish in. ``means``: a (B, texels, 3) array that receives each batch's texel
    means (:attr:`ObjectBake.batch_means`), or None."""
    n_tex = len(ts)
    group, units = work_units(n_tex, B, per_batch, min_units)
    acc = np.zeros((n_tex, 3), np.float64)
    acc2 = np.zeros((n_tex, 3), np.float64)
    stats = TraceStats()
    job = UnitJob(ts, triangles, states, units, group, per_batch, seed, object_number)

    def run(unit_id):
        return trace_unit(tracer, job, unit_id)

    total = len(units)
    pending = {}
    order = [0]  # the next unit to add

    def collect(done, outcome):
        unit_id, part, st = outcome
        pending[unit_id] = part
        while order[0] in pending:
            b0, lo, hi = units[order[0]]
            for b, mean in enumerate(pending.pop(order[0]) / per_batch, start=b0):   # the unit's batches
                acc[lo:hi] += mean
                acc2[lo:hi] += mean * mean
                if means is not None:
                    means[b, lo:hi] = mean
            order[0] += 1
        stats.add(st)
        progress.update(done / total, f"{name}: {done}/{total} work units")

    if runner is not None:                   # a farm: closing the stream cancels what is left
        with closing(runner(job, range(total))) as outcomes:
            for done, outcome in enumerate(outcomes, start=1):
                collect(done, outcome)
    elif int(threads) <= 1:
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
    return acc, acc2, stats


# ---- the bake ---------------------------------------------------------------------------------------

def make_tracer(scene, settings, lmdp=None, caster=None, portals=None):
    """``(IndirectTracer, StateGuide or None, guide info dict)`` of ``settings.bake_mode`` for
    ``scene``. The bake reuses the build's BVH (``lmdp.dynamics.caster``) when the traced scene
    is the one the states were sampled on, and the build's locator (``guide.build_guide``).
    ``portals``: the world portals its environment map's light samples follow (``portals``)."""
    mode = settings.bake_mode
    guide = gather = None
    info = {}
    control = None
    if mode in ("GUIDED", "FINAL_GATHER", "RESIDUAL"):
        guide = build_guide(scene, lmdp, fine=mode == "GUIDED", seed=settings.seed,
                            paths=settings.bake_resolution ** 2 * settings.bake_samples,
                            table_rays=getattr(settings, "guide_table_rays", 0.0))
        info = {"same_scene": bool(guide.same_scene), "points": int(lmdp.states.n_points),
                "strata": int(lmdp.states.n_strata), "cost_mode": lmdp.solution.cost_mode,
                **getattr(guide, "info", {})}
        if mode in ("FINAL_GATHER", "RESIDUAL"):
            gather = build_gather(guide, lmdp, settings.max_bounces, seed=settings.seed)
        if mode == "RESIDUAL":    # cosine paths: the guide only serves the gather's locator
            control = ControlVariate(gather)
            info["control_ratio"] = control.ratio
            guide = None
        if caster is None and info["same_scene"]:  # same geometry: the build's BVH serves
            caster = lmdp.dynamics.caster
    split = None
    if mode == "GUIDED" and getattr(settings, "splitting", False) and lmdp.solution.cost_mode == "PHYSICAL":
        split = SplitField.from_lmdp(scene, lmdp)     # V: where the paths' light will come from
    tracer = IndirectTracer(scene, mode, max_bounces=settings.max_bounces, guide=guide, gather=gather,
                            guide_fraction=settings.guide_fraction, caster=caster, control=control,
                            content=BakeContent.from_settings(settings),
                            glossy_bounces=settings.glossy_bounces, total_bounces=settings.total_bounces,
                            clamp=SampleClamp.from_settings(settings),
                            min_light_bounces=getattr(settings, "min_light_bounces", 0),
                            light_share=getattr(settings, "light_share", 0.0),
                            splitting=split, path_reuse=getattr(settings, "path_reuse", 1))
    tracer.use_portals(portals)
    return tracer, guide, info


def bake(scene, names, settings, lmdp=None, progress=None, precompute_seconds=None, threads=None,
         plan=None, farm=None, solve=None):
    """Bake the lightmaps of the objects ``names`` of ``scene`` (module docstring).

    scene     :class:`~lmdp_addon.scene_arrays.SceneArrays` to trace (with UVs)
    names     object names to bake
    settings  :class:`~lmdp_addon.settings.Settings` (bake_mode, bake_resolution, bake_samples,
              bake_margin, guide_fraction, max_bounces, seed)
    lmdp      anything with ``scene``, ``states``, ``dynamics``, ``solution`` (e.g.
              ``pipeline.LMDPResult``): required by GUIDED and FINAL_GATHER
    precompute_seconds  {'sample', 'build', 'solve'} wall times to report with the bake
    threads   work units in flight (None: :func:`bake_threads`, every core unless capped)
    plan      the :class:`~lmdp_addon.bake.checks.BakePlan` of ``checks.check_bake`` for these
              arguments: no check runs again and its texels are used (a plan whose texel checks
              are still to run gets them here first: ``checks.check_texels``, a "texels" step
              that reports progress and can be cancelled); None: :func:`check_bake` runs here once
    farm      a :class:`lmdp_addon.farm.Farm` whose workers trace the work units (the result is
              byte-identical); None: the farm in use in this process (``farm.session.use``), if
              any, else ``threads`` local threads
    solve     AUTO without ``lmdp``: ``solve() -> LMDPResult`` samples, builds and solves when the
              pilot asks for the solution (:mod:`~lmdp_addon.bake.auto`; None: AUTO stays unguided)
    Returns :class:`BakeResult` (AUTO: its ``auto`` says what was chosen, ``lmdp`` the solution
    it solved, if any). Raises the errors of :func:`check_bake`, or ``Cancelled``.
    """
    with scene.held():
        if plan is None:
            plan = check_bake(scene, names, settings, lmdp)
        if settings.bake_mode == "AUTO":
            return _bake_auto(scene, list(names), settings, lmdp, progress, precompute_seconds, threads, plan,
                              farm, solve)
        return _bake(scene, list(names), settings, lmdp, progress, precompute_seconds, threads, plan, farm)


def _bake_auto(scene, names, settings, lmdp, progress, precompute_seconds, threads, plan, farm, solve):
    """AUTO (:mod:`~lmdp_addon.bake.auto`): the pilots on a share of the texels, the choice, then
    the bake itself in the chosen mode (its result is that mode's bake, relabelled AUTO)."""
    progress = progress if progress is not None else Progress()
    t0 = time.perf_counter()
    S = int(settings.bake_samples)
    seconds = dict(precompute_seconds or {})
    unguided_settings = replace(settings, bake_mode="UNGUIDED")
    unguided = make_tracer(scene, unguided_settings, None)
    choice = auto.AutoChoice(relative_variance=float("nan"))
    mode, made, main_settings, used = "UNGUIDED", unguided, unguided_settings, None
    probe = _portal_probe(unguided[0], settings)
    if S >= auto.MIN_SAMPLES:
        targets = [_auto_texels(scene, plan, settings, name) for name in names]
        paths = auto.pilot_paths(sum(t[4] for t in targets) * S)
        if paths < auto.PILOT_PATHS:       # a small bake: a smaller pilot
            targets = [_auto_texels(scene, plan, settings, name, paths // auto.PILOT_SAMPLES) for name in names]
        unguided[0].world_probe = probe           # the unguided pilot is the portals' probe too
        first = _auto_pilot(scene, targets, unguided_settings, unguided, 1, progress, threads, paths)
        unguided[0].world_probe = None
        choice.relative_variance = auto.relative_variance(first)
        per_path = sum(ob.stats.total_rays for ob in first) / max(sum(ob.n_texels * ob.samples for ob in first), 1)
        texels = sum(t[4] for t in targets)
        noisy = choice.relative_variance >= auto.NOISY
        moderate = not noisy and choice.relative_variance >= auto.MODERATE
        share = auto.MODERATE_SOLVE_SHARE if moderate else None
        unsolved = (noisy or moderate) and lmdp is None      # wants a solution it was not given
        choice.too_small = unsolved and not auto.worth_solving(per_path, texels, settings, S, share)
        choice.no_solution = unsolved and solve is None and not choice.too_small
        if (noisy or moderate) and (lmdp is not None or (solve is not None and not choice.too_small)):
            if lmdp is None:
                progress.begin("AUTO: solve")
                lmdp = choice.lmdp = solve()
                progress.end("solved")
                seconds.update(getattr(lmdp, "seconds", {}) or {})
            choice.solved, choice.moderate = True, moderate
            choice.sure = choice.relative_variance >= auto.SURE
            guided_settings = replace(settings, bake_mode="GUIDED", **({"splitting": False} if moderate else {}),
                                      **({"guide_table_rays": auto.SURE_TABLE_RAYS} if choice.sure else {}))
            guided = make_tracer(scene, guided_settings, lmdp)
            if not choice.sure:
                second = _auto_pilot(scene, targets, guided_settings, guided, 2, progress, threads, paths)
                choice.guided_gain = auto.efficiency(second, auto.GUIDED_RAY_COST) / auto.efficiency(first)
            if choice.sure or choice.guided_gain > (auto.MODERATE_GAIN if moderate else 1.0):
                mode, made, main_settings, used = "GUIDED", guided, guided_settings, lmdp
    # The world portals: learned by the unguided pilot (both pilots drew the map's own world
    # samples, so that they compare the two modes alike), or without pilots by a probe.
    portals = None
    if probe is not None:
        portals = (world_portals.learn(probe) if S >= auto.MIN_SAMPLES
                   else _run_portal_probe(scene, plan, settings, names, unguided[0], probe, progress, threads))
    made[0].use_portals(portals)
    choice.mode = mode
    choice.samples = ((mode, S),)
    seconds["auto"] = time.perf_counter() - t0        # pilots, solve, guide: before the bake itself
    result = _bake(scene, names, main_settings, used, progress, None, threads, plan, farm, made=made)
    result.seconds = {**seconds, **result.seconds, "bake": time.perf_counter() - t0}
    result.mode, result.settings, result.auto = "AUTO", settings.as_dict(), choice
    result.portals = _portals_info(portals, probe, made[0], settings)
    return result


def _auto_texels(scene, plan, settings, name, count=auto.PILOT_TEXELS):
    """``(object number, name, (TexelSet, triangles), resolution, texels of the object)`` of a
    pilot of AUTO (or a portal probe): every k-th texel of the object, k such that all objects
    together give about ``count`` texels."""
    index = object_index(scene, name)
    same = plan.resolution == int(settings.bake_resolution)
    R = plan.resolution_of(index) if same else int(settings.bake_resolution)
    texels = plan.texels.get(index) if same else None
    ts, tris = texels if texels is not None else object_texels(scene, index, R)
    total = sum(len(t[0]) for t in plan.texels.values()) if same and plan.texels else len(ts)
    stride = max(1, -(-total // int(count)))
    number = plan.names.index(name) if name in plan.names else 0
    return number, name, (ts.subset(slice(0, None, stride)), tris), R, len(ts)


def _auto_pilot(scene, targets, settings, made, part, progress, threads=None, paths=auto.PILOT_PATHS):
    """The ObjectBakes of an AUTO pilot of about ``paths`` paths: ``auto.pilot_samples`` samples
    at the ``targets`` texels (:func:`_auto_texels`) with the tracer ``made``, in one work unit
    per object (a pilot's arrays are too small for a second thread to gain: it waits on the
    first's Python), on random streams of their own (seed ``PILOT_STREAMS · seed + part``):
    measurements only, never part of the lightmaps (no image). The pilot's paths keep their own
    first bounces (no path reuse): AUTO's thresholds are the variance of single paths."""
    tracer, guide, _ = made
    n = auto.pilot_samples(sum(len(t[2][0]) for t in targets), settings.bake_samples, paths)
    s = replace(settings, bake_samples=n, seed=auto.PILOT_STREAMS * int(settings.seed) + part)
    out = []
    tile, tracer.path_reuse = tracer.path_reuse, 1
    try:
        for number, name, texels, R, _ in targets:
            progress.begin(f"AUTO pilot ({settings.bake_mode}) {name}")
            out.append(bake_object(tracer, scene, name, s, object_number=number, guide=guide, progress=progress,
                                   threads=threads, texels=texels, resolution=R, min_units=1, image=False))
            progress.end(f"{out[-1].n_texels} texels")
    finally:
        tracer.path_reuse = tile
    return out


# ---- world portals ---------------------------------------------------------------------------------

#: Why a bake whose settings ask for world portals draws the map's own world samples.
PORTALS_CLAMPED = ("world portals off: a sample clamp is on (Cycles clamps the values of its own world "
                   "samples; Clamp Direct / Indirect 0 turns them on)")


def _portals_asked(tracer, settings):
    """``settings.world_portals`` is on and the scene has an environment map that lights it."""
    return getattr(settings, "world_portals", False) and tracer.environment is not None


def _portal_probe(tracer, settings):
    """A :class:`portals.PortalProbe` for a bake with ``tracer`` when portals are asked for
    (:func:`_portals_asked`) and no sample clamp is on (the clamped light samples must be
    distributed as Cycles', as for light connections), else None."""
    if not _portals_asked(tracer, settings) or tracer.clamp is not None:
        return None
    return world_portals.PortalProbe(tracer.scene)


def _run_portal_probe(scene, plan, settings, names, tracer, probe, progress, threads):
    """:data:`portals.PROBE_PATHS` unguided paths (no light connections) from every k-th texel of
    the baked objects, on a random stream of their own (seed ``PILOT_STREAMS · seed + 3``),
    recorded by ``probe``; returns the learned :class:`portals.Portals` (or None)."""
    probe_settings = replace(settings, bake_mode="UNGUIDED", light_share=0.0,
                             bake_samples=world_portals.PROBE_SAMPLES,
                             seed=auto.PILOT_STREAMS * int(settings.seed) + 3)
    probe_tracer = make_tracer(scene, probe_settings, None, caster=tracer.caster)[0]
    probe_tracer.world_probe = probe
    count = world_portals.PROBE_PATHS // world_portals.PROBE_SAMPLES
    progress.begin("world portals: probe")
    for number, name, texels, R, _ in [_auto_texels(scene, plan, settings, n, count) for n in names]:
        bake_object(probe_tracer, scene, name, probe_settings, object_number=number, progress=progress,
                    threads=threads, texels=texels, resolution=R, min_units=1, image=False)
    portals = world_portals.learn(probe)
    progress.end(_portals_sentence(portals, probe))
    return portals


def _portals_sentence(portals, probe):
    if portals is None:
        return (f"{probe.samples} world samples, {probe.visible} saw the world (fewer than "
                f"{world_portals.MIN_VISIBLE}): the map's own sampling")
    return (f"{probe.samples} world samples, {100 * portals.info['probe_visible']:.0f} % saw the world; "
            f"{portals.info['regions']} region(s)")


def _portals_info(portals, probe, tracer, settings):
    """``BakeResult.portals``: what the probe learned, or why there was none although
    ``settings`` asked for portals under an environment map (empty otherwise)."""
    if probe is None:
        clamped = _portals_asked(tracer, settings) and tracer.clamp is not None
        return {"used": False, "off": PORTALS_CLAMPED} if clamped else {}
    return {"used": portals is not None, **(portals.info if portals is not None else
                                            {"probe_samples": probe.samples, "probe_seen": probe.visible})}


def _bake(scene, names, settings, lmdp, progress, precompute_seconds, threads, plan, farm=None, made=None):
    """:func:`bake` with the scene's derived geometry held and its plan (``made``: the
    :func:`make_tracer` triple of ``settings`` and ``lmdp`` to trace with, made here when None;
    a farm's workers make theirs of the same)."""
    progress = progress if progress is not None else Progress()
    check_texels(scene, plan, progress)                # when the plan still needs them
    names = [n for n in names if n in plan.names]      # the texel checks may leave objects out
    t0 = time.perf_counter()
    tracer, guide, info = made if made is not None else make_tracer(scene, settings, lmdp)
    probe = _portal_probe(tracer, settings) if made is None else None
    if probe is not None:        # the world portals (AUTO found its own with its pilot)
        tracer.use_portals(_run_portal_probe(scene, plan, settings, names, tracer, probe, progress, threads))
    setup = time.perf_counter() - t0
    same = plan.resolution == int(settings.bake_resolution)
    texels = plan.texels if same else {}
    objects = []
    farm = farm if farm is not None else farm_session.current()
    with farm.bake_units(scene, settings, lmdp, tracer.portals) if farm is not None else nullcontext() as runner:
        for number, name in enumerate(names):
            progress.begin(f"bake {name}")
            index = object_index(scene, name)
            ob = bake_object(tracer, scene, name, settings, object_number=number, guide=guide, progress=progress,
                             threads=threads, texels=texels.get(index),
                             resolution=plan.resolution_of(index) if same else None, runner=runner)
            progress.end(f"{ob.n_texels} texels, {ob.stats.total_rays} rays in {ob.seconds:.2f} s "
                         f"({ob.stats.total_rays / max(ob.seconds, 1e-9) / 1e6:.2f} Mrays/s)")
            objects.append(ob)
    atlases = [compose_atlas(ATLAS_NAME, objects, int(settings.bake_margin))] if plan.atlas and objects else []
    seconds = dict(precompute_seconds or {})
    seconds["bake_setup"] = setup
    seconds["bake"] = time.perf_counter() - t0
    return BakeResult(mode=settings.bake_mode, objects=objects, settings=settings.as_dict(),
                      seconds=seconds, warnings=list(plan.warnings) + list(plan.texel_warnings),
                      guide_info=info, atlases=atlases,
                      portals=_portals_info(tracer.portals, probe, tracer, settings) if made is None else {})


def compose_atlas(name, objects, margin):
    """One shared lightmap of ``objects`` (``ObjectBake`` at one resolution, covering disjoint
    texels: ``checks`` refuses an atlas whose objects overlap): every object's texels in its
    region of the image, the margin around all of them filled at once (``texels.dilate``), so
    no object's margin covers another's texels. Each object's ``image`` becomes that shared
    image and its ``atlas`` the atlas's name; returns the :class:`AtlasBake`."""
    R = objects[0].resolution
    rgb = np.zeros((R, R, 3), np.float32)
    covered = np.zeros((R, R), bool)
    for ob in objects:
        rgb[ob.texels.row, ob.texels.col] = ob.value
        covered[ob.texels.row, ob.texels.col] = True
    image = np.zeros((R, R, 4), np.float32)
    if covered.any():
        filled_rgb, filled = dilate(rgb, covered, int(margin), return_mask=True)
        image[..., :3] = filled_rgb
        image[..., 3] = filled.astype(np.float32)
    for ob in objects:
        ob.image = image
        ob.atlas = name
    return AtlasBake(name=name, members=[ob.name for ob in objects], image=image)
