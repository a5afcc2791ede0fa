"""Runners that trace a bake's work units or a build's batches on a farm's workers.

A runner is made per bake (:class:`BakeUnits`) or build (:class:`BuildBatches`) as a context
manager. On entry it scatters the recipe (``worker.BakeRecipe`` / ``worker.BuildRecipe``: the
scene arrays, the settings, the solved stages) to every worker once (``broadcast=True``; Dask
keys it by a hash of its content). A bake then scatters each object's :class:`UnitJob` once; per
unit only the unit's number travels, and its sums come back. Results stream back in the order
they finish (``as_completed``); the engine adds them in unit order, so the result is the local
one. Closing a stream (the engine does on ``Cancelled`` or an error) cancels its futures;
leaving the block releases the scattered data.

Tasks are pure: a unit has the same key, the same inputs and the same seed wherever it runs. When
a worker dies, the scheduler runs its units again on the others (the recipe is on every worker),
and each unit's result is taken once.
"""
import io
import pickle
from dataclasses import fields, replace
from types import SimpleNamespace

from ..scene_arrays import SceneArrays
from . import worker


def _plain_scene(values):
    """A :class:`SceneArrays` of the field ``values`` (how :func:`dumps` sends subclasses)."""
    return SceneArrays(**values)


class _EnginePickler(pickle.Pickler):
    """Pickles a :class:`SceneArrays` subclass from another layer (the Blender adapters'
    ``CapturedScene``, not importable on the workers) as the plain SceneArrays of its arrays."""

    def reducer_override(self, obj):
        if isinstance(obj, SceneArrays) and type(obj) is not SceneArrays:
            return _plain_scene, ({f.name: getattr(obj, f.name) for f in fields(SceneArrays) if f.init},)
        return NotImplemented


def dumps(value):
    """``value`` pickled for the workers (:class:`_EnginePickler`): what is scattered."""
    buffer = io.BytesIO()
    _EnginePickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
    return buffer.getvalue()


def _remote(name):
    """``lmdp_addon.farm.worker.<name>`` as a task function that cloudpickle sends by value (it
    is defined here): the scheduler, which unpickles the tasks, needs no engine, and the workers
    import it under their own package name whatever the client's (Blender's extension name)."""
    def task(*args):
        import importlib
        return getattr(importlib.import_module("lmdp_addon.farm.worker"), name)(*args)
    task.__name__ = name
    return task


#: The workers' functions, as tasks.
BAKE_UNIT = _remote("bake_unit")
BUILD_BATCH = _remote("build_batch")


def _without_caster(lmdp):
    """The solved stages a worker needs: ``lmdp`` with its dynamics' ray caster (an embree BVH,
    not picklable; the worker builds its own of the same scene) left out."""
    if lmdp is None:
        return None
    dynamics = getattr(lmdp, "dynamics", None)
    if dynamics is not None and getattr(dynamics, "caster", None) is not None:
        dynamics = replace(dynamics, caster=None)
    return SimpleNamespace(scene=lmdp.scene, states=lmdp.states, dynamics=dynamics,
                           lmdp=getattr(lmdp, "lmdp", None), solution=getattr(lmdp, "solution", None))


class _Runner:
    """Scatter a recipe once; submit units that depend on it; count the bytes sent."""

    def __init__(self, farm, recipe):
        self.farm = farm
        self.recipe = recipe
        self.future = None
        self.held = []

    def __enter__(self):
        self.future = self._scatter(self.recipe)
        return self

    def _scatter(self, value):
        """``value`` pickled (:func:`dumps`) and scattered to every worker; its future."""
        blob = dumps(value)
        future = self.farm.client.scatter(blob, broadcast=True, hash=True)
        self.held.append(future)
        self.farm.traffic.add_once(len(blob), self.farm.n_workers)
        return future

    def __exit__(self, *exc):
        for future in self.held:
            future.release()
        self.held.clear()
        return False

    def _stream(self, futures):
        """The futures' results as they finish; on close (or an error) cancel the rest."""
        from distributed import as_completed
        try:
            for future in as_completed(futures, loop=self.farm.client.loop):
                result = future.result()
                self.farm.traffic.add_result(_nbytes(result))
                yield result
        finally:
            self.farm.client.cancel([f for f in futures if not f.done()])


class BakeUnits(_Runner):
    """``runner(job, unit_ids)``: ``driver.trace_unit`` of each unit on the workers."""

    def __init__(self, farm, scene, settings, lmdp, portals=None):
        super().__init__(farm, worker.BakeRecipe(scene, settings, _without_caster(lmdp), farm.engine, portals))

    def __call__(self, job, unit_ids):
        client = self.farm.client
        job_future = self._scatter(job)
        ids = [int(u) for u in unit_ids]
        n = len(ids)
        futures = client.map(BAKE_UNIT, [self.future.key] * n, [self.future] * n, [job_future.key] * n,
                             [job_future] * n, ids, pure=True)
        self.farm.traffic.add_tasks(n, _task_bytes(BAKE_UNIT, [(self.future.key, self.future.key, job_future.key,
                                                                job_future.key, u) for u in ids]))
        return self._stream(futures)


class BuildBatches(_Runner):
    """``runner(starts)``: ``(batch, _DynamicsBuild.trace_batch(start))`` on the workers."""

    def __init__(self, farm, scene, states, rays_per_stratum, seed, exact_nearest, light_samples,
                 points_per_batch):
        super().__init__(farm, worker.BuildRecipe(scene, states, int(rays_per_stratum), int(seed),
                                                  bool(exact_nearest), int(light_samples), int(points_per_batch),
                                                  farm.engine))

    def __call__(self, starts):
        client = self.farm.client
        n = len(starts)
        futures = client.map(BUILD_BATCH, [self.future.key] * n, [self.future] * n, list(range(n)),
                             [int(s) for s in starts], pure=True)
        self.farm.traffic.add_tasks(n, _task_bytes(BUILD_BATCH, [(self.future.key, self.future.key, b, int(s))
                                                                 for b, s in enumerate(starts)]))
        return self._stream(futures)


def _task_bytes(function, arguments):
    """Pickled size (cloudpickle, as Dask sends a graph) of the tasks ``function(*a)`` for each
    ``a`` of ``arguments`` submitted together (the by-value function once), futures counted by
    their keys."""
    import cloudpickle
    return len(cloudpickle.dumps((function, list(arguments)), protocol=pickle.HIGHEST_PROTOCOL))


def _nbytes(value):
    """Pickled size of ``value`` in bytes (what Dask sends of it, to within its framing)."""
    return len(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))


class Traffic:
    """Bytes a farm sent and received, as pickled sizes: ``once`` (recipes and jobs, scattered
    to every worker: size x workers), ``unit_bytes`` (the units' tasks: the function, once per
    submission, and each unit's arguments: the recipe's and the job's keys, its number),
    ``results`` (the units' outcomes)."""

    def __init__(self):
        self.once = 0
        self.units = 0
        self.unit_bytes = 0
        self.results = 0

    def add_once(self, nbytes, workers):
        self.once += int(nbytes) * max(1, int(workers))

    def add_tasks(self, n, nbytes):
        self.units += int(n)
        self.unit_bytes += int(nbytes)

    def add_result(self, nbytes):
        self.results += int(nbytes)

    def as_dict(self):
        return {"scattered_bytes": self.once, "units": self.units,
                "unit_task_bytes": self.unit_bytes, "result_bytes": self.results}
