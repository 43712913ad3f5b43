"""The paper's behavioural analysis: who reaches the hidden obstacle first, and how close each
robot comes to it.

"For the robots trained with CCR-aided MADDPG, only the first two robots will run into the
obstacle, while others steer away from it" (paper, Behavioral Analysis). To compare teams
on this, each robot of each recorded episode gets its *arrival rank* (the order in which
robots first come within ``reach`` of the obstacle's surface; robots that never do come
last, the closer ones first) and two distances: its closest approach to the obstacle's
surface (negative if its centre is inside the obstacle) and its average distance to the
obstacle's centre over the episode (the paper's "average distance to the obstacle").

Plain numpy on recorded episodes (:attr:`ccrjax.training.grid.GridRuns.episodes`).
"""

from __future__ import annotations

import numpy as np


def rectangle_distance(position: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distance to an axis-aligned rectangle's surface (negative inside), numpy.

    ``position`` ``[..., 2, E]``; ``centre``, ``half`` ``[2, E]``.
    """
    rel = np.abs(position - centre) - half
    outside = np.linalg.norm(np.maximum(rel, 0.0), axis=-2)
    inside = np.minimum(np.max(rel, axis=-2), 0.0)
    return outside + inside


def arrival_analysis(episodes: dict[str, np.ndarray], reach: float) -> dict[str, np.ndarray]:
    """Per run, episode and arrival rank: closest approach and mean distance to the centre.

    ``episodes``: recorded evaluation episodes (:attr:`ccrjax.training.grid.GridRuns.episodes`),
    leading run axis ``G``.
    Returns ``closest`` and ``centre_distance``, ``[G, E, N]`` ordered by arrival rank,
    and, where the episodes record ``success`` (``[G, N, E]``, in the target area at the
    end), ``succeeded`` in the same order.
    """
    position = episodes["position"]  # [G, T + 1, N, 2, E]
    centre = episodes["hazard_centre"][:, None, None]  # [G, 1, 1, 2, E]
    half = episodes["hazard_half_extent"][:, None, None]
    surface = rectangle_distance(position, centre, half)  # [G, T + 1, N, E]
    centre_distance = np.linalg.norm(position - centre, axis=3).mean(axis=1)  # [G, N, E]
    closest = surface.min(axis=1)  # [G, N, E]
    steps = surface.shape[1]
    reached = surface <= reach
    first = np.where(reached.any(axis=1), reached.argmax(axis=1), steps)  # [G, N, E]
    # Arrival order; robots that never reach come last, the closer ones first.
    order_key = first * 1000.0 + np.clip(closest, -1.0, 998.0)
    rank = np.argsort(order_key, axis=1, kind="stable")  # [G, N(rank), E]
    closest = np.take_along_axis(closest, rank, axis=1).transpose(0, 2, 1)
    centre_distance = np.take_along_axis(centre_distance, rank, axis=1).transpose(0, 2, 1)
    result = {"closest": closest, "centre_distance": centre_distance}
    if "success" in episodes:
        success = np.asarray(episodes["success"], bool)
        result["succeeded"] = np.take_along_axis(success, rank, axis=1).transpose(0, 2, 1)
    return result


def followers_closest(analysis: dict[str, np.ndarray]) -> np.ndarray:
    """Per run ``[G]``: the mean closest approach to the obstacle's surface of the robots
    that arrive after the first *and* end in the target area (a robot that kept away by
    abandoning the task does not count); NaN for a run with no such robot."""
    closest = analysis["closest"][..., 1:]  # [G, E, N - 1]
    counted = analysis["succeeded"][..., 1:]
    total = np.where(counted, closest, 0.0).sum(axis=(1, 2))
    count = counted.sum(axis=(1, 2))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)
