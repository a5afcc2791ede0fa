"""What runs on a farm's workers: one bake work unit or one batch of the build, from the recipe
the client scattered once (:mod:`~lmdp_addon.farm.units`).

A recipe arrives pickled (``units.dumps``) and is turned into its tracer (``driver.make_tracer``: BVH, guide, gather) or its build
(``dynamics._DynamicsBuild``: BVH, locator, ray patterns) once per worker process and kept in
:data:`WORKER_RECIPES`, keyed by the recipe's Dask key (a hash of its content); every unit of it
that lands on the worker reuses it. Both are deterministic functions of the recipe, so a unit
computes the same numbers on any worker, and a unit that is run again (its worker died) gives the
same result. No dask here: these are plain functions that Dask calls.
"""
import ctypes
import pickle
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from . import versions

#: Recipes set up in this worker process: {Dask key: (recipe, tracer or build)}, the most
#: recent last; and the bakes' jobs (``driver.UnitJob``) unpickled here, {Dask key: job}.
WORKER_RECIPES = OrderedDict()
WORKER_JOBS = OrderedDict()
#: Recipes kept (a worker serves one bake or build at a time; one more for an overlap).
KEEP = 2
_LOCK = threading.Lock()
#: glibc's ``mallopt`` parameters (malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3


@dataclass
class BakeRecipe:
    """What every work unit of a bake needs: ``driver.make_tracer(scene, settings, lmdp)``.

    scene     the traced :class:`~lmdp_addon.scene_arrays.SceneArrays`
    settings  :class:`~lmdp_addon.settings.Settings`
    lmdp      the solved stages (``scene``, ``states``, ``dynamics`` without its ray caster,
              ``lmdp``, ``solution``), or None (UNGUIDED)
    engine    the client's ``versions.probe()`` the worker must match
    portals   the world portals of the client's tracer (``bake.portals.Portals``), or None
    """

    scene: object
    settings: object
    lmdp: object = None
    engine: dict = None
    portals: object = None

    def set_up(self):
        from ..bake.driver import make_tracer
        with self.scene.held():
            return make_tracer(self.scene, self.settings, self.lmdp, portals=self.portals)[0]


@dataclass
class BuildRecipe:
    """What every batch of the build needs: the arguments of ``dynamics._DynamicsBuild`` and
    the client's batch size (points per batch: the batches' bounds are the client's), and the
    client's ``versions.probe()`` the worker must match."""

    scene: object
    states: object
    rays_per_stratum: int
    seed: int
    exact_nearest: bool
    light_samples: int
    points_per_batch: int
    engine: dict = None

    def set_up(self):
        from ..model.dynamics import _DynamicsBuild
        with self.scene.held():
            build = _DynamicsBuild(self.scene, self.states, self.rays_per_stratum, self.seed, None,
                                   self.exact_nearest, self.light_samples)
            build.tables.result()        # the locator; then the set-up pool is not needed
        build.pool.shutdown(wait=True)
        if build.points_per_batch != self.points_per_batch:      # the client's batch size rules
            build.points_per_batch = self.points_per_batch
            build.ray_rows = np.repeat(np.arange(self.points_per_batch * build.S, dtype=np.int32), build.R)
        return build


def _cached(cache, key, make):
    """``cache[key]``, made by ``make()`` on first use; the :data:`KEEP` most recent are kept."""
    with _LOCK:
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
        made = cache[key] = make()
        while len(cache) > KEEP:
            cache.popitem(last=False)
        return made


def tune_allocator():
    """Give glibc's allocator fixed thresholds (mmap 32 MiB, trim 64 MiB; what it adapts to by
    itself) in this worker process. Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_``
    set, which turns glibc's adaptive mmap threshold off: every large temporary array of the
    wavefront is then mapped and unmapped anew (page faults on every bounce).
    Elsewhere than glibc: nothing."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 64 << 20)
    except (OSError, AttributeError):
        pass


def set_up(key, blob):
    """``(recipe, its tracer or build)`` of the pickled recipe ``blob`` in this process
    (unpickled and set up on first use, then reused)."""
    def make():
        if not WORKER_RECIPES:
            tune_allocator()
        recipe = pickle.loads(blob)
        versions.check_engine(recipe.engine)
        return recipe, recipe.set_up()
    return _cached(WORKER_RECIPES, key, make)


def job(key, blob):
    """The pickled ``driver.UnitJob`` ``blob`` (unpickled once per process)."""
    return _cached(WORKER_JOBS, key, lambda: pickle.loads(blob))


def bake_unit(recipe_key, recipe_blob, job_key, job_blob, unit_id):
    """``driver.trace_unit`` of unit ``unit_id`` of the job with the recipe's tracer."""
    from ..bake.driver import trace_unit
    recipe, tracer = set_up(recipe_key, recipe_blob)
    unit_job = job(job_key, job_blob)
    with recipe.scene.held():
        return trace_unit(tracer, unit_job, unit_id)


def build_batch(recipe_key, recipe_blob, batch, start):
    """``(batch, _DynamicsBuild.trace_batch(start))`` with the recipe's build."""
    recipe, build = set_up(recipe_key, recipe_blob)
    with recipe.scene.held():
        return batch, build.trace_batch(start)
