"""Statistics over seeds: intervals, tests, the paper's relative changes, rliable aggregates.

* :func:`mean_ci`: the mean and Student's t interval of the mean,
  ``mean +- t_{0.975, n-1} s / sqrt(n)`` with ``s`` the sample standard deviation
  (``ddof=1``): the usual choice for a handful of independent seeds, wider than the
  normal interval when ``n`` is small (``t = 2.26`` for 10 seeds). The interval is
  clipped to the metric's range (``bounds``): a success rate's interval never leaves
  [0, 1]. With one seed there is no interval (``None``).
* :func:`welch`: Welch's unequal-variance t-test of two groups of seeds (and
  :func:`one_sided_below`, its one-sided form); :func:`holm`: Holm's correction of a family
  of such tests; :func:`difference_of_differences`: an effect's change between two
  conditions, with a bootstrap interval over seeds.
* :func:`relative_change` and :func:`mean_relative_change`: the paper's headline
  numbers (the average over scenario x learner pairs of the relative change of the
  mean), with a bootstrap interval over seeds.
* :func:`iqm` and :func:`probability_of_improvement`: the aggregate view of rliable
  (Agarwal et al., 2021) over tasks (scenario x learner pairs) with stratified-bootstrap
  intervals.
* :func:`plateau`: whether learning curves have levelled off.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
from rliable import library as rly
from rliable import metrics as rly_metrics
from scipy import stats as scipy_stats

Bounds = tuple[float, float]
UNBOUNDED: Bounds = (-math.inf, math.inf)


def t_quantile(num_values: int, level: float = 0.95) -> float:
    """``t_{(1 + level) / 2, n - 1}``, the half-width factor of the interval."""
    return float(scipy_stats.t.ppf(0.5 + level / 2, num_values - 1))


def mean_ci(values: Sequence[float] | np.ndarray, level: float = 0.95,
            bounds: Bounds = UNBOUNDED) -> dict:
    """``{"mean", "ci_low", "ci_high", "half_width", "std", "n"}`` of ``values``.

    Non-finite values are kept (the mean then is not finite either): a summary
    must not hide a seed that failed. ``ci_*`` and ``half_width`` are ``None`` for
    fewer than two values. ``ci_low`` and ``ci_high`` are clipped to ``bounds`` (the
    metric's range); ``half_width`` is the unclipped ``t s / sqrt(n)``.
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
    low, high = bounds
    return {"mean": mean, "ci_low": float(np.clip(mean - half, low, high)),
            "ci_high": float(np.clip(mean + half, low, high)), "half_width": half,
            "std": std, "n": n}


def format_mean_ci(stats: dict, percent: bool = False, digits: int = 2) -> str:
    """A :func:`mean_ci` summary as text: ``mean [low, high]`` (the clipped interval), in
    percent if asked, or the mean alone when there is no interval."""
    scale, unit = (100.0, "%") if percent else (1.0, "")
    text = f"{stats['mean'] * scale:.{digits}f}{unit}"
    if stats.get("ci_low") is not None:
        text += f" [{stats['ci_low'] * scale:.{digits}f}, {stats['ci_high'] * scale:.{digits}f}]"
    return text


def mean_ci_along(values: np.ndarray, axis: int = 0, level: float = 0.95,
                  bounds: Bounds = UNBOUNDED) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means and interval ends along ``axis`` (for curves with bands), the ends clipped
    to ``bounds``; with fewer than 2 values the ends are the mean."""
    array = np.asarray(values, dtype=np.float64)
    n = array.shape[axis]
    mean = np.mean(array, axis=axis)
    if n < 2:
        return mean, mean.copy(), mean.copy()
    half = t_quantile(n, level) * np.std(array, axis=axis, ddof=1) / math.sqrt(n)
    low, high = bounds
    return mean, np.clip(mean - half, low, high), np.clip(mean + half, low, high)


def _two_groups(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
                what: str) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if a.size < 2 or b.size < 2:
        raise ValueError(f"{what} needs at least 2 seeds per group, got {a.size} and {b.size}")
    return a, b


def welch(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
          alpha: float = 0.05) -> dict:
    """Welch's t-test of ``mean(a) == mean(b)`` (unequal variances, Welch-Satterthwaite
    degrees of freedom): ``{"difference", "p", "significant"}``, ``difference`` being
    ``mean(a) - mean(b)`` and ``significant`` meaning ``p < alpha``. Two groups without
    any spread (all values equal) differ exactly when their values differ (p is 0 or 1).
    A group of equal values has variance 0, though the computed one is rounding noise
    (``[0.7] * 3`` gives about 1e-32): scipy's warning of that precision loss is silenced,
    as the noise is negligible beside the other group's variance."""
    a, b = _two_groups(a, b, "welch")
    difference = float(a.mean() - b.mean())
    constant_a, constant_b = bool(np.all(a == a[0])), bool(np.all(b == b[0]))
    if constant_a and constant_b:
        p = 0.0 if a[0] != b[0] else 1.0
    else:
        with warnings.catch_warnings():
            if constant_a or constant_b:
                warnings.filterwarnings("ignore", "Precision loss", RuntimeWarning)
            p = float(scipy_stats.ttest_ind(a, b, equal_var=False).pvalue)
    return {"difference": difference, "p": p, "significant": bool(p < alpha)}


def one_sided_below(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
                    alpha: float = 0.05) -> dict:
    """Welch's one-sided test of ``mean(a) < mean(b)``: :func:`welch`'s two-sided p halved
    where ``a``'s mean is below ``b``'s, ``1 - p / 2`` where it is not. Returns ``{"difference",
    "p", "significant"}`` as :func:`welch` does."""
    two_sided = welch(a, b, alpha)
    p = two_sided["p"] / 2 if two_sided["difference"] < 0 else 1.0 - two_sided["p"] / 2
    return {"difference": two_sided["difference"], "p": p, "significant": bool(p < alpha)}


def difference_of_differences(a1: Sequence[float] | np.ndarray, b1: Sequence[float] | np.ndarray,
                              a2: Sequence[float] | np.ndarray, b2: Sequence[float] | np.ndarray,
                              resamples: int = 2000, seed: int = 0) -> dict:
    """``(mean(a1) - mean(b1)) - (mean(a2) - mean(b2))`` (how much larger an effect is in
    one condition than in another, e.g. plain's danger minus CCR's in two regimes), with its
    95% percentile bootstrap interval: the seeds of each of the four groups resampled with
    replacement, ``resamples`` times. ``{"difference", "ci_low", "ci_high"}``."""
    groups = [np.asarray(g, np.float64).reshape(-1) for g in (a1, b1, a2, b2)]
    if min(g.size for g in groups) < 2:
        raise ValueError("difference_of_differences needs at least 2 seeds per group, got "
                         + ", ".join(str(g.size) for g in groups))
    rng = np.random.default_rng(seed)
    means = [rng.choice(g, (resamples, g.size), replace=True).mean(axis=1) for g in groups]
    boot = (means[0] - means[1]) - (means[2] - means[3])
    point = (groups[0].mean() - groups[1].mean()) - (groups[2].mean() - groups[3].mean())
    return {"difference": float(point), "ci_low": float(np.percentile(boot, 2.5)),
            "ci_high": float(np.percentile(boot, 97.5))}


def holm(p_values: Sequence[float] | np.ndarray, alpha: float = 0.05) -> np.ndarray:
    """Holm's step-down correction for ``m`` tests: which null hypotheses are rejected with
    the family-wise error held at ``alpha``. The ``k``-th smallest p-value (``k`` from 1)
    is compared with ``alpha / (m - k + 1)``; hypotheses are rejected in that order until
    the first comparison that fails. Returns booleans in the order of ``p_values``."""
    p = np.asarray(p_values, dtype=np.float64).reshape(-1)
    order = np.argsort(p, kind="stable")
    thresholds = alpha / (p.size - np.arange(p.size))
    passed = p[order] <= thresholds
    # Step-down: everything before the first failure is rejected, nothing after it.
    count = p.size if passed.all() else int(np.argmin(passed))
    rejected = np.zeros(p.size, dtype=bool)
    rejected[order[:count]] = True
    return rejected


def relative_change(new: Sequence[float] | np.ndarray, base: Sequence[float] | np.ndarray
                    ) -> float:
    """``(mean(new) - mean(base)) / mean(base)``; NaN where the base mean is 0."""
    base_mean = float(np.mean(base))
    return float((np.mean(new) - base_mean) / base_mean) if base_mean != 0 else float("nan")


def mean_relative_change(pairs: Sequence[tuple[np.ndarray, np.ndarray]], sign: float,
                         resamples: int = 2000, seed: int = 0) -> dict:
    """The paper's headline number: the average over ``pairs`` (``(new, base)`` per-seed
    values of one scenario x learner pair) of ``sign * relative_change(new, base)``.

    ``sign = -1``: a reduction ``(base - new) / base``; ``+1``: an increase. Pairs whose
    base mean is 0 are left out (and counted in ``left_out``). The 95% interval resamples
    the seeds of every group with replacement (bootstrap, ``resamples`` times) and takes
    the 2.5 and 97.5 percentiles of the average. A resample in which a pair's base mean is
    0 has no relative change: it is dropped (counted in ``resamples_dropped``), not read as
    "no change", which would pull the interval towards 0, so the interval is conditional
    on every base mean staying above 0. ``per_pair`` holds each pair's own
    ``sign * relative_change`` (``None`` where left out): a base near 0 makes its pair's
    change large, and the average then follows that one pair.
    """
    rng = np.random.default_rng(seed)
    changes = [sign * relative_change(n, b) for n, b in pairs]
    per_pair = [float(c) if np.isfinite(c) else None for c in changes]
    used = [(np.asarray(n, np.float64), np.asarray(b, np.float64))
            for (n, b), c in zip(pairs, per_pair, strict=True) if c is not None]
    if not used:
        return {"mean": None, "ci_low": None, "ci_high": None, "pairs": 0,
                "left_out": len(pairs), "resamples_dropped": 0, "per_pair": per_pair}
    values = [c for c in per_pair if c is not None]
    boot = np.zeros(resamples)
    for n, b in used:
        new_means = rng.choice(n, (resamples, n.size), replace=True).mean(axis=1)
        base_means = rng.choice(b, (resamples, b.size), replace=True).mean(axis=1)
        safe = np.where(base_means != 0, base_means, 1.0)
        boot += np.where(base_means != 0, sign * (new_means - base_means) / safe, np.nan)
    boot /= len(used)
    kept = boot[np.isfinite(boot)]
    low = float(np.percentile(kept, 2.5)) if kept.size else None
    high = float(np.percentile(kept, 97.5)) if kept.size else None
    return {"mean": float(np.mean(values)), "ci_low": low, "ci_high": high,
            "pairs": len(used), "left_out": len(pairs) - len(used),
            "resamples_dropped": int(resamples - kept.size), "per_pair": per_pair}


def _score_matrix(scores: np.ndarray, what: str) -> np.ndarray:
    array = np.asarray(scores, dtype=np.float64)
    if array.ndim != 2 or array.shape[0] < 2 or array.shape[1] < 1:
        raise ValueError(f"{what} needs scores [runs >= 2, tasks >= 1], got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} needs finite scores")
    return array


def _seeded(seed: int, function, *args, **kwargs):
    """``function(*args, **kwargs)`` with NumPy's global generator seeded (rliable's
    stratified bootstrap draws its indices from it), the caller's generator restored."""
    saved = np.random.get_state()  # noqa: NPY002 (rliable uses the legacy generator)
    np.random.seed(seed)  # noqa: NPY002
    try:
        return function(*args, **kwargs)
    finally:
        np.random.set_state(saved)  # noqa: NPY002


def iqm(scores: dict[str, np.ndarray], resamples: int = 2000, seed: int = 0) -> dict[str, dict]:
    """The interquartile mean over runs and tasks of each method's ``scores`` ``[runs,
    tasks]`` (the mean of the middle 50% of all run x task scores), with its 95%
    stratified-bootstrap interval (runs resampled within every task), by rliable:
    ``{method: {"iqm", "ci_low", "ci_high"}}``."""
    matrices = {name: _score_matrix(value, "iqm") for name, value in scores.items()}
    points, intervals = _seeded(seed, rly.get_interval_estimates, matrices,
                                lambda x: np.array([rly_metrics.aggregate_iqm(x)]),
                                reps=resamples)
    return {name: {"iqm": float(points[name][0]), "ci_low": float(intervals[name][0, 0]),
                   "ci_high": float(intervals[name][1, 0])} for name in matrices}


def probability_of_improvement(x: np.ndarray, y: np.ndarray, resamples: int = 2000,
                               seed: int = 0) -> dict:
    """``P(X > Y)``: the probability that a run of method ``x`` scores higher than a run
    of ``y`` on the same task, averaged over tasks (the Mann-Whitney statistic per task,
    ties counting half), with its 95% stratified-bootstrap interval, by rliable.
    ``x`` and ``y``: ``[runs, tasks]``, higher is better (negate a cost such as danger).
    """
    x = _score_matrix(x, "probability_of_improvement")
    y = _score_matrix(y, "probability_of_improvement")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"probability_of_improvement needs the same tasks, got {x.shape[1]} "
                         f"and {y.shape[1]}")
    points, intervals = _seeded(seed, rly.get_interval_estimates, {"pair": (x, y)},
                                rly_metrics.probability_of_improvement, reps=resamples)
    return {"probability": float(np.asarray(points["pair"]).reshape(-1)[0]),
            "ci_low": float(np.asarray(intervals["pair"]).reshape(-1)[0]),
            "ci_high": float(np.asarray(intervals["pair"]).reshape(-1)[1])}


def plateau(curves: np.ndarray, fraction: float = 0.2, level: float = 0.95) -> dict:
    """Whether learning curves have levelled off by their end.

    ``curves``: ``[seeds, points]``, one evaluated metric (the return) per evaluation
    point. Each seed's curve is averaged over its last ``fraction`` of points and over
    the ``fraction`` before; the curves have plateaued if the mean over seeds of the
    last window lies within the 95% Student-t interval (over seeds) of the window
    before (a curve still rising ends above it). Returns ``{"plateaued", "last",
    "previous", "ci_low", "ci_high", "window"}``, ``window`` the points per window (at
    least one); needs at least 2 seeds and two windows of points. ``plateaued`` is
    ``None`` (undetermined) where a curve holds a NaN or infinity.
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
    finite = all(np.isfinite(x) for x in (value, previous["ci_low"], previous["ci_high"]))
    return {"plateaued": bool(previous["ci_low"] <= value <= previous["ci_high"])
            if finite else None,
            "last": value, "previous": previous["mean"], "ci_low": previous["ci_low"],
            "ci_high": previous["ci_high"], "window": window}


def plateau_or_undetermined(curves: np.ndarray) -> dict:
    """:func:`plateau` of ``curves``, or ``{"plateaued": None, "why": ...}`` where the
    curves are too few or too short to tell (what a results file records either way)."""
    try:
        return plateau(curves)
    except ValueError as error:
        return {"plateaued": None, "why": str(error)}
