#!/usr/bin/env python3
"""LMDP Light Transport benchmarks: speed against error with Cycles' bake as the yardstick, and the
engine's own figures (issue 6).

    .venv/bin/python bench/run.py            # the full suite (`make bench`)
    .venv/bin/python bench/run.py --quick    # the short version (`make bench-quick`)

Sections (``--sections``, default all):

* ``bake``         every bake method on the same texels against a cached Cycles reference
                   (``bench/speed_error.py``)
* ``build``        passive-dynamics build throughput against raw embreex on the same rays
* ``solve``        POWER / DIRECT / ITERATIVE time, residual and peak memory, 10^3 .. 10^6 states,
                   including the 10^6-state build with its memory estimate
* ``convergence``  the power method's ||z_i - z_{i-1}|| against λ (thesis Figures 3 and 4)
* ``policy``       u*(k|x) of one state for several λ (thesis Figure 5)
* ``farm``         one bake and build on a Dask LocalCluster of 1 and 2 worker processes: wall
                   time, bytes sent, byte-identity with the local run (``bench/farm_scaling.py``)

Results go to ``bench/results/<profile>/results.json`` (plus a log of every run); the report
(``benchmarks.md`` and ``bench_*.png`` plots) is generated from that file only: the full suite
writes it to ``docs/benchmarks.md`` + ``docs/images/`` and refreshes the README's benchmark block,
``--quick`` writes it next to its results (``--docs`` forces the docs). ``--report-only`` redoes
the report from an existing results.json.
"""
import argparse
import os
import shlex
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import common  # noqa: E402
from bench.common import DEFAULT_NAME, RESULTS, log  # noqa: E402

SECTIONS = ("bake", "build", "solve", "convergence", "policy", "farm")
#: Plain path tracing, the issue's reference: cosine directions and light sampling, without the
#: bake's light connections, path reuse and world portals.
PLAIN = {"light_share": 0.0, "world_portals": False, "path_reuse": 1}


def profiles():
    """The two profiles: ``full`` (make bench) and ``quick`` (make bench-quick)."""
    from bench.engine_figures import EngineProfile
    from bench.speed_error import Profile
    ladder = (4, 16, 64, 256)
    all_cases = ("cornell", "narrow_opening", "heavy", "sun_hdri", "glossy")
    light = ("cornell", "narrow_opening")
    full = Profile(
        name="full",
        cases=all_cases,
        resolution={"cornell": 128, "narrow_opening": 128, "heavy": 128, "sun_hdri": 128, "glossy": 128},
        ref_samples={"cornell": 1024, "narrow_opening": 1024, "heavy": 1024, "sun_hdri": 1024, "glossy": 1024},
        repeats=3,
        # The narrow opening's light is a heavy tail (3 % of the paths carry 82 % of the
        # variance): over 3 repeats plain path tracing's 16-sample error was 158 % (all three
        # bakes 4-6 % dark), over 12 it was 216 %, as its variance per path at 64-256 samples
        # predicts (203-212 %); 12 repeats made the whole run about 4 minutes longer (30 against 26).
        case_repeats={"narrow_opening": 12},
        bounces=8,
        cycles_ladder=(1, 4, 16, 64, 256),
        # Cycles with Open PGL guiding: a column beside Cycles (the heavy scene without 256 samples,
        # which alone would add about a minute per repeat).
        cycles_guided_ladder={"cornell": (16, 64, 256), "narrow_opening": (16, 64, 256), "heavy": (16, 64),
                              "sun_hdri": (16, 64, 256), "glossy": (16, 64, 256)},
        lmdp_methods=[
            # the reference: plain path tracing (no light connections, the map's own world samples)
            dict(mode="UNGUIDED", name="UNGUIDED", ladder=ladder, settings=PLAIN),
            dict(mode="UNGUIDED", name="UNGUIDED + light connections", ladder=ladder,
                 settings={"world_portals": False, "path_reuse": 1}),
            dict(mode="UNGUIDED", name="UNGUIDED + connections + path reuse", ladder=ladder,
                 settings={"world_portals": False}),
            dict(mode="UNGUIDED", name="UNGUIDED + world portals", ladder=ladder, cases=("sun_hdri",),
                 settings={"light_share": 0.0, "path_reuse": 1}),
            # 4, 8: below AUTO's pilot (unguided); 32, 128: a finer curve for the time to Cycles
            dict(mode="AUTO", name=DEFAULT_NAME, ladder=(4, 8, 16, 32, 64, 128, 256)),
            dict(mode="RESIDUAL", name="RESIDUAL 2048 pts (defaults)", ladder=(16, 64, 256)),
            dict(mode="GUIDED", name="GUIDED 2048 pts (defaults)", ladder=ladder),
            dict(mode="GUIDED", name="GUIDED without splitting", ladder=(16, 64, 256), settings={"splitting": False}),
            dict(mode="GUIDED", name="GUIDED THESIS λ x0.01", ladder=(4, 16, 64), cases=light,
                 settings={"cost_mode": "THESIS", "lambda_scale": 0.01}),
            dict(mode="GUIDED", name="GUIDED THESIS λ x1", ladder=(4, 16, 64), cases=light,
                 settings={"cost_mode": "THESIS", "lambda_scale": 1.0}),
            dict(mode="FINAL_GATHER", name="FINAL_GATHER 2048 pts (defaults)", ladder=(1, 4, 16, 64)),
            dict(mode="FINAL_GATHER", name="FINAL_GATHER 8192 pts", ladder=(1, 4, 16, 64), cases=light,
                 settings={"point_count": 8192}),
            dict(mode="FINAL_GATHER", name="FINAL_GATHER 32768 pts", ladder=(1, 4, 16, 64),
                 settings={"point_count": 32768}),
        ],
    )
    quick = Profile(
        name="quick",
        cases=light + ("sun_hdri", "glossy"),
        resolution={"cornell": 64, "narrow_opening": 64, "sun_hdri": 64, "glossy": 64},
        ref_samples={"cornell": 512, "narrow_opening": 512, "sun_hdri": 512, "glossy": 512},
        repeats=1,
        bounces=8,
        cycles_ladder=(1, 4, 16, 64),
        cycles_guided_ladder={"cornell": (16, 64), "narrow_opening": (16, 64)},
        lmdp_methods=[
            dict(mode="UNGUIDED", name="UNGUIDED", ladder=(4, 16, 64), settings=PLAIN),
            dict(mode="UNGUIDED", name="UNGUIDED + light connections", ladder=(4, 16, 64),
                 settings={"world_portals": False, "path_reuse": 1}),
            dict(mode="UNGUIDED", name="UNGUIDED + connections + path reuse", ladder=(4, 16, 64),
                 settings={"world_portals": False}),
            dict(mode="UNGUIDED", name="UNGUIDED + world portals", ladder=(4, 16, 64), cases=("sun_hdri",),
                 settings={"light_share": 0.0, "path_reuse": 1}),
            dict(mode="AUTO", name=DEFAULT_NAME, ladder=(4, 16, 64)),
            dict(mode="RESIDUAL", name="RESIDUAL 2048 pts", ladder=(16, 64)),
            dict(mode="GUIDED", name="GUIDED 2048 pts (defaults)", ladder=(4, 16, 64)),
            dict(mode="GUIDED", name="GUIDED without splitting", ladder=(4, 16, 64), settings={"splitting": False}),
            dict(mode="GUIDED", name="GUIDED THESIS λ x1", ladder=(4, 16), settings={"cost_mode": "THESIS"}),
            dict(mode="FINAL_GATHER", name="FINAL_GATHER 2048 pts", ladder=(1, 4, 16)),
        ],
    )
    engine_full = EngineProfile(name="full", repeats=3,
                                build_points=16384, build_cases=("CORNELL_BOX", "NARROW_OPENING", "HEAVY"),
                                solve_points=(63, 625, 6250, 62500), solve_repeats=3,
                                lambdas=(0.1, 0.5, 1.0, 1.5, 10.0), convergence_points=256,
                                policy_points=2048)
    engine_quick = EngineProfile(name="quick", repeats=1,
                                 build_points=2048, build_cases=("CORNELL_BOX", "NARROW_OPENING", "HEAVY"),
                                 solve_points=(63, 625, 2500), solve_repeats=1,
                                 lambdas=(0.1, 1.0, 10.0), convergence_points=128,
                                 policy_points=512)
    return {"full": (full, engine_full), "quick": (quick, engine_quick)}


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        prog="bench/run.py",
        description="LMDP Light Transport benchmarks: bake speed against error with Cycles' bake as the "
                    "yardstick, dynamics build throughput, solver scaling and memory, power-method "
                    "convergence and u* against λ. Writes bench/results/<profile>/ and a generated report.")
    p.add_argument("--quick", action="store_true", help="the short profile (under 3 minutes): smaller "
                   "images and ladders, one repeat, no heavy-scene bake; report next to the results")
    p.add_argument("--sections", default=",".join(SECTIONS),
                   help=f"comma-separated subset of {','.join(SECTIONS)} (default: all)")
    p.add_argument("--cases", default=None, help="comma-separated subset of the bake cases "
                   "(cornell, narrow_opening, heavy) for a partial run; never written to docs/")
    p.add_argument("--out", type=Path, default=None, help="results folder (default bench/results/<profile>)")
    p.add_argument("--docs", action="store_true", help="write the report to docs/benchmarks.md, "
                   "docs/images/ and the README block even with --quick")
    p.add_argument("--no-docs", action="store_true", help="never touch docs/ or README.md (report "
                   "next to the results)")
    p.add_argument("--report-only", action="store_true", help="regenerate the report from the existing "
                   "results.json of the profile without running anything")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        print(f"error: unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}", file=sys.stderr)
        return 2
    name = "quick" if args.quick else "full"
    out = args.out or RESULTS / name
    # The docs are only ever written from a complete run (or when asked to).
    to_docs = (args.docs or (name == "full" and set(sections) == set(SECTIONS))) and not args.no_docs
    from bench import report
    if args.report_only:
        results = common.read_json(out / "results.json")
        report.write_report(results, out, to_docs=to_docs)
        return 0

    bake_profile, engine_profile = profiles()[name]
    if args.cases:
        import dataclasses
        cases = tuple(c.strip() for c in args.cases.split(",") if c.strip())
        bad = [c for c in cases if c not in bake_profile.resolution]
        if bad:
            print(f"error: unknown case(s) {', '.join(bad)} for the {name} profile; choose from "
                  f"{', '.join(bake_profile.resolution)}", file=sys.stderr)
            return 2
        bake_profile = dataclasses.replace(bake_profile, cases=cases)
        to_docs = to_docs and args.docs
    out.mkdir(parents=True, exist_ok=True)
    started = time.time()
    t0 = time.perf_counter()
    results = {
        "meta": {
            "profile": name,
            "command": "bench/run.py " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])),
            "started": time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime(started)),
            "machine": common.machine(),
            "git": common.git_revision(),
            "sections": sections,
        }
    }
    log(f"profile {name}, sections {', '.join(sections)}; results in {out}")
    log("machine: " + common.machine_line(results["meta"]["machine"]))
    if results["meta"]["git"]["engine_changes"]:
        log("note: uncommitted engine changes: " + ", ".join(results["meta"]["git"]["engine_changes"]))
    section_seconds = {}

    if "bake" in sections:
        from bench import speed_error
        from bench.blender_session import BlenderSession
        with common.Stopwatch() as sw:
            blender = BlenderSession()
            try:
                results["meta"]["cycles_threads"] = blender.cycles_threads
                results["bake"] = speed_error.run(bake_profile, blender)
                results["bake_profile"] = {k: v for k, v in vars(bake_profile).items()}
            finally:
                blender.close()
        section_seconds["bake"] = sw.seconds
        common.write_json(out / "results.json", results)
    from bench import engine_figures
    for section in ("build", "solve", "convergence", "policy"):
        if section in sections:
            with common.Stopwatch() as sw:
                results[section] = getattr(engine_figures, f"run_{section}")(engine_profile, out)
            section_seconds[section] = sw.seconds
            common.write_json(out / "results.json", results)

    if "farm" in sections:
        from bench import farm_scaling
        with common.Stopwatch() as sw:
            results["farm"] = farm_scaling.run(name)
        section_seconds["farm"] = sw.seconds
        common.write_json(out / "results.json", results)

    results["meta"]["section_seconds"] = section_seconds
    results["meta"]["wall_seconds"] = time.perf_counter() - t0
    results["meta"]["finished"] = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    results["meta"]["load_average_end"] = list(os.getloadavg())
    common.write_json(out / "results.json", results)
    md = report.write_report(results, out, to_docs=to_docs)
    print(md.read_text())          # the tables, each with its machine line, on stdout
    log(f"report: {md}")
    log(f"done in {results['meta']['wall_seconds']:.0f} s; results: {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
