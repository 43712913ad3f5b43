"""Searches of a run parameter (CCR's lambda, the pessimistic penalty): the grid of values
x seeds that one program trains, and the per-value summary of its results.

Used by ``python -m ccrjax.sweep`` (one scenario and learner) and
``experiments/search.py`` (all of them, with the selection rule of
:mod:`experiments.selection`); the summaries of per-seed values and of runs whose updates
went non-finite serve every experiment's grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ccrjax.run.folder import METRIC_RANGES, POINT_METRICS
from ccrjax.run.stats import mean_ci
from ccrjax.training import TrainConfig
from ccrjax.training.grid import GridRuns

# The run parameter each searchable variant takes, and the values searched by default
# (the protocol's, docs/protocol.md).
# CCR's parts with an intrinsic reward (the reward alone, the perfect detector) take CCR's
# lambda and its values.
SEARCHED_PARAMETER = {"ccr": "lam", "pessimistic": "penalty", "lagrangian": "cost_limit",
                      "ccr_reward": "lam", "ccr_perfect": "lam"}
LAMBDAS = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
DEFAULT_VALUES = {"ccr": LAMBDAS, "pessimistic": (0.03, 0.1, 0.3, 1.0, 3.0, 10.0),
                  "lagrangian": (0.003, 0.01, 0.02, 0.05, 0.1, 0.3),
                  "ccr_reward": LAMBDAS, "ccr_perfect": LAMBDAS}
# Where the value 0 of a parameter is not itself the reference, the run numbers that make
# the reference: a cost limit of 0 would be the strictest constraint, so the Lagrangian's
# reference is its multiplier held at 0 (no gain), which is exactly the plain learner.
REFERENCE_PARAMS = {"cost_limit": {"cost_limit": 1.0, "kp": 0.0, "ki": 0.0, "kd": 0.0}}
# What the value 0 of each searched parameter is (the selection rule's reference): the
# penalty 0 is exactly the plain learner; CCR's lambda 0 leaves the reward unchanged, but
# its robots still observe the shared scores. A short name for tables and legends, and a
# sentence for captions.
REFERENCE_NAME = {"penalty": "plain", "lam": "no CCR reward", "cost_limit": "plain"}
REFERENCE_TEXT = {"penalty": "penalty 0 is exactly the plain learner",
                  "cost_limit": "cost limit 0 stands for no constraint (the multiplier held at "
                                "0), exactly the plain learner",
                  "lam": "lambda 0 is the learner without CCR's reward (its robots still "
                         "observe the shared scores)"}


def summarise(values: np.ndarray, metric: str) -> dict[str, Any]:
    """Per-seed values of ``metric`` with their mean and 95% interval (within its range)."""
    return {"per_seed": [float(v) for v in values],
            **mean_ci(values, bounds=METRIC_RANGES[metric])}


def search_grid(config: TrainConfig, values: Sequence[float], seeds: Sequence[int]
                ) -> tuple[str, list[int], list[float]]:
    """The grid of a search of ``config.variant``'s run parameter (CCR's ``lam``, the
    pessimistic ``penalty``): every value with every seed, values outer."""
    name = SEARCHED_PARAMETER.get(config.variant)
    if name is None:
        raise ValueError(f"variant must be one of {sorted(SEARCHED_PARAMETER)} to search, "
                         f"got {config.variant!r}")
    grid_seeds = [int(s) for _ in values for s in seeds]
    grid_values = [float(v) for v in values for _ in seeds]
    return name, grid_seeds, grid_values


def grid_params(config: TrainConfig, name: str, grid_values: Sequence[float]
                ) -> dict[str, list[float]]:
    """The transform numbers of a search's runs: ``name`` takes ``grid_values``, except in
    the runs of value 0 where the parameter's :data:`REFERENCE_PARAMS` make the reference
    (the other numbers keep ``config``'s transform's values)."""
    reference = REFERENCE_PARAMS.get(name)
    if reference is None:
        return {name: [float(v) for v in grid_values]}
    defaults = config.resolved_transform.default_params()
    return {key: [float(reference[key]) if v == 0.0 else
                  float(v) if key == name else float(defaults[key]) for v in grid_values]
            for key in (name, *(k for k in reference if k != name))}


def search_rows(runs: GridRuns, values: Sequence[float], grid_values: Sequence[float],
                seeds: Sequence[int]) -> list[dict[str, Any]]:
    """One row per value: the per-seed final metrics with their means and intervals."""
    final = runs.final
    rows = []
    for value in values:
        mask = np.asarray(grid_values) == float(value)
        rows.append({"value": float(value), "seeds": list(seeds),
                     **{m: summarise(final[m][mask], m) for m in POINT_METRICS}})
    return rows


def nonfinite_runs(cell: dict[str, Any], label: str) -> list[str]:
    """The runs of a grid's record (a search's, a table's or budgets' cell, a sweep's
    result) whose updates went non-finite (skipped by the program, the learner keeping its
    last finite state: :attr:`ccrjax.training.grid.GridRuns.nonfinite_iteration`), one line
    each: ``label``, the searched value where the record has one, the seed and the first
    such iteration. A cell written before these were recorded (``nonfinite_iteration``
    absent) has none: a non-finite run then stopped its program, and no cell was written."""
    iterations = cell.get("nonfinite_iteration") or []
    seeds = cell.get("grid_seeds") or cell.get("seeds") or []
    values = cell.get("grid_values")
    found = []
    for index, iteration in enumerate(iterations):
        if iteration >= 0:
            value = f" {cell['parameter']} {values[index]:g}," if values else ""
            found.append(f"{label},{value} seed {seeds[index]}, from iteration {iteration}")
    return found


def nonfinite_text(lines: list[str], runs: str) -> str:
    """One sentence on ``runs`` (e.g. "the 252 runs"): every update finite, or which runs
    had non-finite updates skipped (``lines`` from :func:`nonfinite_runs`)."""
    if not lines:
        return f"Every update of {runs} stayed finite."
    return (f"{len(lines)} of {runs} had non-finite updates, skipped (the learner kept its "
            "last finite state and trained on; docs/protocol.md): " + "; ".join(lines) + ".")


def nonfinite_log(runs: GridRuns, label: str) -> str | None:
    """The log line naming ``runs``' runs whose updates went non-finite, or ``None``."""
    lines = nonfinite_runs({"nonfinite_iteration": runs.nonfinite_iteration.tolist(),
                            "seeds": runs.seeds}, label)
    return nonfinite_text(lines, f"the {len(runs.seeds)} runs") if lines else None
