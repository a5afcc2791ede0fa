#!/usr/bin/env python3
"""Subprocess jobs of the engine benchmarks, so that each measures its own peak memory.

    python bench/worker.py build --kind CORNELL_BOX --points 6250 --save P.npz --json out.json
    python bench/worker.py solve --load P.npz --solver ITERATIVE --repeats 3 --json out.json

Peak memory of a job = the process's resident-set high-water mark (``VmHWM``) during the job
minus its resident set just before it (``VmRSS``); the high-water mark is reset before the job
(``/proc/self/clear_refs`` = 5) so that imports and input loading do not count. Where that reset
is refused, ``ru_maxrss`` after minus before is used instead (then the figure is a lower bound)
and the JSON says which. ``solve`` also runs once more under ``tracemalloc`` (numpy's and
Python's own allocations only; LAPACK / SuperLU work arrays are invisible to it).
"""
import argparse
import gc
import json
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _status_kib(field):
    try:
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


class PeakMemory:
    """``with PeakMemory() as pm: ...`` then ``pm.bytes`` (peak extra resident memory) and
    ``pm.method``."""

    def __enter__(self):
        gc.collect()
        self.before_rss = _status_kib("VmRSS")
        self.method = "VmHWM - VmRSS (high-water mark reset)"
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
        except OSError:
            self.method = "ru_maxrss delta (lower bound)"
        self.before_max = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return self

    def __exit__(self, *exc):
        if self.method.startswith("VmHWM") and self.before_rss is not None:
            self.bytes = max(_status_kib("VmHWM") - self.before_rss, 0) * 1024
        else:
            self.bytes = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - self.before_max, 0) * 1024
        return False


def build(args):
    import numpy as np
    from lmdp_addon.model import dynamics
    from lmdp_addon import demo_geometry as scenes
    from lmdp_addon.model import states as states_mod
    from lmdp_addon.model.costs import build_first_exit_lmdp
    scene = scenes.build_scene_arrays(args.kind)
    t = time.perf_counter()
    states = states_mod.sample_states(scene, args.points, args.strata_u, args.strata_v, seed=args.seed)
    sample_seconds = time.perf_counter() - t
    S = states.n_strata
    estimate = dynamics.estimate_build_bytes(states.n_points, S, args.rays, args.light_samples, scene.n_triangles,
                                             states.unknowns.n_glossy)
    print(f"[worker] {states.n_points} points x {S} strata = {states.n_states} states; "
          f"estimated build memory {estimate / 1024 ** 2:.1f} MiB (dynamics.estimate_build_bytes)",
          file=sys.stderr, flush=True)
    with PeakMemory() as pm:
        t = time.perf_counter()
        dyn = dynamics.build_passive_dynamics(scene, states, args.rays, seed=args.seed,
                                              light_samples=args.light_samples)
        seconds = time.perf_counter() - t
    lmdp = build_first_exit_lmdp(dyn, states, "PHYSICAL")
    P = lmdp.P.tocsr()
    np.savez(args.save, P_data=P.data, P_indices=P.indices, P_indptr=P.indptr, P_shape=np.array(P.shape),
             q=lmdp.q, g=lmdp.g, z_terminal=lmdp.z_terminal, lambda_=np.array(lmdp.lambda_),
             cost_mode=np.array(lmdp.cost_mode), epsilon=np.array(lmdp.epsilon))
    return {
        "kind": args.kind, "points": states.n_points, "strata": S, "states": states.n_states,
        "rays_per_stratum": args.rays, "light_samples": args.light_samples,
        "rays": int(dyn.rays), "shadow_rays": int(dyn.counts.get("nee_rays", 0)),
        "sample_seconds": sample_seconds, "build_seconds": seconds,
        "stage_seconds": {k: float(v) for k, v in dyn.seconds.items()},
        "estimate_bytes": int(estimate), "peak_bytes": int(pm.bytes), "peak_method": pm.method,
        "dynamics_bytes": int(dyn.memory_bytes()), "nnz": int(dyn.P.nnz),
        "stratum_nnz": int(dyn.stratum_transitions.nnz),
    }


def solve(args):
    import numpy as np
    import scipy.sparse as sp
    from lmdp_addon.model.costs import FirstExitLMDP
    from lmdp_addon.errors import LMDPError
    from lmdp_addon.model.solvers import solve_desirability
    d = np.load(args.load)
    P = sp.csr_matrix((d["P_data"], d["P_indices"], d["P_indptr"]), shape=tuple(d["P_shape"]))
    lmdp = FirstExitLMDP(P=P, q=d["q"], z_terminal=d["z_terminal"], lambda_=float(d["lambda_"]),
                         cost_mode=str(d["cost_mode"]), g=d["g"], epsilon=float(d["epsilon"]))
    out = {"solver": args.solver, "points": int(P.shape[0]), "unknowns": int(P.shape[0] * lmdp.q.shape[1]),
           "tolerance": args.tolerance, "max_iterations": args.max_iterations}
    seconds = []
    try:
        with PeakMemory() as pm:
            sol = solve_desirability(lmdp, args.solver, args.tolerance, args.max_iterations, seed=0)
        seconds.append(sol.seconds)
        for r in range(1, args.repeats):
            sol = solve_desirability(lmdp, args.solver, args.tolerance, args.max_iterations, seed=r)
            seconds.append(sol.seconds)
    except LMDPError as exc:
        out.update(refused=str(exc))
        return out
    out.update(seconds=seconds, residual=float(sol.residual), residual_z=float(sol.residual_z),
               iterations=int(sol.iterations), converged=bool(sol.converged), message=sol.message,
               peak_bytes=int(pm.bytes), peak_method=pm.method)
    if args.tracemalloc and seconds[0] < 5.0:     # skipped for long solves (DIRECT at 10^5 states)
        import tracemalloc
        gc.collect()
        tracemalloc.start()
        solve_desirability(lmdp, args.solver, args.tolerance, args.max_iterations, seed=0)
        out["tracemalloc_peak_bytes"] = int(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog="bench/worker.py", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="job", required=True)
    b = sub.add_parser("build")
    b.add_argument("--kind", default="CORNELL_BOX")
    b.add_argument("--points", type=int, required=True)
    b.add_argument("--strata-u", type=int, default=4)
    b.add_argument("--strata-v", type=int, default=4)
    b.add_argument("--rays", type=int, default=4)
    b.add_argument("--light-samples", type=int, default=32)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--save", required=True)
    b.add_argument("--json", required=True)
    s = sub.add_parser("solve")
    s.add_argument("--load", required=True)
    s.add_argument("--solver", required=True, choices=("POWER", "DIRECT", "ITERATIVE"))
    s.add_argument("--tolerance", type=float, default=1e-8)
    s.add_argument("--max-iterations", type=int, default=10000)
    s.add_argument("--repeats", type=int, default=1)
    s.add_argument("--tracemalloc", action="store_true")
    s.add_argument("--json", required=True)
    args = p.parse_args(argv)
    result = build(args) if args.job == "build" else solve(args)
    Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
