"""Error and timing arithmetic of the benchmark suite (plain numpy, no bpy, no engine).

Error of a bake against a reference, over the scored texels and all three channels:

    relative RMSE  = sqrt(mean((x - r)^2)) / mean(r)
    relative bias  = mean(x - r) / mean(r)

The reference is itself a Monte Carlo estimate. It is the average of two independent halves
``a`` and ``b`` (each with half of its samples), so its own error is estimated without any model
of the estimator: ``E[(a - b)^2] = 2 var_half`` and ``var_ref = var_half / 2``, hence

    reference noise (relative RMSE) = sqrt(mean((a - b)^2)) / 2 / mean(r).

Measured against a noisy reference, a bake's mean squared error is its true error plus the
reference's (the two are independent), so the suite reports the corrected error
``sqrt(max(raw^2 - noise^2, 0))`` next to the raw one, and flags points whose raw error is less
than twice the reference noise (there the correction dominates).

Speed against error: "time to reach Cycles' error" interpolates a method's (time, error) curve
linearly in log-log between the two ladder points that bracket the target error (the first
crossing in sample order). Outside the measured range nothing is extrapolated: the answer is a
bound (``<`` the cheapest point's time, or ``>`` the most expensive one), or ``never`` when the
method's mean bias alone exceeds the target (the relative RMSE is at least the magnitude of the
relative bias, so a biased method cannot get there with more samples).
"""
import math
from dataclasses import dataclass

import numpy as np


def relative_errors(estimate, reference):
    """``(relative RMSE, relative bias)`` of ``estimate`` against ``reference`` (same shape)."""
    x = np.asarray(estimate, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if x.shape != r.shape:
        raise ValueError(f"estimate {x.shape} and reference {r.shape} differ in shape")
    mean = float(r.mean())
    if not mean > 0:
        raise ValueError("the reference has no positive mean: nothing to compare relative to")
    d = x - r
    return float(np.sqrt(np.mean(d * d)) / mean), float(d.mean() / mean)


def reference_noise(half_a, half_b):
    """Relative RMSE of the average of two independent half references (module docstring)."""
    a = np.asarray(half_a, dtype=np.float64)
    b = np.asarray(half_b, dtype=np.float64)
    mean = float((0.5 * (a + b)).mean())
    return float(np.sqrt(np.mean((a - b) ** 2)) / 2.0 / mean)


def corrected_error(raw, noise):
    """Error against the converged answer: ``sqrt(max(raw^2 - noise^2, 0))``."""
    return float(math.sqrt(max(raw * raw - noise * noise, 0.0)))


def median(values):
    values = [float(v) for v in values]
    if not values:
        raise ValueError("median of nothing")
    return float(np.median(values))


def combine_repeats(rmses):
    """Root of the mean squared relative error over repeats (the expected error's estimate)."""
    rmses = np.asarray(rmses, dtype=np.float64)
    return float(np.sqrt(np.mean(rmses ** 2)))


@dataclass
class Crossing:
    """Time at which a curve reaches a target error.

    kind     'interpolated' (``seconds`` is the log-log interpolation), 'below' (already better at
             its cheapest point: the time is < ``seconds``), 'above' (still worse at its most
             expensive point: > ``seconds``), 'never' (the error stopped falling above the target)
    seconds  the interpolated time or the bound
    """

    kind: str
    seconds: float

    def status(self, reference_seconds):
        """'wins' (needs at most the reference time), 'loses' (needs more, or never gets there) or
        'undecided' (a bound on the wrong side of 1: the ladder does not reach far enough)."""
        r = self.seconds / reference_seconds
        if self.kind == "never":
            return "loses"
        if self.kind == "interpolated":
            return "wins" if r <= 1.0 else "loses"
        if self.kind == "below":
            return "wins" if r <= 1.0 else "undecided"
        return "loses" if r >= 1.0 else "undecided"

    def ratio_text(self, reference_seconds, digits=2):
        r = self.seconds / reference_seconds
        if self.kind == "interpolated":
            return f"{r:.{digits}f}"
        if self.kind == "below":
            return f"< {r:.{digits}f}"
        if self.kind == "above":
            return f"> {r:.{digits}f}"
        return "never"


def time_to_reach(seconds, errors, target, bias=None):
    """When does the curve ``(seconds[i], errors[i])`` (in ladder order) reach ``target``?

    Log-log linear interpolation between the first pair of consecutive points that brackets the
    target. If the first point is already at or below it: ``'below'`` its time. If no point
    reaches it: ``'never'`` when ``|bias|`` (the method's relative bias at its last point) is
    above the target, since the relative RMSE can never fall below the magnitude of the mean
    bias; else ``'above'`` the last time.
    """
    t = np.asarray(seconds, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    if len(t) == 0 or len(t) != len(e):
        raise ValueError("need matching, non-empty time and error lists")
    if not target > 0:
        raise ValueError("target error must be positive")
    if e[0] <= target:
        return Crossing("below", float(t[0]))
    for i in range(1, len(e)):
        if e[i] <= target:
            # Interpolate log t linearly in log e between points i-1 and i.
            le0, le1 = math.log(max(e[i - 1], 1e-300)), math.log(max(e[i], 1e-300))
            lt0, lt1 = math.log(t[i - 1]), math.log(t[i])
            if le1 == le0:
                return Crossing("interpolated", float(t[i]))
            f = (math.log(target) - le0) / (le1 - le0)
            return Crossing("interpolated", float(math.exp(lt0 + f * (lt1 - lt0))))
    if bias is not None and abs(bias) > target:
        return Crossing("never", float("inf"))
    return Crossing("above", float(t[-1]))


def loglog_slope(x, y):
    """Least-squares slope of log y against log x (e.g. error against time: -1/2 for plain MC)."""
    x = np.log(np.asarray(x, dtype=np.float64))
    y = np.log(np.asarray(y, dtype=np.float64))
    if len(x) < 2:
        return float("nan")
    return float(np.polyfit(x, y, 1)[0])
