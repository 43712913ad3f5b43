"""What every learner shares: the transition it learns from and the interface it offers.

Learners work in the usual *batch-major* layout of neural-network code
(``[batch, robot, feature]``); the training loop moves the environment's
batch-last arrays into this layout once, when transitions are stored.

A learner never knows which reward or observation transform (plain, pessimistic,
CCR) produced its transitions: it sees observations of some width and rewards.
"""

from __future__ import annotations

from typing import Any, Protocol

import jax
from flax import struct


@struct.dataclass
class Transition:
    """A batch of multi-robot transitions, batch-major.

    ``obs``/``next_obs``: ``float32[batch, N, F]``; ``action``: ``float32[batch, N, 2]``
    (continuous) or ``int32[batch, N]`` (discrete); ``reward``: ``float32[batch, N]``;
    ``done``: ``float32[batch]``, 1 only where the episode *terminated* (the
    particle tasks end by time limit only, which is not a termination, so
    targets bootstrap through it, as in the original MADDPG and MAAC code).
    ``cost``: ``float32[batch, N]``, the step's cost (the environment's danger flag), a
    reward channel of its own for a transform that weighs it at update time
    (:attr:`ccrjax.transforms.base.Plain.reward_channels`); ``None`` (no array) otherwise,
    so that the other variants' programs are unchanged.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    done: jax.Array
    cost: jax.Array | None = None


class Learner(Protocol):
    """A multi-agent learner: pure functions over an immutable learner state."""

    name: str
    # True for a discrete action space (an action set's index), False for continuous forces.
    discrete: bool
    # True if :meth:`normalise_rewards` must see every sampled batch with the replay
    # buffer's per-robot reward mean and standard deviation (MAAC's normalisation).
    needs_reward_stats: bool

    def init(self, key: jax.Array, num_robots: int, obs_size: int) -> Any:
        """Fresh parameters, target parameters and optimiser states."""

    def act(self, state: Any, obs: jax.Array, key: jax.Array, explore: bool) -> jax.Array:
        """Actions for ``obs`` ``float[batch, N, F]``.

        Returns ``float32[batch, N, 2]`` in ``[-1, 1]`` or ``int32[batch, N]``;
        ``explore=False`` is the deterministic evaluation policy (argmax for MAAC).
        """

    def update(self, state: Any, batch: Transition, key: jax.Array) -> tuple[Any, dict]:
        """One update of every robot's networks from ``batch``; returns scalar metrics."""

    def normalise_rewards(self, batch: Transition, mean: jax.Array, std: jax.Array
                          ) -> Transition:
        """``batch`` with its rewards normalised by the buffer's per-robot statistics
        (called only when :attr:`needs_reward_stats`)."""

    def flops_per_update(self, num_robots: int, obs_size: int) -> float:
        """Floating-point operations of one :meth:`update` (multiply-adds count 2)."""


def soft_update(target: Any, online: Any, tau: float) -> Any:
    """Polyak averaging ``target <- (1 - tau) target + tau online``, leaf by leaf."""
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)
