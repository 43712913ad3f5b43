"""CCR as a transform (:mod:`ccrjax.transforms.base`): scores in the observation, intrinsic reward.

Per transition ``t -> t+1`` of a batch of environments (paper, Fig. 2):

1. the physical model (:mod:`ccrjax.transforms.ccr.dynamics`) predicts each robot's own
   state ``s_hat_{t+1}`` from what the robot observed at ``t`` (velocity,
   observation features ``2:4``) and its command; the raw emergency score is
   ``|s_hat_{t+1} - s_{t+1}|^2`` against what it observes at ``t+1`` (position and
   velocity, features ``0:4``);
2. the transition is kept for the model's robust statistics, which take in the
   whole episode at its end (:meth:`CCR.end_episode`); the model is refitted at
   every episode start;
3. the rolling mean over ``m + 1`` steps gives the smoothed score ``E_{t+1}``;
4. the intrinsic reward uses the smoothed scores ``E_t`` (those robot ``i`` saw
   when it acted) and the positions at ``t`` and ``t+1``
   (:mod:`ccrjax.transforms.ccr.intrinsic`); it is added to the environment reward;
5. the next observation is the environment's, followed by the ``N - 1`` other
   robots' ``E_{t+1}`` (zero out of communication range; :mod:`ccrjax.transforms.ccr.scores`).

The pairs of robots are read from what the robots observe: the distances and
directions to the other robots are observation features already
(:func:`ccrjax.envs.env.other_robot_features`), so a step computes no pairwise
geometry of its own; ``intrinsic_reward`` and ``shared_scores`` (from positions)
are the reference definitions the tests compare with.

Three class-level switches take CCR apart (:mod:`ccrjax.transforms.ccr.parts` sets them, one
variant each): :attr:`CCR.scores_in_obs` (step 5's shared scores), :attr:`CCR.intrinsic` (step
4's reward) and :attr:`CCR.detector`, the raw score of step 1: ``"model"`` (the dynamics model's
prediction error, steps 1-2) or ``"danger"`` (the environment's true danger flags, 1 or 0: a
perfect detector, with no model to fit). CCR itself has them all on, with the model.

``info`` reports, per robot ``[N, E]``: ``emergency_score`` (``E_{t+1}``),
``intrinsic_reward`` (the one added to the reward: zero without it) and ``ccr_state``,
the paper's trajectory colour (index into ``ccrjax.viz.record.CCR_STATE_NAMES``): 1
"sensing danger" if the own smoothed score exceeds ``sensing_threshold``, else 2
"activated" if ``|R_in|`` exceeds ``activation_threshold``, else 0 "standby".
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import chex
import jax
import jax.numpy as jnp
from flax import struct

import ccrjax.transforms.ccr.dynamics as dynamics
from ccrjax.checks import check_int, check_number
from ccrjax.envs.env import EmergencyEnv
from ccrjax.envs.env import State as EnvState
from ccrjax.transforms.base import as_params
from ccrjax.transforms.ccr.intrinsic import intrinsic_reward_from_observation
from ccrjax.transforms.ccr.scores import (
    ScoreWindow,
    emergency_score,
    init_window,
    push_score,
    shared_scores_from_observation,
    smoothed_score,
)

STANDBY, SENSING_DANGER, ACTIVATED = 0, 1, 2  # ccrjax.viz.record.CCR_STATE_NAMES order


@dataclasses.dataclass(frozen=True)
class CCRConfig:
    """CCR's hyperparameters. The paper gives only ``lam``; the rest are ours.

    * ``lam = 30``: the paper's choice after its parameter search (a run
      parameter: ``CCR.init`` may override it with a traced value);
    * ``window = 4``: ``m``, the rolling mean runs over ``m + 1 = 5`` steps (0.5 s);
      a turbulence or wind push is then still felt a few steps after it happened;
    * ``comm_range = 1.0``: the team starts in a 0.5 x 1.0 box about one unit
      before the hazard, so at the start nearly every pair can talk, and a robot
      entering the hazard reaches the robots close behind it;
    * ``degree = 2``: the nominal dynamics are linear in ``(v, u)``, so degree 2
      already has headroom; ``ridge = 1e-4``, relative to each feature's moment;
    * ``tolerance = 1e-3``: squared prediction error (units^2, per 0.1 s step)
      below which a transition counts fully in the fit;
    * ``sensing_threshold = 1e-2``, ``activation_threshold = 2e-2``: the colours'
      thresholds, calibrated on measured scores (see the comments on the fields).
      The activation threshold compares ``|R_in|`` with ``lam`` included, so it is
      calibrated for ``lam = 30``; with ``lam = 0`` no robot is ever "activated".
    """

    lam: float = 30.0  # weight lambda of the intrinsic reward
    window: int = 4  # m: scores averaged over the last m + 1 steps
    comm_range: float = 1.0  # robots share scores within this distance
    degree: int = 2  # degree of the polynomial dynamics model
    ridge: float = 1e-4  # ridge term of the model's least-squares fit
    # Squared prediction error of full weight in the robust fit: well above quiet nominal
    # motion (about 2e-7 a step) and below a hazard's push (0.1 and more), so transitions
    # the hazards disturb barely bend the model.
    tolerance: float = 1e-3  # squared error of full weight in the robust fit
    # Below one wind push averaged over the window (0.16 / 5), orders of magnitude above
    # nominal motion: most robot-steps inside turbulence or wind count as sensing.
    sensing_threshold: float = 1e-2  # own smoothed score of 'sensing danger'
    # Above the |R_in| of robots with no teammate in range above the sensing threshold, for
    # lam = 30 (the pictures' colours only).
    activation_threshold: float = 2e-2  # |R_in| of 'activated' (pictures)

    def __post_init__(self) -> None:
        check_number("CCRConfig", "lam", self.lam, positive=False)
        check_int("CCRConfig", "window", self.window, 0)
        check_number("CCRConfig", "comm_range", self.comm_range, positive=False)
        check_int("CCRConfig", "degree", self.degree, dynamics.MIN_DEGREE, dynamics.MAX_DEGREE)
        for name in ("ridge", "tolerance", "sensing_threshold", "activation_threshold"):
            check_number("CCRConfig", name, getattr(self, name), positive=True)


@struct.dataclass
class EpisodeArrays:
    """What CCR carries within one episode (shapes depend on the batch ``E``)."""

    window: ScoreWindow  # raw scores of the last m + 1 transitions
    score: jax.Array  # float32[N, E]: smoothed E_t of the current observation
    # The episode's transitions for the model, one row per step: phi(x) [P], the targets
    # y [4] and the squared error e [1] under this episode's coefficients, [T, N, P + 5, E];
    # they enter the statistics once, at the episode's end (one large product instead of
    # T small ones: the same weighted means, fewer operations per step). None without a model.
    transitions: jax.Array | None


@struct.dataclass
class CCRState:
    """CCR's state from one episode to the next: nothing in it depends on the batch ``E``
    (training and evaluation episodes share it). Without a model (``detector="danger"``)
    ``statistics`` and ``coefficients`` are ``None``, and ``params`` may be empty (no
    intrinsic reward, no ``lam``)."""

    params: dict[str, jax.Array]  # {"lam": float32[]}, or {} without the intrinsic reward
    statistics: dynamics.DynamicsStatistics | None
    coefficients: jax.Array | None  # float32[P, 4], fitted at the last episode start
    discrete_actions: bool = struct.field(pytree_node=False, default=False)
    discrete_action_set: str = struct.field(pytree_node=False, default="box9")
    episode_length: int = struct.field(pytree_node=False, default=0)  # T: rows of transitions


@struct.dataclass
class CCREpisodeState:
    """CCR's state within an episode (:meth:`CCR.start_episode` to :meth:`CCR.end_episode`):
    the state it carries between episodes and this episode's arrays."""

    between: CCRState
    episode: EpisodeArrays


@dataclasses.dataclass(frozen=True)
class CCR:
    """Collective Conditioned Reflex (see the module docstring)."""

    config: CCRConfig = CCRConfig()
    name = "ccr"
    # CCR's parts, on or off (class constants, not configuration: one variant each).
    scores_in_obs: ClassVar[bool] = True  # the other robots' scores follow the observation
    intrinsic: ClassVar[bool] = True  # the intrinsic reward is added to the reward
    detector: ClassVar[str] = "model"  # raw score: "model" error or true "danger" flags

    def __post_init__(self) -> None:
        if not isinstance(self.config, CCRConfig):
            raise ValueError(f"{type(self).__name__}.config must be a CCRConfig, "
                             f"got {self.config!r}")

    def extra_obs_size(self, env: EmergencyEnv) -> int:
        """The other robots' shared scores: ``N - 1`` (0 without them)."""
        return env.num_robots - 1 if self.scores_in_obs else 0

    def default_params(self) -> dict[str, float]:
        """``lam``, where the intrinsic reward is added; nothing otherwise."""
        return {"lam": float(self.config.lam)} if self.intrinsic else {}

    def init(self, env: EmergencyEnv, params: dict[str, Any] | None = None) -> CCRState:
        """An untrained model (zero statistics and coefficients; none for the ``danger``
        detector) and the run's ``lam``."""
        model = self.detector == "model"
        return CCRState(
            params=as_params(self.default_params(), params),
            statistics=dynamics.init_statistics(self.config.degree) if model else None,
            coefficients=dynamics.init_coefficients(self.config.degree) if model else None,
            discrete_actions=env.discrete_actions,
            discrete_action_set=env.discrete_action_set,
            episode_length=env.episode_length,
        )

    def start_episode(self, state: CCRState, env_state: EnvState
                      ) -> tuple[CCREpisodeState, jax.Array]:
        """Refits the model, empties the window; the observation gets zero scores."""
        obs = env_state.obs
        chex.assert_rank(obs, 3)
        num_robots, _, num_envs = obs.shape
        score = jnp.zeros((num_robots, num_envs), jnp.float32)
        between, transitions = state, None  # the danger detector: no model
        if self.detector == "model":
            rows = dynamics.num_features(self.config.degree) + dynamics.NUM_OUTPUTS + 1
            between = state.replace(coefficients=dynamics.fit(state.statistics,
                                                              self.config.ridge))
            transitions = jnp.zeros((state.episode_length, num_robots, rows, num_envs))
        episode_state = CCREpisodeState(
            between=between,
            episode=EpisodeArrays(
                window=init_window(self.config.window, num_robots, num_envs), score=score,
                transitions=transitions,
            ),
        )
        if not self.scores_in_obs:
            return episode_state, obs
        shared = jnp.zeros((num_robots, num_robots - 1, num_envs), obs.dtype)
        return episode_state, jnp.concatenate([obs, shared], axis=1)

    def step(
        self, episode_state: CCREpisodeState, env_state: EnvState, action: jax.Array,
        next_env_state: EnvState,
    ) -> tuple[CCREpisodeState, jax.Array, jax.Array, dict[str, jax.Array]]:
        """One transition: score, model statistics, intrinsic reward, next observation."""
        if not isinstance(episode_state, CCREpisodeState):
            raise ValueError("CCR.step needs an episode's state: call start_episode first")
        config, state, episode = self.config, episode_state.between, episode_state.episode
        obs, next_obs = env_state.obs, next_env_state.obs
        chex.assert_rank(obs, 3)
        chex.assert_equal_shape([obs, next_obs])
        num_robots, _, num_envs = obs.shape
        if state.discrete_actions:
            chex.assert_shape(action, (num_robots, num_envs))
        else:
            chex.assert_shape(action, (num_robots, 2, num_envs))
        chex.assert_shape(next_env_state.reward, (num_robots, num_envs))

        own_state, next_own_state = obs[:, 0:4], next_obs[:, 0:4]  # (p, v) as observed
        if self.detector == "model":
            raw_score, transitions = self._model_score(state, episode, own_state,
                                                       next_own_state, action)
        else:  # a perfect detector: the environment's own danger flags (1.0 or 0.0)
            raw_score, transitions = next_env_state.metrics["danger"], None
        window = push_score(episode.window, raw_score)
        next_score = smoothed_score(window)
        # What the robots observe of each other (distances, directions) gives the pairs.
        displacement = next_own_state[:, 0:2] - own_state[:, 0:2]
        if self.intrinsic:
            reward_in = intrinsic_reward_from_observation(
                episode.score, obs, displacement, config.comm_range, state.params["lam"]
            )
            reward = next_env_state.reward + reward_in
        else:
            reward_in, reward = jnp.zeros_like(next_score), next_env_state.reward
        shared = shared_scores_from_observation(next_score, next_obs, config.comm_range)
        if self.scores_in_obs:
            next_obs = jnp.concatenate([next_obs, shared.astype(next_obs.dtype)], axis=1)
        ccr_state = jnp.where(
            next_score > config.sensing_threshold,
            SENSING_DANGER,
            jnp.where(jnp.abs(reward_in) > config.activation_threshold, ACTIVATED, STANDBY),
        ).astype(jnp.int32)
        episode_state = episode_state.replace(
            episode=EpisodeArrays(window=window, score=next_score, transitions=transitions)
        )
        info = {
            "emergency_score": next_score,
            "intrinsic_reward": reward_in,
            "ccr_state": ccr_state,
        }
        return episode_state, next_obs, reward, info

    def _model_score(
        self, state: CCRState, episode: EpisodeArrays, own_state: jax.Array,
        next_own_state: jax.Array, action: jax.Array,
    ) -> tuple[jax.Array, jax.Array]:
        """Steps 1-2: the raw score ``|s_hat_{t+1} - s_{t+1}|^2`` of the model's prediction
        (paper, "Emergency Score Assessment") and the episode's transitions with this one
        kept for the model's statistics."""
        command = dynamics.command_vector(action, state.discrete_actions,
                                          state.discrete_action_set)
        # phi(x) once, for the prediction and for the model's statistics.
        features = dynamics.polynomial_features(
            dynamics.model_inputs(own_state, command), self.config.degree
        )
        predicted = jnp.einsum("npe,pk->nke", features, state.coefficients)  # y_hat
        targets = dynamics.model_targets(own_state, next_own_state)  # y = (dp, v_{t+1})
        # s_hat - s = (p_t + dp_hat - p_{t+1}, v_hat - v_{t+1}) = y_hat - y, so the score
        # |s_hat - s|^2 is computed on the model's targets.
        raw_score = emergency_score(predicted, targets)
        transitions = jax.lax.dynamic_update_index_in_dim(
            episode.transitions,
            jnp.concatenate([features, targets, raw_score[:, None]], axis=1),
            jnp.minimum(episode.window.count, state.episode_length - 1),
            axis=0,
        )
        return raw_score, transitions

    def end_episode(self, episode_state: CCREpisodeState) -> CCRState:
        """Adds the episode's transitions to the model's statistics (robust weights under the
        episode's coefficients) and drops the per-episode arrays: what remains (model,
        params) is independent of ``E``. Without a model there is nothing to add."""
        state, episode = episode_state.between, episode_state.episode
        if self.detector != "model":
            return state
        transitions = episode.transitions  # [T, N, P + 5, E]
        steps, num_robots, rows, num_envs = transitions.shape
        p = rows - dynamics.NUM_OUTPUTS - 1
        taken = (jnp.arange(steps) < episode.window.count)[:, None, None]  # [T, 1, 1]
        # One batch of T x E samples per robot: [N, rows, T E].
        samples = jnp.moveaxis(transitions, 0, 2).reshape(num_robots, rows, steps * num_envs)
        error = jnp.where(taken, transitions[:, :, -1], jnp.inf)  # slots not taken: weight 0
        error = jnp.moveaxis(error, 0, 1).reshape(num_robots, steps * num_envs)
        statistics = dynamics.accumulate_features(
            state.statistics, samples[:, :p], samples[:, p:p + dynamics.NUM_OUTPUTS], error,
            self.config.tolerance,
        )
        return state.replace(statistics=statistics)
