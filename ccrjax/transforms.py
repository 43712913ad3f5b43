"""Transforms of what learners see: observations and rewards, between env and replay.

A transform sits between the environment and a learner. It may widen each
robot's observation and reshape its reward before the transition is stored;
the learner only sees the result. ``plain`` changes nothing; ``pessimistic``
(the paper's baseline) lowers the reward on dangerous steps; CCR
(:mod:`ccrjax.ccr`) is a third transform of the same kind.

All arrays are in the environment's layout (batch axis last): observations
``[N, F, E]``, rewards ``[N, E]``.

Interface (pure functions; ``state`` is the transform's own pytree)::

    extra_obs_size(env) -> int
    init(env) -> state                                  # once per training run
    start_episode(state, env_state) -> (state, obs)    # after env.reset
    step(state, env_state, action, next_env_state) -> (state, obs, reward)
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol

import jax

from ccrjax.env import CCREnv
from ccrjax.env import State as EnvState


class Transform(Protocol):
    name: str

    def extra_obs_size(self, env: CCREnv) -> int: ...

    def init(self, env: CCREnv) -> Any: ...

    def start_episode(self, state: Any, env_state: EnvState) -> tuple[Any, jax.Array]: ...

    def step(
        self, state: Any, env_state: EnvState, action: jax.Array, next_env_state: EnvState
    ) -> tuple[Any, jax.Array, jax.Array]: ...


@dataclasses.dataclass(frozen=True)
class Plain:
    """The environment's observations and rewards, unchanged."""

    name = "plain"

    def extra_obs_size(self, env: CCREnv) -> int:
        return 0

    def init(self, env: CCREnv) -> tuple:
        return ()

    def start_episode(self, state, env_state):
        return state, env_state.obs

    def step(self, state, env_state, action, next_env_state):
        return state, next_env_state.obs, next_env_state.reward


@dataclasses.dataclass(frozen=True)
class Pessimistic(Plain):
    """The paper's pessimistic baseline: ``r_i - penalty`` on every step robot ``i`` is in danger.

    Danger is the environment's own predicate (inside the turbulence or wind
    area, touching the obstacle) at the state the step led to. The paper does not
    give the penalty; the default 1.0 is one unit of distance-to-destination, the
    size of the environment reward itself. Observations are the plain ones.
    """

    penalty: float = 1.0
    name = "pessimistic"

    def __post_init__(self) -> None:
        value = self.penalty
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise ValueError(f"penalty must be a finite number >= 0, got {value!r}")

    def step(self, state, env_state, action, next_env_state):
        reward = next_env_state.reward - self.penalty * next_env_state.metrics["danger"]
        return state, next_env_state.obs, reward
