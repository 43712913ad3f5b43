"""Learning is real: each learner's evaluated return improves clearly within a small budget.

The budget is small enough for the suite (well under 2 minutes per learner on 2 cores):
smaller networks and batches than the defaults, more updates per environment step.
The full-size check, success on `nominal` at the default budget, is
``experiments/sanity.py``.
"""

from __future__ import annotations

import jax
import pytest

from ccrjax.learners.ddpg import DDPGConfig
from ccrjax.training import TrainConfig, make_train

SMALL_DDPG = DDPGConfig(
    batch_size=256,
    actor_hidden=(32, 32),
    critic_hidden=(32, 32),
    update_every=25,
    exploration_noise=0.3,
    actor_lr=1e-2,  # small networks, short run: the original's faster rate
    critic_lr=1e-2,
)


@pytest.mark.parametrize("algo", ["iddpg", "maddpg"])
def test_ddpg_family_improves_its_return(algo):
    config = TrainConfig(
        algo=algo,
        scenario="nominal",
        num_envs=8,
        total_env_steps=40_000,
        eval_every=40_000,
        eval_episodes=32,
        learning_starts=2_000,
        ddpg=SMALL_DDPG,
    )
    program = make_train(config)
    state, history = jax.jit(program.train)(jax.random.PRNGKey(0))
    program.raise_if_nonfinite(state)
    initial, final = float(history["return"][0]), float(history["return"][-1])
    # Returns are negative distances summed over the episode: improving = closer to 0.
    print(f"{algo}: evaluated return {initial:.1f} -> {final:.1f}")
    assert final > initial + 0.2 * abs(initial), (initial, final)
