"""The farm section of the report (``bench/farm_scaling.py``)."""
from .report_format import fmt_bytes, fmt_s, machine_caption, table


def farm_section(farm, results):
    p = farm["profile"]
    rows = []
    for r in farm["rows"]:
        t = r.get("bake_traffic")
        rows.append([r["where"], fmt_s(r["bake_seconds"]),
                     fmt_s(r["again_seconds"]) if "again_seconds" in r else "–",
                     fmt_s(r["build_seconds"]) if r.get("build_seconds") is not None else "–",
                     fmt_s(r["start_seconds"]) if "start_seconds" in r else "–",
                     fmt_bytes(t["scattered_bytes"]) if t else "–",
                     f"{t['units']} x {t['unit_task_bytes'] / max(t['units'], 1):.0f} B" if t else "–",
                     fmt_bytes(t["result_bytes"]) if t else "–",
                     ("yes" if r["bake_identical"] and r["build_identical"] else "**no**") if t else "–"])
    return "\n".join([
        "## Bake farms: wall time against local worker processes", "",
        f"{p['kind']}, {p['mode']}, {p['point_count']} points, {farm['objects']} objects at {p['resolution']} px "
        f"({farm['texels']} texels) x {p['samples']} samples. `lmdp_addon.farm` on a Dask `LocalCluster` of "
        "1 and 2 worker processes (1 thread each) on this machine; bake and build times are those of the "
        "`driver.bake` / `farm.build` call on a connected farm (the cluster's start is listed apart); "
        "*bake again*: the same bake once more, its recipe already set up on the workers (the "
        "one-off per-worker set-up, unpickling, BVH, guide and gather, left out). "
        "Bytes are pickled sizes: the recipe (scene arrays, settings, solved stages) and each object's "
        "job scattered to every worker once (size x workers), each unit's task (function name, two keys, "
        "the unit number), and the units' results (per-batch sums of the texels). Identical: the images "
        "and the build's sparse matrices `np.array_equal` to the local ones.", "",
        table(["where", "bake", "bake again", "sample + build + solve", "cluster start", "scattered once", "per unit", "results back",
               "identical"], rows), "",
        machine_caption(results), ""])
