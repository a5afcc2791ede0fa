"""The engine's own figures (issue 6, "The engine's own figures"; issue 3, "Speed").

* :func:`run_build`: ``dynamics.build_passive_dynamics`` throughput, all stages (locator tables,
  direction patterns, tracing, hit classification, next-event shadow rays, sparse assembly), in
  rays per second counting the stratum rays *and* the shadow rays, against raw embreex on the
  very same rays: every batch the build hands to the ray caster is recorded (a build with a
  recording caster, not timed) and replayed straight into ``EmbreeScene.run`` with the same batch
  sizes and query types (closest hit with hit data for stratum rays, occlusion for shadow rays),
  on one thread and on a pool of one thread per usable CPU; the faster counts. The recorded
  arrays are converted to contiguous float32 before the replay is timed (the engine's own
  conversions are part of its time).
* :func:`run_solve`: ``solvers.solve_desirability`` per solver for 10^3 .. 10^6 states
  (points x 16 strata; the Lambertian reduction solves one unknown per point and RGB channel),
  each build and each solve in its own subprocess (``bench/worker.py``) for its peak memory.
* :func:`run_convergence`: the power method's ``||z_i - z_{i-1}||_2`` per iteration against λ
  (THESIS cost mode), as in the thesis's Figures 3 and 4.
* :func:`run_policy`: u*(k|x) of one floor state over its strata for several λ (Figure 5).
"""
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import metrics
from .common import ROOT, Stopwatch, log


#: Where the state of the u* figure sits: the front-left floor, which sees the light directly.
POLICY_POINT = (-0.3, -0.3, 0.0)


@dataclass
class EngineProfile:
    name: str
    repeats: int
    build_points: int
    build_cases: tuple
    solve_points: tuple
    solve_repeats: int
    lambdas: tuple
    convergence_points: int
    policy_points: int
    strata: tuple = (4, 4)
    convergence_strata: tuple = (4, 2)   #: 8 states per point, as in the thesis's Figures 3-4
    policy_strata: tuple = (8, 8)
    tolerance: float = 1e-8
    convergence_tolerance: float = 1e-13
    convergence_max_iterations: int = 5000


def _defaults():
    from lmdp_addon.settings import Settings
    return Settings()


# -- build throughput ----------------------------------------------------------------------------

def _recording_caster(scene):
    """A ``RayCaster`` that keeps a copy of every batch it is asked to trace."""
    from lmdp_addon.raycast import RayCaster

    class RecordingCaster(RayCaster):
        def __init__(self, scene):
            super().__init__(scene)
            self.calls = []

        def intersect(self, origins, directions, barycentrics=False):
            self.calls.append(("intersect", np.array(origins, np.float32), np.array(directions, np.float32), None))
            return super().intersect(origins, directions, barycentrics)

        def occluded(self, origins, directions, distances):
            self.calls.append(("occluded", np.array(origins, np.float32), np.array(directions, np.float32),
                               np.array(distances, np.float32)))
            return super().occluded(origins, directions, distances)

    return RecordingCaster(scene)


def raw_embree_seconds(scene, calls, threads):
    """Wall time of ``calls`` replayed straight into embreex (module docstring)."""
    from lmdp_addon.raycast import BATCH, RayCaster
    embree = RayCaster(scene)._embree     # the same BVH as the engine's caster (build not timed)
    jobs = []
    for kind, o, d, t in calls:           # the caster's own chunking into embreex calls
        for start in range(0, len(o), BATCH):
            sl = slice(start, start + BATCH)
            jobs.append((kind, np.ascontiguousarray(o[sl]), np.ascontiguousarray(d[sl]),
                         None if t is None else np.ascontiguousarray(t[sl])))

    def one(job):
        kind, o, d, t = job
        if kind == "intersect":
            embree.run(o, d, output=1)
        else:
            embree.run(o, d, dists=t, query="OCCLUDED")

    with Stopwatch() as sw:
        if threads <= 1:
            for job in jobs:
                one(job)
        else:
            with ThreadPoolExecutor(max_workers=threads) as pool:
                list(pool.map(one, jobs))
    return sw.seconds


def run_build(profile, out):
    import os
    from lmdp_addon.model import dynamics
    from lmdp_addon import demo_geometry as scenes
    from lmdp_addon.model.states import sample_states
    defaults = _defaults()
    R, K = defaults.rays_per_stratum, defaults.light_samples
    cpus = len(os.sched_getaffinity(0))
    rows = []
    for kind in profile.build_cases:
        scene = scenes.build_scene_arrays(kind)
        with Stopwatch() as sw:
            states = sample_states(scene, profile.build_points, *profile.strata, seed=0)
        sample_seconds = sw.seconds
        builds = []
        dyn = None
        for r in range(profile.repeats):
            with Stopwatch() as sw:
                dyn = dynamics.build_passive_dynamics(scene, states, R, seed=0, light_samples=K)
            builds.append({"seconds": sw.seconds, "stages": {k: float(v) for k, v in dyn.seconds.items()}})
        rays = int(dyn.rays)
        shadow = int(dyn.counts.get("nee_rays", 0))
        recorder = _recording_caster(scene)
        dynamics.build_passive_dynamics(scene, states, R, seed=0, light_samples=K, caster=recorder)
        recorded_closest = sum(len(c[1]) for c in recorder.calls if c[0] == "intersect")
        recorded_shadow = sum(len(c[1]) for c in recorder.calls if c[0] == "occluded")
        raw = {}
        for threads in sorted({1, cpus}):
            raw[threads] = metrics.median([raw_embree_seconds(scene, recorder.calls, threads)
                                           for _ in range(profile.repeats)])
        recorder.calls.clear()
        total_rays = recorded_closest + recorded_shadow
        build_s = metrics.median([b["seconds"] for b in builds])
        best_threads = min(raw, key=raw.get)
        row = {
            "kind": kind, "triangles": int(scene.n_triangles), "points": states.n_points,
            "strata": states.n_strata, "states": states.n_states, "rays_per_stratum": R, "light_samples": K,
            "stratum_rays": rays, "shadow_rays": shadow, "recorded_closest": recorded_closest,
            "recorded_shadow": recorded_shadow, "repeats": profile.repeats,
            "sample_seconds": sample_seconds, "build_seconds": build_s,
            "stage_seconds": {k: metrics.median([b["stages"].get(k, 0.0) for b in builds])
                              for k in builds[0]["stages"]},
            "build_rays_per_second": total_rays / build_s,
            "raw_seconds": {str(k): v for k, v in raw.items()},
            "raw_rays_per_second": {str(k): total_rays / v for k, v in raw.items()},
            "raw_best_threads": best_threads,
            "fraction_of_raw": (total_rays / build_s) / (total_rays / raw[best_threads]),
        }
        log(f"build {kind}: {row['states']} states, {total_rays} rays ({shadow} shadow) in {build_s:.2f} s = "
            f"{row['build_rays_per_second'] / 1e6:.2f} Mrays/s; raw embreex {total_rays / raw[best_threads] / 1e6:.2f} "
            f"Mrays/s ({best_threads} thread(s)): {100 * row['fraction_of_raw']:.0f}%")
        rows.append(row)
    return {"rows": rows, "target_fraction": 0.5, "cpus": cpus}


# -- solver scaling ------------------------------------------------------------------------------

def _worker(args, timeout=3600):
    with tempfile.TemporaryDirectory(prefix="lmdp_bench_job_") as tmp:
        out = Path(tmp) / "out.json"
        cmd = [sys.executable, str(ROOT / "bench" / "worker.py"), *args, "--json", str(out)]
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if run.returncode != 0:
            raise RuntimeError(f"worker {' '.join(args[:1])} failed:\n{run.stderr[-3000:]}")
        for line in run.stderr.splitlines():
            if line.startswith("[worker]"):
                log(line)
        return json.loads(out.read_text())


def run_solve(profile, out):
    defaults = _defaults()
    rows = []
    with tempfile.TemporaryDirectory(prefix="lmdp_bench_solve_") as tmp:
        for points in profile.solve_points:
            path = str(Path(tmp) / f"lmdp_{points}.npz")
            b = _worker(["build", "--kind", "CORNELL_BOX", "--points", str(points),
                         "--strata-u", str(profile.strata[0]), "--strata-v", str(profile.strata[1]),
                         "--rays", str(defaults.rays_per_stratum), "--light-samples", str(defaults.light_samples),
                         "--save", path])
            log(f"solve scaling: built {b['states']} states ({b['points']} points) in {b['build_seconds']:.2f} s, "
                f"peak {b['peak_bytes'] / 2 ** 20:.0f} MiB (estimate {b['estimate_bytes'] / 2 ** 20:.0f} MiB)")
            row = {"build": b, "solvers": {}}
            for solver in ("POWER", "DIRECT", "ITERATIVE"):
                s = _worker(["solve", "--load", path, "--solver", solver, "--tolerance", str(profile.tolerance),
                             "--repeats", str(profile.solve_repeats), "--tracemalloc"])
                if "refused" not in s:
                    s["median_seconds"] = metrics.median(s["seconds"])
                    s["peak_bytes_per_state"] = s["peak_bytes"] / b["states"]
                    log(f"solve scaling: {solver:9s} {b['states']:8d} states: {s['median_seconds']:.3f} s, "
                        f"{s['iterations']} iterations, residual {s['residual']:.1e}, "
                        f"peak {s['peak_bytes'] / 2 ** 20:.1f} MiB")
                else:
                    log(f"solve scaling: {solver:9s} {b['states']:8d} states: refused ({s['refused'][:80]}...)")
                row["solvers"][solver] = s
            rows.append(row)
    return {"rows": rows, "tolerance": profile.tolerance, "scene": "CORNELL_BOX", "cost_mode": "PHYSICAL",
            "strata": list(profile.strata), "repeats": profile.solve_repeats}


# -- power method against λ (Figures 3 and 4) ----------------------------------------------------

def _small_problem(points, strata, seed=0):
    from lmdp_addon.model import dynamics
    from lmdp_addon import demo_geometry as scenes
    from lmdp_addon.model.states import sample_states
    defaults = _defaults()
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    states = sample_states(scene, points, *strata, seed=seed)
    dyn = dynamics.build_passive_dynamics(scene, states, defaults.rays_per_stratum, seed=seed,
                                          light_samples=defaults.light_samples)
    return scene, states, dyn


def run_convergence(profile, out):
    from lmdp_addon.model.costs import build_first_exit_lmdp, thesis_lambda
    from lmdp_addon.model.solvers import solve_desirability
    defaults = _defaults()
    scene, states, dyn = _small_problem(profile.convergence_points, profile.convergence_strata)
    default_lambda = thesis_lambda(scene.total_emitted_power_density(), 1.0)
    curves = []
    for lam in list(profile.lambdas) + [default_lambda]:
        lmdp = build_first_exit_lmdp(dyn, states, "THESIS", lam, defaults.epsilon)
        sol = solve_desirability(lmdp, "POWER", profile.convergence_tolerance, profile.convergence_max_iterations,
                                 seed=0)
        curves.append({"lambda": lam, "lambda_scale": lam / default_lambda, "is_default": lam == default_lambda,
                       "history": [float(h) for h in sol.history],
                       "history_relative": [float(h) for h in sol.history_relative],
                       "iterations": sol.iterations, "converged": sol.converged, "seconds": sol.seconds,
                       "residual": sol.residual})
        log(f"convergence: λ = {lam:.3g}: {sol.iterations} power iterations, "
            f"{'converged' if sol.converged else 'NOT converged'}, {sol.seconds:.3f} s")
    return {"points": states.n_points, "strata": states.n_strata, "states": states.n_states,
            "tolerance": profile.convergence_tolerance, "default_lambda": default_lambda,
            "rays_per_stratum": defaults.rays_per_stratum, "light_samples": defaults.light_samples,
            "curves": curves}


# -- u* of one state against λ (Figure 5) --------------------------------------------------------

def run_policy(profile, out):
    from lmdp_addon.model.costs import build_first_exit_lmdp, thesis_lambda
    from lmdp_addon.model.hemisphere import world_to_local
    from lmdp_addon.model.policy import stratum_policy
    from lmdp_addon.model.solvers import solve_desirability
    defaults = _defaults()
    scene, states, dyn = _small_problem(profile.policy_points, profile.policy_strata)
    floor = scene.object_names.index("Floor")
    ids = np.flatnonzero(states.point_object == floor)
    target = np.array(POLICY_POINT)
    i = int(ids[np.argmin(np.linalg.norm(states.points[ids] - target, axis=1))])
    light = scene.object_names.index("Light")
    light_centre = scene.corners()[scene.triangle_object == light].reshape(-1, 3).mean(axis=0)
    to_light = light_centre - states.points[i]
    local_light = world_to_local(to_light / np.linalg.norm(to_light), states.frames[i])
    default_lambda = thesis_lambda(scene.total_emitted_power_density(), 1.0)
    w = np.asarray(dyn.stratum_transitions.sum(axis=1)).reshape(dyn.n_points, dyn.n_strata)[i]
    passive = w / w.sum()
    dists = []
    for lam in list(profile.lambdas) + [default_lambda]:
        lmdp = build_first_exit_lmdp(dyn, states, "THESIS", lam, defaults.epsilon)
        sol = solve_desirability(lmdp, "ITERATIVE", 1e-10, 10000, seed=0)
        u = stratum_policy(dyn, sol, "all")[i]
        dists.append({"lambda": lam, "lambda_scale": lam / default_lambda, "u": u.tolist(),
                      "kl_from_passive": float(np.sum(np.where(u > 0, u * np.log(np.where(u > 0, u, 1) / passive), 0))),
                      "max": float(u.max())})
    lmdp = build_first_exit_lmdp(dyn, states, "PHYSICAL")
    sol = solve_desirability(lmdp, "ITERATIVE", 1e-10, 10000, seed=0)
    physical = stratum_policy(dyn, sol, "all")[i]
    log(f"policy: state {i} at {np.round(states.points[i], 3).tolist()}, {dyn.n_strata} strata, "
        f"{len(dists)} values of λ")
    from lmdp_addon.model.hemisphere import stratum_of_local_direction
    light_stratum = int(stratum_of_local_direction(local_light, *profile.policy_strata))
    return {"point": i, "target": list(POLICY_POINT), "light_stratum": light_stratum,
            "position": states.points[i].tolist(), "normal": states.normals[i].tolist(),
            "strata_u": profile.policy_strata[0], "strata_v": profile.policy_strata[1],
            "points": states.n_points, "states": states.n_states, "default_lambda": default_lambda,
            "light_direction_local": local_light.tolist(), "passive": passive.tolist(),
            "physical": physical.tolist(), "distributions": dists}
