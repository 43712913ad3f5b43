"""A trained policy on its own: exported at the end of a run, loaded without the training state.

:func:`export_policy` writes ``<run>/policy/``: the learner's state of every seed (the
networks and what the learner carries with them; no replay buffer, no optimiser of the
environment), the transform's state between episodes (CCR's fitted dynamics model and its
statistics, the pessimistic penalty) with orbax, and ``policy.json`` naming the learner,
the scenario, the robots and observation size, and the seeds. :func:`load_policy` reads it
back into a function from observations to the deterministic evaluation actions::

    import ccrjax
    act = ccrjax.load_policy("runs/my-run", seed=0)
    actions = act(obs)          # obs float32[batch, N, F] -> float32[batch, N, 2] (int32 for MAAC)

The observations are what the learner saw in training (:func:`ccrjax.training.run_episode`
builds them, batch first): the environment's ``F`` features (``EmergencyEnv.observe``), and for a
CCR run the other ``N - 1`` robots' shared emergency scores after them (``policy.json``
gives ``obs_size`` and ``extra_obs``). Those scores come from CCR's model and the team's
recent steps, not from one observation, so a CCR policy acts in whole episodes:
:func:`load_team` runs the trained team, transform included, as the run's evaluation does::

    team = ccrjax.load_team("runs/my-run", seed=0)
    episode = team.episode(jax.random.PRNGKey(1))    # positions, danger, success, CCR's info
    metrics = team.evaluate(jax.random.PRNGKey(1))   # success rate, danger frequency, ...
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from ccrjax.run.folder import write_atomic
from ccrjax.run.spec import RunSpec
from ccrjax.training import (
    Episode,
    TrainProgram,
    episode_metrics,
    make_learner,
    make_train,
    run_episode,
)

POLICY_DIR = "policy"
POLICY_RECORD = "policy.json"
TRANSFORM_STATE = "transform"
# What a variant's observations hold after the environment's features (policy.json's
# extra_obs); the variants not named here add nothing.
EXTRA_OBS = {
    "ccr": "the other robots' shared emergency scores (N - 1), after the environment's features",
    "ccr_scores": "the other robots' shared emergency scores (N - 1), after the environment's "
                  "features",
    "ccr_perfect": "the other robots' shared emergency scores (N - 1) of their true danger "
                   "flags, after the environment's features",
    "danger_flags": "the other robots' current danger flags within range (N - 1), after the "
                    "environment's features",
}


def export_policy(run_folder: str | Path, program: TrainProgram, learner_state: Any,
                  seeds: list[int], transform_state: Any = None) -> Path:
    """Writes the learner state and the transform's state between episodes of every seed
    (leaves ``[seeds, ...]``) to ``<run_folder>/policy`` and returns that folder; an
    existing export is replaced. A transform state without leaves (plain) is not written."""
    folder = Path(run_folder).absolute() / POLICY_DIR
    checkpointer = ocp.StandardCheckpointer()
    checkpointer.save(folder / "state", learner_state, force=True)
    if jax.tree_util.tree_leaves(transform_state):
        checkpointer.save(folder / TRANSFORM_STATE, transform_state, force=True)
    checkpointer.wait_until_finished()
    config = program.config
    record = {"algo": config.algo, "scenario": config.scenario, "variant": config.variant,
              "num_robots": config.num_robots, "obs_size": int(program.obs_size),
              "env_obs_size": int(program.env.observation_size),
              "extra_obs": EXTRA_OBS.get(config.variant),
              "discrete_actions": bool(program.learner.discrete), "seeds": list(seeds),
              "transform_state": bool(jax.tree_util.tree_leaves(transform_state))}
    write_atomic(folder / POLICY_RECORD, json.dumps(record, indent=1) + "\n")
    return folder


def load_policy(run_folder: str | Path, seed: int = 0) -> Callable[[jax.Array], jax.Array]:
    """The deterministic policy of ``seed`` trained in ``run_folder``: a function (jitted
    inside) from observations ``float32[batch, N, F]`` to actions (``float32[batch, N, 2]``
    in [-1, 1], or ``int32[batch, N]`` for MAAC's discrete actions, indices into its
    ``MAACConfig.action_set``); one team's ``[N, F]`` gives ``[N, 2]`` (or ``[N]``), so it
    can be used under ``jax.vmap`` and ``jax.jit``.

    Raises ``FileNotFoundError`` if the run exported no policy (it is written when a run
    finishes) and ``ValueError`` for a seed the run did not train; the function raises
    ``ValueError`` for observations of another shape.
    """
    run_folder, record, spec = _read_export(run_folder, seed)
    folder = run_folder / POLICY_DIR
    learner = make_learner(spec.train)
    one = jax.eval_shape(lambda key: learner.init(key, record["num_robots"],
                                                  record["obs_size"]), jax.random.PRNGKey(0))
    count = len(record["seeds"])
    abstract = jax.tree_util.tree_map(
        lambda leaf: jax.ShapeDtypeStruct((count, *leaf.shape), leaf.dtype), one)
    state = _restore_seed(folder / "state", abstract, record["seeds"].index(seed))
    key = jax.random.PRNGKey(0)  # unused: evaluation actions are deterministic
    expected = (record["num_robots"], record["obs_size"])

    @jax.jit
    def greedy(obs: jax.Array) -> jax.Array:
        return learner.act(state, obs, key, False)

    def act(obs: jax.Array) -> jax.Array:
        shape = tuple(jnp.shape(obs))
        if shape[-2:] != expected or len(shape) not in (2, 3):
            raise ValueError(f"obs must be [batch, {expected[0]}, {expected[1]}] or "
                             f"[{expected[0]}, {expected[1]}] (robots, features: policy.json's "
                             f"num_robots and obs_size), got {shape}")
        if len(shape) == 2:  # one team (e.g. under jax.vmap)
            return greedy(obs[None])[0]
        return greedy(obs)

    return act


def _restore_seed(path: Path, abstract: Any, index: int) -> Any:
    """Seed ``index``'s slice of the state saved at ``path`` (leaves ``[seeds, ...]``,
    shaped as ``abstract``)."""
    state = ocp.StandardCheckpointer().restore(path, abstract)
    return jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf[index]), state)


def _read_export(run_folder: str | Path, seed: int) -> tuple[Path, dict, RunSpec]:
    """The run folder (absolute), its ``policy.json`` and its run specification; raises
    ``FileNotFoundError`` without an export and ``ValueError`` for a seed not trained."""
    run_folder = Path(run_folder).absolute()
    try:
        record = json.loads((run_folder / POLICY_DIR / POLICY_RECORD).read_text())
        spec = RunSpec.from_dict(json.loads((run_folder / "config.json").read_text())["run"])
    except (OSError, ValueError, KeyError) as error:
        raise FileNotFoundError(f"{run_folder} holds no exported policy (a run exports it "
                                f"when it finishes): {error}") from None
    if seed not in record["seeds"]:
        raise ValueError(f"seed must be one of the run's seeds {record['seeds']}, got {seed!r}")
    return run_folder, record, spec


@dataclass(frozen=True)
class Team:
    """A trained team as its run exported it: the training program's pure functions
    (``program``: environment, transform, learner, of the run's configuration), and one
    seed's learner state and transform state between episodes."""

    program: TrainProgram
    learner_state: Any
    transform_state: Any
    seed: int

    def episode(self, key: jax.Array) -> Episode:
        """One evaluation episode in each of the run's ``eval_episodes`` environments:
        deterministic actions, through the transform (CCR's scores shared and observed),
        as the run's evaluations ran them (:func:`ccrjax.training.run_episode`)."""
        return _episode(self.program, self.learner_state, self.transform_state, key)

    def evaluate(self, key: jax.Array) -> dict[str, jax.Array]:
        """The evaluation metrics of :meth:`episode` (:func:`ccrjax.training.episode_metrics`:
        success rate, dangerous-behaviour frequency, final distance, return)."""
        return episode_metrics(self.episode(key))


@functools.partial(jax.jit, static_argnums=0)
def _episode(program: TrainProgram, learner_state: Any, transform_state: Any,
             key: jax.Array) -> Episode:
    def greedy(obs: jax.Array, step_key: jax.Array) -> jax.Array:
        return program.learner.act(learner_state, obs, step_key, False)

    _, episode = run_episode(program.eval_env, program.transform, transform_state, greedy,
                             program.learner.discrete, key)
    return episode


def load_team(run_folder: str | Path, seed: int = 0) -> Team:
    """The team of ``seed`` trained in ``run_folder`` (see :class:`Team`), from the run's
    policy export and ``config.json`` only. Raises ``FileNotFoundError`` without an export,
    or where the export holds no transform state a transform needs (exported before
    ccrjax kept it: ``python -m ccrjax.evaluate`` runs such a run's episodes from its
    checkpoint), and ``ValueError`` for a seed the run did not train."""
    run_folder, record, spec = _read_export(run_folder, seed)
    folder = run_folder / POLICY_DIR
    program = make_train(spec.train)
    count = len(record["seeds"])
    keys = jax.random.split(jax.random.PRNGKey(0), count)
    abstract = jax.eval_shape(jax.vmap(program.init), keys)
    index = record["seeds"].index(seed)
    learner_state = _restore_seed(folder / "state", abstract.learner, index)
    transform_state = abstract.transform  # no leaves: nothing to restore (plain)
    if jax.tree_util.tree_leaves(abstract.transform):
        if not (folder / TRANSFORM_STATE).is_dir():
            raise FileNotFoundError(
                f"{folder} holds no transform state (exported before ccrjax kept it); "
                f"python -m ccrjax.evaluate {run_folder} runs its episodes from the checkpoint")
        transform_state = _restore_seed(folder / TRANSFORM_STATE, abstract.transform, index)
    return Team(program=program, learner_state=learner_state,
                transform_state=transform_state, seed=seed)
