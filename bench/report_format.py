"""Number formats, markdown tables and the machine caption of the benchmark report."""
import math

from .common import machine_line


def fmt_s(seconds):
    if seconds is None or (isinstance(seconds, float) and not math.isfinite(seconds)):
        return "–"
    if seconds < 0.01:
        return f"{1000 * seconds:.1f} ms"
    if seconds < 10:
        return f"{seconds:.2f} s"
    return f"{seconds:.1f} s"


def fmt_pct(x, digits=1):
    return f"{100 * x:.{digits}f}%"


def fmt_signed_pct(x, digits=1):
    return f"{100 * x:+.{digits}f}%"


def fmt_bytes(b):
    if b is None:
        return "–"
    for unit, scale in (("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
        if b >= scale:
            return f"{b / scale:.1f} {unit}"
    return f"{b:.0f} B"


def fmt_rate(r):
    return f"{r / 1e6:.2f} M/s"


def table(header, rows):
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out)



def machine_caption(results):
    return "Machine: " + machine_line(results["meta"]["machine"], results["meta"].get("cycles_threads")) + "."
