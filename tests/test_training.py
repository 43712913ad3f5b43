"""The training program: transforms, seeds under vmap, configuration errors, non-finite runs."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.envs.env import EmergencyEnv
from ccrjax.training import (
    NonFiniteTraining,
    TrainConfig,
    config_from_dict,
    config_to_dict,
    default_budgets,
    make_train,
)
from ccrjax.training.acting import episode_metrics, run_episode
from ccrjax.training.program import NonFinite, first_nonfinite
from ccrjax.transforms import Pessimistic, Plain

TINY = TrainConfig(
    algo="maddpg",
    scenario="hidden_obstacle",
    num_envs=2,
    episode_length=20,  # long enough that robots reach the obstacle (danger to count)
    total_env_steps=400,
    eval_every=200,
    eval_episodes=4,
    learning_starts=80,
    learner=DDPGConfig(batch_size=32, actor_hidden=(16,), critic_hidden=(16,), update_every=10),
)


def stepped_states(scenario: str = "hidden_obstacle"):
    env = EmergencyEnv(scenario, num_envs=64, episode_length=30)
    state = env.reset(jax.random.PRNGKey(0))
    # Everyone runs flat out to +x, straight into whatever is on the way.
    action = jnp.zeros((env.num_robots, 2, env.num_envs)).at[:, 0].set(1.0)
    states = []
    for _ in range(25):
        next_state = env.transition(state, action)
        states.append((state, action, next_state))
        state = next_state
    return env, states


def test_pessimistic_subtracts_the_penalty_exactly_on_danger_steps():
    env, states = stepped_states()
    transform = Pessimistic(penalty=2.5)
    saw_danger = saw_safe = False
    for state, action, next_state in states:
        _, obs, reward, _ = transform.step(transform.init(env), state, action, next_state)
        danger = np.asarray(next_state.metrics["danger"]) > 0
        env_reward = np.asarray(next_state.reward)
        np.testing.assert_array_equal(np.asarray(reward)[danger], env_reward[danger] - 2.5)
        np.testing.assert_array_equal(np.asarray(reward)[~danger], env_reward[~danger])
        np.testing.assert_array_equal(obs, next_state.obs)
        saw_danger |= danger.any()
        saw_safe |= (~danger).any()
    assert saw_danger and saw_safe, "the rollout should contain both kinds of steps"


def test_plain_changes_nothing():
    env, states = stepped_states("strong_wind")
    state, action, next_state = states[3]
    _, obs, reward, _ = Plain().step({}, state, action, next_state)
    np.testing.assert_array_equal(reward, next_state.reward)
    np.testing.assert_array_equal(obs, next_state.obs)


@pytest.fixture(scope="module")
def tiny_program():
    return make_train(TINY)


@pytest.fixture(scope="module")
def separate_runs(tiny_program):
    """Two seeds trained one at a time (one compilation, reused by several tests)."""
    keys = jax.random.split(jax.random.PRNGKey(42), 2)
    train = jax.jit(tiny_program.train)
    return keys, [train(key) for key in keys]


def test_vmapped_seeds_equal_separate_runs(tiny_program, separate_runs):
    keys, runs = separate_runs
    together_state, together = jax.jit(jax.vmap(tiny_program.train))(keys)
    for s, (alone_state, alone) in enumerate(runs):
        for name in alone:
            np.testing.assert_allclose(together[name][s], alone[name], rtol=1e-4, atol=1e-4)
        seed_learner = jax.tree_util.tree_map(lambda x, s=s: x[s], together_state.learner)
        for a, b in zip(
            jax.tree_util.tree_leaves(alone_state.learner),
            jax.tree_util.tree_leaves(seed_learner),
            strict=True,
        ):
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    assert int(together_state.updates[0]) > 0
    # Two seeds are two different runs.
    assert not np.allclose(together["return"][0], together["return"][1])


def test_training_counts_steps_updates_and_dangerous_steps(tiny_program, separate_runs):
    keys, runs = separate_runs
    state, history = runs[1]
    assert int(state.env_steps) == TINY.num_iterations * TINY.steps_per_iteration
    assert int(state.iteration) == TINY.num_iterations
    # Updates start once 80 transitions are stored: from the second iteration on.
    assert int(state.updates) == (TINY.num_iterations - 1) * TINY.updates_per_iteration
    assert len(history["return"]) == tiny_program.num_evaluations + 1
    np.testing.assert_array_equal(
        history["env_steps"], np.arange(len(history["return"])) * TINY.eval_every
    )
    tiny_program.raise_if_nonfinite(state)

    # The dangerous robot-steps, counted again from each iteration's training episode:
    # the same episode (same key, same exploring policy) run on its own.
    program = tiny_program

    @jax.jit
    def iteration_and_its_episode(state):
        _, rollout_key, _ = jax.random.split(state.key, 3)

        def explore(obs, key):
            return program.learner.act(state.learner, obs, key, True)

        _, episode = run_episode(program.env, program.transform, state.transform, explore,
                                 program.learner.discrete, rollout_key)
        return program.iteration(state)[0], jnp.sum(episode.danger)

    state = program.init(keys[1])
    counts, cumulative, learning_states = [], [0.0], []
    for _ in range(TINY.num_iterations):
        next_state, danger = iteration_and_its_episode(state)
        counts.append(float(danger))
        assert float(next_state.danger_steps) == float(state.danger_steps) + float(danger)
        # Since learning started: episodes collected once the buffer held enough to learn.
        learning = int(state.buffer.size) >= TINY.learning_starts_transitions
        if learning and float(danger) > 0:
            learning_states.append(state)
        assert float(next_state.learning_danger_steps) == (
            float(state.learning_danger_steps) + (float(danger) if learning else 0.0)
        )
        cumulative.append(float(next_state.danger_steps))
        state = next_state
    assert sum(counts) > 0 and len(set(counts)) > 1, counts  # something to count
    assert counts[0] > 0, counts  # the warm-up's episode has danger the second count skips
    assert float(state.learning_danger_steps) < float(state.danger_steps)
    per_point = np.asarray(cumulative)[:: TINY.iterations_per_eval]
    np.testing.assert_array_equal(history["cumulative_danger_steps"], per_point)

    # The counts stay exact past 2^24 robot-steps, where a float32 count stops adding ones
    # (5 robots in danger half the time get there after about 6.7M steps).
    far = 2**24 + 1
    late = learning_states[0].replace(
        danger_steps=jnp.asarray(far, state.danger_steps.dtype),
        learning_danger_steps=jnp.asarray(far, state.learning_danger_steps.dtype),
    )
    after, danger = iteration_and_its_episode(late)
    assert int(danger) > 0
    assert int(after.danger_steps) == far + int(danger)
    assert int(after.learning_danger_steps) == far + int(danger)


def test_evaluation_runs_the_deterministic_policy(tiny_program):
    """``evaluate`` is the greedy policy's episode metrics (no exploration noise)."""
    program = tiny_program
    state = program.init(jax.random.PRNGKey(3))
    key = jax.random.PRNGKey(7)

    @jax.jit
    def evaluated_and_by_hand(state):
        def metrics(explore):
            def act(obs, step_key):
                return program.learner.act(state.learner, obs, step_key, explore)

            _, episode = run_episode(program.eval_env, program.transform, state.transform, act,
                                     program.learner.discrete, key)
            return episode_metrics(episode)

        return program.evaluate(state, key), metrics(False), metrics(True)

    evaluated, greedy, noisy = evaluated_and_by_hand(state)
    for name, value in evaluated.items():
        np.testing.assert_allclose(value, greedy[name], rtol=1e-6, err_msg=name)
    # Exploration would show: the noisy policy's numbers differ.
    assert not np.isclose(float(noisy["return"]), float(greedy["return"]), rtol=1e-4)


def test_a_run_that_turns_non_finite_is_stopped_with_its_iteration(tiny_program):
    state = tiny_program.init(jax.random.PRNGKey(0))
    # Finite but enormous critic weights: the first update overflows to inf and NaN.
    huge = jax.tree_util.tree_map(lambda x: x * 1e20, state.learner.critic)
    state = state.replace(learner=state.learner.replace(critic=huge))
    state, _ = jax.jit(tiny_program.run, static_argnums=1)(state, TINY.num_iterations)
    bad = int(state.nonfinite_iteration)
    assert bad >= 1  # the first iteration only fills the buffer
    # The parameters kept are the last finite ones.
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(state.learner))
    with pytest.raises(NonFiniteTraining, match=f"iteration {bad}"):
        tiny_program.raise_if_nonfinite(state)


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"algo": "ppo"}, "algo"),
        ({"scenario": "lava"}, "scenario"),
        ({"variant": "optimistic"}, "variant"),
        ({"num_envs": 0}, "num_envs"),
        ({"total_env_steps": -5}, "total_env_steps"),
        ({"learner": "big"}, "learner"),
        ({"transform": "soft"}, "transform"),
        ({"scenario_params": {"max_force": -1.0}}, "max_force"),
        ({"num_robots": 1}, "num_robots"),
        ({"episode_length": 0}, "episode_length"),
    ],
)
def test_bad_config_is_refused_before_anything_compiles(changes, field):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(TINY, **changes)


@pytest.mark.parametrize("penalty", [-1.0, float("nan")])
def test_a_bad_penalty_is_refused_by_the_pessimistic_transform(penalty):
    with pytest.raises(ValueError, match="penalty"):
        Pessimistic(penalty=penalty)


def test_a_config_is_not_rewritten_and_says_what_it_uses():
    config = TrainConfig(algo="iddpg", variant="pessimistic")
    assert (config.total_env_steps, config.learner, config.transform) == (None, None, None)
    assert config.budget == default_budgets()["iddpg"] == 400_000
    assert config.resolved_learner == DDPGConfig(centralised_critic=False)
    assert config.resolved_transform == Pessimistic()
    again = config_from_dict(config_to_dict(config))
    assert again == config
    explicit = dataclasses.replace(config, transform=Pessimistic(penalty=3.0),
                                   learner=DDPGConfig(batch_size=64))
    assert config_from_dict(json.loads(json.dumps(config_to_dict(explicit)))) == explicit


def test_a_budget_that_ends_before_learning_starts_is_refused():
    """Learning starts after an absolute number of transitions per seed (25,600 by default,
    whatever the learner, batch or episode length); a budget that never gets there is
    refused, naming --steps and the minimum: the first whole iteration at which the buffer
    holds ``learning_starts`` transitions."""
    default = TrainConfig(algo="iddpg", scenario="nominal")
    assert default.learning_starts == 25_600
    assert dataclasses.replace(default, episode_length=50).learning_starts == 25_600
    assert default.min_total_env_steps == 25_600  # 8 envs x 25 steps divides 25,600
    with pytest.raises(ValueError, match=r"\(--steps\) 20,000 ends before learning starts: "
                                         r"at least 25,600"):
        TrainConfig(algo="maddpg", total_env_steps=20_000)
    with pytest.raises(ValueError, match="at least 25,680"):  # 107 iterations of 8 x 30
        TrainConfig(algo="maac", total_env_steps=25_600, episode_length=30)
    assert TrainConfig(total_env_steps=25_600).min_total_env_steps == 25_600
    # The tiny configuration of these tests learns from its 80th transition.
    assert TINY.min_total_env_steps <= TINY.total_env_steps
    with pytest.raises(ValueError, match="--steps"):
        make_train(dataclasses.replace(TINY, learning_starts=10 * TINY.total_env_steps))


def test_rounded_budgets_are_reported_not_hidden():
    """A budget or evaluation interval that is not a whole number of iterations runs rounded,
    and the schedule says what was asked, what runs, and why."""
    config = TrainConfig(algo="maddpg", total_env_steps=30_000, eval_every=4_900)
    schedule = config.schedule()
    assert schedule["requested"] == {"total_env_steps": 30_000, "eval_every": 4_900}
    # 8 envs x 25 steps = 200 per iteration: 4,900 -> 24 iterations = 4,800; 30,000 ->
    # 150 iterations -> 7 intervals of 24 = 168 iterations = 33,600.
    assert schedule["ran"] == {"total_env_steps": 33_600, "eval_every": 4_800}
    assert len(schedule["notes"]) == 2
    assert "--eval-every 4,900 runs as 4,800" in schedule["notes"][0]
    assert "--steps 30,000 runs as 33,600" in schedule["notes"][1]
    exact = TrainConfig(algo="maddpg", total_env_steps=40_000, eval_every=20_000).schedule()
    assert exact["notes"] == [] and exact["ran"] == exact["requested"]


def test_the_non_finite_report_names_the_earliest_iteration_and_its_seed():
    assert first_nonfinite(np.array([-1, -1]), [3, 4]) is None
    assert first_nonfinite(np.array([-1, 9, 5, 5]), [10, 11, 12, 13]) == NonFinite(5, 12)
    # As training hands it over: int32 on the device, a run that stayed finite first.
    iterations = jnp.array([-1, 9, 5, 5], dtype=jnp.int32)
    assert first_nonfinite(iterations, [10, 11, 12, 13]) == NonFinite(5, 12)
    assert "iteration 5 (seed 12)" in NonFinite(5, 12).message()


@pytest.mark.slow  # two training programs compiled
def test_a_run_is_the_first_part_of_a_longer_run_once_the_budget_fills_the_buffer():
    """With the replay capacity reached (the learner's ``buffer_size`` below the budget),
    nothing else in a run depends on its budget: a run's evaluations are those of a run
    twice as long at the same steps (what lets a smaller budget be read off longer runs'
    evaluations, docs/protocol.md, amendment of 2026-12-02)."""
    base = dict(algo="iddpg", scenario="turbulence", variant="ccr", num_envs=4,
                learning_starts=200, eval_every=200, eval_episodes=4, episode_length=25,
                learner=DDPGConfig(buffer_size=400, batch_size=32))
    short = TrainConfig(total_env_steps=600, **base)
    long = TrainConfig(total_env_steps=1200, **base)
    assert short.replay_capacity == long.replay_capacity == 400
    _, short_history = jax.jit(make_train(short).train)(jax.random.PRNGKey(1), None)
    _, long_history = jax.jit(make_train(long).train)(jax.random.PRNGKey(1), None)
    for name, values in short_history.items():
        values = np.asarray(values)
        np.testing.assert_array_equal(values, np.asarray(long_history[name])[: values.shape[0]],
                                      err_msg=name)
