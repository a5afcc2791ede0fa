"""Bake farms (issue 23): wall time of one bake and one build against the number of local Dask
worker processes (1, 2), next to the local bake, and the bytes a bake sends (scattered once to
every worker, per unit, and the results coming back), with a check that every farm result is
byte-identical to the local one.

    .venv/bin/python bench/run.py --sections farm [--quick]
"""
import time
from dataclasses import dataclass

import numpy as np

from .common import log


@dataclass
class FarmProfile:
    kind: str
    point_count: int
    resolution: int
    samples: int
    workers: tuple = (1, 2)
    mode: str = "FINAL_GATHER"


PROFILES = {
    "full": FarmProfile(kind="CORNELL_BOX", point_count=2048, resolution=128, samples=64),
    "quick": FarmProfile(kind="CORNELL_BOX", point_count=2048, resolution=64, samples=16),
}


def _identical_bakes(a, b):
    return all(np.array_equal(x.image, y.image) for x, y in zip(a.objects, b.objects))


def _identical_builds(a, b):
    return all(np.array_equal(getattr(getattr(a.dynamics, m), p), getattr(getattr(b.dynamics, m), p))
               for m in ("P", "stratum_transitions") for p in ("data", "indices", "indptr"))


def run(profile_name):
    """The farm section's results (``results["farm"]``)."""
    from lmdp_addon import demo_geometry
    from lmdp_addon import farm
    from lmdp_addon.bake import driver
    from lmdp_addon.model import pipeline
    from lmdp_addon.settings import Settings
    profile = PROFILES[profile_name]
    scene = demo_geometry.build_scene_arrays(profile.kind)
    names = demo_geometry.state_part_names(profile.kind)
    settings = Settings(point_count=profile.point_count, bake_mode=profile.mode, bake_resolution=profile.resolution,
                        bake_samples=profile.samples)
    rows = []
    t0 = time.perf_counter()
    lmdp = pipeline.run_all(scene, settings)
    build_local = time.perf_counter() - t0
    for threads in sorted({1, driver.bake_threads()}):
        t0 = time.perf_counter()
        local = driver.bake(scene, names, settings, lmdp=lmdp, threads=threads)
        rows.append({"where": f"local, {threads} thread{'s' if threads > 1 else ''}", "workers": 0,
                     "threads": threads, "bake_seconds": time.perf_counter() - t0,
                     "build_seconds": build_local if threads == 1 else None})
        log(f"farm: local bake on {threads} thread(s) {rows[-1]['bake_seconds']:.2f} s")
    for n in profile.workers:
        t0 = time.perf_counter()
        with farm.Farm(workers=n) as made:
            start = time.perf_counter() - t0
            t0 = time.perf_counter()
            built = farm.build(scene, settings, farm=made)
            build_seconds = time.perf_counter() - t0
            build_traffic = made.traffic.as_dict()
            made.traffic.__init__()
            t0 = time.perf_counter()
            baked = farm.bake(scene, names, settings, lmdp=lmdp, farm=made)
            bake_seconds = time.perf_counter() - t0
            traffic = made.traffic.as_dict()
            t0 = time.perf_counter()        # again: the workers have the recipe set up already
            again = farm.bake(scene, names, settings, lmdp=lmdp, farm=made)
            again_seconds = time.perf_counter() - t0
            rows.append({"where": f"farm, {n} local worker process{'es' if n > 1 else ''}", "workers": n,
                         "threads": 1, "start_seconds": start, "bake_seconds": bake_seconds,
                         "again_seconds": again_seconds, "build_seconds": build_seconds,
                         "bake_traffic": traffic, "build_traffic": build_traffic,
                         "bake_identical": _identical_bakes(local, baked) and _identical_bakes(local, again),
                         "build_identical": _identical_builds(lmdp, built)})
        log(f"farm: {n} worker(s): bake {bake_seconds:.2f} s (again {again_seconds:.2f} s), build {build_seconds:.2f} s, identical "
            f"{rows[-1]['bake_identical']}/{rows[-1]['build_identical']}")
    texels = sum(o.n_texels for o in local.objects)
    return {"profile": vars(profile), "objects": len(names), "texels": texels, "rows": rows}
