"""The farm section of the benchmark report (bench/report_farm.py) from a results dict of the
shape bench/farm_scaling.py writes: every row, the bytes per unit, and a farm result that is
not identical to the local one shown as such."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.farm_scaling import PROFILES  # noqa: E402
from bench.report_farm import farm_section  # noqa: E402


def farm_results(identical=True):
    traffic = {"scattered_bytes": 9391611, "units": 56, "unit_task_bytes": 7077, "result_bytes": 19357616}
    return {"profile": vars(PROFILES["full"]), "objects": 7, "texels": 100731, "rows": [
        {"where": "local, 1 thread", "workers": 0, "threads": 1, "bake_seconds": 6.42, "build_seconds": 0.09},
        {"where": "farm, 2 local worker processes", "workers": 2, "threads": 1, "start_seconds": 0.7,
         "bake_seconds": 6.44, "again_seconds": 5.1, "build_seconds": 0.27, "bake_traffic": traffic, "build_traffic": traffic,
         "bake_identical": identical, "build_identical": True}]}


MACHINE = {"meta": {"machine": {
    "cpu": "Test CPU", "logical_cpus": 2, "physical_cores": 2, "usable_cpus": 2, "memory_gib": 8.0,
    "blas_threads": {"numpy": 1, "scipy": 1}, "thread_env": {}, "engine_threads": {"build_threads": 3, "bake_threads": 2},
    "embree": "", "versions": {"python": "3.11.7", "numpy": "1.26.4", "scipy": "1.15.3", "embreex": "4.4.0.post1",
                               "bpy": "5.0.1"}, "os": "Linux", "load_average": [0.0, 0.0, 0.0]}}}


def test_farm_section_lists_every_row_with_its_bytes():
    md = farm_section(farm_results(), MACHINE)
    assert "| local, 1 thread | 6.42 s |" in md
    row = next(line for line in md.splitlines() if line.startswith("| farm, 2 local worker processes"))
    assert "| 6.44 s | 5.10 s |" in row and "56 x 126 B" in row and "9.0 MiB" in row and row.rstrip().endswith("| yes |")


def test_a_farm_result_that_differs_is_marked():
    md = farm_section(farm_results(identical=False), MACHINE)
    assert "**no**" in md
