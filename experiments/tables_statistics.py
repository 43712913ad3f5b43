"""The tables' numbers from their cells: per-cell statistics, Welch tests, the paper's
headline figures recomputed, rliable's aggregates and the claim scorecard, gathered into
what ``tables.json`` holds (:func:`summary`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ccrjax.run.folder import METRIC_RANGES
from ccrjax.run.stats import (
    holm,
    iqm,
    mean_ci,
    mean_relative_change,
    probability_of_improvement,
    welch,
)
from ccrjax.run.sweep_grid import nonfinite_runs
from ccrjax.training import ALGOS
from experiments import protocol
from experiments.cell_identity import settings_record
from experiments.paper import PAPER, PAPER_HEADLINES, PAPER_OBSTACLE_DISTANCE_RATIO, PAPER_SCENARIOS
from experiments.tables_grid import (
    LEARNER_NAMES,
    METRICS,
    SCENARIO_NAMES,
    VARIANT_SUFFIX,
    VARIANTS,
    Settings,
)


def stats(values: list[float], metric: str) -> dict[str, Any]:
    return {"per_seed": values, **mean_ci(values, bounds=METRIC_RANGES[metric])}


# The paper's averaged relative changes: (metric, new, base, sign, scenarios), the average
# over those scenarios' scenario x learner pairs (sign -1: a reduction).
HEADLINES = {
    "danger_reduction_vs_plain": ("danger_frequency", "ccr", "plain", -1.0, PAPER_SCENARIOS),
    "danger_reduction_vs_pessimistic": ("danger_frequency", "ccr", "pessimistic", -1.0,
                                        PAPER_SCENARIOS),
    "success_change_vs_pessimistic": ("success_rate", "ccr", "pessimistic", 1.0, PAPER_SCENARIOS),
    "success_change_vs_plain_turbulence": ("success_rate", "ccr", "plain", 1.0,
                                           ("turbulence",)),
}


def headline(cells, metric: str, new: str, base: str, sign: float,
             scenarios: tuple[str, ...] = PAPER_SCENARIOS, resamples: int = 2000,
             seed: int = 0, algos: tuple[str, ...] = ALGOS) -> dict[str, Any]:
    """The paper's averaged relative change over the ``scenarios`` x ``algos`` pairs
    (:func:`ccrjax.run.stats.mean_relative_change`), with the pairs named."""
    names = [(s, a) for s in scenarios for a in algos]
    pairs = [(np.asarray(cells[(s, a, new)]["final"][metric]),
              np.asarray(cells[(s, a, base)]["final"][metric])) for s, a in names]
    result = mean_relative_change(pairs, sign, resamples=resamples, seed=seed)
    result["pair_names"] = [f"{SCENARIO_NAMES[s]}, {LEARNER_NAMES[a]}" for s, a in names]
    return result


def obstacle_distance_ratio(cells) -> dict[str, Any]:
    """MADDPG+CCR's average distance to the obstacle's centre over MADDPG's, robot by
    robot in arrival order (means over seeds of the per-seed means over episodes), on the
    hidden obstacle: the paper's "1.2x to 4.7x"."""
    plain, ccr = (np.asarray(cells[("hidden_obstacle", "maddpg", v)]["arrival"]
                             ["centre_distance"]).mean(axis=0) for v in ("plain", "ccr"))
    ratio = ccr / plain
    return {"by_rank": ratio.tolist(), "low": float(ratio.min()), "high": float(ratio.max()),
            "paper": list(PAPER_OBSTACLE_DISTANCE_RATIO)}


def welch_marks(cells, algos: tuple[str, ...] = ALGOS) -> dict[tuple[str, str, str, str], dict]:
    """Welch tests of CCR against plain and pessimistic, per cell and metric."""
    marks = {}
    for scenario in PAPER_SCENARIOS:
        for algo in algos:
            ccr = cells[(scenario, algo, "ccr")]["final"]
            for base in ("plain", "pessimistic"):
                other = cells[(scenario, algo, base)]["final"]
                for metric in ("danger_frequency", "success_rate"):
                    marks[(scenario, algo, base, metric)] = welch(ccr[metric], other[metric])
    return marks


def claims(cells, marks, algos: tuple[str, ...] = ALGOS) -> dict[str, Any]:
    """The direction of the paper's claims, checked cell by cell over the ``algos``' pairs
    (the scorecard)."""
    result: dict[str, Any] = {}
    for base in ("plain", "pessimistic"):
        lower, significant, detail = 0, 0, []
        for scenario in PAPER_SCENARIOS:
            for algo in algos:
                ccr = float(np.mean(cells[(scenario, algo, "ccr")]["final"]["danger_frequency"]))
                other = float(np.mean(cells[(scenario, algo, base)]["final"]["danger_frequency"]))
                is_lower = ccr < other
                is_significant = is_lower and marks[(scenario, algo, base,
                                                     "danger_frequency")]["significant"]
                lower += is_lower
                significant += is_significant
                detail.append({"scenario": scenario, "algo": algo, "ccr": ccr, base: other,
                               "lower": is_lower, "significant": is_significant})
        # The cells' tests as one family (Holm): how many lower cells survive it.
        p_values = [marks[(d["scenario"], d["algo"], base, "danger_frequency")]["p"]
                    for d in detail]
        for d, rejected in zip(detail, holm(p_values), strict=True):
            d["significant_holm"] = bool(d["lower"] and rejected)
        result[f"danger_lower_vs_{base}"] = {
            "cells": lower, "significant": significant,
            "significant_holm": sum(d["significant_holm"] for d in detail),
            "of": len(detail), "detail": detail}
    raised = []
    for algo in algos:
        ccr = float(np.mean(cells[("hidden_obstacle", algo, "ccr")]["final"]["success_rate"]))
        both = []
        for base in ("plain", "pessimistic"):
            other = float(np.mean(cells[("hidden_obstacle", algo, base)]["final"]["success_rate"]))
            mark = marks[("hidden_obstacle", algo, base, "success_rate")]
            both.append({"vs": base, "ccr": ccr, "other": other, "higher": ccr > other,
                         "significant": ccr > other and mark["significant"]})
        raised.append({"algo": algo, "against": both,
                       "above_both": all(b["higher"] for b in both),
                       "significantly_above_both": all(b["significant"] for b in both)})
    result["hidden_obstacle_success_above_both"] = {
        "learners": sum(r["above_both"] for r in raised),
        "significant": sum(r["significantly_above_both"] for r in raised),
        "of": len(raised), "detail": raised}
    return result


def aggregates(cells, resamples: int = 2000, algos: tuple[str, ...] = ALGOS) -> dict[str, Any]:
    """rliable over the scenario x learner pairs of ``algos`` (tasks), seeds as runs: each
    variant's IQM of danger and of success, and the probability that CCR improves on each
    baseline (lower danger, higher success)."""
    pairs = [(s, a) for s in PAPER_SCENARIOS for a in algos]
    result: dict[str, Any] = {}
    for metric, sign in (("danger_frequency", -1.0), ("success_rate", 1.0)):
        scores = {v: np.array([cells[(s, a, v)]["final"][metric] for s, a in pairs]).T
                  for v in VARIANTS}  # [seeds, pairs]
        result[metric] = {
            "iqm": iqm(scores, resamples=resamples),
            "probability_of_improvement": {
                base: probability_of_improvement(sign * scores["ccr"], sign * scores[base],
                                                 resamples=resamples)
                for base in ("plain", "pessimistic")},
        }
    return result


def training_danger_share(cells) -> dict[str, Any]:
    """MADDPG+CCR's dangerous robot-steps during training from the start of learning, as a
    share of plain MADDPG's, on the hidden obstacle (the paper's 28.09%)."""
    ccr, plain = (np.asarray(cells[("hidden_obstacle", "maddpg", v)]["final"]
                             ["learning_danger_steps"]) for v in ("ccr", "plain"))
    share = mean_relative_change([(ccr, plain)], +1.0)
    return {"mean": None if share["mean"] is None else 1.0 + share["mean"],
            "ci_low": None if share["ci_low"] is None else 1.0 + share["ci_low"],
            "ci_high": None if share["ci_high"] is None else 1.0 + share["ci_high"]}


def summary(cells, settings: Settings, invocations: list[dict[str, Any]],
            controllers: dict, sources: dict[str, str]) -> dict[str, Any]:
    """Everything ``tables.json`` holds, over the pairs of ``settings``' learner family (the
    MADDPG figures of the paper only where MADDPG is among them)."""
    algos = protocol.family(settings.algos)
    marks = welch_marks(cells, algos)
    records = []
    for scenario in PAPER_SCENARIOS:
        for algo in algos:
            for variant in VARIANTS:
                cell = cells[(scenario, algo, variant)]
                record = {"scenario": scenario, "algo": algo, "variant": variant,
                          "seeds": cell["seeds"], "return_plateau": cell["return_plateau"],
                          "nonfinite_iteration": cell.get("nonfinite_iteration"),
                          "program_seconds": cell["train_seconds_of_program"]
                          + cell["compile_seconds_of_program"],
                          "device": cell["device"], "commit": cell["commit"]}
                for metric in METRICS:
                    record[metric] = stats(cell["final"][metric], metric)
                    paper = PAPER.get(metric, {}).get((scenario, algo, variant))
                    if paper is not None:
                        record[metric]["paper"] = paper
                    if variant == "ccr" and metric in ("danger_frequency", "success_rate"):
                        record[metric]["welch"] = {
                            base: marks[(scenario, algo, base, metric)]
                            for base in ("plain", "pessimistic")}
                if "arrival" in cell:
                    measured = [x for x in cell["arrival"]["followers_closest_successful"]
                                if np.isfinite(x)]  # seeds with a successful follower
                    values = measured or [float("nan")]
                    record["followers_closest_successful"] = {  # signed: no range to clip to
                        "per_seed": values, **mean_ci(values),
                        "seeds_measured": f"{len(measured)}/{len(cell['seeds'])}"}
                records.append(record)
    headlines = {key: headline(cells, *definition, algos=algos)
                 for key, definition in HEADLINES.items()}
    maddpg = "maddpg" in algos
    headlines["training_danger_share_maddpg_hidden_obstacle"] = (
        training_danger_share(cells) if maddpg else None)
    programs = {(c["scenario"], c["algo"], c["variant"] == "ccr"): c for c in cells.values()}
    return {
        "settings": settings_record(settings),
        "sources": sources,
        "algos": list(algos),
        "budgets": {a: settings.budget(a) for a in algos},
        "invocations": invocations,
        "programs_seconds": sum(c["train_seconds_of_program"] + c["compile_seconds_of_program"]
                                for c in programs.values()),
        "devices": sorted({c["device"] for c in cells.values()}),
        "commits": sorted({str(c["commit"]) for c in cells.values()}),
        "records": records,
        "controllers": [{"scenario": s, "controller": c, **m}
                        for (s, c), m in controllers.items()],
        "nonfinite": [line for (s, a, v), cell in cells.items() for line in nonfinite_runs(
            cell, f"{SCENARIO_NAMES[s]}, {LEARNER_NAMES[a]}{VARIANT_SUFFIX[v]}")],
        "runs": sum(len(cell["seeds"]) for cell in cells.values()),
        "headlines": headlines,
        "paper_headlines": PAPER_HEADLINES,
        "obstacle_distance_ratio_maddpg": obstacle_distance_ratio(cells) if maddpg else None,
        "aggregates": aggregates(cells, algos=algos),
        "claims": claims(cells, marks, algos),
    }

