"""The study's analysis (docs/protocol.md, amendment of 2026-12-01, "Hypotheses" and
"Analysis per cell"), as pure functions of its cells.

``cells`` maps ``(regime, scenario, algo, variant)`` to a cell of ``experiments/study.py``
(per-seed ``final`` metrics and ``measures``). Per scenario and learner:

* **H1** (``today``): CCR's danger equals plain's, two-sided Welch p >= 0.05;
* **H2** (``column``): CCR's danger is below plain's, one-sided Welch p < 0.05, with success
  at most 5 points below plain's;
* **H3**: CCR's effect (plain's danger minus CCR's) is larger in ``column`` than in
  ``today``: the difference of differences' 95% bootstrap interval over seeds above 0;
* **H4**: each of CCR's parts against plain and against CCR (two-sided Welch on danger);
* **H5**: CCR against the tuned pessimistic and Lagrangian baselines (two-sided Welch on
  danger and on success).

A hypothesis whose cells are not all made yet is ``None`` (not yet), never a verdict.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ccrjax.run.stats import (
    difference_of_differences,
    iqm,
    mean_ci,
    one_sided_below,
    probability_of_improvement,
    welch,
)
from experiments.study_measures import FOLLOWER_METRICS

PARTS = ("ccr_scores", "ccr_reward", "ccr_perfect", "danger_flags")
BASELINES = ("pessimistic", "lagrangian")
SUCCESS_TOLERANCE = 0.05  # H2: at most 5 points of success below plain's
SHARES = ("danger_frequency", "success_rate", "forewarned_share", "followers_danger",
          "followers_success")
ROW_METRICS = ("danger_frequency", "success_rate", "forewarned_share", *FOLLOWER_METRICS)
Cells = dict[tuple[str, str, str, str], dict[str, Any]]


def per_seed(cell: dict[str, Any], metric: str) -> np.ndarray:
    """A cell's per-seed values of ``metric``: a final evaluation metric, or one of the
    study's measures (a seed without a value, e.g. no forewarned share, left out)."""
    values = cell["final"][metric] if metric in cell["final"] else cell["measures"][metric]
    return np.array([v for v in values if v is not None], np.float64)


def cell_row(cell: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Mean and Student-t 95% interval over seeds of every :data:`ROW_METRICS` (shares
    clipped to [0, 1]); ``None`` where fewer than one seed has a value."""
    row = {}
    for metric in ROW_METRICS:
        values = per_seed(cell, metric)
        bounds = (0.0, 1.0) if metric in SHARES else (0.0, None)
        row[metric] = mean_ci(values, bounds=bounds) if values.size else None
    return row


def _danger(cells: Cells, key: tuple[str, str, str, str]) -> np.ndarray | None:
    return per_seed(cells[key], "danger_frequency") if key in cells else None


def hypotheses(cells: Cells, scenario: str, algo: str, resamples: int = 2000
               ) -> dict[str, Any]:
    """H1 to H5 for one scenario and learner (module docstring); each entry holds its
    statistics and ``holds`` (``None``: its cells are not all made)."""
    def key(regime: str, variant: str) -> tuple[str, str, str, str]:
        return (regime, scenario, algo, variant)

    def metric(regime: str, variant: str, name: str) -> np.ndarray | None:
        found = cells.get(key(regime, variant))
        return None if found is None else per_seed(found, name)

    result: dict[str, Any] = {}
    plain_today = _danger(cells, key("today", "plain"))
    ccr_today = _danger(cells, key("today", "ccr"))
    plain_col = _danger(cells, key("column", "plain"))
    ccr_col = _danger(cells, key("column", "ccr"))
    if plain_today is not None and ccr_today is not None:
        test = welch(ccr_today, plain_today)
        result["H1"] = {**test, "holds": not test["significant"]}
    else:
        result["H1"] = {"holds": None}
    if plain_col is not None and ccr_col is not None:
        test = one_sided_below(ccr_col, plain_col)
        drop = float(metric("column", "plain", "success_rate").mean()
                     - metric("column", "ccr", "success_rate").mean())
        result["H2"] = {**test, "success_drop": drop,
                        "holds": test["significant"] and drop <= SUCCESS_TOLERANCE + 1e-12}
    else:
        result["H2"] = {"holds": None}
    if all(x is not None for x in (plain_today, ccr_today, plain_col, ccr_col)):
        change = difference_of_differences(plain_col, ccr_col, plain_today, ccr_today,
                                           resamples=resamples)
        result["H3"] = {**change, "holds": change["ci_low"] > 0}
    else:
        result["H3"] = {"holds": None}
    result["H4"] = {}
    result["H5"] = {}
    for regime in ("today", "column"):
        ccr = _danger(cells, key(regime, "ccr"))
        plain = _danger(cells, key(regime, "plain"))
        for part in PARTS:
            mine = _danger(cells, key(regime, part))
            if mine is None:
                continue
            result["H4"][f"{regime}/{part}"] = {
                "against_plain": None if plain is None else welch(mine, plain),
                "against_ccr": None if ccr is None else welch(mine, ccr)}
        for baseline in BASELINES:
            if ccr is None or key(regime, baseline) not in cells:
                continue
            result["H5"][f"{regime}/{baseline}"] = {
                name: welch(metric(regime, "ccr", name), metric(regime, baseline, name))
                for name in ("danger_frequency", "success_rate")}
    return result


def aggregates(cells: Cells, regime: str, resamples: int = 2000) -> dict[str, Any]:
    """Over the regime's scenario x learner pairs: rliable's interquartile mean of danger
    and of success per variant (the variants made in every pair), and the probability
    that a CCR run is safer than a plain one (``P(danger_CCR < danger_plain)``)."""
    pairs = sorted({(s, a) for r, s, a, _ in cells if r == regime})
    variants = [v for v in dict.fromkeys(v for r, _, _, v in cells if r == regime)
                if all((regime, s, a, v) in cells for s, a in pairs)]
    if not pairs or not variants:
        return {"pairs": [], "iqm": {}, "ccr_safer_than_plain": None}

    def scores(variant: str, name: str) -> np.ndarray:  # [seeds, pairs]
        return np.stack([per_seed(cells[(regime, s, a, variant)], name) for s, a in pairs],
                        axis=1)

    result: dict[str, Any] = {"pairs": [f"{s}-{a}" for s, a in pairs], "iqm": {}}
    for name in ("danger_frequency", "success_rate"):
        result["iqm"][name] = iqm({v: scores(v, name) for v in variants}, resamples)
    result["ccr_safer_than_plain"] = (
        probability_of_improvement(-scores("ccr", "danger_frequency"),
                                   -scores("plain", "danger_frequency"), resamples)
        if {"ccr", "plain"} <= set(variants) else None)
    return result
