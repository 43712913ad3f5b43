"""Summaries over seeds: the mean and its 95% confidence interval.

The interval is Student's t interval of the mean, ``mean +- t_{0.975, n-1} s / sqrt(n)``
with ``s`` the sample standard deviation (``ddof=1``): the usual choice for a
handful of independent seeds, wider than the normal interval when ``n`` is small
(``t = 2.78`` for 5 seeds). With one seed there is no interval (``None``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats as scipy_stats


def t_quantile(num_values: int, level: float = 0.95) -> float:
    """``t_{(1 + level) / 2, n - 1}``, the half-width factor of the interval."""
    return float(scipy_stats.t.ppf(0.5 + level / 2, num_values - 1))


def mean_ci(values: Sequence[float] | np.ndarray, level: float = 0.95) -> dict:
    """``{"mean", "ci_low", "ci_high", "half_width", "std", "n"}`` of ``values``.

    Non-finite values are kept (the mean then is not finite either): a summary
    must not hide a seed that failed. ``ci_*`` and ``half_width`` are ``None`` for
    fewer than two values.
    """
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    n = int(array.size)
    if n == 0:
        raise ValueError("mean_ci needs at least one value")
    mean = float(np.mean(array))
    if n < 2:
        return {"mean": mean, "ci_low": None, "ci_high": None, "half_width": None,
                "std": None, "n": n}
    std = float(np.std(array, ddof=1))
    half = t_quantile(n, level) * std / math.sqrt(n)
    return {"mean": mean, "ci_low": mean - half, "ci_high": mean + half, "half_width": half,
            "std": std, "n": n}


def mean_ci_along(values: np.ndarray, axis: int = 0, level: float = 0.95):
    """Means and half-widths along ``axis`` (for curves with bands); half-width 0 if n < 2."""
    array = np.asarray(values, dtype=np.float64)
    n = array.shape[axis]
    mean = np.mean(array, axis=axis)
    if n < 2:
        return mean, np.zeros_like(mean)
    half = t_quantile(n, level) * np.std(array, axis=axis, ddof=1) / math.sqrt(n)
    return mean, half


def plateau(curves: np.ndarray, fraction: float = 0.2, level: float = 0.95) -> dict:
    """Whether learning curves have levelled off by their end.

    ``curves``: ``[seeds, points]``, one evaluated metric (the return) per evaluation
    point. Each seed's curve is averaged over its last ``fraction`` of points and over
    the ``fraction`` before; the curves have plateaued if the mean over seeds of the
    last window lies within the 95% Student-t interval (over seeds) of the window
    before (a curve still rising ends above it). Returns ``{"plateaued", "last",
    "previous", "ci_low", "ci_high", "window"}``, ``window`` the points per window (at
    least one); needs at least 2 seeds and two windows of points.
    """
    array = np.asarray(curves, dtype=np.float64)
    if array.ndim != 2 or array.shape[0] < 2:
        raise ValueError(f"plateau needs curves [seeds >= 2, points], got shape {array.shape}")
    if not 0.0 < fraction <= 0.5:
        raise ValueError(f"plateau fraction must be in (0, 0.5], got {fraction!r}")
    window = max(1, int(round(fraction * array.shape[1])))
    if 2 * window > array.shape[1]:
        raise ValueError(f"plateau needs at least {2 * window} evaluation points, "
                         f"got {array.shape[1]}")
    last = array[:, -window:].mean(axis=1)
    previous = mean_ci(array[:, -2 * window:-window].mean(axis=1), level)
    value = float(last.mean())
    return {"plateaued": bool(previous["ci_low"] <= value <= previous["ci_high"]),
            "last": value, "previous": previous["mean"], "ci_low": previous["ci_low"],
            "ci_high": previous["ci_high"], "window": window}
