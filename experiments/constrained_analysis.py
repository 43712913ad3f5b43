"""The constrained baseline's study (docs/protocol.md, amendment of 2026-12-02), as pure
functions of committed cells: every variant at one budget, the three searches' choices made
there by the one rule, and the Lagrangian's table rows against plain, pessimistic and CCR.

The other variants' numbers at the budget are their longer runs' evaluations at it (a run
of ``B`` steps is exactly the first ``B`` steps of a longer one once the replay buffer is
full: ``tests/test_training.py``), read from the 6M searches' and tables' cells; the
Lagrangian's come from its own search and table cells, trained at the budget.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ccrjax.run.folder import METRIC_RANGES
from ccrjax.run.stats import holm, iqm, mean_ci, probability_of_improvement, welch
from ccrjax.training import ALGOS
from experiments import protocol
from experiments.paper import PAPER_SCENARIOS
from experiments.selection import select

SEARCH_METRICS = ("return", "success_rate", "danger_frequency")
BASELINES = ("plain", "pessimistic", "ccr")
VARIANTS = (*BASELINES, "lagrangian")
PAIRS = [(scenario, algo) for scenario in PAPER_SCENARIOS for algo in ALGOS]


def point_index(env_steps: list[int], steps: int, where: str) -> int:
    """The index of the evaluation at ``steps`` in a cell's ``env_steps``; ``ValueError``
    naming ``where`` if the cell never evaluated there."""
    if steps not in env_steps:
        raise ValueError(f"{where} has no evaluation at {steps:,} steps (it has "
                         f"{env_steps[0]:,} to {env_steps[-1]:,})")
    return env_steps.index(steps)


def search_at(cell: dict[str, Any], steps: int) -> dict[str, dict[str, list[float]]]:
    """A search cell's runs at ``steps``: ``{value: {metric: per-seed values}}``, the values
    in the order searched (value 0, the rule's reference, first)."""
    index = point_index(cell["env_steps"], steps, f"{cell['scenario']}-{cell['algo']}")
    found: dict[float, dict[str, list[float]]] = {}
    for run, value in enumerate(cell["grid_values"]):
        row = found.setdefault(float(value), {m: [] for m in SEARCH_METRICS})
        for metric in SEARCH_METRICS:
            row[metric].append(float(cell["history"][metric][run][index]))
    return found


def selection_at(cells: dict[tuple[str, str], dict], steps: int) -> dict[str, Any]:
    """The protocol's rule (:data:`protocol.RULE`) applied to one search's 9 pairs at
    ``steps``: the reference is each pair's value 0."""
    missing = [f"{s}-{a}" for s, a in PAIRS if (s, a) not in cells]
    if missing:
        raise ValueError(f"the search lacks {', '.join(missing)}")
    runs = {pair: search_at(cells[pair], steps) for pair in PAIRS}
    values = sorted(v for v in runs[PAIRS[0]] if v != 0.0)
    metrics = {m: np.array([[runs[pair][v][m] for pair in PAIRS] for v in values])
               for m in SEARCH_METRICS}  # [values, pairs, seeds]
    reference = {m: np.array([runs[pair][0.0][m] for pair in PAIRS]) for m in SEARCH_METRICS}
    return {**select(protocol.RULE, values, metrics, reference), "values": values,
            "steps": steps}


def table_cell_at(cell: dict[str, Any], steps: int) -> dict[str, list[float]]:
    """A table cell's per-seed evaluation (and training counts) at ``steps``."""
    where = f"{cell['scenario']}-{cell['algo']}-{cell['variant']}"
    index = point_index([int(s) for s in cell["history"]["env_steps"][0]], steps, where)
    return {metric: [float(seed_curve[index]) for seed_curve in curve]
            for metric, curve in cell["history"].items() if metric != "env_steps"}


def training_danger(cell: dict[str, Any], values: dict[str, list[float]],
                    steps: int) -> list[float]:
    """Per seed, the share of robot-steps in danger from the start of learning to
    ``steps``: the dangerous robot-steps counted since learning started over the robot-steps
    trained since (the warm-up's random steps are alike for every variant)."""
    training = cell["training"]
    learning_steps = max(steps - int(training["learning_starts"]), 1)
    robot_steps = learning_steps * int(training["num_robots"])
    return [count / robot_steps for count in values["learning_danger_steps"]]


def last_interval_danger(cell: dict[str, Any], steps: int) -> list[float]:
    """Per seed, the share of robot-steps in danger in the training episodes of the last
    evaluation interval before ``steps``: what the multiplier regulates (the training
    policy's danger, exploration included; the limit is met in training where it is at
    most the limit), beside the greedy policy's evaluated danger."""
    history = cell["history"]
    env_steps = [int(s) for s in history["env_steps"][0]]
    where = f"{cell['scenario']}-{cell['algo']}-{cell['variant']}"
    index = point_index(env_steps, steps, where)
    if index == 0:
        raise ValueError(f"{where}: no evaluation interval ends at {steps:,} steps")
    robot_steps = (env_steps[index] - env_steps[index - 1]) * int(cell["training"]["num_robots"])
    return [float(curve[index] - curve[index - 1]) / robot_steps
            for curve in history["learning_danger_steps"]]


def pair_rows(tables: dict[tuple[str, str, str], dict], steps: int, cost_limit: float
              ) -> dict[tuple[str, str], dict[str, Any]]:
    """Per pair, each variant's per-seed danger, success and training danger at ``steps``
    (and the last interval's training danger), the Welch tests of the Lagrangian against
    each baseline, and which Lagrangian seeds meet the limit (final evaluated danger at most
    ``cost_limit``; in training, the last interval's danger at most it)."""
    rows = {}
    for scenario, algo in PAIRS:
        variants = {}
        for variant in VARIANTS:
            cell = tables[(scenario, algo, variant)]
            values = table_cell_at(cell, steps)
            variants[variant] = {
                "danger_frequency": values["danger_frequency"],
                "success_rate": values["success_rate"],
                "training_danger": training_danger(cell, values, steps),
                "last_interval_danger": last_interval_danger(cell, steps),
            }
        lagrangian = variants["lagrangian"]
        rows[(scenario, algo)] = {
            "variants": variants,
            "welch": {base: {metric: welch(lagrangian[metric], variants[base][metric])
                             for metric in ("danger_frequency", "success_rate",
                                            "training_danger")}
                      for base in BASELINES},
            "meets_limit": [d <= cost_limit for d in lagrangian["danger_frequency"]],
            "meets_limit_in_training": [d <= cost_limit
                                        for d in lagrangian["last_interval_danger"]],
        }
    return rows


def rule_value_rows(cells: dict[tuple[str, str, str], dict], rows: dict[tuple[str, str], dict],
                    steps: int) -> dict[tuple[str, str], dict[str, Any]]:
    """Per pair, the per-seed danger, success and training danger at ``steps`` of the
    pessimistic and CCR cells of ``cells`` (keyed ``(scenario, algo, variant)``: the
    values the rule chose at this budget where they are not the tables'), and the Welch
    tests of the Lagrangian (its rows in ``rows``, :func:`pair_rows`) against each."""
    found = {}
    for scenario, algo in PAIRS:
        lagrangian = rows[(scenario, algo)]["variants"]["lagrangian"]
        variants, tests = {}, {}
        for variant in ("pessimistic", "ccr"):
            cell = cells.get((scenario, algo, variant))
            if cell is None:
                continue
            values = table_cell_at(cell, steps)
            variants[variant] = {"danger_frequency": values["danger_frequency"],
                                 "success_rate": values["success_rate"],
                                 "training_danger": training_danger(cell, values, steps)}
            tests[variant] = {metric: welch(lagrangian[metric], variants[variant][metric])
                              for metric in ("danger_frequency", "success_rate",
                                             "training_danger")}
        found[(scenario, algo)] = {"variants": variants, "welch": tests}
    return found


SCORED = ("danger_frequency", "success_rate", "training_danger")
LOWER_IS_BETTER = {"danger_frequency": True, "success_rate": False, "training_danger": True}


def summary_of(values: list[float], metric: str) -> dict[str, Any]:
    return {"per_seed": values,
            **mean_ci(values, bounds=METRIC_RANGES.get(metric, (0.0, 1.0)))}


def aggregates(rows: dict[tuple[str, str], dict[str, Any]], resamples: int = 2000
               ) -> dict[str, Any]:
    """rliable over the 9 pairs, seeds as runs: each variant's IQM of danger, success and
    training danger, and the probabilities that the Lagrangian improves on each baseline and
    that CCR improves on the Lagrangian (lower danger, higher success)."""
    result: dict[str, Any] = {}
    for metric in SCORED:
        sign = -1.0 if LOWER_IS_BETTER[metric] else 1.0
        scores = {v: np.array([rows[pair]["variants"][v][metric] for pair in PAIRS]).T
                  for v in VARIANTS}  # [seeds, 9]
        improvement = {
            f"lagrangian_over_{base}": probability_of_improvement(
                sign * scores["lagrangian"], sign * scores[base], resamples=resamples)
            for base in BASELINES}
        improvement["ccr_over_lagrangian"] = probability_of_improvement(
            sign * scores["ccr"], sign * scores["lagrangian"], resamples=resamples)
        result[metric] = {"iqm": iqm(scores, resamples=resamples),
                          "probability_of_improvement": improvement}
    return result


def hypotheses(rows: dict[tuple[str, str], dict[str, Any]], cost_limit: float
               ) -> dict[str, Any]:
    """The amendment's hypotheses, checked pair by pair. H-L1: in the pairs where plain's
    mean final danger is above the limit, whether the Lagrangian's mean meets it within the
    seeds' spread (its 95% interval reaches the limit). H-L2: against pessimistic, the
    direction and significance of each difference (danger, success, training danger)."""
    above = [pair for pair in PAIRS
             if np.mean(rows[pair]["variants"]["plain"]["danger_frequency"]) > cost_limit]
    met = []
    for pair in above:
        danger = rows[pair]["variants"]["lagrangian"]["danger_frequency"]
        met.append(mean_ci(danger, bounds=(0.0, 1.0))["ci_low"] <= cost_limit)
    versus = {metric: {
        "lower": sum(rows[p]["welch"]["pessimistic"][metric]["difference"] < 0 for p in PAIRS),
        "significantly_lower": sum(rows[p]["welch"]["pessimistic"][metric]["significant"]
                                   and rows[p]["welch"]["pessimistic"][metric]["difference"]
                                   < 0 for p in PAIRS),
        "significantly_higher": sum(rows[p]["welch"]["pessimistic"][metric]["significant"]
                                    and rows[p]["welch"]["pessimistic"][metric]["difference"]
                                    > 0 for p in PAIRS)}
        for metric in SCORED}
    return {"pairs_plain_above_limit": [f"{s}-{a}" for s, a in above],
            "limit_met_within_spread": int(sum(met)), "h_l1_holds": bool(above) and
            sum(met) > len(above) / 2, "versus_pessimistic": versus}


def scorecard(rows: dict[tuple[str, str], dict[str, Any]]) -> dict[str, Any]:
    """The tables' scorecard extended to the Lagrangian: per baseline and metric, in how
    many of the pairs the Lagrangian's mean is better than the baseline's (lower danger,
    higher success) and worse, and how many of those differences are significant (Welch,
    p < 0.05, each pair alone) and survive Holm's correction over the pairs (one family per
    baseline and metric, as the tables count CCR against plain and pessimistic). "CCR
    better than the Lagrangian" is the ``ccr`` row's ``worse``."""
    pairs = list(rows)
    result: dict[str, Any] = {}
    for base in BASELINES:
        result[base] = {}
        for metric in SCORED:
            tests = [rows[pair]["welch"][base][metric] for pair in pairs]
            rejected = holm([test["p"] for test in tests])
            counts = {}
            for side, sign in (("better", 1.0), ("worse", -1.0)):
                direction = -1.0 if LOWER_IS_BETTER[metric] else 1.0
                wins = [sign * direction * test["difference"] > 0 for test in tests]
                counts[side] = {
                    "cells": int(sum(wins)),
                    "significant": int(sum(w and t["significant"] for w, t in zip(
                        wins, tests, strict=True))),
                    "significant_holm": int(sum(w and bool(r) for w, r in zip(
                        wins, rejected, strict=True))),
                }
            result[base][metric] = {**counts, "of": len(pairs)}
    return result
