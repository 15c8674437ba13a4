"""When a noisy fit has stopped moving: a trend test on its own trajectories.

A Monte Carlo loss late in a fit fluctuates by more than it improves, so a rule such
as "the loss improved by less than 0.1 % over 20 steps" fires on noise while the
parameters are still on their way. This test asks instead whether anything still
moves beyond its own step-to-step noise. Over the second half of the fit so far (at
least ``window`` steps), each logged value (every channel of every parameter; a
texture's channel means) and the relative training loss is fitted with a line; the
fit is still when no slope is more than ``threshold`` standard errors from zero.

The standard error is that of least squares widened for the residuals' lag-one
autocorrelation r by sqrt((1 + r) / (1 - r)) (r's estimate corrected for its bias on
a short series): Adam's momentum makes neighbouring steps alike, and without the
widening a slow wander would pass for a trend. Looking
at half of the fit rather than a fixed window makes the test more sensitive to a
slow drift the longer the fit runs (a line's slope is known to n^-1.5).

Limitations: a value that oscillates without drifting (a limit cycle) counts as
still; a value clamped at a bound is constant and still.
"""

from __future__ import annotations

import math

import numpy as np


def trend_z(series: np.ndarray) -> float:
    """The least-squares slope of ``series`` (against its index) in standard errors,
    widened for lag-one autocorrelation (0: flat; inf: a noiseless line)."""
    values = np.asarray(series, np.float64)
    n = len(values)
    if n < 4:
        return math.inf
    x = np.arange(n) - (n - 1) / 2
    slope = float(x @ (values - values.mean()) / (x @ x))
    residuals = values - values.mean() - slope * x
    variance = float(residuals @ residuals) / (n - 2)
    if variance <= 1e-30 * max(float(values @ values) / n, 1e-300):
        return 0.0 if abs(slope) <= 1e-15 * max(np.abs(values).max(), 1e-300) else math.inf
    lagged = float(residuals[1:] @ residuals[:-1]) / float(residuals @ residuals)
    # the estimate from n detrended steps is low by about (1 + 3r) / n (Kendall)
    r = min(max(lagged + (1 + 3 * lagged) / n, 0.0), 0.95)
    standard_error = math.sqrt(variance / float(x @ x) * (1 + r) / (1 - r))
    return abs(slope) / standard_error


def trajectories(log: list[dict]) -> dict[str, np.ndarray]:
    """Each logged value's series over ``log`` (entries with ``params`` and
    ``relative_loss``), keyed by parameter and channel."""
    series: dict[str, list[float]] = {"relative loss": [entry["relative_loss"] for entry in log]}
    for entry in log:
        for name, values in (entry.get("params") or {}).items():
            for channel, value in enumerate(np.ravel(values)):
                series.setdefault(f"{name}[{channel}]", []).append(float(value))
    return {name: np.asarray(values) for name, values in series.items() if len(values) == len(log)}


def still(log: list[dict], window: int, threshold: float) -> str | None:
    """Why the fit may stop (nothing trends over the second half of ``log``, at least
    ``window`` entries), or None while something still moves or too few steps are logged."""
    if threshold <= 0 or len(log) < window:
        return None
    recent = log[-max(window, len(log) // 2) :]
    trends = {name: trend_z(values) for name, values in trajectories(recent).items()}
    name, largest = max(trends.items(), key=lambda item: item[1])
    if largest >= threshold:
        return None
    return (
        f"nothing moved beyond its noise over the last {len(recent)} steps "
        f"(largest trend {largest:.1f} standard errors, {name}; threshold {threshold:g})"
    )


__all__ = ["still", "trajectories", "trend_z"]
