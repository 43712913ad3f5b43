"""The training program: one configuration compiles into one pure function of a key.

``make_train(config)`` returns a :class:`TrainProgram` whose functions are pure
and jit/vmap friendly:

* ``init(key) -> TrainState``
* ``run(state, num_iterations) -> (state, per-iteration metrics)``: ``lax.scan``
  over training iterations; one iteration = one episode of ``num_envs``
  environments (rollout through the transform, transitions into the on-device
  replay buffer) then ``updates_per_iteration`` learner updates;
* ``evaluate(state, key) -> metrics``: fresh episodes, deterministic policy;
* ``train(key) -> (state, evaluation history)``: the whole schedule.

``jax.jit(jax.vmap(program.train))(keys)`` trains one seed per key in one program.
Python only drives the outside (chunks of iterations for progress, logs and
checkpoints: :mod:`ccrjax.train`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ccrjax.agents.replay import ReplayBuffer, add_episodes, init_replay, sample
from ccrjax.agents.types import Transition
from ccrjax.training.acting import episode_metrics, run_episode
from ccrjax.training.config import (
    TrainConfig,
    make_env,
    make_learner,
    make_transform,
)


class NonFiniteTraining(RuntimeError):
    """A learner's parameters or losses stopped being finite during training."""


@dataclasses.dataclass(frozen=True)
class NonFinite:
    """Where training first turned non-finite: the iteration, and the seed it happened in."""

    iteration: int
    seed: int

    def message(self) -> str:
        return (f"training became non-finite at iteration {self.iteration} (seed {self.seed}); "
                "the parameters kept are the last finite ones")


def first_nonfinite(nonfinite_iteration: Any, seeds: Sequence[int]) -> NonFinite | None:
    """The earliest non-finite iteration over runs (``nonfinite_iteration``: one per run,
    -1 where the run stayed finite; the first of ``seeds`` on a tie), or ``None``."""
    # int64 before the sentinel: JAX hands int32, which cannot hold it (NumPy wraps it to -1,
    # picking a run that stayed finite, or refuses it, by version).
    bad = np.asarray(jax.device_get(nonfinite_iteration)).reshape(-1).astype(np.int64)
    if not np.any(bad >= 0):
        return None
    index = int(np.argmin(np.where(bad >= 0, bad, np.iinfo(np.int64).max)))
    return NonFinite(iteration=int(bad[index]), seed=int(seeds[index]))


def channel_rewards(batch: Transition, weights: tuple[jax.Array, jax.Array]) -> Transition:
    """``batch`` with the reward the learner trains on, ``a reward + b cost``, from the
    stored channels and the weights ``(a, b)`` in force at this update (whatever they were
    when the transitions were stored); the cost channel is dropped, the learner sees
    rewards only."""
    reward_weight, cost_weight = weights
    return batch.replace(reward=reward_weight * batch.reward + cost_weight * batch.cost,
                         cost=None)


@struct.dataclass
class TrainState:
    """Everything a training run carries from one iteration to the next (one seed)."""

    learner: Any
    buffer: ReplayBuffer
    transform: Any
    key: jax.Array
    eval_key: jax.Array  # evaluation point k uses fold_in(eval_key, k)
    iteration: jax.Array  # int32[]
    env_steps: jax.Array  # int32[]
    updates: jax.Array  # int32[]
    # int32[]: dangerous robot-steps during training, cumulative; an integer count, exact up to
    # 2^31 - 1 robot-steps (a float32 one stops counting single steps at 2^24, which 5 robots
    # in danger half the time reach after about 6.7M steps).
    danger_steps: jax.Array
    learning_danger_steps: jax.Array  # int32[]: the same, counted once learning has started
    nonfinite_iteration: jax.Array  # int32[]: first iteration whose update went non-finite, or -1


def all_finite(tree: Any) -> jax.Array:
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


class TrainProgram:
    """The pure functions of one training configuration (see the module docstring)."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.env = make_env(config, config.num_envs)
        self.eval_env = make_env(config, config.eval_episodes)
        self.learner = make_learner(config)
        self.transform = make_transform(config)
        self.obs_size = self.env.observation_size + self.transform.extra_obs_size(self.env)

    # ------------------------------------------------------------------ state
    def default_transform_params(self) -> dict[str, float]:
        """The transform's per-run numbers (penalty, lambda) as the configuration sets them."""
        return self.transform.default_params()

    def init(self, key: jax.Array, transform_params: dict[str, Any] | None = None) -> TrainState:
        """A fresh run. ``transform_params`` overrides the configuration's per-run numbers of
        the transform (e.g. ``{"lam": 10.0}``); they may be traced, so that ``jax.vmap``
        over them runs several values in one program."""
        learner_key, eval_key, key = jax.random.split(key, 3)
        n, f = self.config.num_robots, self.obs_size
        action = (
            jnp.zeros((n,), jnp.int32) if self.learner.discrete else jnp.zeros((n, 2), jnp.float32)
        )
        example = Transition(
            obs=jnp.zeros((n, f), jnp.float32),
            action=action,
            reward=jnp.zeros((n,), jnp.float32),
            next_obs=jnp.zeros((n, f), jnp.float32),
            done=jnp.zeros((), jnp.float32),
            cost=(jnp.zeros((n,), jnp.float32)
                  if getattr(self.transform, "reward_channels", False) else None),
        )
        return TrainState(
            learner=self.learner.init(learner_key, n, f),
            buffer=init_replay(
                example,
                self.config.replay_capacity // self.config.episode_length,
                self.config.episode_length,
            ),
            transform=self.transform.init(self.env, transform_params),
            key=key,
            eval_key=eval_key,
            iteration=jnp.zeros((), jnp.int32),
            env_steps=jnp.zeros((), jnp.int32),
            updates=jnp.zeros((), jnp.int32),
            danger_steps=jnp.zeros((), jnp.int32),
            learning_danger_steps=jnp.zeros((), jnp.int32),
            nonfinite_iteration=jnp.full((), -1, jnp.int32),
        )

    # ------------------------------------------------------------------ iteration
    def iteration(self, state: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        """One episode of every training environment, then the learner's updates."""
        config = self.config
        key, rollout_key, update_key = jax.random.split(state.key, 3)

        def explore(obs, key):
            return self.learner.act(state.learner, obs, key, True)

        transform_state, episode = run_episode(
            self.env, self.transform, state.transform, explore, self.learner.discrete, rollout_key
        )
        channels = getattr(self.transform, "reward_channels", False)
        # The weights of the reward channels in force now (a Lagrange multiplier just
        # updated from this iteration's episodes), whenever the transitions were stored.
        weights = self.transform.reward_weights(transform_state) if channels else None
        # An on-policy learner learns from this rollout alone; the buffer stays empty.
        buffer = (state.buffer if config.on_policy
                  else add_episodes(state.buffer, episode.transitions))

        def learn_from_rollout(learner_state):
            rollout = episode.transitions
            if channels:
                rollout = channel_rewards(rollout, weights)
            return self.learner.update(learner_state, rollout, update_key)

        def do_updates(learner_state):
            def one_update(learner_state, key):
                sample_key, learn_key = jax.random.split(key)
                batch = sample(buffer, sample_key, config.resolved_learner.batch_size)
                if channels:
                    batch = channel_rewards(batch, weights)
                if self.learner.needs_reward_stats:
                    stats = (buffer.combined_mean_std(*weights) if channels
                             else buffer.reward_mean_std())
                    batch = self.learner.normalise_rewards(batch, *stats)
                return self.learner.update(learner_state, batch, learn_key)

            keys = jax.random.split(update_key, config.updates_per_iteration)
            learner_state, metrics = jax.lax.scan(one_update, learner_state, keys)
            return learner_state, jax.tree_util.tree_map(jnp.mean, metrics)

        def skip_updates(learner_state):
            _, metrics = jax.eval_shape(do_updates, learner_state)
            return learner_state, jax.tree_util.tree_map(
                lambda m: jnp.zeros(m.shape, m.dtype), metrics
            )

        learning = buffer.size >= config.learning_starts_transitions
        if config.on_policy:
            learner_state, update_metrics = learn_from_rollout(state.learner)
        else:
            learner_state, update_metrics = jax.lax.cond(
                learning, do_updates, skip_updates, state.learner
            )
        finite = all_finite(learner_state)
        if channels:  # a multiplier gone non-finite stops the run as a non-finite loss does
            finite = finite & all_finite(weights)
            transform_state = jax.tree_util.tree_map(
                lambda new, old: jnp.where(finite, new, old), transform_state, state.transform
            )
        learner_state = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finite, new, old), learner_state, state.learner
        )
        nonfinite_iteration = jnp.where(
            (state.nonfinite_iteration < 0) & ~finite, state.iteration, state.nonfinite_iteration
        )
        episode_danger = jnp.sum(episode.danger.astype(jnp.int32))
        danger_steps = state.danger_steps + episode_danger
        # Episodes collected once the buffer held enough to learn: the policy is learning.
        learned_before = state.buffer.size >= config.learning_starts_transitions
        learning_danger_steps = state.learning_danger_steps + jnp.where(
            learned_before, episode_danger, 0
        )
        new_state = state.replace(
            learner=learner_state,
            buffer=buffer,
            transform=transform_state,
            key=key,
            iteration=state.iteration + 1,
            env_steps=state.env_steps + config.steps_per_iteration,
            updates=state.updates + jnp.where(learning, config.updates_per_iteration, 0),
            danger_steps=danger_steps,
            learning_danger_steps=learning_danger_steps,
            nonfinite_iteration=nonfinite_iteration,
        )
        metrics = {
            **{f"train_{k}": v for k, v in episode_metrics(episode).items()},
            **update_metrics,
            "cumulative_danger_steps": danger_steps,
            "learning_danger_steps": learning_danger_steps,
        }
        return new_state, metrics

    def run(self, state: TrainState, num_iterations: int):
        """``num_iterations`` iterations in one ``lax.scan``; metrics stacked per iteration."""
        return jax.lax.scan(lambda s, _: self.iteration(s), state, None, length=num_iterations)

    def raise_if_nonfinite(self, state: TrainState, seeds: Sequence[int] | None = None
                           ) -> None:
        """Raises :class:`NonFiniteTraining` naming the iteration and seed (``seeds``: the
        seeds of a vmapped ``state``; by default their indices) if any went non-finite.

        The compiled program never applies a non-finite update (it keeps the last
        finite parameters and records the iteration), so the state is still usable.
        """
        bad = np.asarray(jax.device_get(state.nonfinite_iteration)).reshape(-1)
        found = first_nonfinite(bad, range(bad.size) if seeds is None else seeds)
        if found is not None:
            raise NonFiniteTraining(found.message())

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, state: TrainState, key: jax.Array) -> dict[str, jax.Array]:
        """The evaluation metrics (:func:`ccrjax.training.acting.episode_metrics`) on
        ``eval_episodes`` fresh episodes, deterministic policy."""

        def greedy(obs, key):
            return self.learner.act(state.learner, obs, key, False)

        _, episode = run_episode(
            self.eval_env, self.transform, state.transform, greedy, self.learner.discrete, key
        )
        return episode_metrics(episode)

    # ------------------------------------------------------------------ schedule
    @property
    def num_evaluations(self) -> int:
        """Evaluations after the first: one per chunk of ``iterations_per_eval`` iterations."""
        return self.config.num_iterations // self.config.iterations_per_eval

    def evaluation_point(self, state: TrainState) -> dict[str, jax.Array]:
        """The four metrics of :meth:`evaluate` at ``state``, with ``env_steps`` and
        ``cumulative_danger_steps``. Point ``k`` (after ``k`` chunks) evaluates with
        ``fold_in(state.eval_key, k)``, so a run cut into chunks evaluates exactly as
        :meth:`train` does."""
        index = state.iteration // self.config.iterations_per_eval
        # A transform's own numbers at this point (a Lagrange multiplier's path), if any.
        transform_metrics = getattr(self.transform, "metrics", None)
        return {
            **self.evaluate(state, jax.random.fold_in(state.eval_key, index)),
            "env_steps": state.env_steps,
            "cumulative_danger_steps": state.danger_steps,
            "learning_danger_steps": state.learning_danger_steps,
            **(transform_metrics(state.transform) if transform_metrics else {}),
        }

    def chunk(
        self, state: TrainState, train: bool | jax.Array = True
    ) -> tuple[TrainState, dict, dict]:
        """``iterations_per_eval`` iterations, then an evaluation point.

        Returns the state, the evaluation point and the chunk's training metrics
        (means over its iterations of the training episodes' metrics and the
        learner's losses). This is the unit the train command compiles, runs,
        logs and checkpoints. ``train=False`` (a traced flag is fine, but keep it
        unbatched under ``vmap``) skips the iterations and only evaluates: the
        command's first evaluation, without compiling a second program.
        """

        def iterations(state):
            state, metrics = self.run(state, self.config.iterations_per_eval)
            return state, jax.tree_util.tree_map(lambda x: jnp.mean(x, axis=0), metrics)

        def no_iterations(state):
            _, metrics = jax.eval_shape(iterations, state)
            return state, jax.tree_util.tree_map(lambda m: jnp.zeros(m.shape, m.dtype), metrics)

        if isinstance(train, bool):
            state, training = (iterations if train else no_iterations)(state)
        else:
            state, training = jax.lax.cond(train, iterations, no_iterations, state)
        return state, self.evaluation_point(state), training

    def train(
        self, key: jax.Array, transform_params: dict[str, Any] | None = None
    ) -> tuple[TrainState, dict[str, jax.Array]]:
        """The whole run: an evaluation at the start and after every ``eval_every`` steps.

        Returns the final state and the evaluation history, leaves ``[num_evaluations + 1]``
        (with ``env_steps`` and ``cumulative_danger_steps`` at each point).
        """
        state = self.init(key, transform_params)
        first = self.evaluation_point(state)

        def one_chunk(state, _):
            state, point, _ = self.chunk(state)
            return state, point

        state, history = jax.lax.scan(one_chunk, state, None, length=self.num_evaluations)
        history = jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a[None], b]), first, history
        )
        return state, history


def make_train(config: TrainConfig) -> TrainProgram:
    """The training program of ``config``; ``make_train(c).train`` is a pure ``train(key)``."""
    return TrainProgram(config)
