"""The engine figures of the report: dynamics build throughput, solver scaling and memory, the
power method against λ (thesis Figures 3 and 4) and u* of one state against λ (thesis Figure 5)."""
from .report_format import fmt_bytes, fmt_rate, fmt_s, machine_caption, table


def build_section(build, results):
    rows = []
    for r in build["rows"]:
        best = str(r["raw_best_threads"])
        st = r["stage_seconds"]
        rows.append([r["kind"], r["triangles"], f"{r['points']} x {r['strata']} = {r['states']}",
                     f"{r['recorded_closest']} + {r['recorded_shadow']}",
                     fmt_s(r["build_seconds"]),
                     f"setup {fmt_s(st.get('setup'))}, "
                     + (f"locator {fmt_s(st['locator'])}, " if "locator" in st else "")
                     + f"trace {fmt_s(st.get('trace'))}, bin {fmt_s(st.get('bin'))}",
                     fmt_rate(r["build_rays_per_second"]),
                     f"{fmt_rate(r['raw_rays_per_second'][best])} ({best} thr.)",
                     f"{100 * r['fraction_of_raw']:.0f}%",
                     "met" if r["fraction_of_raw"] >= build["target_fraction"] else "**missed**"])
    lines = [
        "## Passive dynamics build throughput", "",
        "`dynamics.build_passive_dynamics` with the engine's default `rays_per_stratum` and `light_samples`, "
        "wall time of the whole call (median of "
        f"{build['rows'][0]['repeats'] if build['rows'] else '?'}), rays = stratum rays + shadow rays actually "
        "traced. Raw embreex: the same rays (recorded from the build) replayed into `EmbreeScene.run` with "
        "the same batches and query types, on 1 thread and on one thread per usable CPU; the faster one "
        "is the baseline. Issue 3's target: build throughput at least "
        f"{100 * build['target_fraction']:.0f}% of raw. The stage split comes from the build itself: "
        "`setup` until the first batch starts (the BVH, direction and light patterns), `locator` the "
        "state locator's grid, built on its own thread meanwhile, `trace` (closest-hit calls) and `bin` "
        "(everything else of a batch, including waiting for the locator) summed over the worker threads, "
        "so the stages overlap and can exceed the wall time.", "",
        table(["scene", "triangles", "states", "rays (closest + shadow)", "build", "stages",
               "build rays/s", "raw embreex rays/s", "build / raw", "≥ 50%?"], rows), "",
        machine_caption(results), "",
        "![build throughput](images/bench_build_throughput.png)", ""]
    return "\n".join(lines)


def solve_section(solve, results):
    rows = []
    for row in solve["rows"]:
        b = row["build"]
        for solver in ("POWER", "DIRECT", "ITERATIVE"):
            s = row["solvers"].get(solver, {})
            head = [f"{b['states']} ({b['points']} x {b['strata']})", solver]
            if "refused" in s:
                rows.append(head + ["refused: " + s["refused"].split(":")[0], "–", "–", "–", "–"])
                continue
            rows.append(head + [fmt_s(s["median_seconds"]), s["iterations"],
                                f"{s['residual']:.1e}" + ("" if s["converged"] else " (not converged)"),
                                fmt_bytes(s["peak_bytes"]), f"{s['peak_bytes_per_state']:.0f} B"])
    big = max(solve["rows"], key=lambda r: r["build"]["states"]) if solve["rows"] else None
    builds = [[f"{r['build']['states']} ({r['build']['points']} x {r['build']['strata']})",
               f"{r['build']['rays']} + {r['build']['shadow_rays']}", fmt_s(r["build"]["build_seconds"]),
               fmt_rate((r["build"]["rays"] + r["build"]["shadow_rays"]) / r["build"]["build_seconds"]),
               fmt_bytes(r["build"]["peak_bytes"]), fmt_bytes(r["build"]["estimate_bytes"]),
               "yes" if r["build"]["estimate_bytes"] >= r["build"]["peak_bytes"] else "**no**"]
              for r in solve["rows"]]
    lines = [
        "## Solvers: time, residual and memory against size", "",
        f"Cornell box, PHYSICAL cost mode (RGB), {solve['strata'][0]}x{solve['strata'][1]} strata, "
        f"tolerance {solve['tolerance']:g}, median of {solve['repeats']} solve(s). States = points x strata "
        "(the thesis's count); the solve carries one unknown per point and channel (the exact Lambertian "
        "reduction, `docs/design.md`), i.e. 3 x points unknowns. Residual: the solver's relative residual "
        "`||y - (Ay + b)||_∞ / ||y||_∞`. Memory: peak extra resident memory of the solve in its own process "
        "(`bench/worker.py`: the `VmHWM` high-water mark, reset before the solve, minus `VmRSS` before it).", "",
        table(["states (points x strata)", "solver", "time", "iterations", "residual", "peak memory",
               "per state"], rows), "",
        machine_caption(results), "",
        "![solver scaling](images/bench_solver_scaling.png)", "",
        "The builds of these problems (one run each, in their own process; shadow samples are the "
        "next-event samples drawn, of which only those above both horizons are traced):", "",
        table(["states", "stratum rays + shadow samples", "build", "samples/s", "peak memory",
               "estimate (`estimate_build_bytes`)", "estimate ≥ peak?"], builds), ""]
    if big:
        b = big["build"]
        solved = [s for s, v in big["solvers"].items() if "median_seconds" in v and v.get("converged")]
        lines += [
            f"**Largest problem**: {b['states']} states ({b['points']} points x {b['strata']} strata, "
            f"{b['rays']} stratum rays + {b['shadow_rays']} shadow samples) built in {fmt_s(b['build_seconds'])} "
            f"with a peak of {fmt_bytes(b['peak_bytes'])} extra resident memory; "
            f"`dynamics.estimate_build_bytes` estimated {fmt_bytes(b['estimate_bytes'])} beforehand"
            f"{'' if b['estimate_bytes'] >= b['peak_bytes'] else ' (**below the measured peak**)'}; the "
            f"dynamics occupy {fmt_bytes(b['dynamics_bytes'])} (nnz {b['nnz']} point-level, "
            f"{b['stratum_nnz']} per stratum). Solved to tolerance by: {', '.join(solved) or 'none'}.", ""]
    return "\n".join(lines)


def convergence_section(conv, results):
    rows = [[f"{c['lambda']:.3g}" + (" (default)" if c["is_default"] else ""), f"{c['lambda_scale']:.3g}",
             c["iterations"], "yes" if c["converged"] else "**no**", fmt_s(c["seconds"]),
             f"{c['history'][0]:.3g}" if c["history"] else "–"] for c in conv["curves"]]
    its = [c["iterations"] for c in sorted(conv["curves"], key=lambda c: c["lambda"])]
    monotone = all(a >= b for a, b in zip(its, its[1:]))
    return "\n".join([
        "## Power method against λ (thesis Figures 3 and 4)", "",
        f"Cornell box, THESIS cost mode, {conv['points']} points x {conv['strata']} strata = {conv['states']} "
        f"states (the thesis used 8 states per point), POWER from random z in [0, 1), stopped at a relative "
        f"change of {conv['tolerance']:g}. The thesis's default λ for this scene (sum of the lights' exitance) "
        f"is {conv['default_lambda']:.4g}. Plotted: `||z_i - z_(i-1)||_2` per iteration (`Solution.history`).",
        "", "![power method convergence](images/bench_power_convergence.png)", "",
        table(["λ", "λ / default", "iterations", "converged", "time", "first step"], rows), "",
        f"Iterations {'fall' if monotone else 'do not fall monotonically'} as λ grows, "
        + ("as in the thesis (small λ: slow convergence; large λ: fast)." if monotone else
           "unlike the thesis's observation."), "", machine_caption(results), ""])


def policy_section(pol, results):
    rows = [[f"{d['lambda']:.3g}", f"{d['lambda_scale']:.3g}", f"{d['max']:.3f}", f"{d['kl_from_passive']:.3f}"]
            for d in pol["distributions"]]
    return "\n".join([
        "## u* of one state against λ (thesis Figure 5)", "",
        f"Cornell box, {pol['points']} points x {pol['strata_u']}x{pol['strata_v']} strata; the floor point "
        f"nearest ({', '.join(f'{x:g}' for x in pol['target'])}) (at "
        f"({', '.join(f'{x:.3f}' for x in pol['position'])})). Each disk is the "
        "point's hemisphere seen from above in the concentric map (equal areas = equal solid angles, the "
        "normal at the centre); a cell is a stratum, coloured by u*(k|x) (`policy.stratum_policy`, all next "
        "states); `+` marks the direction to the light's centre. THESIS mode for each λ, and the PHYSICAL "
        "mode's u* (the zero-variance guide) for comparison.", "",
        "![u* against lambda](images/bench_policy_lambda.png)", "",
        table(["λ", "λ / default", "largest u*(k|x)", "KL divergence of u* from p, nats"], rows), "", machine_caption(results), ""])

