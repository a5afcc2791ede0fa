"""Variance per sample and cost per sample of the bake's techniques, relative to UNGUIDED, in one
interleaved run (engine only, no Blender; issue 20's per-sample efficiency table).

    .venv/bin/python bench/techniques.py [SCENE RECEIVER ...] [--resolution 32] [--samples 64]
                                         [--repeats 3] [--ratios 1,2,4,8]

For each scene: one LMDP (the default 2048 points, sampled, built and solved once, timed) and then,
``repeats`` times in turn, UNGUIDED, GUIDED, FINAL_GATHER and RESIDUAL with each control ratio
(control samples per path, ``residual.CONTROL_RATIO``) bake the receiver on one thread. The
variance per sample is estimated from each bake's own batches: mean over the texels of the
squared standard error, divided by the squared mean of the texels, times the samples (so it does
not depend on the sample count); the cost per sample is the bake's wall time (its setup, e.g. the
gather, included) over the samples. Efficiency = 1 / (variance x cost), relative to UNGUIDED's,
without and with the LMDP precompute. FINAL_GATHER's variance leaves out its bias.
"""
import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lmdp_addon import demo_geometry as scenes  # noqa: E402
from lmdp_addon.bake import driver, residual  # noqa: E402
from lmdp_addon.model import pipeline  # noqa: E402
from lmdp_addon.settings import Settings  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def measure(scene, receiver, settings, lmdp, technique):
    """(variance per sample / mean², wall seconds) of one bake with ``technique`` = (mode, ratio)."""
    mode, ratio = technique
    saved = residual.CONTROL_RATIO
    if ratio is not None:
        residual.CONTROL_RATIO = ratio
    try:
        t0 = time.perf_counter()
        result = driver.bake(scene, [receiver], replace(settings, bake_mode=mode),
                             lmdp if mode != "UNGUIDED" else None, threads=1)
        seconds = time.perf_counter() - t0
    finally:
        residual.CONTROL_RATIO = saved
    ob = result.objects[0]
    value, se = ob.value @ LUMINANCE, ob.standard_error @ LUMINANCE
    return float(np.mean(se ** 2) / np.mean(value) ** 2 * settings.bake_samples), seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", default=["CORNELL_BOX", "Floor", "NARROW_OPENING", "RoomAFloor"])
    parser.add_argument("--resolution", type=int, default=32)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ratios", default="1,2,4,8")
    args = parser.parse_args(argv)
    techniques = [("UNGUIDED", None), ("GUIDED", None), ("FINAL_GATHER", None)] + [
        ("RESIDUAL", int(k)) for k in args.ratios.split(",")]
    for kind, receiver in zip(args.cases[::2], args.cases[1::2]):
        scene = scenes.build_scene_arrays(kind)
        settings = Settings(bake_resolution=args.resolution, bake_samples=args.samples, bake_margin=0)
        t0 = time.perf_counter()
        lmdp = pipeline.run_all(scene, settings)
        precompute = time.perf_counter() - t0
        runs = {t: [] for t in techniques}
        for r in range(args.repeats):
            for t in techniques:
                runs[t].append(measure(scene, receiver, replace(settings, seed=100 + r), lmdp, t))
        base_var = np.mean([v for v, _ in runs[techniques[0]]])
        base_sec = np.mean([s for _, s in runs[techniques[0]]])
        print(f"{kind} / {receiver}: {args.resolution}² texels x {args.samples} samples, {args.repeats} repeats, "
              f"precompute {precompute:.2f} s")
        print(f"  {'technique':18s} {'variance/sample':>16s} {'ratio':>6s} {'cost ratio':>10s} "
              f"{'efficiency':>10s} {'with precompute':>15s}")
        for t in techniques:
            var = np.mean([v for v, _ in runs[t]])
            sec = np.mean([s for _, s in runs[t]])
            wall = sec + (precompute if t[0] != "UNGUIDED" else 0.0)
            label = t[0] if t[1] is None else f"{t[0]} K={t[1]}"
            print(f"  {label:18s} {var:16.3g} {var / base_var:6.2f} {sec / base_sec:10.2f} "
                  f"{base_var * base_sec / (var * sec):10.2f} {base_var * base_sec / (var * wall):15.2f}")


if __name__ == "__main__":
    main()
