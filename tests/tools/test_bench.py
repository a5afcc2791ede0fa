"""The benchmark harness's own logic (bench/): error metrics, reference-noise correction, the
"time to reach Cycles' error" interpolation and its win/lose verdicts, the peak-memory probe of the
subprocess jobs, the command line and bias_map's contact split. Fast (synthetic data and a built-in
scene's arrays); nothing here times anything."""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import metrics  # noqa: E402
from bench import report, report_bake  # noqa: E402
from bench.speed_error import ratio_table, summarise  # noqa: E402


def test_relative_errors_on_known_data():
    ref = np.full((100, 3), 2.0)
    est = ref + np.tile([0.2, -0.2], 150).reshape(100, 3)   # |d| = 0.2 everywhere, mean 0
    rmse, bias = metrics.relative_errors(est, ref)
    assert rmse == pytest.approx(0.1)
    assert bias == pytest.approx(0.0, abs=1e-15)
    rmse, bias = metrics.relative_errors(ref * 1.05, ref)
    assert rmse == pytest.approx(0.05) and bias == pytest.approx(0.05)
    with pytest.raises(ValueError):
        metrics.relative_errors(ref[:10], ref)
    with pytest.raises(ValueError):
        metrics.relative_errors(ref, np.zeros_like(ref))


def test_reference_noise_estimates_the_error_of_the_averaged_halves():
    """Halves with independent noise σ: their average has noise σ/√2. The estimate
    rms(a − b)/2 has relative standard deviation about 1/√(2n); allow 6 of them."""
    rng = np.random.default_rng(3)
    n, sigma = 60000, 0.3
    truth = np.full((n // 3, 3), 1.5)
    a = truth + sigma * rng.standard_normal(truth.shape)
    b = truth + sigma * rng.standard_normal(truth.shape)
    expected = sigma / math.sqrt(2) / 1.5
    est = metrics.reference_noise(a, b)
    assert est == pytest.approx(expected, rel=6 / math.sqrt(2 * n))
    # And it is what the averaged reference's actual error is.
    actual, _ = metrics.relative_errors(0.5 * (a + b), truth)
    assert actual == pytest.approx(expected, rel=6 / math.sqrt(2 * n))


def test_noise_correction_removes_the_reference_error_in_quadrature():
    """A bake with error e measured against a reference with noise s reads sqrt(e² + s²)."""
    rng = np.random.default_rng(5)
    truth = np.full((50000, 3), 1.0)
    ref_a = truth + 0.2 * rng.standard_normal(truth.shape)
    ref_b = truth + 0.2 * rng.standard_normal(truth.shape)
    ref = 0.5 * (ref_a + ref_b)
    bake = truth + 0.3 * rng.standard_normal(truth.shape)
    raw, _ = metrics.relative_errors(bake, ref)
    corrected = metrics.corrected_error(raw, metrics.reference_noise(ref_a, ref_b))
    true, _ = metrics.relative_errors(bake, truth)
    assert raw > 1.05 * true
    assert corrected == pytest.approx(true, rel=0.01)
    assert metrics.corrected_error(0.1, 0.2) == 0.0


def test_time_to_reach_interpolates_power_laws_exactly_in_log_log():
    t = np.array([1.0, 4.0, 16.0, 64.0])
    e = 0.8 * t ** -0.5
    target = 0.8 * 10.0 ** -0.5
    c = metrics.time_to_reach(t, e, target)
    assert c.kind == "interpolated" and c.seconds == pytest.approx(10.0)
    assert metrics.time_to_reach(t, e, 1.0).kind == "below"
    assert metrics.time_to_reach(t, e, 1.0).seconds == 1.0
    above = metrics.time_to_reach(t, e, 0.01)
    assert above.kind == "above" and above.seconds == 64.0
    # A biased method: its relative RMSE is at least |bias|, above the target.
    never = metrics.time_to_reach(t, [0.5, 0.3, 0.25, 0.245], 0.1, bias=-0.2)
    assert never.kind == "never" and math.isinf(never.seconds)
    assert metrics.time_to_reach(t, [0.5, 0.3, 0.25, 0.245], 0.1, bias=0.05).kind == "above"
    # First crossing in ladder order, even if a later point is noisier.
    first = metrics.time_to_reach([1, 2, 4], [0.4, 0.1, 0.2], 0.2)
    assert first.kind == "interpolated" and first.seconds == pytest.approx(2 ** 0.5)


def test_crossing_status_and_text():
    C = metrics.Crossing
    assert C("interpolated", 0.5).status(1.0) == "wins"
    assert C("interpolated", 2.0).status(1.0) == "loses"
    assert C("below", 0.5).status(1.0) == "wins"
    assert C("below", 2.0).status(1.0) == "undecided"
    assert C("above", 2.0).status(1.0) == "loses"
    assert C("above", 0.5).status(1.0) == "undecided"
    assert C("never", math.inf).status(1.0) == "loses"
    assert C("interpolated", 2.0).ratio_text(1.0) == "2.00"
    assert C("below", 0.5).ratio_text(1.0) == "< 0.50"
    assert C("above", 3.0).ratio_text(1.0) == "> 3.00"
    assert C("never", math.inf).ratio_text(1.0) == "never"


def _synthetic_case():
    """Cycles: error 1/√N in 0.01 N s. FAST: the same error per sample at half the time plus a
    0.01 s precompute. SLOW: twice Cycles' time per sample. BIASED: error floor at 0.2."""
    records = []
    ladder = [1, 4, 16, 64, 256]
    for r in range(3):
        for n in ladder:
            jitter = 1.0 + 0.01 * (r - 1)          # median = the middle repeat
            e = n ** -0.5
            records += [
                {"method": "Cycles", "family": "Cycles", "samples": n, "seconds": 0.01 * n * jitter,
                 "bake_seconds": 0.01 * n * jitter, "precompute_seconds": {}, "rel_rmse": e, "bias": 0.0,
                 "info": {}},
                {"method": "FAST", "family": "GUIDED", "samples": n, "seconds": 0.005 * n * jitter + 0.01,
                 "bake_seconds": 0.005 * n * jitter, "precompute_seconds": {"solve": 0.01}, "rel_rmse": e,
                 "bias": 0.0, "info": {}},
                {"method": "SLOW", "family": "UNGUIDED", "samples": n, "seconds": 0.02 * n * jitter,
                 "bake_seconds": 0.02 * n * jitter, "precompute_seconds": {}, "rel_rmse": e, "bias": 0.0,
                 "info": {}},
                {"method": "BIASED", "family": "FINAL_GATHER", "samples": n, "seconds": 0.001 * n * jitter,
                 "bake_seconds": 0.001 * n * jitter, "precompute_seconds": {}, "rel_rmse": math.hypot(e, 0.2),
                 "bias": 0.2, "info": {}},
            ]
    methods = [{"name": n, "family": f, "ladder": ladder, "settings": {}} for n, f in
               (("Cycles", "Cycles"), ("FAST", "GUIDED"), ("SLOW", "UNGUIDED"), ("BIASED", "FINAL_GATHER"))]
    return {"records": records, "methods": methods, "reference": {"noise_relative_rmse": 0.0}}


def test_summary_and_ratio_table_on_synthetic_curves():
    case = _synthetic_case()
    case["curves"] = summarise(case)
    cyc = {p["samples"]: p for p in case["curves"]["Cycles"]}
    assert cyc[16]["seconds"] == pytest.approx(0.16)          # median of the three repeats
    assert cyc[16]["repeats"] == 3
    assert cyc[16]["rel_rmse"] == pytest.approx(0.25)
    fast16 = [p for p in case["curves"]["FAST"] if p["samples"] == 16][0]
    assert fast16["precompute_total"] == pytest.approx(0.01)
    rows = {r["cycles_samples"]: r for r in ratio_table(case)}
    assert 1 not in rows and set(rows) == {4, 16, 64, 256}
    r64 = rows[64]["methods"]
    # FAST needs 0.005 * 64 + 0.01 s at 64 samples: its time is not a power law, so the log-log
    # interpolation lands between ladder points; 64 is a ladder point: exact.
    assert r64["FAST"]["ratio"] == pytest.approx((0.005 * 64 + 0.01) / 0.64)
    assert r64["FAST"]["status"] == "wins"
    assert r64["SLOW"]["ratio"] == pytest.approx(2.0) and r64["SLOW"]["status"] == "loses"
    assert r64["BIASED"]["status"] == "loses" and r64["BIASED"]["kind"] == "never"
    assert rows[256]["methods"]["FAST"]["kind"] == "interpolated"
    text = report_bake.loss_summary({"methods": case["methods"], "ratios": list(rows.values())},
                                     ["FAST", "SLOW", "BIASED"])
    assert "**UNGUIDED loses everywhere in this table.**" in text
    assert "GUIDED wins everywhere in this table." in text
    assert "FINAL_GATHER" in text and "**loses**" in text


PEAK_MEMORY_PROBE = """
import sys
import numpy as np
sys.path.insert(0, {root!r})
from bench.worker import PeakMemory
with PeakMemory() as pm:
    block = np.ones(50 * 2 ** 20 // 8)          # 50 MiB, touched
    block[::512] += 1.0
del block
print(pm.bytes, pm.method)
"""


def test_peak_memory_probe_sees_an_allocation(venv_python):
    """In a fresh process, as the benchmark's worker measures (in the test process, memory that
    earlier tests freed, or that other threads free meanwhile, hides part of the allocation)."""
    run = subprocess.run([venv_python, "-c", PEAK_MEMORY_PROBE.format(root=str(ROOT))],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    nbytes, method = run.stdout.split(maxsplit=1)
    assert int(nbytes) >= 40 * 2 ** 20, (nbytes, method)


def test_run_help_works(venv_python):
    run = subprocess.run([venv_python, str(ROOT / "bench" / "run.py"), "--help"], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "--quick" in run.stdout and "--sections" in run.stdout


def test_run_rejects_unknown_sections(venv_python, tmp_path):
    run = subprocess.run([venv_python, str(ROOT / "bench" / "run.py"), "--sections", "bake,nonsense",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "nonsense" in run.stderr


def test_variance_anatomy_samples_the_receiver_and_reports_each_case(capsys):
    from bench import variance_anatomy
    from lmdp_addon import demo_geometry as scenes
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    rng = np.random.default_rng(0)
    points, normals = variance_anatomy.receiver_points(scene, "Floor", 500, rng)
    assert np.allclose(points[:, 2], 0.0, atol=1e-9) and np.all(normals[:, 2] > 0.5)
    mean, rv = variance_anatomy.relative_variance(scene, points[:50], normals[:50], 16, 8, rng)
    assert mean > 0 and np.isfinite(rv) and rv > 0
    # The tail share grows with the fraction of paths and is 1 for all of them.
    shares = [variance_anatomy.relative_variance(scene, points[:50], normals[:50], 16, 8,
                                                 np.random.default_rng(1), tail=q)[2] for q in (0.01, 0.1, 1.0)]
    assert 0 < shares[0] <= shares[1] <= shares[2] and shares[2] == pytest.approx(1.0)
    variance_anatomy.main(["CORNELL_BOX", "Floor", "--points", "32", "--paths", "8"])
    out = capsys.readouterr().out
    assert out.count("bounce(s)") == 3 and "one-sided light" in out and "states), 8 bounces" not in out
    variance_anatomy.main(["CORNELL_BOX", "Floor", "--points", "32", "--paths", "8", "--guided"])
    guided = [line for line in capsys.readouterr().out.splitlines() if "states), 8 bounces" in line]
    assert len(guided) == 2 and guided[1].startswith("  one-sided light, GUIDED")
    assert all(float(line.split("(")[2].split(" x")[0]) > 0 for line in guided)


def test_bias_map_finds_a_leak_where_the_reference_is_dark():
    """Blocks of the map: the relative bias where the reference has light, LEAK where it has
    none and the bake does; row 0 is the top of the lightmap (Blender stores rows bottom-up)."""
    from bench.bias_map import block_bias, format_map
    ref = np.ones((16, 16))
    ref[:4, :4] = 0.0                   # bottom-left block dark (a texel under a box)
    ref[12:, 12:] = np.nan              # top-right block not covered
    values = 1.02 * ref
    values[:4, :4] = 0.05               # light where there is none
    bias, leak = block_bias(values, ref, 4)
    assert leak[3, 0] and leak.sum() == 1
    assert np.isnan(bias[3, 0]) and np.isnan(bias[0, 3])
    finite = np.isfinite(bias)
    assert finite.sum() == 14 and np.allclose(bias[finite], 0.02)
    text = format_map(bias, leak).splitlines()
    assert text[3].split()[0] == "LEAK" and text[0].split()[3] == "." and text[1].split()[0] == "+2"


def test_contact_classes_find_the_texels_under_the_boxes_and_beside_them():
    """bias_map's split of the Cornell floor: texels inside a box's footprint (found here from
    the boxes' lowest vertices, not by ray casting) are covered; visible texels within 1.5 cm of a
    footprint are in the first distance band, texels more than 6 cm from every box and wall in
    the last. Texels within a texel of a footprint's edge are left out (their centre decides)."""
    from scipy.spatial import Delaunay
    from bench.bias_map import contact_classes
    from lmdp_addon.bake import driver as baking
    from lmdp_addon import demo_geometry as scenes
    scene = scenes.build_scene_arrays("CORNELL_BOX")
    floor = scene.object_names.index("Floor")
    ts, _ = baking.object_texels(scene, floor, 32)
    classes = contact_classes(scene, ts, floor)
    xy = ts.position[:, :2]
    texel = 0.56 / 32 * 1.5
    inside = np.zeros(len(xy), bool)
    edge = np.full(len(xy), np.inf)
    for name in ("TallBox", "ShortBox"):
        tri = scene.triangle_object == scene.object_names.index(name)
        v = scene.corners()[tri].reshape(-1, 3)
        foot = np.unique(v[v[:, 2] < 1e-6, :2].round(9), axis=0)
        hull = Delaunay(foot)
        inside |= hull.find_simplex(xy) >= 0
        a, b = foot[hull.convex_hull[:, 0]], foot[hull.convex_hull[:, 1]]
        ab = b - a
        t = np.clip(np.einsum("kij,ij->ki", xy[:, None] - a[None], ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        edge = np.minimum(edge, np.linalg.norm(xy[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1))
    lo, hi = scene.vertices[:, :2].min(axis=0), scene.vertices[:, :2].max(axis=0)
    wall = np.minimum(xy - lo, hi - xy).min(axis=1)
    sure = edge > texel
    assert np.all(classes[sure & inside] == 0) and (sure & inside).sum() > 20
    assert np.all(classes[sure & ~inside] > 0)
    beside = ~inside & (edge < 0.015) & (wall > 0.1)
    assert beside.sum() > 5 and np.all(classes[beside] == 1)
    far = ~inside & (edge > 0.06) & (wall > 0.06)
    assert far.sum() > 100 and np.all(classes[far] == 3)


def test_readme_keeps_one_generated_benchmark_block_and_stays_short(tmp_path):
    """README.md is for users (at most 250 lines) and holds exactly one block that make bench
    rewrites; rewriting it changes nothing outside the markers."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    assert text.count(report.README_BEGIN) == 1 and text.count(report.README_END) == 1
    readme = tmp_path / "README.md"
    readme.write_text(text, encoding="utf-8")
    meta = {"git": {"commit": "abc1234"}, "started": "today",
            "machine": {"cpu": "a CPU", "usable_cpus": 2}}
    report.update_readme({"meta": meta}, readme=readme)
    new = readme.read_text(encoding="utf-8")
    head, tail = text.split(report.README_BEGIN)[0], text.split(report.README_END)[1]
    assert new.startswith(head) and new.endswith(tail)
    assert "From `make bench` at commit `abc1234`" in new
