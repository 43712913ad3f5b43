"""The constrained baseline (:mod:`ccrjax.transforms.lagrangian`) and the cost channel it
needs: the penalty a learner trains on is the one in force at the update, not the one in
force when the transition was stored; the buffer's statistics of the combined reward are
exact; a multiplier that never moves is the plain learner, bit for bit; the multiplier
follows the training episodes' danger, waits for its warm-up, and several cost limits
train side by side."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.replay import add_episodes, init_replay, sample
from ccrjax.agents.types import Transition
from ccrjax.run.stats import mean_ci
from ccrjax.run.sweep_grid import grid_params, search_grid
from ccrjax.training import TrainConfig, make_train
from ccrjax.training.program import channel_rewards
from ccrjax.transforms.lagrange import init_multiplier
from ccrjax.transforms.lagrangian import Lagrangian
from experiments import protocol

N, T, E = 3, 4, 2


def episodes(key) -> Transition:
    """A block of ``E`` made-up episodes of ``T`` steps, step-major, with a cost channel."""
    k1, k2, k3 = jax.random.split(key, 3)
    return Transition(
        obs=jax.random.normal(k1, (T, E, N, 5)), action=jnp.zeros((T, E, N, 2)),
        reward=jax.random.normal(k2, (T, E, N)),
        next_obs=jax.random.normal(k1, (T, E, N, 5)), done=jnp.zeros((T, E)),
        cost=(jax.random.uniform(k3, (T, E, N)) < 0.3).astype(jnp.float32))


def buffer_with_cost():
    example = jax.tree_util.tree_map(lambda x: x[0, 0], episodes(jax.random.PRNGKey(0)))
    buffer = init_replay(example, 4 * E, T)
    for k in range(3):
        buffer = add_episodes(buffer, episodes(jax.random.PRNGKey(k)))
    return buffer


def test_the_learner_trains_on_the_multiplier_in_force_at_the_update():
    transform = Lagrangian()
    buffer = buffer_with_cost()  # stored while the multiplier was 0
    batch = sample(buffer, jax.random.PRNGKey(5), 64)
    state = {"multiplier": init_multiplier(3.0, 1)}  # the multiplier now
    trained = channel_rewards(batch, transform.reward_weights(state))
    np.testing.assert_allclose(trained.reward, (batch.reward - 3.0 * batch.cost) / 4.0,
                               rtol=1e-6)
    assert trained.cost is None  # the learner sees rewards only


def test_the_buffer_knows_the_combined_rewards_mean_and_spread():
    buffer = buffer_with_cost()
    reward = np.concatenate([np.asarray(episodes(jax.random.PRNGKey(k)).reward).reshape(-1, N)
                             for k in range(3)])
    cost = np.concatenate([np.asarray(episodes(jax.random.PRNGKey(k)).cost).reshape(-1, N)
                           for k in range(3)])
    for a, b in ((1.0, 0.0), (0.25, -0.75), (0.5, -0.5)):
        mean, std = buffer.combined_mean_std(jnp.float32(a), jnp.float32(b))
        combined = a * reward + b * cost
        np.testing.assert_allclose(mean, combined.mean(axis=0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(std, combined.std(axis=0), rtol=1e-4, atol=1e-5)


def test_a_buffer_without_a_cost_channel_keeps_its_structure():
    plain = jax.tree_util.tree_map(lambda x: x[0, 0], episodes(jax.random.PRNGKey(0)))
    plain = plain.replace(cost=None)
    buffer = init_replay(plain, 2 * E, T)
    assert buffer.cost is None and buffer.cost_sum is None
    with pytest.raises(ValueError, match="disagree on a cost channel"):
        add_episodes(buffer, episodes(jax.random.PRNGKey(1)))


TINY = dict(scenario="turbulence", total_env_steps=600, num_envs=4, learning_starts=200,
            eval_every=200, eval_episodes=4, episode_length=25)


def final(config, params=None):
    program = make_train(config)
    return jax.jit(program.train)(jax.random.PRNGKey(3), params)


@pytest.mark.slow  # four training programs compiled
@pytest.mark.parametrize("algo", ["iddpg", "maac"])
def test_a_multiplier_that_never_moves_is_the_plain_learner(algo):
    """With the multiplier held at 0 (no gain), the combined reward is the stored reward
    exactly: the learner's parameters and the evaluations are plain's, bit for bit."""
    plain_state, plain_history = final(TrainConfig(algo=algo, variant="plain", **TINY))
    still = Lagrangian(kp=0.0, ki=0.0, kd=0.0)
    state, history = final(TrainConfig(algo=algo, variant="lagrangian", transform=still, **TINY))
    for a, b in zip(jax.tree_util.tree_leaves(plain_state.learner),
                    jax.tree_util.tree_leaves(state.learner), strict=True):
        np.testing.assert_array_equal(a, b)
    for name, values in plain_history.items():
        np.testing.assert_array_equal(values, history[name], err_msg=name)
    assert (np.asarray(history["lagrange_multiplier"]) == 0).all()


@pytest.mark.slow  # a training program compiled
def test_the_multiplier_follows_the_danger_of_the_training_episodes():
    """In turbulence a nearly random team is in danger more often than a limit of 0.001
    allows: the multiplier rises after the warm-up, and a limit of 1 (never reached) leaves
    it at 0; several limits train in one program."""
    config = TrainConfig(algo="iddpg", variant="lagrangian",
                         transform=Lagrangian(controller="ascent", ki=1.0, warmup_episodes=2),
                         **TINY)
    program = make_train(config)
    limits = jnp.array([0.001, 1.0])
    keys = jnp.stack([jax.random.PRNGKey(0)] * 2)
    state, history = jax.jit(jax.vmap(program.train))(keys, {"cost_limit": limits})
    path = np.asarray(history["lagrange_multiplier"])  # [limits, evaluations]
    assert path[0, 0] == 0.0 and path[0, -1] > 0.0
    assert (path[1] == 0.0).all()
    # Two training episodes per evaluation (200 steps of 4 environments x 25): the first
    # evaluation after training sees the warm-up's two episodes, the multiplier still 0.
    assert path[0, 1] == 0.0
    np.testing.assert_array_equal(np.asarray(state.transform["episodes"]), [6, 6])


@pytest.mark.slow  # an iteration compiled
def test_a_multiplier_gone_non_finite_stops_the_run_like_a_non_finite_loss():
    """The reward weights are checked with the learner's parameters: a non-finite multiplier
    marks the iteration non-finite (the run stops naming it) and keeps the last good state."""
    program = make_train(TrainConfig(algo="iddpg", variant="lagrangian", **TINY))
    state = program.init(jax.random.PRNGKey(0))
    multiplier = state.transform["multiplier"].replace(integral=jnp.float32(jnp.nan),
                                                       multiplier=jnp.float32(jnp.nan))
    broken = state.replace(transform={**state.transform, "multiplier": multiplier})
    after, _ = jax.jit(program.iteration)(broken)
    assert int(after.nonfinite_iteration) == 0
    assert np.isnan(float(after.transform["multiplier"].multiplier))  # the state it had
    healthy, _ = jax.jit(program.iteration)(state)
    assert int(healthy.nonfinite_iteration) == -1


@pytest.mark.parametrize("fields, message", [
    ({"controller": "bang"}, "Lagrangian.controller must be one of"),
    ({"cost_limit": -0.1}, "Lagrangian.cost_limit must be a finite number >= 0"),
    ({"cost_limit": 1.5}, "Lagrangian.cost_limit must be at most 1"),
    ({"cap": 0.0}, "Lagrangian.cap must be a finite number > 0"),
    ({"ema_p": 1.0}, r"Lagrangian.ema_p must be in \[0, 1\)"),
    ({"delay": 0}, "Lagrangian.delay must be an integer >= 1"),
    ({"warmup_episodes": -1}, "Lagrangian.warmup_episodes must be an integer >= 0"),
])
def test_bad_settings_are_named(fields, message):
    with pytest.raises(ValueError, match=message):
        Lagrangian(**fields)


def test_a_search_of_the_cost_limit_trains_the_unconstrained_learner_as_its_reference():
    """Value 0 of the cost limit stands for no constraint: its runs hold the multiplier at 0
    (no gain), the other runs take their limit with the protocol's gains."""
    config = protocol.run_config(protocol.Settings(seeds=(100,)), "turbulence", "iddpg",
                                 "lagrangian")
    name, seeds, values = search_grid(config, [0.0, 0.01, 0.3], [100, 101])
    params = grid_params(config, name, values)
    assert name == "cost_limit" and seeds == [100, 101] * 3
    assert params["cost_limit"] == [1.0, 1.0, 0.01, 0.01, 0.3, 0.3]
    for gain in ("kp", "ki", "kd"):
        default = getattr(config.resolved_transform, gain)
        assert params[gain] == [0.0, 0.0, *[default] * 4] and default > 0
    assert grid_params(config, "penalty", [0.0, 3.0]) == {"penalty": [0.0, 3.0]}


def test_the_multiplier_waits_for_the_end_of_the_random_warm_up_by_default():
    """A run that names no Lagrangian (the command line's, the protocol's) holds the
    multiplier at 0 through its learner's random warm-up, in training iterations; an
    on-policy learner has none."""
    settings = protocol.Settings(seeds=(100,))
    config = protocol.run_config(settings, "turbulence", "maddpg", "lagrangian")
    transform = config.resolved_transform
    assert transform.warmup_episodes == 25_600 // config.steps_per_iteration == 128
    assert transform.ki == 0.02  # the addition of 2026-12-03
    assert config.total_env_steps == protocol.BUDGETS["maddpg"]
    quick = protocol.run_config(dataclasses.replace(settings, quick=True, steps=400,
                                                    eval_every=200),
                                "turbulence", "maddpg", "lagrangian")
    assert quick.resolved_transform.warmup_episodes == 2  # 40 transitions, 20 per episode
    assert TrainConfig(variant="lagrangian").resolved_transform == transform
    assert TrainConfig(variant="lagrangian", algo="mappo").resolved_transform.warmup_episodes == 0
    given = Lagrangian(cost_limit=0.1)
    assert TrainConfig(variant="lagrangian", transform=given).resolved_transform is given


@pytest.mark.slow  # two iterations compiled
def test_the_update_uses_the_multiplier_set_by_this_iterations_episodes():
    """A multiplier driven from 0 to its cap by the first training episode trains the
    learner exactly as a multiplier held at the cap from the start: the update weighs the
    channels with the multiplier in force after the episode, not before it."""
    config = dict(algo="iddpg", variant="lagrangian", **{**TINY, "learning_starts": 0})
    jumping = Lagrangian(controller="ascent", ki=1e4, cost_limit=0.0, cap=100.0)
    held = Lagrangian(controller="ascent", ki=0.0, cost_limit=0.0, cap=100.0, initial=100.0)
    states = []
    for transform in (jumping, held):
        program = make_train(TrainConfig(transform=transform, **config))
        state, _ = jax.jit(program.iteration)(program.init(jax.random.PRNGKey(4)))
        states.append(state)
    assert float(states[0].transform["multiplier"].multiplier) == 100.0  # the episode's danger
    assert int(states[0].updates) > 0
    for a, b in zip(jax.tree_util.tree_leaves(states[0].learner),
                    jax.tree_util.tree_leaves(states[1].learner), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # two programs of 3 seeds x 150,000 steps: about 3 minutes on 2 cores
def test_a_trained_lagrangian_team_holds_its_danger_near_the_limit():
    """In turbulence the plain IDDPG team crosses the turbulent area (danger about 0.4 at
    150,000 steps); the Lagrangian team with a limit of 0.2 ends near the limit, within its
    seeds' spread, far below plain. The integral gain is the first amendment's 0.2: a run of
    150,000 steps needs the faster integral the protocol's 2M runs must not have."""
    base = dict(algo="iddpg", scenario="turbulence", total_env_steps=150_000,
                learning_starts=5_000, eval_every=37_500, eval_episodes=32)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in range(3)])
    final = {}
    fast = Lagrangian(cost_limit=0.2, ki=0.2, warmup_episodes=25)
    for variant, transform in (("plain", None), ("lagrangian", fast)):
        program = make_train(TrainConfig(variant=variant, transform=transform, **base))
        _, history = jax.jit(jax.vmap(program.train))(keys, None)
        final[variant] = np.asarray(history["danger_frequency"])[:, -1]
    plain, constrained = (mean_ci(final[v], bounds=(0.0, 1.0)) for v in ("plain", "lagrangian"))
    assert plain["ci_low"] > 0.3  # plain is far above the limit
    assert constrained["ci_low"] <= 0.2 <= constrained["ci_high"]
    assert constrained["mean"] < 0.7 * plain["mean"]
