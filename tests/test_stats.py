"""Statistics over seeds (:mod:`ccrjax.run.stats`) and the selection rule
(:mod:`experiments.selection`) against hand computations: Student's t interval (clipped to a
metric's range), the Welch
test, the headline's bootstrap interval, rliable's IQM and probability of improvement,
the plateau check.

The t quantiles are the printed table's: ``t_{0.975, 1} = 12.706``, ``t_{0.975, 4} = 2.776``
(three decimals, hence ``rtol=2e-4``).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import stats as scipy_stats

from ccrjax.run.stats import (
    difference_of_differences,
    holm,
    iqm,
    mean_ci,
    mean_ci_along,
    mean_relative_change,
    one_sided_below,
    plateau,
    plateau_or_undetermined,
    probability_of_improvement,
    welch,
)
from experiments.selection import SelectionRule, select

TABLE_RTOL = 2e-4


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
    mean, low, high = mean_ci_along(curves, axis=0)
    np.testing.assert_allclose(mean, [2.0, 10.0])
    np.testing.assert_allclose(high - mean, [12.706, 0.0], rtol=TABLE_RTOL)
    np.testing.assert_allclose(mean - low, [12.706, 0.0], rtol=TABLE_RTOL)
    five = np.array([[4.0], [1.0], [3.0], [5.0], [2.0]])
    mean, _, high = mean_ci_along(five, axis=0)
    np.testing.assert_allclose(high - mean, [2.776 / math.sqrt(2.0)], rtol=TABLE_RTOL)
    mean, low, high = mean_ci_along(curves[:1], axis=0)
    np.testing.assert_array_equal(low, mean)
    np.testing.assert_array_equal(high, mean)


def test_intervals_are_clipped_to_the_metric_range():
    # Success rates near 1: the raw interval 0.9925 +- 0.0152 would pass 1.
    result = mean_ci([0.99, 1.0, 1.0, 0.98], bounds=(0.0, 1.0))
    assert result["ci_high"] == 1.0
    assert result["ci_low"] == pytest.approx(result["mean"] - result["half_width"])
    assert result["half_width"] > 1.0 - result["mean"]  # the clip did something
    # A danger count near 0 never gets a negative end.
    result = mean_ci([0.0, 0.0, 0.02], bounds=(0.0, math.inf))
    assert result["ci_low"] == 0.0 and result["ci_high"] > 0.02 / 3
    curves = np.array([[0.0, 1.0], [0.1, 0.9]])
    _, low, high = mean_ci_along(curves, axis=0, bounds=(0.0, 1.0))
    assert low.min() >= 0.0 and high.max() <= 1.0
    assert low[0] == 0.0 and high[1] == 1.0


def welch_by_hand(a, b):
    """Welch's t statistic, the Welch-Satterthwaite degrees of freedom and the two-sided p."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    t = (a.mean() - b.mean()) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    return t, df, 2.0 * scipy_stats.t.sf(abs(t), df)


STEADY = [1.0, 1.1, 0.9, 1.05, 0.95, 1.0, 1.02, 0.98, 1.01, 0.99]


def test_welch_test_against_a_hand_computation():
    # Unequal spreads: Welch (p = 0.118) is not significant where the pooled-variance
    # Student test would be (p = 0.0003).
    wide = [1.5, 1.2, 1.9]
    t, df, p = welch_by_hand(STEADY, wide)
    assert (t, df, p) == pytest.approx((-2.621, 2.028, 0.118), abs=1e-3)
    assert scipy_stats.ttest_ind(STEADY, wide, equal_var=True).pvalue < 0.001
    assert welch(STEADY, wide)["significant"] is False
    # A clear difference is significant; p just above / below 0.05 decides.
    narrow = [1.5, 1.45, 1.55]
    assert welch_by_hand(STEADY, narrow)[2] < 0.01
    assert welch(STEADY, narrow)["significant"] is True
    decisions = []
    for shift in (0.6, 0.8, 0.85, 0.9, 1.0, 1.5):
        other = [1.0 + shift + x for x in (0.0, -0.3, 0.4)]
        expected = bool(welch_by_hand(STEADY, other)[2] < 0.05)
        assert welch(STEADY, other)["significant"] is expected, shift
        decisions.append(expected)
    assert decisions[0] is False and decisions[-1] is True  # the threshold is crossed
    assert welch(STEADY, wide)["p"] == pytest.approx(p, rel=1e-9)
    assert welch(STEADY, wide)["difference"] == pytest.approx(np.mean(STEADY) - np.mean(wide))
    # Degenerate cases: fewer than two values is refused; no spread at all.
    with pytest.raises(ValueError, match="at least 2 seeds"):
        welch([1.0], [2.0, 3.0])
    assert welch([1.0, 1.0], [2.0, 2.0])["significant"] is True
    assert welch([1.0, 1.0], [1.0, 1.0])["significant"] is False
    # Equal values whose computed spread is rounding noise: no spread either, and no
    # warning (the tables test many cells of constant success).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert welch([0.7] * 3, [0.1] * 3)["p"] == 0.0
        assert welch([0.7] * 3, [0.7] * 3)["p"] == 1.0
        spread = [0.95, 0.96, 0.97]
        assert welch([0.8] * 3, spread)["p"] == pytest.approx(
            welch_by_hand([0.8] * 3, spread)[2], rel=1e-9)


def test_bootstrap_interval_of_the_headline_matches_the_normal_approximation():
    """Every base cell is constant 1 and every new cell holds the same 20 values (mean
    0.8, population sd ``sigma``): the headline reduction is ``1 - 0.8 = 0.2`` and its
    bootstrap distribution is the mean of 9 independent bootstrap means, close to normal
    with sd ``sigma / sqrt(9 * 20)``; the 95% interval is ``0.2 +- 1.96`` of those."""
    rng = np.random.default_rng(5)
    new = rng.normal(size=20)
    new = 0.8 + 0.1 * (new - new.mean()) / new.std()  # mean 0.8, population sd 0.1
    pairs = 9
    result = mean_relative_change([(new, np.ones(5))] * pairs + [(new, np.zeros(5))], -1,
                                  resamples=4000)
    assert result["pairs"] == pairs and result["left_out"] == 1  # a zero base is left out
    assert result["mean"] == pytest.approx(0.2, rel=1e-9)
    sd = 0.1 / math.sqrt(pairs * new.size)
    half = (result["ci_high"] - result["ci_low"]) / 2
    centre = (result["ci_high"] + result["ci_low"]) / 2
    assert half == pytest.approx(1.96 * sd, rel=0.1)
    assert centre == pytest.approx(0.2, abs=0.2 * sd)


def test_a_resample_with_a_zero_base_is_dropped_not_read_as_no_change():
    """Base: nine seeds at 0 and one at 0.04; new: 0.002 on every seed. A resample holding
    the 0.04 seed ``k >= 1`` times has base mean ``0.004 k`` and reduction ``1 - 0.5 / k``,
    at least 0.5; one without it (probability ``0.9^10 = 0.35``) has no relative change.
    Counting those as 0 pulled the interval's lower end to 0."""
    base = np.array([0.0] * 9 + [0.04])
    result = mean_relative_change([(np.full(10, 0.002), base)], -1, resamples=4000)
    assert result["mean"] == pytest.approx(0.5)
    assert result["ci_low"] == pytest.approx(0.5)
    assert 0.5 < result["ci_high"] < 1.0
    assert result["resamples_dropped"] / 4000 == pytest.approx(0.9**10, abs=0.03)


def test_each_pairs_change_is_kept_so_a_dominating_pair_shows():
    """Two ordinary pairs (reductions 0.5 and 0.25) and one whose base is near 0 (an
    increase of 40 times): the average is that pair's; ``per_pair`` shows it, and a zero
    base appears as ``None``."""
    pairs = [(np.full(3, 0.1), np.full(3, 0.2)), (np.full(3, 0.3), np.full(3, 0.4)),
             (np.full(3, 0.041), np.full(3, 0.001)), (np.full(3, 0.1), np.zeros(3))]
    result = mean_relative_change(pairs, -1, resamples=100)
    assert result["per_pair"][:3] == pytest.approx([0.5, 0.25, -40.0])
    assert result["per_pair"][3] is None and result["left_out"] == 1
    assert result["mean"] == pytest.approx((0.5 + 0.25 - 40.0) / 3)


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
    # A seed that diverged (NaN) leaves the question open: undetermined, not "did not".
    broken = flat.copy()
    broken[1, -1] = np.nan
    assert plateau(broken)["plateaued"] is None
    # What the results record: the check itself, or undetermined with the reason.
    assert plateau_or_undetermined(rising) == result
    short = plateau_or_undetermined(flat[:, :1])
    assert short["plateaued"] is None and "points" in short["why"]


def test_rliable_iqm_is_the_mean_of_the_middle_half():
    # 4 runs x 2 tasks: the 8 scores 1..8; the IQM drops the lowest and highest quarter
    # (1, 2 and 7, 8) and averages 3..6 = 4.5. A method whose every score is equal has a
    # zero-width interval.
    scores = np.arange(1.0, 9.0).reshape(4, 2)
    result = iqm({"a": scores, "flat": np.full((4, 2), 0.25)}, resamples=200)
    assert result["a"]["iqm"] == pytest.approx(4.5)
    assert result["a"]["ci_low"] <= 4.5 <= result["a"]["ci_high"]
    assert result["a"]["ci_low"] < result["a"]["ci_high"]
    assert result["flat"] == {"iqm": 0.25, "ci_low": 0.25, "ci_high": 0.25}
    # Reproducible, and the caller's global generator is left alone.
    np.random.seed(3)  # noqa: NPY002 (rliable draws from the legacy global generator)
    expected_next = np.random.random()  # noqa: NPY002
    np.random.seed(3)  # noqa: NPY002
    assert iqm({"a": scores}, resamples=200) == iqm({"a": scores}, resamples=200)
    assert np.random.random() == expected_next  # noqa: NPY002
    with pytest.raises(ValueError, match="runs >= 2"):
        iqm({"a": scores[:1]})


def test_rliable_probability_of_improvement():
    rng = np.random.default_rng(0)
    low = rng.random((10, 9))
    # Every run of x above every run of y on every task: P = 1; the reverse: 0.
    assert probability_of_improvement(low + 2.0, low, resamples=20)["probability"] == 1.0
    assert probability_of_improvement(low, low + 2.0, resamples=20)["probability"] == 0.0
    # The same scores: ties count half.
    same = probability_of_improvement(low, low, resamples=20)
    assert same["probability"] == pytest.approx(0.5)
    # Against the Mann-Whitney U statistic of each task, averaged.
    other = rng.random((10, 9)) + 0.2
    by_task = [scipy_stats.mannwhitneyu(low[:, k], other[:, k]).statistic / 100 for k in range(9)]
    result = probability_of_improvement(low, other, resamples=50)
    assert result["probability"] == pytest.approx(np.mean(by_task))
    assert result["ci_low"] <= result["probability"] <= result["ci_high"]
    with pytest.raises(ValueError, match="same tasks"):
        probability_of_improvement(low, other[:, :3])


def made_up_search(success, danger, reference_success, pairs=3, seeds=2):
    """``[values, pairs, seeds]`` metrics whose means are ``success[v]`` and ``danger[v]`` in
    every pair (the seeds spread symmetrically), and a reference of ``reference_success``."""
    spread = np.array([-0.01, 0.01])[:seeds]

    def cube(means):
        return np.asarray(means)[:, None, None] + np.zeros((1, pairs, 1)) + spread

    return ({"success_rate": cube(success), "danger_frequency": cube(danger)},
            {"success_rate": np.full((pairs, seeds), reference_success)})


def test_selection_rule_picks_the_safest_value_that_keeps_success():
    values = [0.3, 1.0, 3.0, 10.0, 30.0, 100.0]
    success = [0.90, 0.89, 0.86, 0.84, 0.60, 0.20]  # the reference: 0.90
    danger = [0.30, 0.25, 0.20, 0.15, 0.05, 0.01]
    metrics, reference = made_up_search(success, danger, 0.90)
    result = select(SelectionRule(), values, metrics, reference)
    # 10 is the last value within 5 points (0.84 < 0.85 is not): 3 is chosen.
    assert result["eligible"] == [True, True, True, False, False, False]
    assert result["value"] == 3.0 and not result["fallback"]
    # A looser tolerance admits 10; success is averaged over pairs.
    assert select(SelectionRule(tolerance=0.1), values, metrics, reference)["value"] == 10.0
    # Ties in danger go to the smaller value.
    metrics, reference = made_up_search(success, [0.3, 0.2, 0.2, 0.1, 0.0, 0.0], 0.90)
    assert select(SelectionRule(), values, metrics, reference)["value"] == 1.0
    # Nothing eligible: the value closest to the reference's success, flagged.
    metrics, reference = made_up_search(success, danger, 0.99)
    result = select(SelectionRule(), values, metrics, reference)
    assert result["fallback"] and result["value"] == 0.3


def test_selection_rule_refuses_unknown_metrics():
    with pytest.raises(ValueError, match="objective must be one of"):
        SelectionRule(objective="safety")
    with pytest.raises(ValueError, match="tolerance"):
        SelectionRule(tolerance=-0.1)
    metrics, reference = made_up_search([0.9], [0.1], 0.9)
    with pytest.raises(ValueError, match="no metric 'return'"):
        select(SelectionRule(objective="return"), [1.0], metrics, reference)


def test_holm_steps_down_and_stops_at_the_first_failure():
    """m = 4: thresholds 0.0125, 0.0167, 0.025, 0.05 for the sorted p-values. 0.01 and 0.015
    pass; 0.03 > 0.025 fails, so 0.04 is not rejected although it is below 0.05."""
    rejected = holm([0.04, 0.01, 0.03, 0.015])
    assert rejected.tolist() == [False, True, False, True]
    assert holm([0.001, 0.002]).tolist() == [True, True]
    assert holm([0.2, 0.001]).tolist() == [False, True]
    assert not holm([0.06, 0.5]).any()


def test_one_sided_below_halves_the_two_sided_p_in_its_direction():
    low, high = [0.1, 0.12, 0.11, 0.13], [0.3, 0.31, 0.29, 0.32]
    two = welch(low, high)
    below = one_sided_below(low, high)
    assert below["p"] == pytest.approx(two["p"] / 2) and below["significant"]
    above = one_sided_below(high, low)
    assert above["p"] == pytest.approx(1 - two["p"] / 2) and not above["significant"]


def test_difference_of_differences_and_its_bootstrap_interval():
    a1, b1 = np.array([0.3, 0.31, 0.29]), np.array([0.1, 0.11, 0.09])  # effect 0.2
    a2, b2 = np.array([0.3, 0.31, 0.29]), np.array([0.28, 0.29, 0.27])  # effect 0.02
    found = difference_of_differences(a1, b1, a2, b2, resamples=500)
    assert found["difference"] == pytest.approx(0.18)
    assert 0.0 < found["ci_low"] < 0.18 < found["ci_high"]
    same = difference_of_differences(a1, b1, a1, b1, resamples=500)
    assert same["ci_low"] < 0 < same["ci_high"]
    with pytest.raises(ValueError, match="at least 2 seeds per group"):
        difference_of_differences([1.0], b1, a2, b2)
