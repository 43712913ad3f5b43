"""A trained policy on its own: exported at the end of a run, loaded without the training state.

:func:`export_policy` writes ``<run>/policy/``: the learner's state of every seed (the
networks and what the learner carries with them; no replay buffer, no transform state,
no optimiser of the environment) with orbax, and ``policy.json`` naming the learner, the
scenario, the robots and observation size, and the seeds. :func:`load_policy` reads it
back into a function from observations to the deterministic evaluation actions::

    import ccrjax
    act = ccrjax.load_policy("runs/my-run", seed=0)
    actions = act(obs)          # obs float32[batch, N, F] -> float32[batch, N, 2] (int32 for MAAC)

The observations are what the learner saw in training (:func:`ccrjax.training.run_episode`
builds them, batch first): the environment's ``F`` features (``CCREnv.observe``), and for a
CCR run the other ``N - 1`` robots' shared emergency scores after them (``policy.json``
gives ``obs_size`` and ``extra_obs``).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from ccrjax.run.folder import write_atomic
from ccrjax.run.spec import RunSpec
from ccrjax.training import TrainProgram, make_learner

POLICY_DIR = "policy"
POLICY_RECORD = "policy.json"


def export_policy(run_folder: str | Path, program: TrainProgram, learner_state: Any,
                  seeds: list[int]) -> Path:
    """Writes the learner state of every seed (leaves ``[seeds, ...]``) to
    ``<run_folder>/policy`` and returns that folder; an existing export is replaced."""
    folder = Path(run_folder).absolute() / POLICY_DIR
    checkpointer = ocp.StandardCheckpointer()
    checkpointer.save(folder / "state", learner_state, force=True)
    checkpointer.wait_until_finished()
    config = program.config
    record = {"algo": config.algo, "scenario": config.scenario, "variant": config.variant,
              "num_robots": config.num_robots, "obs_size": int(program.obs_size),
              "env_obs_size": int(program.env.observation_size),
              "extra_obs": ("the other robots' shared emergency scores (N - 1), after the "
                            "environment's features" if config.variant == "ccr" else None),
              "discrete_actions": bool(program.learner.discrete), "seeds": list(seeds)}
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
    run_folder = Path(run_folder).absolute()
    folder = run_folder / POLICY_DIR
    try:
        record = json.loads((folder / POLICY_RECORD).read_text())
        spec = RunSpec.from_dict(json.loads((run_folder / "config.json").read_text())["run"])
    except (OSError, ValueError, KeyError) as error:
        raise FileNotFoundError(f"{run_folder} holds no exported policy (a run exports it "
                                f"when it finishes): {error}") from None
    if seed not in record["seeds"]:
        raise ValueError(f"seed must be one of the run's seeds {record['seeds']}, got {seed!r}")
    learner = make_learner(spec.train)
    one = jax.eval_shape(lambda key: learner.init(key, record["num_robots"],
                                                  record["obs_size"]), jax.random.PRNGKey(0))
    count = len(record["seeds"])
    abstract = jax.tree_util.tree_map(
        lambda leaf: jax.ShapeDtypeStruct((count, *leaf.shape), leaf.dtype), one)
    state = ocp.StandardCheckpointer().restore(folder / "state", abstract)
    index = record["seeds"].index(seed)
    state = jax.tree_util.tree_map(lambda leaf: jnp.asarray(leaf[index]), state)
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
