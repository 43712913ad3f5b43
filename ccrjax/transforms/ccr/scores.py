"""Emergency scores: the model's surprise, its rolling mean, and what robots share of it.

Paper, section "Emergency Score Assessment":

* raw score ``E_t^i = |s_hat_t^i - s_t^i|^2`` (:func:`emergency_score`);
* rolling mean ``E_t^i <- 1/(m + 1) sum_{k=0..m} E_{t-k}^i`` (:class:`ScoreWindow`),
  restarted at every episode start: near the start, where fewer than ``m + 1``
  transitions exist, it is the mean over the transitions since the episode
  started; at the episode's first observation (no transition yet) it is 0;
* the score is "appended to other robots' states within robot ``i``'s
  communication range" (:func:`shared_scores`).

Arrays are in the environment's layout (batch axis last): ``[N, E]`` per robot.
"""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ccrjax.envs.env import of_other_robots, other_robot_features


def emergency_score(predicted: jax.Array, observed: jax.Array) -> jax.Array:
    """``E_t^i = |s_hat_t^i - s_t^i|^2`` over the predicted numbers (axis 1), ``float32[N, E]``.

    Args:
      predicted: ``s_hat_t``, ``float[N, 4, E]`` (position and velocity).
      observed: ``s_t``, same shape.
    """
    chex.assert_rank(predicted, 3)
    chex.assert_equal_shape([predicted, observed])
    difference = predicted - observed
    return jnp.sum(difference * difference, axis=1)


@struct.dataclass
class ScoreWindow:
    """The last ``m + 1`` raw scores of every robot, a ring buffer restarted per episode.

    ``scores``: ``float32[m + 1, N, E]``, zeros where no transition was pushed yet;
    ``count``: ``int32[]``, transitions pushed since the episode started (all
    environments run in lockstep, so one clock serves the batch).
    """

    scores: jax.Array
    count: jax.Array

    @property
    def length(self) -> int:
        """``m + 1``: the number of steps the mean runs over."""
        return self.scores.shape[0]


def init_window(window: int, num_robots: int, num_envs: int) -> ScoreWindow:
    """An empty window for a new episode; ``window`` is ``m >= 0``."""
    return ScoreWindow(
        scores=jnp.zeros((window + 1, num_robots, num_envs), jnp.float32),
        count=jnp.zeros((), jnp.int32),
    )


def push_score(window: ScoreWindow, raw_score: jax.Array) -> ScoreWindow:
    """The window after the transition whose raw score is ``raw_score`` ``[N, E]``."""
    chex.assert_shape(raw_score, window.scores.shape[1:])
    slot = window.count % window.length
    scores = jax.lax.dynamic_update_index_in_dim(
        window.scores, raw_score.astype(jnp.float32), slot, axis=0
    )
    return ScoreWindow(scores=scores, count=window.count + 1)


def smoothed_score(window: ScoreWindow) -> jax.Array:
    """``1/(m + 1) sum_{k=0..m} E_{t-k}``, over the steps that exist since the episode start.

    The sum of the held scores divided by ``min(count, m + 1)`` (the window holds
    zeros where nothing was pushed); 0 before the first transition. ``float32[N, E]``.
    """
    held = jnp.minimum(window.count, window.length)
    return jnp.sum(window.scores, axis=0) / jnp.maximum(held, 1).astype(jnp.float32)


@functools.cache
def other_robots(num_robots: int) -> np.ndarray:
    """For robot ``i``, the other robots' indices in increasing order, ``int32[N, N - 1]``
    (the order of :class:`ccrjax.envs.env.EmergencyEnv`'s other-robot features)."""
    return np.array(
        [[j for j in range(num_robots) if j != i] for i in range(num_robots)], dtype=np.int32
    )


def shared_scores(smoothed: jax.Array, position: jax.Array, comm_range: float) -> jax.Array:
    """What each robot receives of the others' smoothed scores, ``float32[N, N - 1, E]``.

    Entry ``[i, k]`` is ``E_j`` for ``j = others(i)[k]`` (the other robots in
    increasing index order) if ``|p_i - p_j| <= comm_range``, else 0.

    Args:
      smoothed: smoothed scores ``float[N, E]``.
      position: ``float[N, 2, E]`` at the same time.
      comm_range: communication range.
    """
    chex.assert_rank([smoothed, position], [2, 3])
    num_robots = smoothed.shape[0]
    chex.assert_shape(position, (num_robots, 2, smoothed.shape[1]))
    others = other_robots(num_robots)
    rel = position[others] - position[:, None]  # [N, N - 1, 2, E]: p_j - p_i
    distance = jnp.sqrt(jnp.sum(rel * rel, axis=2))  # [N, N - 1, E]
    return jnp.where(distance <= comm_range, smoothed[others], 0.0)


def shared_scores_from_observation(smoothed: jax.Array, obs: jax.Array,
                                   comm_range: float) -> jax.Array:
    """:func:`shared_scores` with the distances read from the observations ``obs``
    ``[N, F, E]`` taken at the same time (:func:`ccrjax.envs.env.other_robot_features`)."""
    chex.assert_rank([smoothed, obs], [2, 3])
    distance, _, _ = other_robot_features(obs)
    return jnp.where(distance <= comm_range, of_other_robots(smoothed), 0.0)
