"""CCR's intrinsic reward: the paper's "potential consequences evaluation".

For robot ``i`` and every other robot ``j`` within communication range
(``|p_i(t) - p_j(t)| <= comm_range``)::

    h_i(j)      = |p_i(t+1) - p_j(t)| - |p_i(t) - p_j(t)|
    R_in^i(j)   = lam (E_j - E_i) h_i(j) / (1 + |p_i(t) - p_j(t)|)
    R_in^i      = sum_{j != i} R_in^i(j)

Our reading of the paper: ``s`` in its distances is the robot's position;
``E`` are the smoothed emergency scores at time ``t``, the ones shared in the
observation robot ``i`` acted on; everything about ``j`` is at time ``t`` (its
position and score), and only robot ``i``'s own move ``t -> t+1`` is judged.
A robot safer than ``j`` (``E_i < E_j``) is rewarded for moving away from ``j``
(``h > 0``) and penalised for moving towards it, and the reverse when ``j`` is
the safer one. ``lam`` multiplies once (the paper writes it both inside
``R_in^i(j)`` and when adding ``R_in^i`` to the reward; it is one coefficient).
Robots out of range contribute nothing: they cannot share their score.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np

from ccrjax.envs.env import of_other_robots, other_robot_features


def intrinsic_reward(
    score: jax.Array,
    position: jax.Array,
    next_position: jax.Array,
    comm_range: float,
    lam: jax.Array | float,
) -> jax.Array:
    """``R_in^i = lam sum_{j != i, in range} (E_j - E_i) h_i(j) / (1 + |p_i(t) - p_j(t)|)``.

    Args:
      score: smoothed emergency scores at time ``t``, ``float[N, E]``.
      position: positions at ``t``, ``float[N, 2, E]``.
      next_position: positions at ``t + 1``, ``float[N, 2, E]``.
      comm_range: communication range (pairs further apart at ``t`` are ignored).
      lam: the coefficient ``lambda`` (may be a traced array).

    Returns:
      ``float32[N, E]``.
    """
    chex.assert_rank([score, position], [2, 3])
    num_robots, num_envs = score.shape
    chex.assert_shape([position, next_position], (num_robots, 2, num_envs))
    rel = position[None, :] - position[:, None]  # [i, j, 2, E]: p_j(t) - p_i(t)
    distance = jnp.sqrt(jnp.sum(rel * rel, axis=2))  # [i, j, E]
    rel_next = position[None, :] - next_position[:, None]  # p_j(t) - p_i(t+1)
    next_distance = jnp.sqrt(jnp.sum(rel_next * rel_next, axis=2))
    change = next_distance - distance  # h_i(j)
    score_gap = score[None, :] - score[:, None]  # E_j - E_i
    others = ~np.eye(num_robots, dtype=bool)[:, :, None]
    counted = others & (distance <= comm_range)
    pair_reward = jnp.where(counted, score_gap * change / (1.0 + distance), 0.0)
    return lam * jnp.sum(pair_reward, axis=1)


def intrinsic_reward_from_observation(
    score: jax.Array,
    obs: jax.Array,
    displacement: jax.Array,
    comm_range: float,
    lam: jax.Array | float,
) -> jax.Array:
    """:func:`intrinsic_reward` from what the robots observe, as CCR's transform computes it.

    The distances ``|p_i(t) - p_j(t)|`` and directions to the other robots are observation
    features already (:func:`ccrjax.envs.env.other_robot_features`), so ``p_j(t) - p_i(t)`` comes
    from them and ``|p_i(t+1) - p_j(t)| = |(p_j(t) - p_i(t)) - (p_i(t+1) - p_i(t))|``; the sum
    runs over the ``N - 1`` other robots directly. The same numbers as
    :func:`intrinsic_reward` (``tests/test_ccr.py`` checks it) with fewer operations per step.

    Args:
      score: smoothed emergency scores at time ``t``, ``float[N, E]``.
      obs: the environment's observations at ``t``, ``float[N, F, E]``.
      displacement: ``p_i(t+1) - p_i(t)``, ``float[N, 2, E]``.
      comm_range: communication range.
      lam: the coefficient ``lambda`` (may be a traced array).
    """
    chex.assert_rank([score, obs, displacement], [2, 3, 3])
    distance, ux, uy = other_robot_features(obs)  # [N, N - 1, E]
    rel_x = distance * ux - displacement[:, 0:1]  # p_j(t) - p_i(t+1)
    rel_y = distance * uy - displacement[:, 1:2]
    change = jnp.sqrt(rel_x * rel_x + rel_y * rel_y) - distance  # h_i(j)
    score_gap = of_other_robots(score) - score[:, None]  # E_j - E_i
    pair_reward = jnp.where(distance <= comm_range, score_gap * change / (1.0 + distance), 0.0)
    return lam * jnp.sum(pair_reward, axis=1)
