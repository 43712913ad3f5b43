"""The rule that picks one hyperparameter value from a search, fixed before the search runs.

The pessimistic penalty and CCR's lambda are searched alike (``experiments/search.py``),
and one value of each is kept for every scenario and learner, as the paper kept one
lambda. The rule is the same for both searches and is written down in
``docs/protocol.md``:

1. For every candidate value ``v`` and every scenario x learner pair ``k``, average
   each metric over the selection seeds: ``m_k(v)``; the reference is the value 0 on the
   same seeds and budget, ``m_k(ref)`` (the plain learner for the penalty; for CCR's
   lambda, the learner without CCR's reward).
2. ``v`` is *eligible* if its constraint metric (success rate), averaged over the pairs,
   is at most ``tolerance`` below the reference's:
   ``mean_k c_k(v) >= mean_k c_k(ref) - tolerance``.
3. Among the eligible values, the one with the lowest objective (dangerous-behaviour
   frequency) averaged over the pairs is chosen; a tie goes to the smaller value (the
   gentler intervention).
4. If no value is eligible, the one whose constraint is closest to the reference's is
   chosen, and the result says so (``fallback``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ccrjax.run.folder import EVAL_METRICS


@dataclasses.dataclass(frozen=True)
class SelectionRule:
    """Minimise ``objective`` among values whose ``constraint`` (higher is better) is at
    most ``tolerance`` below the reference's, both averaged over seeds and then pairs."""

    objective: str = "danger_frequency"
    constraint: str = "success_rate"
    tolerance: float = 0.05

    def __post_init__(self) -> None:
        for name in ("objective", "constraint"):
            value = getattr(self, name)
            if value not in EVAL_METRICS:
                raise ValueError(f"selection rule {name} must be one of {list(EVAL_METRICS)}, "
                                 f"got {value!r}")
        if not (isinstance(self.tolerance, int | float) and 0 <= self.tolerance < 1):
            raise ValueError(f"selection rule tolerance must be in [0, 1), "
                             f"got {self.tolerance!r}")

    def describe(self) -> str:
        return (f"the lowest mean {self.objective} among the values whose mean {self.constraint} "
                f"is at most {self.tolerance:g} below the reference's, value 0 (means over seeds, "
                "then over scenario x learner pairs; ties to the smaller value)")


def select(rule: SelectionRule, values: Sequence[float], metrics: dict[str, np.ndarray],
           reference: dict[str, np.ndarray]) -> dict:
    """Applies ``rule`` to a search.

    ``metrics[name]``: ``[values, pairs, seeds]`` final evaluations of every candidate
    value; ``reference[name]``: ``[pairs, seeds]`` the plain learner's. Returns ``{"value",
    "index", "fallback", "eligible", "objective", "constraint", "reference_constraint"}``
    (the per-value means over pairs).
    """
    values = [float(v) for v in values]
    for name in (rule.objective, rule.constraint):
        if name not in metrics:
            raise ValueError(f"the search has no metric {name!r}; it has {sorted(metrics)}")
    if rule.constraint not in reference:
        raise ValueError(f"the reference has no metric {rule.constraint!r}")
    objective = np.asarray(metrics[rule.objective], np.float64)
    constraint = np.asarray(metrics[rule.constraint], np.float64)
    ref = np.asarray(reference[rule.constraint], np.float64)
    if objective.ndim != 3 or objective.shape[0] != len(values):
        raise ValueError(f"metrics must be [values={len(values)}, pairs, seeds], "
                         f"got {objective.shape}")
    if constraint.shape != objective.shape or ref.shape[0] != objective.shape[1]:
        raise ValueError("the metrics and the reference must cover the same pairs")
    objective_mean = objective.mean(axis=2).mean(axis=1)  # [values]
    constraint_mean = constraint.mean(axis=2).mean(axis=1)
    reference_mean = float(ref.mean(axis=1).mean())
    eligible = constraint_mean >= reference_mean - rule.tolerance - 1e-12
    order = sorted(range(len(values)), key=lambda i: values[i])  # ties to the smaller value
    if eligible.any():
        index = min((i for i in order if eligible[i]), key=lambda i: objective_mean[i])
        fallback = False
    else:
        index = min(order, key=lambda i: abs(constraint_mean[i] - reference_mean))
        fallback = True
    return {"value": values[index], "index": int(index), "fallback": fallback,
            "eligible": [bool(e) for e in eligible],
            "objective": [float(x) for x in objective_mean],
            "constraint": [float(x) for x in constraint_mean],
            "reference_constraint": reference_mean, "rule": rule.describe()}
