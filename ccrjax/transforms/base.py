"""Transforms of what learners see: observations and rewards, between env and replay.

A transform sits between the environment and a learner. It may widen each
robot's observation and reshape its reward before the transition is stored;
the learner only sees the result. ``plain`` changes nothing; ``pessimistic``
(the paper's baseline) lowers the reward on dangerous steps; CCR
(:mod:`ccrjax.transforms.ccr`) is a third transform of the same kind.

All arrays are in the environment's layout (batch axis last): observations
``[N, F, E]``, rewards ``[N, E]``.

Interface (pure functions; ``state`` and ``episode_state`` are the transform's own
pytrees, each of one fixed structure)::

    extra_obs_size(env) -> int
    default_params() -> dict[str, float]                       # per-run numbers, may be traced
    init(env, params) -> state                                 # once per training run
    start_episode(state, env_state) -> (episode_state, obs)    # after env.reset
    step(episode_state, env_state, action, next_env_state)
        -> (episode_state, obs, reward, info)
    end_episode(episode_state) -> state                        # after the episode's last step
    reward_channels: bool                                      # a class attribute
    reward_weights(state) -> (a, b)                            # when reward_channels

A transform with ``reward_channels`` has each transition store the step's cost (the
environment's danger flag) beside the reward it returns, and the learner trains on
``a reward + b cost`` with the weights of the transform's state *at the update*, not those
in force when the transition was stored: an off-policy learner's replay buffer outlives
many changes of a Lagrange multiplier (:mod:`ccrjax.transforms.lagrangian`). The learner
sees rewards only, as always.

``params`` holds the transform's numeric hyperparameters (the pessimistic
penalty, CCR's lambda) as arrays inside the state, so that one compiled program
can run several values side by side under ``jax.vmap``. ``info`` is a dict of
per-robot diagnostics ``[N, E]`` of the step (empty for plain and pessimistic;
CCR reports its emergency scores, intrinsic rewards and robot states). A
transform's state must not depend on the number of environments ``E``, so that
training and evaluation (which run different batches) share it: per-episode
arrays live in the episode state, which ``start_episode`` creates and
``end_episode`` turns back into the state, so that the state a training iteration
carries has one structure and the same shapes before and after an episode
(``lax.scan`` needs that). Plain and pessimistic use one pytree for both.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import jax.numpy as jnp

from ccrjax.checks import check_number
from ccrjax.envs.env import EmergencyEnv
from ccrjax.envs.env import State as EnvState


class Transform(Protocol):
    name: str

    def extra_obs_size(self, env: EmergencyEnv) -> int: ...

    def default_params(self) -> dict[str, float]: ...

    def init(self, env: EmergencyEnv, params: dict[str, Any]) -> Any: ...

    def start_episode(self, state: Any, env_state: EnvState) -> tuple[Any, jax.Array]: ...

    def step(
        self, episode_state: Any, env_state: EnvState, action: jax.Array,
        next_env_state: EnvState,
    ) -> tuple[Any, jax.Array, jax.Array, dict[str, jax.Array]]: ...

    def end_episode(self, episode_state: Any) -> Any: ...


def as_params(defaults: dict[str, float], params: dict[str, Any] | None) -> dict[str, jax.Array]:
    """``params`` completed from ``defaults`` as float32 arrays; unknown names are refused."""
    params = dict(params or {})
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(
            f"unknown transform parameter(s) {unknown}; this transform takes {sorted(defaults)}"
        )
    return {name: jnp.asarray(params.get(name, value), jnp.float32)
            for name, value in defaults.items()}


@dataclasses.dataclass(frozen=True)
class Plain:
    """The environment's observations and rewards, unchanged."""

    name = "plain"
    reward_channels = False  # no cost channel: the learner trains on the stored reward

    def extra_obs_size(self, env: EmergencyEnv) -> int:
        return 0

    def default_params(self) -> dict[str, float]:
        return {}

    def init(self, env: EmergencyEnv, params: dict[str, Any] | None = None) -> dict[str, jax.Array]:
        return as_params(self.default_params(), params)

    def start_episode(self, state, env_state):
        return state, env_state.obs

    def step(self, state, env_state, action, next_env_state):
        return state, next_env_state.obs, next_env_state.reward, {}

    def end_episode(self, state):
        return state


@dataclasses.dataclass(frozen=True)
class Pessimistic(Plain):
    """The paper's pessimistic baseline: ``r_i - penalty`` on every step robot ``i`` is in danger.

    Danger is the environment's own predicate (inside the turbulence or wind
    area, touching the obstacle) at the state the step led to. The paper does not
    give the penalty; the default 1.0 is one unit of distance-to-destination, the
    size of the environment reward itself. Observations are the plain ones.
    ``penalty`` is the default of the run parameter of the same name, which
    :meth:`init` may override with a (possibly traced) value; penalty 0 is
    exactly the plain learner.
    """

    penalty: float = 1.0  # reward lowered on every step a robot is in danger
    name = "pessimistic"

    def __post_init__(self) -> None:
        check_number("", "penalty", self.penalty, positive=False)

    def default_params(self) -> dict[str, float]:
        return {"penalty": float(self.penalty)}

    def step(self, state, env_state, action, next_env_state):
        reward = next_env_state.reward - state["penalty"] * next_env_state.metrics["danger"]
        return state, next_env_state.obs, reward, {}
