"""The speed-against-error part of the report: what is timed, the error method, one section per
bake case (curves, per-sample efficiency, ratio table, verdict sentence) and issue 5's targets."""
import math

from .common import DEFAULT_NAME
from .report_format import fmt_pct, fmt_s, fmt_signed_pct, table


def what_is_timed():
    return (
        "**What is timed** (`time.perf_counter` around the calls, medians over the repeats): "
        "*Cycles*: `operators.adapters.demo_scenes.bake_cycles` = `bpy.ops.object.bake(type='DIFFUSE', "
        "pass_filter={'INDIRECT'})` of the receiver into a scratch float image (Cycles' scene sync, BVH, "
        "sampling, readback; adaptive sampling, denoising and indirect clamping (`sample_clamp_indirect`) off, margin 0). "
        "*LMDP precompute* (GUIDED, FINAL_GATHER): `pipeline.run_sample`, `run_build`, `run_solve`, the "
        "engine calls of the `lmdp.sample_states` / `build_dynamics` / `solve` operators, each timed. "
        "*LMDP bake*: `lmdp_addon.bake.driver.bake`, the engine call of `lmdp.bake` (input checks, ray-caster BVH (GUIDED and "
        "FINAL_GATHER trace with the build's, built in the precompute), guide construction, texel "
        "rasterisation, path tracing; margin 0). The wall time of a GUIDED or "
        "FINAL_GATHER point is precompute + bake; the precompute is also listed on its own. Writing "
        "results into Blender images is not timed on either side. LMDP runs on the engine's scene "
        "arrays of the same built-in scene (`lmdp_addon.demo_geometry`), which is what the operators extract "
        "from the Blender scene (`tests/addon/test_extract.py`).")


def error_method(results):
    return (
        "**Error**: over the scored texels and all three channels, relative RMSE = "
        "sqrt(mean((x − r)²)) / mean(r) and bias = mean(x − r) / mean(r) against the reference r. "
        "The reference is Cycles' bake of the same texels with many samples, made of two halves with "
        "seeds 1 and 2; its own noise (relative RMSE) is half the RMS difference of the halves over "
        "mean(r). The error shown is corrected for it, sqrt(raw² − noise²) (the raw figure is in the "
        "tables; a `*` marks raw errors below twice the reference noise, where the correction "
        "dominates). Over repeats the error is the root mean square, the bias the mean. "
        "**Time to reach Cycles' error at N samples**: each method's (time, error) points are "
        "interpolated linearly in log-log between the two ladder points that bracket Cycles' corrected "
        "error at N (first crossing in sample order) and divided by Cycles' median time at N. Outside "
        "a method's measured range nothing is extrapolated: `< x` means it is already better at its "
        "cheapest point, `> x` that it is still worse at its most expensive one, `never` that its "
        "mean bias alone exceeds the target (the relative RMSE is at least |bias|). A ratio above 1 means the method loses to Cycles there.")


def case_section(key, case, image_rel):
    lines = [f"### {case['title']}", ""]
    ref = case["reference"]
    cov = case["coverage"]
    ref_time = sum(ref["seconds"])
    lines.append(
        f"Scene `{case['kind']}` ({case['triangles']} triangles), receiver `{case['receiver']}`, "
        f"{case['resolution']}x{case['resolution']} texels, path length {case['bounces']} bounces on both "
        f"sides (Cycles `max_bounces` = `diffuse_bounces` = {case['bounces']}; engine `max_bounces` = "
        f"{case['bounces']}), {case['repeats']} repeat(s) per point. "
        f"Reference: Cycles, {ref['samples']} samples (2 x {ref['samples'] // 2}, seeds "
        f"{ref['seeds'][0]} and {ref['seeds'][1]}), {fmt_s(ref_time)} to bake "
        f"({'cached, baked ' + ref['created'] if ref['cached'] else 'baked in this run'}), "
        f"noise {fmt_pct(ref['noise_relative_rmse'], 2)} relative RMSE, mean "
        f"({', '.join(f'{m:.4g}' for m in ref['mean'])}). "
        f"Texels: Cycles covers {cov['cycles_covered']}, the engine's rasterisation {cov['engine_covered']} "
        f"({cov['only_engine']} only in the engine, {cov['only_cycles']} only in Cycles); scored: "
        f"{cov['scored']} ({cov['scored_rule']}).")
    lines.append("")
    if not case.get("lmdp_available", True):
        lines += [f"LMDP bakes were not run: {case.get('lmdp_unavailable_reason')}.", ""]
    for name, msg in case.get("failures", {}).items():
        lines += [f"**{name} failed**: {msg}", ""]
    lines += [f"![{case['title']}]({image_rel})", ""]
    # curves table
    rows = []
    for m in case["methods"]:
        for p in case["curves"].get(m["name"], []):
            pre = p["precompute_total"]
            stages = ", ".join(f"{k} {fmt_s(v)}" for k, v in p["precompute_seconds"].items())
            rows.append([m["name"], p["samples"], fmt_s(p["seconds"]),
                         (f"{fmt_s(pre)} ({stages})" if pre > 0 else "–"), fmt_s(p["bake_seconds"]),
                         fmt_pct(p["rel_rmse"]) + ("*" if p["at_noise_floor"] else ""),
                         fmt_pct(p["rel_rmse_raw"]), fmt_signed_pct(p["bias"], 2)])
    lines += [table(["method", "samples", "wall time", "of which precompute", "bake", "rel. RMSE",
                     "raw rel. RMSE", "bias"], rows), ""]
    eff = _efficiency_table(case)
    if eff:
        lines += [eff, ""]
    # ratio table
    ratios = case.get("ratios", [])
    names = [m["name"] for m in case["methods"] if m["name"] != "Cycles" and case["curves"].get(m["name"])]
    if ratios and names:
        lines += ["Time to reach Cycles' error at N samples, as a ratio to Cycles' time at N "
                  "(**bold**: the method loses, i.e. needs more time than Cycles or never gets there; "
                  "_italic_: undecided, the ladder stops before the answer is known):", ""]
        rows = []
        for row in ratios:
            cells = [f"{row['cycles_samples']} ({fmt_s(row['cycles_seconds'])}, "
                     f"{fmt_pct(row['target_rel_rmse'])}{'*' if row['target_at_noise_floor'] else ''})"]
            for n in names:
                r = row["methods"].get(n)
                if r is None:
                    cells.append("–")
                else:
                    cells.append(f"**{r['text']}**" if r["status"] == "loses" else
                                 f"_{r['text']}_" if r["status"] == "undecided" else r["text"])
            rows.append(cells)
        lines += [table(["Cycles N (time, error)"] + names, rows), ""]
        lines += [loss_summary(case, names), ""]
    return "\n".join(lines)


#: Sample counts of the per-sample efficiency table (issue 20: 64 and 256 samples).
EFFICIENCY_SAMPLES = (16, 64, 256)


def efficiency_rows(case):
    """``[(method, samples, error² ratio, bake-time ratio, efficiency, efficiency with the
    precompute, bias)]`` of every method against UNGUIDED at each sample count of
    :data:`EFFICIENCY_SAMPLES` both were run at: variance per sample (the squared relative
    error, Cycles' reference noise removed) and cost per sample (the bake's wall time) as ratios,
    efficiency = 1 / (error² ratio x time ratio), and the same with the precompute in the time."""
    base = {p["samples"]: p for p in case["curves"].get("UNGUIDED", [])}
    out = []
    for m in case["methods"]:
        if m["name"] == "UNGUIDED":
            continue
        pts = {p["samples"]: p for p in case["curves"].get(m["name"], [])}
        for n in sorted(set(pts) & set(base) & set(EFFICIENCY_SAMPLES)):
            p, b = pts[n], base[n]
            if not (p["rel_rmse"] > 0 and b["rel_rmse"] > 0 and b["bake_seconds"] > 0 and b["seconds"] > 0):
                continue
            var = (p["rel_rmse"] / b["rel_rmse"]) ** 2
            cost = p["bake_seconds"] / b["bake_seconds"]
            wall = p["seconds"] / b["seconds"]
            out.append((m["name"], n, var, cost, 1.0 / (var * cost), 1.0 / (var * wall), p["bias"]))
    return out


def _efficiency_table(case):
    """The table of :func:`efficiency_rows`."""
    rows = [[name, n, f"{var:.2f}", f"{cost:.2f}", f"{eff:.2f}", f"{eff_wall:.2f}", fmt_signed_pct(bias, 2)]
            for name, n, var, cost, eff, eff_wall, bias in efficiency_rows(case)]
    if not rows:
        return ""
    return ("Per sample, relative to UNGUIDED at the same sample count (error² ratio: variance per sample, "
            "below 1 = less noise; bake-time ratio: cost per sample without the precompute; efficiency = "
            "1 / (error² ratio x time ratio), above 1 = better than UNGUIDED; the last efficiency counts "
            "the precompute in the time). Techniques tried and dropped are in docs/design.md "
            "(\"RESIDUAL\"); bench/techniques.py measures them per sample:\n\n"
            + table(["method", "samples", "error² ratio", "bake-time ratio", "efficiency",
                     "efficiency with precompute", "bias"], rows))


#: Issue 20's bars for the default bake mode: (case, least efficiency against UNGUIDED with the
#: precompute at 64 and 256 samples, largest time to reach Cycles' error as a fraction of Cycles'
#: time or None); on every case the efficiency is at least 1 from 16 samples up.
DEFAULT_MODE_BARS = (("narrow_opening", 2.0, 0.33), ("cornell", 1.3, 0.5), ("heavy", 1.3, None),
                     ("sun_hdri", 1.0, None), ("glossy", 1.0, None))


def default_mode_verdicts(results):
    """Issue 20's bars, checked for the default bake mode (``Settings.bake_mode``) on the
    per-sample efficiency rows and the ratio tables: efficiency with the precompute at least the
    bar at 64 and 256 samples and at least 1 from 16 up, time to Cycles' error at most the bar."""
    from lmdp_addon.settings import Settings
    mode = Settings().bake_mode
    out = []
    for key, bar, time_bar in DEFAULT_MODE_BARS:
        case = results.get("bake", {}).get(key)
        names = [m["name"] for m in (case or {}).get("methods", []) if m["family"] == mode]
        names = [n for n in names if n == DEFAULT_NAME] or names   # the entry run with the defaults
        if not case or (not names and mode != "UNGUIDED"):
            out.append((f"default mode {mode} on {key}", "not measured in this run"))
            continue
        name = names[0] if names else "UNGUIDED"
        effs = {n: e for (m, n, _, _, _, e, _) in efficiency_rows(case) if m == name}
        if name == "UNGUIDED":     # the reference itself, at the counts it was run at
            effs = {p["samples"]: 1.0 for p in case["curves"].get("UNGUIDED", [])
                    if p["samples"] in EFFICIENCY_SAMPLES}
        at = ", ".join(f"{n} spp {e:.2f} x" for n, e in sorted(effs.items()))
        ok = all(effs.get(n, 0) >= bar for n in (64, 256)) and all(e >= 1.0 for n, e in effs.items() if n >= 16)
        text = f"{'**met**' if ok else '**missed**'}: efficiency against UNGUIDED {at} (bar {bar:g} x)"
        if time_bar is not None:
            cells = [f"N = {row['cycles_samples']}: {row['methods'][name]['text']}" for row in case.get("ratios", [])
                     if name in row["methods"] and row["cycles_samples"] in (64, 256)]
            fast = all(row["methods"][name]["ratio"] <= time_bar and row["methods"][name]["kind"] != "never"
                       for row in case.get("ratios", [])
                       if name in row["methods"] and row["cycles_samples"] in (64, 256))
            text += (f"; time to Cycles' error {'**met**' if fast and cells else '**missed**'}: "
                     f"{'; '.join(cells) or 'not measured'} (bar {time_bar:g} x)")
        out.append((f"default mode {name} on {key}", text))
    return out


def loss_summary(case, names):
    """One sentence per family: where it wins, loses, or cannot tell."""
    out = []
    for family in ("AUTO", "UNGUIDED", "GUIDED", "FINAL_GATHER", "RESIDUAL", "Cycles"):
        fam = [m["name"] for m in case["methods"] if m["family"] == family and m["name"] in names]
        if not fam:
            continue
        by = {"wins": [], "loses": [], "undecided": []}
        for row in case["ratios"]:
            for n in fam:
                r = row["methods"].get(n)
                if r is not None:
                    by[r["status"]].append(f"{n} at N = {row['cycles_samples']}")
        if by["loses"] and not by["wins"] and not by["undecided"]:
            out.append(f"**{family} loses everywhere in this table.**")
        elif by["wins"] and not by["loses"] and not by["undecided"]:
            out.append(f"{family} wins everywhere in this table.")
        else:
            parts = [f"{'**loses**' if k == 'loses' else k} at {', '.join(v)}" for k, v in by.items() if v]
            out.append(f"{family}: " + "; ".join(parts) + ".")
    return " ".join(out)


def bake_verdicts(results):
    """Issue 5's speed targets, checked on the ratio tables."""
    bake = results.get("bake", {})
    out = []
    targets = [("cornell", 1.0, "GUIDED reaches Cycles' error in at most Cycles' time on the Cornell box floor"),
               ("narrow_opening", 0.5, "GUIDED reaches Cycles' error in at most half of Cycles' time on the "
                                       "narrow-opening scene")]
    for key, limit, text in targets:
        case = bake.get(key)
        if not case or not case.get("ratios"):
            out.append((text, "not measured in this run"))
            continue
        guided = [m["name"] for m in case["methods"] if m["family"] == "GUIDED"]
        met, missed, open_ = [], [], []

        def label(row, cand):
            return f"N = {row['cycles_samples']}: {cand[2]['text']} ({cand[1]})"

        for row in case["ratios"]:
            cands = [(r["ratio"] if r["kind"] != "never" else math.inf, n, r)
                     for n in guided if (r := row["methods"].get(n)) is not None]
            if not cands:
                continue
            winners = [c for c in cands if c[2]["status"] == "wins" and c[0] <= limit]
            # An undecided bound below the limit: that configuration's ladder stops too early.
            pending = [c for c in cands if c[2]["status"] == "undecided" and c[0] < limit]
            decided = [c for c in cands if c[2]["status"] != "undecided"]
            if winners:
                met.append(label(row, min(winners, key=lambda c: c[0])))
            elif pending:
                open_.append(label(row, min(pending, key=lambda c: c[0])))
            elif decided:
                missed.append(label(row, min(decided, key=lambda c: c[0])))
            else:
                open_.append(label(row, min(cands, key=lambda c: c[0])))
        res = case["resolution"]
        verdict = ("**met**" if met and not missed and not open_ else
                   "**missed**" if missed and not met and not open_ else
                   "**partly met**" if met else "**missed** where decided" if missed else "undecided")
        out.append((f"{text} ({res}x{res}; limit {limit:g} x, best GUIDED configuration per N)",
                    f"{verdict}. Met at: {', '.join(met) or 'none'}. Missed at: {', '.join(missed) or 'none'}. "
                    f"Undecided (the configuration's ladder ends first) at: {', '.join(open_) or 'none'}."))
    gathers = []
    for key, case in bake.items():
        for m in case["methods"]:
            if m["family"] != "FINAL_GATHER":
                continue
            pts = case["curves"].get(m["name"], [])
            if pts:
                best = min(pts, key=lambda p: p["rel_rmse"])
                gathers.append(f"{case['title']}: {m['name']} bias {fmt_signed_pct(pts[-1]['bias'], 1)}, lowest "
                               f"error {fmt_pct(best['rel_rmse'])} at {fmt_s(best['seconds'])}")
    if gathers:
        out.append(("FINAL_GATHER far faster at a stated bias", "; ".join(gathers) + "."))
    return out

