"""Bake farms: a bake's work units and the LMDP build's ray batches run on a Dask distributed
cluster, byte-identical to a local run with the same seed.

* :mod:`~lmdp_addon.farm.cluster`: :class:`Farm` (connect to a scheduler or start a local
  cluster, check every worker's engine and dependency versions), :class:`FarmError`;
* :mod:`~lmdp_addon.farm.units`: the runners the engine's seams call (scatter once, submit the
  units, stream the results back, cancel);
* :mod:`~lmdp_addon.farm.worker`: what the workers run (the recipe set up once per process);
* :mod:`~lmdp_addon.farm.session`: the farm in use in this process (``with use(farm)``);
* :mod:`~lmdp_addon.farm.versions`: the engine version (a hash of its sources) and dependencies.

Dask is imported only when a :class:`Farm` is made. :func:`bake` and :func:`build` are the
Python API.
"""
from .cluster import Farm, FarmError
from .session import current, use


def bake(scene, names, settings, lmdp=None, scheduler=None, workers=None, progress=None, farm=None):
    """``driver.bake(scene, names, settings, lmdp)`` on a farm: ``farm`` if given, else one
    connected to ``scheduler`` or started with ``workers`` local processes (closed after)."""
    from ..bake import driver
    if farm is not None:
        return driver.bake(scene, names, settings, lmdp=lmdp, progress=progress, farm=farm)
    with Farm(scheduler=scheduler, workers=workers) as made:
        return driver.bake(scene, names, settings, lmdp=lmdp, progress=progress, farm=made)


def build(scene, settings, progress=None, scheduler=None, workers=None, farm=None):
    """``pipeline.run_all(scene, settings)`` (sample, build, solve) with the build's ray batches
    on a farm (as :func:`bake`); returns the ``LMDPResult``."""
    from ..model import pipeline
    if farm is not None:
        with use(farm):
            return pipeline.run_all(scene, settings, progress)
    with Farm(scheduler=scheduler, workers=workers) as made, use(made):
        return pipeline.run_all(scene, settings, progress)


__all__ = ["Farm", "FarmError", "bake", "build", "current", "use"]
