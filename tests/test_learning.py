"""Learning is real: each learner's evaluated return improves clearly within a small budget,
on every one of three seeds (trained side by side in one vmapped program), so that no
single lucky seed makes the test pass.

The budget is small (well under a minute per learner on 2 cores): smaller networks and
batches than the defaults, more updates per environment step. The checks run with the slow
ones (``make test-slow``), beside the on-policy learners' learning checks.
The full-size check, success on `nominal` at the default budget, is
``experiments/sanity.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.training import TrainConfig, make_train

SEEDS = (0, 1, 2)
SMALL_DDPG = DDPGConfig(
    batch_size=128,
    actor_hidden=(32, 32),
    critic_hidden=(32, 32),
    update_every=25,
    exploration_noise=0.3,
    actor_lr=1e-2,  # small networks, short run: the original's faster rate
    critic_lr=1e-2,
)


def train_seeds(config: TrainConfig):
    """The evaluation history of every seed of :data:`SEEDS`, leaves ``[seeds, points]``."""
    program = make_train(config)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in SEEDS])
    state, history = jax.jit(jax.vmap(program.train))(keys)
    program.raise_if_nonfinite(state)
    return state, {name: np.asarray(values) for name, values in history.items()}


@pytest.mark.slow  # a training program per learner: about 35 s each of the fast suite
@pytest.mark.parametrize("algo", ["iddpg", "maddpg"])
def test_ddpg_family_improves_its_return(algo):
    config = TrainConfig(
        algo=algo,
        scenario="nominal",
        num_envs=8,
        total_env_steps=40_000,
        eval_every=40_000,
        eval_episodes=16,
        learning_starts=2_000,
        learner=SMALL_DDPG,
    )
    _, history = train_seeds(config)
    initial, final = history["return"][:, 0], history["return"][:, -1]
    success = history["success_rate"][:, -1]
    # Returns are negative distances summed over the episode: improving = closer to 0.
    print(f"{algo}: evaluated return {initial.round(1)} -> {final.round(1)}, success {success}")
    assert np.all(final > initial + 0.2 * np.abs(initial)), (initial, final)
