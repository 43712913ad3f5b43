"""What the study measures in a cell's recorded evaluation episodes, beyond the tables'
metrics (docs/protocol.md, amendment of 2026-12-01, "Analysis per cell").

* The **forewarned share**: of the trained team's dangerous robot-steps, the share whose
  spell of danger a teammate within CCR's communication range had forewarned at least
  ``regimes.FOREWARNING_LEAD`` steps before (:func:`experiments.regimes.forewarned_share`,
  the measure the reference controllers were read with). It says how much a teammate's
  trouble could have told the robots in the episodes the learners produced.
* The **followers**: every robot but the one that starts furthest along the way (the
  column's leader; abreast, the one a little ahead). Their mean distance to the hazard's
  centre over the episode, their danger frequency and their success: whether the robots
  behind keep away from where the first met trouble, and what it costs them. Success is
  reported beside the distance because a robot that keeps away by abandoning the task
  would otherwise look careful.

Each is per seed (a list over the cell's seeds), so the study's statistics treat seeds as
the units, as the tables do. A seed whose episodes hold no dangerous step has no
forewarned share (``None``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from experiments.regimes import forewarned_share

FOLLOWER_METRICS = ("followers_centre_distance", "followers_danger", "followers_success")


def follower_mask(position: np.ndarray) -> np.ndarray:
    """``[N, E]``: whether each robot is a follower in each episode, from the positions
    ``[T + 1, N, 2, E]``: every robot but the one whose start is furthest along x (towards
    the target area; ties to the lower index)."""
    start_x = position[0, :, 0]  # [N, E]
    leader = np.argmax(start_x, axis=0)  # [E]
    return np.arange(start_x.shape[0])[:, None] != leader[None, :]


def followers(position: np.ndarray, danger: np.ndarray, success: np.ndarray,
              centre: np.ndarray) -> dict[str, float]:
    """One seed's followers: their mean distance to the hazard's centre over the episodes'
    states, their dangerous share of steps and their success rate, averaged over the
    followers of every episode. ``position`` ``[T + 1, N, 2, E]``, ``danger`` ``[T, N, E]``,
    ``success`` ``[N, E]``, ``centre`` ``[2, E]``."""
    mask = follower_mask(position)  # [N, E]
    distance = np.linalg.norm(position - centre[None, None], axis=2).mean(axis=0)  # [N, E]
    per_robot = {"followers_centre_distance": distance,
                 "followers_danger": np.asarray(danger, bool).mean(axis=0),
                 "followers_success": np.asarray(success, bool).astype(float)}
    return {name: float(values[mask].mean()) for name, values in per_robot.items()}


def cell_measures(episodes: dict[str, np.ndarray]) -> dict[str, Any]:
    """Per seed of a cell's recorded episodes (leaves with a leading seed axis, as
    :attr:`ccrjax.training.grid.GridRuns.episodes` gives them): the forewarned share and
    the followers' measures (:data:`FOLLOWER_METRICS`)."""
    position = np.asarray(episodes["position"])  # [S, T + 1, N, 2, E]
    danger = np.asarray(episodes["danger"]) > 0  # [S, T, N, E]
    success = np.asarray(episodes["success"])  # [S, N, E]
    centre = np.asarray(episodes["hazard_centre"])  # [S, 2, E]
    result: dict[str, Any] = {"forewarned_share": [], **{m: [] for m in FOLLOWER_METRICS}}
    for seed in range(position.shape[0]):
        result["forewarned_share"].append(forewarned_share(danger[seed], position[seed]))
        for name, value in followers(position[seed], danger[seed], success[seed],
                                     centre[seed]).items():
            result[name].append(value)
    return result
