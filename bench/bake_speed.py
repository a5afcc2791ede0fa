#!/usr/bin/env python3
"""Speed against error of lmdp.bake against Cycles' bake, on one receiver (default: the Cornell box
floor at 128 x 128), plus the tracer's throughput against raw embreex.

    .venv/bin/python bench/bake_speed.py                       # Cornell floor, 128 px
    .venv/bin/python bench/bake_speed.py --scene narrow_opening --resolution 64
    .venv/bin/python bench/bake_speed.py --cycles 16,64 --lmdp 16,64 --modes GUIDED

What it does (one process, headless bpy):

1. builds the demo scene in Blender (``operators.adapters.demo_scenes``), Cycles on the CPU with adaptive
   sampling and indirect clamping off, ``max_bounces`` = diffuse bounces = ``--bounces`` on both
   sides;
2. a high-sample Cycles reference of the same bake, as two halves (seeds 1, 2) so that its own
   noise is known, cached in ``bench/results/bake_speed/`` (ignored by git);
3. Cycles at ``--cycles`` samples and the engine (``lmdp_addon.bake.driver.bake``, what ``lmdp.bake``
   calls, on the scene extracted from Blender) in each ``--modes`` at ``--lmdp`` samples; the
   GUIDED / FINAL_GATHER times include the LMDP precompute (sample + build + solve), also shown
   separately;
4. error = relative RMSE over the covered texels against the reference, with the reference's
   noise removed (E[(x - ref)²] = var_x + bias² + var_ref); bias = relative difference of the
   means (Rec.709 luminance);
5. "time to Cycles' error": for every Cycles sample count, the time each method needs for the same
   relative RMSE, interpolating its own measurements as error ∝ time^-1/2 (least squares in log
   space), as a ratio to Cycles' time.

Times are wall-clock medians over ``--repeats`` runs on this machine (threads: the engine's
``baking.BAKE_THREADS``, Cycles' default). Nothing here is a test; the benchmark suite
(``bench/run.py``) is the place for the full figures.
"""
import argparse
import hashlib
import importlib
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "bench" / "results" / "bake_speed"
LUM = np.array([0.2126, 0.7152, 0.0722])
SCENES = {"cornell": ("CORNELL_BOX", "Floor"), "narrow_opening": ("NARROW_OPENING", "RoomAFloor")}


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", choices=sorted(SCENES), default="cornell")
    p.add_argument("--object", default="", help="receiver (default: the scene's floor)")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--bounces", type=int, default=8)
    p.add_argument("--ref-samples", type=int, default=2048, help="Cycles reference samples (two halves)")
    p.add_argument("--cycles", default="16,64,256", help="Cycles sample counts")
    p.add_argument("--lmdp", default="16,64,256", help="engine sample counts")
    p.add_argument("--gather", default="1,4,16", help="FINAL_GATHER sample counts")
    p.add_argument("--modes", default="UNGUIDED,GUIDED,FINAL_GATHER")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="engine Settings override for GUIDED / FINAL_GATHER (e.g. point_count=8192)")
    p.add_argument("--repeats", type=int, default=1)
    return p.parse_args(argv)


def start_blender():
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lmdp_bench_user_"))
    sys.path.insert(0, str(ROOT / "scripts"))
    sys.path.insert(0, str(ROOT))
    import bpy  # noqa: F401
    import lmdp_extension
    module, _ = lmdp_extension.register_checkout(str(ROOT), tempfile.mkdtemp(prefix="lmdp_bench_repo_"),
                                                 repo_module="lmdp_bench")
    return module


def settings_overrides(items):
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        for cast in (int, float):
            try:
                value = cast(value)
                break
            except ValueError:
                continue
        out[key.strip()] = value
    return out


def reference(demo, obj, args, fingerprint):
    import bpy
    halves = []
    for seed in (1, 2):
        key = "|".join(map(str, (fingerprint, obj.name, args.resolution, args.ref_samples // 2, seed,
                                 args.bounces, bpy.app.version_string)))
        path = CACHE / (hashlib.sha1(key.encode()).hexdigest()[:20] + ".npz")
        if path.exists():
            data = np.load(path)
            halves.append((data["pixels"], float(data["seconds"])))
            continue
        print(f"reference half {seed}: {args.ref_samples // 2} samples ...", flush=True)
        t = time.perf_counter()
        px = demo.bake_cycles(bpy.context, obj, 'DIFFUSE', ('INDIRECT',), args.resolution,
                              samples=args.ref_samples // 2, margin=0, max_bounces=args.bounces, seed=seed,
                              fill=-1.0)
        seconds = time.perf_counter() - t
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(path, pixels=px, seconds=seconds)
        halves.append((px, seconds))
    (a, ta), (b, tb) = halves
    return a, b, ta + tb


def score(values, ts, ref, var_ref):
    """(relative RMSE corrected for the reference noise, relative bias), luminance."""
    x = values.astype(np.float64) @ LUM
    r = ref[ts.row, ts.col] @ LUM
    v = var_ref[ts.row, ts.col] @ (LUM ** 2)
    mse = np.mean((x - r) ** 2) - np.mean(v)
    return np.sqrt(max(mse, 0.0)) / r.mean(), (x.mean() - r.mean()) / r.mean()


def raw_embree_rate(scene, n=1 << 19, repeats=3):
    """Rays/s of embreex alone on this scene: closest-hit rays from the surfaces, cosine directions."""
    from lmdp_addon.raycast import RayCaster
    caster = RayCaster(scene)
    rng = np.random.default_rng(0)
    normals, areas = scene.triangle_geometry()
    tri = rng.choice(len(areas), n, p=areas / areas.sum())
    c = scene.corners()[tri]
    u = np.sqrt(rng.random(n))[:, None]
    v = rng.random(n)[:, None]
    p = (1 - u) * c[:, 0] + u * (1 - v) * c[:, 1] + u * v * c[:, 2] + caster.offset(tri)[:, None] * normals[tri]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.sign(np.einsum("ij,ij->i", d, normals[tri]))[:, None]
    o = p.astype(np.float32)
    d = d.astype(np.float32)
    best = []
    for _ in range(repeats):
        t = time.perf_counter()
        caster._embree.run(o, d, output=1)
        best.append(time.perf_counter() - t)
    return n / float(np.median(best))


def fit_time(points, target):
    """Time at which error = target, from (time, error) points, error ∝ time^-1/2 fitted in logs."""
    t = np.array([p[0] for p in points])
    e = np.array([p[1] for p in points])
    ok = (t > 0) & (e > 0)
    if ok.sum() == 0:
        return float("nan")
    # log e = c - 0.5 log t  ->  c = mean(log e + 0.5 log t)
    c = np.mean(np.log(e[ok]) + 0.5 * np.log(t[ok]))
    return float(np.exp(2.0 * (c - np.log(target))))


def cycles_rows(demo, obj, ts, ref, var_ref, args):
    """One row per Cycles sample count: (method, samples, time, 0, rel RMSE, bias, None)."""
    import bpy
    rows = []
    for spp in [int(x) for x in args.cycles.split(",") if x]:
        times, errs, biases = [], [], []
        for r in range(args.repeats):
            t = time.perf_counter()
            px = demo.bake_cycles(bpy.context, obj, 'DIFFUSE', ('INDIRECT',), args.resolution, samples=spp,
                                  margin=0, max_bounces=args.bounces, seed=100 + r)[..., :3]
            times.append(time.perf_counter() - t)
            e, b = score(px[ts.row, ts.col], ts, ref, var_ref)
            errs.append(e)
            biases.append(b)
        rows.append(("Cycles", spp, float(np.median(times)), 0.0, float(np.sqrt(np.mean(np.square(errs)))),
                     float(np.mean(biases)), None))
    return rows


def engine_rows(arrays, receiver, ref, var_ref, args, baking, pipeline, Settings):
    """The engine's rows per mode and sample count (precompute included), and the (time, error)
    curve of each mode."""
    overrides = settings_overrides(args.settings)
    rows, curves = [], {}
    for mode in [m.strip().upper() for m in args.modes.split(",") if m.strip()]:
        ladder = args.gather if mode == "FINAL_GATHER" else args.lmdp
        for spp in [int(x) for x in ladder.split(",") if x]:
            times, pre, errs, biases, rates = [], [], [], [], []
            for r in range(args.repeats):
                s = Settings(bake_mode=mode, bake_resolution=args.resolution, bake_samples=spp, bake_margin=0,
                             max_bounces=args.bounces, seed=100 + r, **(overrides if mode != "UNGUIDED" else {}))
                t = time.perf_counter()
                lm = pipeline.run_all(arrays, s) if mode != "UNGUIDED" else None
                tp = time.perf_counter() - t
                result = baking.bake(arrays, [receiver], s, lmdp=lm)
                total = time.perf_counter() - t
                ob = result.objects[0]
                e, b = score(ob.value, ob.texels, ref, var_ref)
                times.append(total)
                pre.append(tp)
                errs.append(e)
                biases.append(b)
                rates.append(ob.stats.total_rays / max(ob.seconds, 1e-9))
            row = (mode, spp, float(np.median(times)), float(np.median(pre)),
                   float(np.sqrt(np.mean(np.square(errs)))), float(np.mean(biases)), float(np.median(rates)))
            rows.append(row)
            curves.setdefault(mode, []).append((row[2], row[4]))
    return rows, curves


def print_tables(rows, cyc, curves, embree):
    """The speed-against-error table and each mode's time to reach Cycles' error."""
    print(f"{'method':<14}{'samples':>8}{'time s':>9}{'precomp s':>11}{'rel RMSE':>10}{'bias':>9}{'Mrays/s':>9}")
    for m, spp, t, tp, e, b, rate in rows:
        print(f"{m:<14}{spp:>8}{t:>9.2f}{tp:>11.2f}{e:>10.4f}{100 * b:>8.2f}%"
              + (f"{rate / 1e6:>9.2f}" if rate else f"{'':>9}"))
    print(f"\nraw embreex on this scene: {embree / 1e6:.2f} Mrays/s (closest hit, one thread)")
    print("\ntime to reach Cycles' error, as a ratio to Cycles' time (< 1: faster than Cycles):")
    header = "".join(f"{'@' + str(r[1]) + ' spp':>12}" for r in cyc)
    print(f"{'method':<14}{header}")
    for mode, pts in curves.items():
        if mode == "Cycles":
            continue
        ratios = [fit_time(pts, r[4]) / r[2] for r in cyc]
        print(f"{mode:<14}" + "".join(f"{x:>12.2f}" for x in ratios))


def main(argv=None):
    args = parse(sys.argv[1:] if argv is None else argv)
    module = start_blender()
    import bpy
    demo = importlib.import_module(module + ".operators.adapters.demo_scenes")
    extract = importlib.import_module(module + ".operators.adapters.extract")
    from lmdp_addon.bake import checks, driver as baking
    from lmdp_addon.model import pipeline
    from lmdp_addon.settings import Settings

    kind, receiver = SCENES[args.scene]
    receiver = args.object or receiver
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    carriers = demo.build_demo_scene(kind, bpy.context)
    scene = bpy.context.scene
    scene.cycles.sample_clamp_indirect = 0.0
    obj = bpy.data.objects[receiver]
    arrays = extract.extract_scene(bpy.context, carriers)
    ref_a, ref_b, ref_seconds = reference(demo, obj, args, checks.scene_fingerprint(arrays))
    ref = (ref_a[..., :3] + ref_b[..., :3]) / 2.0
    var_ref = (ref_a[..., :3] - ref_b[..., :3]) ** 2 / 4.0
    ts, _ = checks.object_texels(arrays, arrays.object_names.index(receiver), args.resolution)
    covered = ref_a[..., 0] >= 0
    mismatch = int(np.count_nonzero(covered != ts.covered_mask()))

    print(f"\n{args.scene}: '{receiver}' at {args.resolution} x {args.resolution} ({len(ts)} texels, "
          f"coverage mismatch with Cycles: {mismatch}), {args.bounces} bounces both sides")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}, "
          f"Blender {bpy.app.version_string}, engine threads {baking.BAKE_THREADS}")
    print(f"reference: Cycles {args.ref_samples} samples ({ref_seconds:.1f} s), mean "
          f"{ref[ts.row, ts.col].mean(axis=0) @ LUM:.5f} (luminance)\n")

    cyc = cycles_rows(demo, obj, ts, ref, var_ref, args)
    rows, curves = engine_rows(arrays, receiver, ref, var_ref, args, baking, pipeline, Settings)
    curves["Cycles"] = [(r[2], r[4]) for r in cyc]
    print_tables(cyc + rows, cyc, curves, raw_embree_rate(arrays))
    return 0


if __name__ == "__main__":
    sys.exit(main())
