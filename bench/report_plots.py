"""The report's plots (``docs/images/bench_*.png``), drawn with matplotlib from ``results.json``."""
import numpy as np

from .common import ROOT

FAMILY_STYLE = {
    "Cycles": dict(color="black", marker="s", linestyle="-"),
    "UNGUIDED": dict(color="tab:blue", marker="o", linestyle="-"),
    "GUIDED": dict(marker="^", linestyle="-"),
    "FINAL_GATHER": dict(marker="D", linestyle="--"),
    "RESIDUAL": dict(color="tab:olive", marker="v", linestyle="-."),
    "AUTO": dict(color="magenta", marker="*", linestyle="-", linewidth=2.0),   # the default: drawn to stand out
}
GUIDED_COLOURS = ["tab:orange", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive"]
GATHER_COLOURS = ["tab:green", "tab:cyan", "tab:gray"]
#: Plain path tracing and its variants (light connections, world portals): blues, one line style each.
UNGUIDED_STYLES = [dict(color="tab:blue", linestyle="-"), dict(color="deepskyblue", linestyle="--"),
                   dict(color="navy", linestyle="-.")]


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.rcParams.update({"font.size": 8, "axes.titlesize": 9, "legend.fontsize": 7, "figure.dpi": 100})
    return plt


def _method_styles(methods):
    styles, g, f, u = {}, 0, 0, 0
    for m in methods:
        style = dict(FAMILY_STYLE.get(m["family"], {}))
        if m["family"] == "UNGUIDED":
            style.update(UNGUIDED_STYLES[u % len(UNGUIDED_STYLES)])
            u += 1
        if m["family"] == "Cycles" and m["name"] != "Cycles":      # Cycles with path guiding
            style.update(color="dimgray", linestyle=":")
        if m["family"] == "GUIDED":
            style["color"] = GUIDED_COLOURS[g % len(GUIDED_COLOURS)]
            g += 1
        elif m["family"] == "FINAL_GATHER":
            style["color"] = GATHER_COLOURS[f % len(GATHER_COLOURS)]
            f += 1
        styles[m["name"]] = style
    return styles


def plot_speed_error(key, case, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    styles = _method_styles(case["methods"])
    for m in case["methods"]:
        pts = case["curves"].get(m["name"], [])
        if not pts:
            continue
        t = [p["seconds"] for p in pts]
        e = [max(p["rel_rmse"], 1e-4) for p in pts]
        ax.plot(t, e, label=m["name"], markersize=4, **{"linewidth": 1.2, **styles[m["name"]]})
        for p, ti, ei in zip(pts, t, e):
            ax.annotate(str(p["samples"]), (ti, ei), textcoords="offset points", xytext=(3, 3), fontsize=6,
                        color=styles[m["name"]].get("color", "black"))
    noise = case["reference"]["noise_relative_rmse"]
    ax.axhline(noise, color="grey", linewidth=0.8, linestyle=":",
               label=f"reference noise ({case['reference']['samples']} spp)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time, s (median of repeats; LMDP precompute included)")
    ax.set_ylabel("relative RMSE vs reference (noise-corrected)")
    import textwrap
    title = f"{case['title']} ({case['resolution']}x{case['resolution']}, {case['bounces']} bounces)"
    ax.set_title("\n".join(textwrap.wrap(title, 70)))     # long titles on two lines, not cut off
    ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_build(build, path):
    plt = _plt()
    rows = build["rows"]
    fig, ax = plt.subplots(figsize=(6.0, 3.2))
    x = np.arange(len(rows))
    raw = [r["raw_rays_per_second"][str(r["raw_best_threads"])] / 1e6 for r in rows]
    eng = [r["build_rays_per_second"] / 1e6 for r in rows]
    ax.bar(x - 0.2, raw, 0.4, label="raw embreex, same rays", color="tab:gray")
    ax.bar(x + 0.2, eng, 0.4, label="build_passive_dynamics (all stages)", color="tab:blue")
    for xi, r, e in zip(x, raw, eng):
        ax.annotate(f"{100 * e / r:.0f}%", (xi + 0.2, e), textcoords="offset points", xytext=(0, 2),
                    ha="center", fontsize=7)
    ax.axhline(0, color="black", linewidth=0.5)
    ax.set_xticks(x, [f"{r['kind']}\n{r['triangles']} tris, {r['states']} states" for r in rows])
    ax.set_ylabel("million rays per second")
    ax.set_title("Passive dynamics build throughput (stratum + shadow rays)")
    ax.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_solve(solve, path):
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8.0, 3.4))
    colours = {"POWER": "tab:blue", "DIRECT": "tab:red", "ITERATIVE": "tab:green"}
    for solver, colour in colours.items():
        xs, ts, ms = [], [], []
        for row in solve["rows"]:
            s = row["solvers"].get(solver, {})
            if "median_seconds" in s:
                xs.append(row["build"]["states"])
                ts.append(s["median_seconds"])
                ms.append(s["peak_bytes_per_state"])
        if xs:
            a1.plot(xs, ts, marker="o", color=colour, label=solver, markersize=4)
            a2.plot(xs, ms, marker="o", color=colour, label=solver, markersize=4)
    builds = [(row["build"]["states"], row["build"]["build_seconds"]) for row in solve["rows"]]
    a1.plot([b[0] for b in builds], [b[1] for b in builds], marker="s", color="gray", linestyle=":",
            label="build (for scale)", markersize=3)
    for ax in (a1, a2):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("states (points x 16 strata)")
        ax.grid(True, which="both", linewidth=0.3, alpha=0.5)
    a1.set_ylabel("solve time, s (median)")
    a1.set_title(f"Solve time, tolerance {solve['tolerance']:g}")
    a2.set_ylabel("peak extra resident memory per state, bytes")
    a2.set_title("Peak memory of the solve per state")
    a1.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_convergence(conv, path):
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8.0, 3.4))
    cmap = plt.get_cmap("viridis")
    n = len(conv["curves"])
    for j, c in enumerate(conv["curves"]):
        h = np.asarray(c["history"])
        it = np.arange(1, len(h) + 1)
        label = f"λ = {c['lambda']:.3g}" + (" (thesis default)" if c["is_default"] else "")
        colour = cmap(j / max(n - 1, 1))
        a1.plot(it, h, color=colour, label=label, linewidth=1.0)
        pos = h > 0
        a2.plot(it[pos], h[pos], color=colour, label=label, linewidth=1.0)
    a1.set_xlim(0, min(60, max(len(c["history"]) for c in conv["curves"])))
    a1.set_title("||z_i - z_(i-1)|| (linear, cf. thesis Figure 3)")
    a2.set_yscale("log")
    a2.set_title("||z_i - z_(i-1)|| (log, cf. thesis Figure 4)")
    for ax in (a1, a2):
        ax.set_xlabel("power iteration i")
        ax.grid(True, linewidth=0.3, alpha=0.5)
    a1.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _stratum_polygons(U, V, per_edge=12):
    """Outline of every stratum on the unit disk (top view of the hemisphere, the concentric map
    is the disk the equal-area lift starts from, so areas on the disk are solid angles)."""
    import sys
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from lmdp_addon.model.hemisphere import concentric_square_to_disk
    polys = []
    s = np.linspace(0.0, 1.0, per_edge)
    for k in range(U * V):
        iu, iv = k // V, k % V
        u0, u1, v0, v1 = iu / U, (iu + 1) / U, iv / V, (iv + 1) / V
        us = np.concatenate([u0 + (u1 - u0) * s, np.full(per_edge, u1), u1 - (u1 - u0) * s, np.full(per_edge, u0)])
        vs = np.concatenate([np.full(per_edge, v0), v0 + (v1 - v0) * s, np.full(per_edge, v1), v1 - (v1 - v0) * s])
        x, y = concentric_square_to_disk(us, vs)
        polys.append(np.stack([x, y], axis=1))
    return polys


def plot_policy(pol, path):
    plt = _plt()
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import PowerNorm
    U, V = pol["strata_u"], pol["strata_v"]
    polys = _stratum_polygons(U, V)
    panels = [("passive p(k|x)", pol["passive"])]
    panels += [(f"u*, λ = {d['lambda']:.3g}" + (" (default)" if abs(d["lambda_scale"] - 1) < 1e-12 else ""), d["u"])
               for d in pol["distributions"]]
    panels.append(("u*, PHYSICAL mode", pol["physical"]))
    fig, axes = plt.subplots(1, len(panels), figsize=(1.9 * len(panels), 2.3))
    vmax = max(max(p[1]) for p in panels)
    light = np.asarray(pol["light_direction_local"])
    # The concentric disk point of the light direction (inverse of the equal-area lift).
    lxy = light[:2] / np.sqrt(1.0 + max(light[2], 0.0))
    for ax, (title, u) in zip(axes, panels):
        coll = PolyCollection(polys, array=np.asarray(u), cmap="magma", edgecolors="grey", linewidths=0.1,
                              norm=PowerNorm(gamma=0.4, vmin=0.0, vmax=vmax))
        ax.add_collection(coll)
        ax.plot(lxy[0], lxy[1], marker="+", color="cyan", markersize=7)
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-1.05, 1.05)
        ax.set_aspect("equal")
        ax.axis("off")
        ax.set_title(title, fontsize=7)
    fig.colorbar(coll, ax=axes, shrink=0.7, label="u*(k|x) (power scale)")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)

