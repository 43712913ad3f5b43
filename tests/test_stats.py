"""Statistics over seeds: Student's t interval (:mod:`ccrjax.stats`), and the Welch test and
bootstrap interval of ``experiments/tables.py``, against hand computations.

The t quantiles are the printed table's: ``t_{0.975, 1} = 12.706``, ``t_{0.975, 4} = 2.776``
(three decimals, hence ``rtol=2e-4``).
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as scipy_stats

from ccrjax.stats import mean_ci, mean_ci_along, plateau

TABLE_RTOL = 2e-4
SCRIPT = Path(__file__).resolve().parent.parent / "experiments" / "tables.py"


def test_t_interval_of_two_values():
    # mean 2, s = sqrt(2) (ddof 1), half width 12.706 * sqrt(2) / sqrt(2) = 12.706.
    result = mean_ci([1.0, 3.0])
    assert result["n"] == 2 and result["mean"] == 2.0
    assert result["std"] == pytest.approx(math.sqrt(2.0), rel=1e-12)
    assert result["half_width"] == pytest.approx(12.706, rel=TABLE_RTOL)
    # The ends are off by at most the half width's rounding.
    assert result["ci_low"] == pytest.approx(2.0 - 12.706, abs=TABLE_RTOL * 12.706)
    assert result["ci_high"] == pytest.approx(2.0 + 12.706, abs=TABLE_RTOL * 12.706)


def test_t_interval_of_five_values():
    # mean 3, s = sqrt(2.5), half width 2.776 * sqrt(2.5) / sqrt(5) = 2.776 / sqrt(2).
    result = mean_ci([4.0, 1.0, 3.0, 5.0, 2.0])
    assert result["n"] == 5 and result["mean"] == 3.0
    assert result["std"] == pytest.approx(math.sqrt(2.5), rel=1e-12)
    half = 2.776 / math.sqrt(2.0)
    assert result["half_width"] == pytest.approx(half, rel=TABLE_RTOL)
    assert (result["ci_low"], result["ci_high"]) == pytest.approx((3.0 - half, 3.0 + half),
                                                                  abs=TABLE_RTOL * half)


def test_one_value_has_no_interval_and_non_finite_values_show():
    assert mean_ci([0.25]) == {"mean": 0.25, "ci_low": None, "ci_high": None,
                               "half_width": None, "std": None, "n": 1}
    assert math.isnan(mean_ci([1.0, float("nan")])["mean"])
    with pytest.raises(ValueError):
        mean_ci([])


def test_t_bands_along_an_axis():
    curves = np.array([[1.0, 10.0], [3.0, 10.0]])  # two seeds, two points
    mean, half = mean_ci_along(curves, axis=0)
    np.testing.assert_allclose(mean, [2.0, 10.0])
    np.testing.assert_allclose(half, [12.706, 0.0], rtol=TABLE_RTOL)
    five = np.array([[4.0], [1.0], [3.0], [5.0], [2.0]])
    _, half = mean_ci_along(five, axis=0)
    np.testing.assert_allclose(half, [2.776 / math.sqrt(2.0)], rtol=TABLE_RTOL)
    _, half = mean_ci_along(curves[:1], axis=0)
    np.testing.assert_array_equal(half, 0.0)


# ---------------------------------------------------------------- experiments/tables.py
@pytest.fixture(scope="module")
def tables():
    spec = importlib.util.spec_from_file_location("tables_for_stats", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def welch_by_hand(a, b):
    """Welch's t statistic, the Welch-Satterthwaite degrees of freedom and the two-sided p."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    t = (a.mean() - b.mean()) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    return t, df, 2.0 * scipy_stats.t.sf(abs(t), df)


STEADY = [1.0, 1.1, 0.9, 1.05, 0.95, 1.0, 1.02, 0.98, 1.01, 0.99]


def test_welch_test_against_a_hand_computation(tables):
    # Unequal spreads: Welch (p = 0.118) is not significant where the pooled-variance
    # Student test would be (p = 0.0003).
    wide = [1.5, 1.2, 1.9]
    t, df, p = welch_by_hand(STEADY, wide)
    assert (t, df, p) == pytest.approx((-2.621, 2.028, 0.118), abs=1e-3)
    assert scipy_stats.ttest_ind(STEADY, wide, equal_var=True).pvalue < 0.001
    assert tables.welch_significant(STEADY, wide) is False
    # A clear difference is significant; p just above / below 0.05 decides.
    narrow = [1.5, 1.45, 1.55]
    assert welch_by_hand(STEADY, narrow)[2] < 0.01
    assert tables.welch_significant(STEADY, narrow) is True
    decisions = []
    for shift in (0.6, 0.8, 0.85, 0.9, 1.0, 1.5):
        other = [1.0 + shift + x for x in (0.0, -0.3, 0.4)]
        expected = bool(welch_by_hand(STEADY, other)[2] < 0.05)
        assert tables.welch_significant(STEADY, other) is expected, shift
        decisions.append(expected)
    assert decisions[0] is False and decisions[-1] is True  # the threshold is crossed
    # Degenerate cases: fewer than two values; no spread at all.
    assert tables.welch_significant([1.0], [2.0, 3.0]) is False
    assert tables.welch_significant([1.0, 1.0], [2.0, 2.0]) is True
    assert tables.welch_significant([1.0, 1.0], [1.0, 1.0]) is False


def test_bootstrap_interval_of_the_headline_matches_the_normal_approximation(tables):
    """Every base cell is constant 1 and every new cell holds the same 20 values (mean
    0.8, population sd ``sigma``): the headline reduction is ``1 - 0.8 = 0.2`` and its
    bootstrap distribution is the mean of 9 independent bootstrap means, close to normal
    with sd ``sigma / sqrt(9 * 20)``; the 95% interval is ``0.2 +- 1.96`` of those."""
    rng = np.random.default_rng(5)
    new = rng.normal(size=20)
    new = 0.8 + 0.1 * (new - new.mean()) / new.std()  # mean 0.8, population sd 0.1
    cells = {}
    for scenario in tables.SCENARIOS:
        for algo in tables.ALGOS:
            cells[(scenario, algo, "ccr")] = {"final": {"danger_frequency": list(new)}}
            cells[(scenario, algo, "plain")] = {"final": {"danger_frequency": [1.0] * 5}}
    pairs = len(tables.SCENARIOS) * len(tables.ALGOS)
    result = tables.headline(cells, "danger_frequency", "ccr", "plain", -1, resamples=4000)
    assert result["pairs"] == pairs == 9 and result["left_out"] == 0
    assert result["mean"] == pytest.approx(0.2, rel=1e-9)
    sd = 0.1 / math.sqrt(pairs * new.size)
    half = (result["ci_high"] - result["ci_low"]) / 2
    centre = (result["ci_high"] + result["ci_low"]) / 2
    assert half == pytest.approx(1.96 * sd, rel=0.1)
    assert centre == pytest.approx(0.2, abs=0.2 * sd)


def test_plateau_tells_a_rising_curve_from_a_flat_one():
    steps = np.arange(20, dtype=np.float64)
    noise = np.array([[0.1, -0.1, 0.05, -0.05] * 5, [-0.1, 0.1, -0.05, 0.05] * 5,
                      [0.05, 0.05, -0.1, 0.0] * 5])
    flat = -30.0 + noise
    rising = -60.0 + 1.5 * steps + noise
    assert plateau(flat)["plateaued"]
    result = plateau(rising)
    assert not result["plateaued"]
    # Windows of 4 points (20% of 20): the last is 16..19, the one before 12..15.
    assert result["window"] == 4
    assert result["last"] == pytest.approx(np.mean(rising[:, 16:]))
    assert result["previous"] == pytest.approx(np.mean(rising[:, 12:16]))
    assert result["last"] > result["ci_high"]
    with pytest.raises(ValueError, match="seeds"):
        plateau(flat[:1])
    with pytest.raises(ValueError, match="points"):
        plateau(flat[:, :1])
