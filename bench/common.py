"""Shared helpers of the benchmark suite: paths, logging, JSON, and the machine description that
is printed with every table (CPU, cores, threads, versions, load, code revision)."""
import ctypes
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

#: The method run with the default settings (AUTO: ``lmdp_addon.bake.auto``): issue 20's
#: "default mode" in the profiles (``run``) and their verdicts (``report_bake``).
DEFAULT_NAME = "AUTO (default)"

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DOCS = ROOT / "docs"
IMAGES = DOCS / "images"

_T0 = time.perf_counter()


def log(message):
    """One progress line on stderr, with the time since the suite started."""
    print(f"[bench {time.perf_counter() - _T0:7.1f} s] {message}", file=sys.stderr, flush=True)


def write_json(path, data):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=False, default=_jsonable))
    tmp.replace(path)


def read_json(path):
    return json.loads(Path(path).read_text())


def _jsonable(value):
    try:
        import numpy as np
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")


# -- the machine ----------------------------------------------------------------------------------

def cpu_model():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def physical_cores():
    """Distinct (physical id, core id) pairs in /proc/cpuinfo (None if unavailable)."""
    try:
        pairs, phys = set(), "0"
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("physical id"):
                phys = line.split(":", 1)[1].strip()
            elif line.startswith("core id"):
                pairs.add((phys, line.split(":", 1)[1].strip()))
        return len(pairs) or None
    except OSError:
        return None


def memory_gib():
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return round(int(line.split()[1]) / 1024 ** 2, 1)
    except OSError:
        pass
    return None


def blas_threads():
    """Threads of every OpenBLAS loaded in this process (numpy's and scipy's), asked through
    their own ``*_get_num_threads`` entry points."""
    import numpy  # noqa: F401  (loads numpy's OpenBLAS)
    import scipy.linalg  # noqa: F401  (loads scipy's)
    out = {}
    try:
        libs = sorted({line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line.lower()})
    except OSError:
        return out
    for lib in libs:
        try:
            handle = ctypes.CDLL(lib)
        except OSError:
            continue
        for symbol in ("openblas_get_num_threads64_", "openblas_get_num_threads",
                       "scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads"):
            fn = getattr(handle, symbol, None)
            if fn is not None:
                owner = "scipy" if "scipy" in lib else "numpy"
                out[owner] = int(fn())
                break
    return out


def versions():
    import numpy
    import scipy
    out = {"python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__}
    for name in ("embreex", "matplotlib"):
        try:
            from importlib.metadata import version
            out[name] = version(name)
        except Exception:  # pragma: no cover - not installed
            out[name] = None
    try:
        from importlib.metadata import version
        out["bpy"] = version("bpy")
    except Exception:  # pragma: no cover
        out["bpy"] = None
    return out


def git_revision():
    """Commit of the checkout and whether the engine / Blender layer had uncommitted changes."""
    def run(*args):
        try:
            return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True,
                                  timeout=30).stdout.rstrip("\n")
        except (OSError, subprocess.SubprocessError):
            return ""
    commit = run("rev-parse", "--short=10", "HEAD").strip()
    status = run("status", "--porcelain", "--", "lmdp_addon", "operators")
    return {"commit": commit or None,
            "engine_changes": [line[3:] for line in status.splitlines() if line.strip()]}


def engine_threads():
    """Worker threads the engine itself uses (module constants), if importable."""
    out = {}
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    try:
        from lmdp_addon.model import dynamics
        out["build_threads"] = int(dynamics.BUILD_THREADS)
    except Exception:  # pragma: no cover
        pass
    try:
        from lmdp_addon.bake import driver as baking
        out["bake_threads"] = int(baking.BAKE_THREADS)
    except Exception:
        pass
    return out


def machine():
    """Everything that is printed with every table."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover
        affinity = os.cpu_count()
    return {
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "physical_cores": physical_cores(),
        "usable_cpus": affinity,
        "memory_gib": memory_gib(),
        "blas_threads": blas_threads(),
        "thread_env": {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
                       if k in os.environ},
        "engine_threads": engine_threads(),
        "embree": "embreex traces each call's rays on the calling thread (one call = one core); "
                  "the engine overlaps calls on its worker threads",
        "versions": versions(),
        "os": platform.platform(),
        "load_average": list(os.getloadavg()),
    }


def machine_line(m, cycles_threads=None):
    """One-line machine description for a table caption."""
    v = m["versions"]
    blas = ", ".join(f"{k} {n}" for k, n in sorted(m["blas_threads"].items())) or "unknown"
    eng = m.get("engine_threads", {})
    parts = [
        f"{m['cpu']}, {m['usable_cpus']} logical CPUs ({m['physical_cores']} cores), {m['memory_gib']} GiB",
        f"BLAS threads: {blas}",
        f"engine worker threads: build {eng.get('build_threads', '?')}, bake {eng.get('bake_threads', '?')}",
        "embreex: 1 thread per call",
    ]
    if cycles_threads is not None:
        parts.append(f"Cycles threads: {cycles_threads}")
    parts.append(f"bpy {v.get('bpy')}, numpy {v.get('numpy')}, scipy {v.get('scipy')}, "
                 f"embreex {v.get('embreex')}, Python {v.get('python')}")
    return "; ".join(parts)


class Stopwatch:
    """``with Stopwatch() as sw: ...`` then ``sw.seconds`` (wall time, perf_counter)."""

    def __enter__(self):
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.start
        return False
