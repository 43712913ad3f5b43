"""CCR taken apart: its two uses of the emergency score alone, a perfect detector, and flags.

The paper's CCR (section "Collective Conditioned Reflex"; :mod:`ccrjax.transforms.ccr.transform`)
does two things with the emergency scores ``E_t^i``: it appends them "to other robots' states
within robot i's communication range" (section "Emergency Score Assessment") and turns them
into the intrinsic reward ``R_in^i = sum_j lam (E_j - E_i) h_i(j) / (1 + |s_t^i - s_t^j|)``
added to the environment's reward (section "Potential Consequences Evaluation"). Its scores
come from a learned dynamics model, ``E_t^i = |s_hat_t^i - s_t^i|^2`` smoothed over ``m + 1``
steps. To tell which part helps, and how much hangs on the model's detection, each part is a
transform of its own (:mod:`ccrjax.transforms.base`), a variant of ``python -m ccrjax.train``:

* ``ccr_scores`` (:class:`CCRScores`): the shared scores in the observations exactly as CCR
  appends them, no intrinsic reward (the reward is the environment's; no ``lam``);
* ``ccr_reward`` (:class:`CCRReward`): CCR's intrinsic reward exactly, the environment's
  observations (no extra features);
* ``ccr_perfect`` (:class:`CCRPerfect`): all of CCR with the true danger flags (1 in danger,
  0 not) as raw score ``E_t^i`` instead of the model's error: a perfect detector. The rolling
  mean makes ``E_t^i`` the fraction of the last ``m + 1`` steps robot ``i`` spent in danger
  (exactly 0 for a robot not in danger in those steps); sharing, intrinsic reward and ``lam``
  are CCR's. No model, nothing to fit: its state holds ``lam`` only;
* ``danger_flags`` (:class:`DangerFlags`): the simplest sharing, no CCR: each robot observes
  the other robots' current danger flags (``N - 1`` numbers in CCR's order, zero beyond
  ``comm_range``), no smoothing, no intrinsic reward.

The first three are CCR's own code with its switches set (:attr:`CCR.scores_in_obs`,
:attr:`CCR.intrinsic`, :attr:`CCR.detector`), so they compute exactly what CCR computes and
report the same ``info`` (``intrinsic_reward`` is the one added: zero for ``ccr_scores``);
``danger_flags`` shares through CCR's own function
(:func:`ccrjax.transforms.ccr.scores.shared_scores_from_observation`) and reports nothing,
like ``plain``. All take ``CCRConfig``'s fields for what they share
(``ccr_perfect`` ignores the model's ``degree``, ``ridge`` and ``tolerance``, ``ccr_scores``
ignores ``lam``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import chex
import jax
import jax.numpy as jnp

from ccrjax.checks import check_number
from ccrjax.envs.env import EmergencyEnv
from ccrjax.envs.env import State as EnvState
from ccrjax.transforms.base import Plain
from ccrjax.transforms.ccr.scores import shared_scores_from_observation
from ccrjax.transforms.ccr.transform import CCR, CCRConfig


@dataclasses.dataclass(frozen=True)
class CCRScores(CCR):
    """CCR's shared emergency scores in the observations, no intrinsic reward."""

    name = "ccr_scores"
    intrinsic: ClassVar[bool] = False


@dataclasses.dataclass(frozen=True)
class CCRReward(CCR):
    """CCR's intrinsic reward, no scores in the observations."""

    name = "ccr_reward"
    scores_in_obs: ClassVar[bool] = False


@dataclasses.dataclass(frozen=True)
class CCRPerfect(CCR):
    """CCR with the true danger flags as raw emergency scores (a perfect detector)."""

    name = "ccr_perfect"
    detector: ClassVar[str] = "danger"


@dataclasses.dataclass(frozen=True)
class DangerFlags(Plain):
    """Each robot observes the other robots' current danger flags within ``comm_range``.

    Entry ``k`` of the ``N - 1`` appended features of robot ``i`` is
    ``metrics["danger"]`` (1.0 or 0.0) of its ``k``-th other robot (increasing index order,
    CCR's), at the same time as the observation, if that robot is within ``comm_range``, else
    0. The reward is the environment's.
    """

    comm_range: float = CCRConfig().comm_range  # robots share flags within this distance
    name = "danger_flags"

    def __post_init__(self) -> None:
        check_number("DangerFlags", "comm_range", self.comm_range, positive=False)

    def extra_obs_size(self, env: EmergencyEnv) -> int:
        """The other robots' flags: ``N - 1``."""
        return env.num_robots - 1

    def observe(self, env_state: EnvState) -> jax.Array:
        """``env_state``'s observations ``[N, F, E]`` with the flags appended,
        ``[N, F + N - 1, E]``."""
        obs, danger = env_state.obs, env_state.metrics["danger"]
        chex.assert_rank([obs, danger], [3, 2])
        flags = shared_scores_from_observation(danger, obs, self.comm_range)
        return jnp.concatenate([obs, flags.astype(obs.dtype)], axis=1)

    def start_episode(self, state: dict[str, jax.Array], env_state: EnvState
                      ) -> tuple[dict[str, jax.Array], jax.Array]:
        return state, self.observe(env_state)

    def step(self, state: dict[str, jax.Array], env_state: EnvState, action: jax.Array,
             next_env_state: EnvState) -> tuple[Any, jax.Array, jax.Array, dict[str, jax.Array]]:
        return state, self.observe(next_env_state), next_env_state.reward, {}
