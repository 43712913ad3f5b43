"""The constrained baseline: a Lagrange multiplier on the danger, for every learner.

The learners maximise the return subject to the expected per-robot danger frequency (the
share of robot-steps in danger, the paper's dangerous-behaviour frequency) staying at or
below a cost limit ``d``. The transform keeps one multiplier ``lambda_c`` for the team, the
constraint's (the protocol's metric is the team's frequency, and one multiplier is what
MAPPO-L and DGPPO's Lagrangian baseline keep); after every training episode it measures the
team's danger frequency over that episode's robot-steps and updates ``lambda_c`` by PID
control or by projected gradient ascent (:mod:`ccrjax.transforms.lagrange`).

The learner trains on ``(r - lambda_c c) / (1 + lambda_c)``, where ``c`` is the step's
danger flag: the reward channels weighed *when the learner updates*, with the multiplier in
force then, for transitions stored under older multipliers too (the transform has
:attr:`reward_channels`; the replay buffer keeps the cost beside the reward). Dividing by
``1 + lambda_c`` keeps the reward's scale bounded as the multiplier grows, as PPO-Lag does
with its advantages. A single reward critic of the combined reward, rather than a second
critic of the cost, avoids the off-policy cost critics' known bias (the cost Q-values
under-estimated, openai/safety-starter-agents issue 4), at the price of a target that moves
with the multiplier.

Early in training the policy is random and its danger high, so the multiplier would climb
before anything is learnt: it is capped (``cap``), and ``warmup_episodes`` training episodes
may pass before it moves. Its numbers are run parameters (``default_params``), so one
program trains several cost limits or gains side by side under ``jax.vmap``; the path of
the multiplier is in the run's history (``lagrange_multiplier``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from ccrjax.checks import check_number
from ccrjax.envs.env import EmergencyEnv
from ccrjax.transforms.base import Plain, as_params
from ccrjax.transforms.lagrange import ascent_multiplier, init_multiplier, pid_multiplier

CONTROLLERS = ("pid", "ascent")


@dataclasses.dataclass(frozen=True)
class Lagrangian(Plain):
    """The danger frequency held at or below ``cost_limit`` by a Lagrange multiplier."""

    cost_limit: float = 0.05  # d: the per-robot danger frequency allowed
    controller: str = "pid"  # "pid", or "ascent" (integral only: gradient ascent at rate ki)
    kp: float = 1.0  # proportional gain, on the smoothed danger error
    # integral gain: the multiplier's ascent per update per unit of error (docs/protocol.md,
    # addition of 2026-12-03: at 0.2 its integral of a plain learner's early danger winds up)
    ki: float = 0.02
    kd: float = 1.0  # derivative gain, on the rise of the smoothed danger
    ema_p: float = 0.9  # smoothing of the error for the proportional term
    ema_d: float = 0.9  # smoothing of the danger for the derivative term
    delay: int = 10  # episodes between the two smoothed dangers the derivative compares
    cap: float = 100.0  # the multiplier's (and its integral's) largest value
    initial: float = 0.0  # the multiplier before the first episode
    warmup_episodes: int = 0  # training episodes before the multiplier moves
    name = "lagrangian"
    reward_channels = True

    @classmethod
    def for_run(cls, config: Any) -> Lagrangian:
        """The defaults for a run of ``config`` (a :class:`~ccrjax.training.TrainConfig`):
        the multiplier held at 0 through the random warm-up, its learning start in training
        iterations (none for an on-policy learner, which learns from its first rollout)."""
        return cls(warmup_episodes=-(-config.learning_starts_transitions
                                     // config.steps_per_iteration))

    def __post_init__(self) -> None:
        check_number("Lagrangian", "cost_limit", self.cost_limit, positive=False)
        if self.cost_limit > 1.0:
            raise ValueError("Lagrangian.cost_limit must be at most 1 (a frequency of dangerous "
                             f"robot-steps), got {self.cost_limit!r}")
        if self.controller not in CONTROLLERS:
            raise ValueError(f"Lagrangian.controller must be one of {CONTROLLERS}, "
                             f"got {self.controller!r}")
        for name in ("kp", "ki", "kd", "initial"):
            check_number("Lagrangian", name, getattr(self, name), positive=False)
        check_number("Lagrangian", "cap", self.cap, positive=True)
        for name in ("ema_p", "ema_d"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"Lagrangian.{name} must be in [0, 1), got {value}")
        if not (isinstance(self.delay, int) and self.delay >= 1):
            raise ValueError(f"Lagrangian.delay must be an integer >= 1, got {self.delay!r}")
        if not (isinstance(self.warmup_episodes, int) and self.warmup_episodes >= 0):
            raise ValueError("Lagrangian.warmup_episodes must be an integer >= 0, got "
                             f"{self.warmup_episodes!r}")

    def default_params(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in
                ("cost_limit", "kp", "ki", "kd", "ema_p", "ema_d", "cap", "initial")}

    def init(self, env: EmergencyEnv, params: dict[str, Any] | None = None) -> dict[str, Any]:
        params = as_params(self.default_params(), params)
        return {"params": params,
                "multiplier": init_multiplier(params["initial"], self.delay),
                "episodes": jnp.zeros((), jnp.int32)}

    def start_episode(self, state, env_state):
        episode = {**state, "danger_sum": jnp.zeros((), jnp.float32),
                   "robot_steps": jnp.zeros((), jnp.float32)}
        return episode, env_state.obs

    def step(self, state, env_state, action, next_env_state):
        danger = next_env_state.metrics["danger"]  # [N, E]
        state = {**state, "danger_sum": state["danger_sum"] + jnp.sum(danger),
                 "robot_steps": state["robot_steps"] + danger.size}
        return state, next_env_state.obs, next_env_state.reward, {}

    def end_episode(self, state):
        """The multiplier updated from the episode's danger frequency (after the warm-up)."""
        params = state["params"]
        frequency = state["danger_sum"] / jnp.maximum(state["robot_steps"], 1.0)
        if self.controller == "pid":
            gains = {k: params[k] for k in ("kp", "ki", "kd", "ema_p", "ema_d", "cap")}
            updated = pid_multiplier(state["multiplier"], frequency, params["cost_limit"], gains)
        else:
            updated = ascent_multiplier(state["multiplier"], frequency, params["cost_limit"],
                                        params["ki"], params["cap"])
        moving = state["episodes"] >= self.warmup_episodes
        multiplier = jax.tree_util.tree_map(lambda new, old: jnp.where(moving, new, old),
                                            updated, state["multiplier"])
        return {"params": params, "multiplier": multiplier,
                "episodes": state["episodes"] + 1}

    def reward_weights(self, state) -> tuple[jax.Array, jax.Array]:
        """``(1, -lambda_c) / (1 + lambda_c)``: the weights of the reward and the cost."""
        multiplier = state["multiplier"].multiplier
        return 1.0 / (1.0 + multiplier), -multiplier / (1.0 + multiplier)

    def metrics(self, state) -> dict[str, jax.Array]:
        """For the run's history: the multiplier in force, and the training episodes' danger
        frequency as the controller sees it (smoothed, ``ema_d``), beside the limit."""
        return {"lagrange_multiplier": state["multiplier"].multiplier,
                "lagrange_cost": state["multiplier"].cost_ema}
