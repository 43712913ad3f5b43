"""One episode of a batch of environments under a policy, and the paper's metrics.

Shared by training (which stores the transitions) and evaluation (which keeps
the metrics). Both run the same transform (plain, pessimistic, CCR), so a policy
trained on CCR's widened observations is evaluated on them too; the *metrics*
always come from the environment itself, never from a transformed reward. Pictures of a
hand-written policy use the same episode without a transform (:func:`plain_episode`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from ccrjax.agents.types import Transition
from ccrjax.envs.env import EmergencyEnv, WorldState
from ccrjax.envs.scenarios import Hazard
from ccrjax.transforms import Plain, Transform


def to_batch_major_obs(obs: jax.Array) -> jax.Array:
    """Environment observations ``[N, F, E]`` to the learners' ``[E, N, F]``."""
    return jnp.transpose(obs, (2, 0, 1))


def to_env_action(action: jax.Array, discrete: bool) -> jax.Array:
    """Learner actions ``[E, N, 2]`` or ``[E, N]`` to env actions ``[N, 2, E]`` or ``[N, E]``."""
    return action.T if discrete else jnp.transpose(action, (1, 2, 0))


@struct.dataclass
class Episode:
    """What one episode of ``E`` environments produced, step-major (``T`` steps).

    ``transitions``: batch-major learner transitions, leaves ``[T, E, ...]``, with the
    transformed rewards; the remaining fields are the environment's own, batch-last:
    ``env_reward``, ``danger``, ``success`` (in the target area at that step),
    ``target_distance``, ``hazard_distance``: ``[T, N, E]``;
    ``position``: ``[T + 1, N, 2, E]`` (start included); ``hazard``: the episode's
    hazards (leaves ``[2, E]``); ``info``: the transform's per-step diagnostics,
    leaves ``[T, N, E]`` (empty for plain and pessimistic).
    """

    transitions: Transition
    env_reward: jax.Array
    danger: jax.Array
    success: jax.Array
    target_distance: jax.Array
    hazard_distance: jax.Array
    position: jax.Array
    hazard: Hazard
    info: dict[str, jax.Array]


ActFn = Callable[[jax.Array, jax.Array], jax.Array]  # (obs [E, N, F], key) -> action
# A hand-written controller reads the world instead: (world, key) -> env action [N, 2, E].
ControllerFn = Callable[[WorldState, jax.Array], jax.Array]


class StatefulController(NamedTuple):
    """A hand-written controller with memory across the steps of an episode.

    ``init(world) -> memory`` (any pytree) at the episode's start; ``act(world, memory,
    key) -> (env action, memory)`` every step; :func:`run_episode` carries the memory
    in its scan. Controllers without memory stay plain ``(world, key) -> action``.
    """

    init: Callable[[WorldState], Any]
    act: Callable[[WorldState, Any, jax.Array], tuple[jax.Array, Any]]


def run_episode(
    env: EmergencyEnv,
    transform: Transform,
    transform_state: Any,
    act: ActFn | None,
    discrete: bool,
    key: jax.Array,
    *,
    controller: ControllerFn | StatefulController | None = None,
) -> tuple[Any, Episode]:
    """Resets ``env`` and runs ``env.episode_length`` steps of ``act``, through ``transform``.

    ``controller``, if given, acts instead of ``act``: a hand-written policy that
    reads the environment's state (the reference controllers of ``experiments/``),
    evaluated by the very same loop and metrics as the learners; a
    :class:`StatefulController` has its memory carried from step to step.
    """
    if (act is None) == (controller is None):
        raise ValueError("run_episode needs exactly one of act and controller")
    reset_key, key = jax.random.split(key)
    env_state = env.reset(reset_key)
    transform_state, obs = transform.start_episode(transform_state, env_state)
    stateful = isinstance(controller, StatefulController)
    # An empty tuple adds no leaf to the scan's carry: act's path is the same program.
    memory = controller.init(env_state.pipeline_state) if stateful else ()

    def one_step(carry, step_key):
        env_state, transform_state, obs, memory = carry
        obs_bm = to_batch_major_obs(obs)
        if controller is None:
            action = act(obs_bm, step_key)
        else:
            if stateful:
                env_action, memory = controller.act(env_state.pipeline_state, memory, step_key)
            else:
                env_action = controller(env_state.pipeline_state, step_key)
            action = env_action.T if discrete else jnp.transpose(env_action, (2, 0, 1))
        next_env_state = env.transition(env_state, to_env_action(action, discrete))
        transform_state, next_obs, reward, info = transform.step(
            transform_state, env_state, to_env_action(action, discrete), next_env_state
        )
        transition = Transition(
            obs=obs_bm,
            action=action,
            reward=reward.T,
            next_obs=to_batch_major_obs(next_obs),
            done=jnp.zeros((env.num_envs,), jnp.float32),
            # The cost channel, for a transform that weighs it when the learner updates.
            cost=(next_env_state.metrics["danger"].T
                  if getattr(transform, "reward_channels", False) else None),
        )
        outputs = (
            transition,
            next_env_state.reward,
            next_env_state.metrics["danger"],
            next_env_state.metrics["success"],
            next_env_state.metrics["target_distance"],
            next_env_state.metrics["hazard_distance"],
            next_env_state.pipeline_state.position,
            info,
        )
        return (next_env_state, transform_state, next_obs, memory), outputs

    step_keys = jax.random.split(key, env.episode_length)
    (_, transform_state, _, _), outputs = jax.lax.scan(
        one_step, (env_state, transform_state, obs, memory), step_keys
    )
    transform_state = transform.end_episode(transform_state)
    transitions, env_reward, danger, success, target_distance, hazard_distance, position, info = (
        outputs
    )
    position = jnp.concatenate([env_state.pipeline_state.position[None], position], axis=0)
    return transform_state, Episode(
        transitions=transitions,
        env_reward=env_reward,
        danger=danger,
        success=success,
        target_distance=target_distance,
        hazard_distance=hazard_distance,
        position=position,
        hazard=env_state.pipeline_state.hazard,
        info=info,
    )


def episode_metrics(episode: Episode) -> dict[str, jax.Array]:
    """The paper's four metrics of a batch of episodes, and the final distance (scalars).

    * ``danger_frequency``: share of robot-steps in a dangerous state;
    * ``success_rate``: share of robots in the target area at the episode's last step
      (not "ever reached": a robot that passes through or wanders off fails);
    * ``target_distance``: mean distance of a robot to its own target at the last
      step, shown beside success so that near misses and fleeing are visible;
    * ``hazard_distance``: mean distance of a robot to the hazard centre per step
      (large for a team that flees, so always read it beside ``target_distance``);
    * ``return``: undiscounted sum of the environment reward per robot and episode.
    """
    return {
        "danger_frequency": jnp.mean(episode.danger),
        "success_rate": jnp.mean(episode.success[-1]),
        "target_distance": jnp.mean(episode.target_distance[-1]),
        "hazard_distance": jnp.mean(episode.hazard_distance),
        "return": jnp.mean(jnp.sum(episode.env_reward, axis=0)),
    }


def compile_for(
    function: Callable[..., Any], examples: tuple, optimize: bool = False
) -> Callable[..., Any]:
    """``jax.jit(function)`` compiled for the arguments ``examples``; unoptimised unless
    ``optimize`` (on CPU that halves the compile time, most of what a recording costs)."""
    lowered = jax.jit(function).lower(*examples)
    if not optimize:
        try:
            return lowered.compile(compiler_options={"xla_backend_optimization_level": 0})
        except Exception:  # an XLA without this option: compile normally
            pass
    return lowered.compile()


def plain_episode(env: EmergencyEnv, policy: Callable[[jax.Array, jax.Array], jax.Array],
                  key: jax.Array, optimize: bool = False) -> tuple[Any, jax.Array, jax.Array]:
    """One episode of ``policy`` (``(obs [N, F, B], key) -> action [N, 2, B]``, the env's
    layout) with the environment's own rewards (no transform), compiled once
    (:func:`compile_for`): the hazard, positions ``[T + 1, N, 2, B]`` and per-step danger
    ``[T, N, B]``, for pictures of a hand-written or random policy."""
    plain = Plain()

    def rollout(key: jax.Array) -> tuple[Any, Any, Any]:
        def act(obs: jax.Array, step_key: jax.Array) -> jax.Array:  # learners' layout
            action = policy(jnp.transpose(obs, (1, 2, 0)), step_key)  # [N, 2, B]
            return jnp.transpose(action, (2, 0, 1))

        _, episode = run_episode(env, plain, plain.init(env), act, False, key)
        return episode.hazard, episode.position, episode.danger

    return compile_for(rollout, (key,), optimize)(key)
