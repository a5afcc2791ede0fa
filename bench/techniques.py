"""Variance per sample and cost per sample of the bake's techniques, relative to UNGUIDED, in one
interleaved run (engine only, no Blender; issue 20's per-sample efficiency table).

    .venv/bin/python bench/techniques.py [SCENE RECEIVER ...] [--resolution 32] [--samples 64]
                                         [--repeats 3] [--ratios 1,2,4,8] [--fine strata,G8] [--only-fine]

For each scene: one LMDP (the default 2048 points, sampled, built and solved once, timed) and then,
``repeats`` times in turn, UNGUIDED, GUIDED, FINAL_GATHER and RESIDUAL with each control ratio
(control samples per path, ``residual.CONTROL_RATIO``) bake the receiver on one thread. The
variance per sample is estimated from each bake's own batches: mean over the texels of the
squared standard error, divided by the squared mean of the texels, times the samples (so it does
not depend on the sample count); the cost per sample is the bake's wall time (its setup, e.g. the
gather, included) over the samples. Efficiency = 1 / (variance x cost), relative to UNGUIDED's,
without and with the LMDP precompute. FINAL_GATHER's variance leaves out its bias.

UNGUIDED is plain path tracing (``light_share`` 0, ``path_reuse`` 1); "+ connections" the light
connections (``bake/connections.py``); "+ path reuse" the first bounces shared by tiles of texels
(``bake/reuse.py``); "+ splitting" the solution's Russian roulette and splitting
(``bake/splitting.py``); AUTO the default mode (``bake/auto.py``), given the solved LMDP. GUIDED uses the fine guide (``bake/fine_guide.py``); ``--fine`` adds GUIDED bakes with other
guides (:data:`FINE_VARIANTS`: ``strata``, u* over the solve's 16 strata; fine-guide variants,
``G16@0.3`` with α = 0.3). The time of a guide's table is listed on its own ("table s"): the
cost ratio and the first efficiency leave it out, the efficiency with precompute counts it and
the LMDP's. ``--only-fine``: UNGUIDED, GUIDED and the ``--fine`` variants only. "median": the
median over the texels of each texel's variance ratio to UNGUIDED's (robust to the rare bright
paths that make the mean variance noisy). ``--cpu``: times in CPU seconds of the process.
"""
import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lmdp_addon import demo_geometry as scenes  # noqa: E402
from lmdp_addon.bake import driver, fine_guide, residual  # noqa: E402
from lmdp_addon.model import pipeline  # noqa: E402
from lmdp_addon.settings import Settings  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: Time the bakes in CPU seconds of this process (``--cpu``): on a machine that other work
#: shares, wall time also counts the waits for a core.
CPU_TIME = False


#: Fine-guide variants (``--fine``): label -> ``fine_guide.build_fine_guide`` keywords.
FINE_VARIANTS = {
    "strata": None,          # u*(k|s) over the solve's 16 strata (GUIDED before the fine guide)
    "G8": dict(resolution=8),
    "G16": dict(resolution=16),
    "G32": dict(resolution=32),
    "G16-nocos": dict(resolution=16, product=False),
    "G16-R1/4": dict(resolution=16, rays_per_cell=0.25),
    "G32-R1/4": dict(resolution=32, rays_per_cell=0.25),
    "G16-nodirect": dict(resolution=16, direct=False),
    "G16-nonbr": dict(resolution=16, neighbours=1),
    "G16-n16": dict(resolution=16, neighbours=16),
    "G16-n4": dict(resolution=16, neighbours=4),
    "G8-n16": dict(resolution=8, neighbours=16),
    "G8-n4": dict(resolution=8, neighbours=4),
    "G8-n32": dict(resolution=8, neighbours=32),
    "G16-floor0.05": dict(resolution=16, floor=0.05),
    "G16-floor0.2": dict(resolution=16, floor=0.2),
}


def measure(scene, receiver, settings, lmdp, technique):
    """``(variance per sample / mean², wall seconds, guide-table seconds)`` of one bake with
    ``technique`` = (label, mode, options): ``ratio`` RESIDUAL's control ratio, ``fine`` the
    keywords of the fine guide that replaces GUIDED's (its table's time is part of the wall
    time and also returned on its own), ``fraction`` the guide fraction α."""
    _, mode, options = technique
    saved = residual.CONTROL_RATIO, driver.build_guide
    seconds_table = []
    if mode == "GUIDED" and "fine" not in options:   # the default guide: time its table too
        def build(scene_, lmdp_, fine=False, seed=0, paths=None):
            t0 = time.process_time() if CPU_TIME else time.perf_counter()
            g = saved[1](scene_, lmdp_, fine=fine, seed=seed, paths=paths)
            if hasattr(g, "info"):
                seconds_table.append((time.process_time() if CPU_TIME else time.perf_counter()) - t0)
            return g
        driver.build_guide = build
    if "ratio" in options:
        residual.CONTROL_RATIO = options["ratio"]
    if "fine" in options:
        def build(scene_, lmdp_, fine=False, seed=0, paths=None):
            if options["fine"] is None:
                return saved[1](scene_, lmdp_)
            t0 = time.process_time() if CPU_TIME else time.perf_counter()
            g = fine_guide.build_fine_guide(scene_, lmdp_, seed=seed, **options["fine"])
            seconds_table.append((time.process_time() if CPU_TIME else time.perf_counter()) - t0)
            return g
        driver.build_guide = build
    if "fraction" in options:
        settings = replace(settings, guide_fraction=options["fraction"])
    settings = replace(settings, light_share=options.get("light_share", settings.light_share),
                       splitting=options.get("splitting", settings.splitting),
                       path_reuse=options.get("path_reuse", settings.path_reuse))
    try:
        t0 = time.process_time() if CPU_TIME else time.perf_counter()
        result = driver.bake(scene, [receiver], replace(settings, bake_mode=mode),
                             lmdp if mode != "UNGUIDED" else None, threads=1)
        seconds = (time.process_time() if CPU_TIME else time.perf_counter()) - t0
    finally:
        residual.CONTROL_RATIO, driver.build_guide = saved
    ob = result.objects[0]
    value, se = ob.value @ LUMINANCE, ob.standard_error @ LUMINANCE
    return (float(np.mean(se ** 2) / np.mean(value) ** 2 * settings.bake_samples), seconds,
            float(sum(seconds_table)), se.astype(np.float64) ** 2)


def techniques_of(args):
    """The techniques of the command line: (label, mode, options)."""
    one = {"path_reuse": 1}
    out = [("UNGUIDED", "UNGUIDED", {"light_share": 0.0, **one})]      # plain path tracing: the reference
    out += [("UNGUIDED + connections", "UNGUIDED", one)]
    out += [("UNGUIDED + path reuse", "UNGUIDED", {"light_share": 0.0})]
    out += [("UNGUIDED + connections + path reuse", "UNGUIDED", {})]
    out += [("GUIDED", "GUIDED", {"light_share": 0.0, "splitting": False, **one})]
    out += [("GUIDED + connections", "GUIDED", {"splitting": False, **one})]
    out += [("GUIDED + connections + splitting", "GUIDED", one)]
    out += [("GUIDED + connections + splitting + path reuse", "GUIDED", {})]
    out += [("AUTO (default)", "AUTO", {})]
    if not args.only_fine:
        out += [("FINAL_GATHER", "FINAL_GATHER", {})]
        out += [(f"RESIDUAL K={k}", "RESIDUAL", {"ratio": int(k)}) for k in args.ratios.split(",") if k]
    for label in [x for x in args.fine.split(",") if x]:
        fraction = None
        if "@" in label:
            label, fraction = label.split("@")
        options = {"fine": FINE_VARIANTS[label], "light_share": 0.0, "splitting": False, **one}   # the guide alone
        if fraction is not None:
            options["fraction"] = float(fraction)
        out.append((f"GUIDED {label}" + (f" α={fraction}" if fraction else ""), "GUIDED", options))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", default=["CORNELL_BOX", "Floor", "NARROW_OPENING", "RoomAFloor"])
    parser.add_argument("--resolution", type=int, default=32)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ratios", default="1,2,4,8")
    parser.add_argument("--fine", default="strata",
                        help="fine-guide variants, comma-separated (FINE_VARIANTS; 'G16@0.3': α = 0.3)")
    parser.add_argument("--only-fine", action="store_true", help="UNGUIDED, GUIDED and the fine variants only")
    parser.add_argument("--cpu", action="store_true", help="time in CPU seconds of this process (CPU_TIME)")
    args = parser.parse_args(argv)
    global CPU_TIME
    CPU_TIME = args.cpu
    techniques = techniques_of(args)
    for kind, receiver in zip(args.cases[::2], args.cases[1::2]):
        scene = scenes.build_scene_arrays(kind)
        settings = Settings(bake_resolution=args.resolution, bake_samples=args.samples, bake_margin=0)
        t0 = time.perf_counter()
        lmdp = pipeline.run_all(scene, settings)
        precompute = time.perf_counter() - t0
        runs = {t[0]: [] for t in techniques}
        for r in range(args.repeats):
            for t in techniques:
                runs[t[0]].append(measure(scene, receiver, replace(settings, seed=100 + r), lmdp, t))
        base_var = np.mean([r[0] for r in runs["UNGUIDED"]])
        base_sec = np.mean([r[1] for r in runs["UNGUIDED"]])
        print(f"{kind} / {receiver}: {args.resolution}² texels x {args.samples} samples, {args.repeats} repeats, "
              f"UNGUIDED bake {base_sec:.2f} s{' CPU' if CPU_TIME else ''}, LMDP precompute {precompute:.2f} s")
        print(f"  {'technique':22s} {'variance/sample':>16s} {'ratio':>6s} {'median':>6s} {'table s':>8s} "
              f"{'cost ratio':>10s} {'efficiency':>10s} {'with precompute':>15s}")
        for label, mode, _ in techniques:
            var = np.mean([r[0] for r in runs[label]])
            sec = np.mean([r[1] for r in runs[label]])
            table = np.mean([r[2] for r in runs[label]])
            median = np.mean([_median_ratio(r[3], u[3]) for r, u in zip(runs[label], runs["UNGUIDED"])])
            trace = sec - table            # the bake without the guide's table
            wall = sec + (precompute if mode != "UNGUIDED" else 0.0)
            print(f"  {label:22s} {var:16.3g} {var / base_var:6.2f} {median:6.2f} {table:8.2f} "
                  f"{trace / base_sec:10.2f} {base_var * base_sec / (var * trace):10.2f} "
                  f"{base_var * base_sec / (var * wall):15.2f}")


def _median_ratio(var, base):
    """Median over the texels lit in both of the ratio of their variances (``var`` over
    ``base``, luminance): robust to the rare bright paths that dominate the mean variance."""
    lit = (var > 0) & (base > 0)
    return float(np.median(var[lit] / base[lit])) if np.any(lit) else float("nan")

if __name__ == "__main__":
    main()
