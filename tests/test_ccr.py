"""Tests of CCR (:mod:`ccrjax.transforms.ccr`): intrinsic reward, shared and smoothed scores, the
learned dynamics model on every scenario, the transform, its configuration, training.

Arrays are batch-last, as in the environment: per robot ``[N, E]``, positions ``[N, 2, E]``.
Compiling costs seconds on a 2-core CPU: the rollouts are compiled once per scenario
(module-scoped fixtures) and the small arithmetic tests run eagerly.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.envs.env import EmergencyEnv
from ccrjax.training import TrainConfig, make_train
from ccrjax.training.acting import run_episode, to_batch_major_obs, to_env_action
from ccrjax.transforms.ccr import (
    CCR,
    CCRConfig,
    CCRState,
    accumulate,
    command_vector,
    fit,
    init_coefficients,
    init_statistics,
    intrinsic_reward,
    polynomial_features,
    predict_targets,
    shared_scores,
)


def column(*values):
    """A per-robot array ``[N, 1]`` (one environment)."""
    return jnp.asarray(values, jnp.float32)[:, None]


def points(*xy):
    """Positions ``[N, 2, 1]`` (one environment)."""
    return jnp.asarray(xy, jnp.float32)[:, :, None]


# ---------------------------------------------------------------- intrinsic reward
# Three robots at t: p0 = (0, 0), p1 = (1, 0), p2 = (0, 2); scores E = (0.1, 0.5, 0.3).
# At t+1 robot 0 is at (0.5, 0), robot 1 at (1, 1), robot 2 has not moved. lam = 2.
SCORES = column(0.1, 0.5, 0.3)
POSITION = points((0.0, 0.0), (1.0, 0.0), (0.0, 2.0))
NEXT_POSITION = points((0.5, 0.0), (1.0, 1.0), (0.0, 2.0))
LAM = 2.0


def test_intrinsic_reward_by_hand_all_in_range():
    reward = intrinsic_reward(SCORES, POSITION, NEXT_POSITION, comm_range=10.0, lam=LAM)
    # Robot 0. j = 1: d = 1, d' = |(0.5, 0) - (1, 0)| = 0.5, h = -0.5, E1 - E0 = 0.4:
    #   0.4 * -0.5 / (1 + 1) = -0.1.
    # j = 2: d = 2, d' = |(0.5, 0) - (0, 2)| = sqrt(4.25), h = sqrt(4.25) - 2, E2 - E0 = 0.2:
    #   0.2 * (sqrt(4.25) - 2) / (1 + 2).
    robot0 = LAM * (-0.1 + 0.2 * (math.sqrt(4.25) - 2.0) / 3.0)
    # Robot 1. j = 0: d = 1, d' = |(1, 1) - (0, 0)| = sqrt(2), E0 - E1 = -0.4:
    #   -0.4 * (sqrt(2) - 1) / 2.
    # j = 2: d = |(1, 0) - (0, 2)| = sqrt(5), d' = |(1, 1) - (0, 2)| = sqrt(2), E2 - E1 = -0.2:
    #   -0.2 * (sqrt(2) - sqrt(5)) / (1 + sqrt(5)).
    robot1 = LAM * (
        -0.4 * (math.sqrt(2) - 1.0) / 2.0
        - 0.2 * (math.sqrt(2) - math.sqrt(5)) / (1.0 + math.sqrt(5))
    )
    # Robot 2 did not move: every h is 0.
    np.testing.assert_allclose(reward[:, 0], [robot0, robot1, 0.0], rtol=1e-5, atol=1e-7)
    # The second pair of each robot matters (it is not lost under the tolerance).
    assert abs(robot0 - LAM * -0.1) > 1e-3
    assert abs(robot1 - LAM * -0.4 * (math.sqrt(2) - 1.0) / 2.0) > 1e-3


def test_intrinsic_reward_by_hand_one_pair_in_range():
    # comm_range 1.5: only the pair (0, 1) (distance 1) can talk; |p0 - p2| = 2 and
    # |p1 - p2| = sqrt(5) are out of range and contribute nothing.
    reward = intrinsic_reward(SCORES, POSITION, NEXT_POSITION, comm_range=1.5, lam=LAM)
    expected = [LAM * -0.1, LAM * -0.4 * (math.sqrt(2) - 1.0) / 2.0, 0.0]
    np.testing.assert_allclose(reward[:, 0], expected, rtol=1e-5, atol=1e-7)
    # Whatever the out-of-range robot's score, nothing changes.
    hot = SCORES.at[2, 0].set(1e6)
    np.testing.assert_array_equal(
        intrinsic_reward(hot, POSITION, NEXT_POSITION, comm_range=1.5, lam=LAM), reward
    )


def test_intrinsic_reward_signs():
    # Robot 1 sits at (1, 0); robot 0 starts at (0, 0) and moves 0.1 along x, either away
    # (to -0.1) or towards (to +0.1); robot 1's score is either higher or lower. Environments:
    # [away & j higher, towards & j higher, away & j lower, towards & j lower].
    position = jnp.asarray([[[0.0] * 4, [0.0] * 4], [[1.0] * 4, [0.0] * 4]], jnp.float32)
    step_x = jnp.asarray([-0.1, 0.1, -0.1, 0.1], jnp.float32)
    next_position = position.at[0, 0].add(step_x)
    score = jnp.asarray([[0.1, 0.1, 0.9, 0.9], [0.9, 0.9, 0.1, 0.1]], jnp.float32)
    reward = np.asarray(intrinsic_reward(score, position, next_position, 2.0, 30.0))
    np.testing.assert_array_equal(np.sign(reward[0]), [1.0, -1.0, -1.0, 1.0])
    # Robot 1 did not move, so its reward is zero; lam = 0 switches everything off.
    np.testing.assert_array_equal(reward[1], 0.0)
    zero = intrinsic_reward(score, position, next_position, 2.0, 0.0)
    np.testing.assert_array_equal(zero, 0.0)


def test_shared_scores_order_and_range():
    # Four robots on the x axis at 0, 0.5, 3, 0.9; comm_range 1: robots 0, 1, 3 talk,
    # robot 2 talks to nobody.
    smoothed = column(1.0, 2.0, 3.0, 4.0)
    position = points((0.0, 0.0), (0.5, 0.0), (3.0, 0.0), (0.9, 0.0))
    shared = np.asarray(shared_scores(smoothed, position, 1.0))[:, :, 0]
    # Row i lists robots j != i in increasing order (the env's other-robot order).
    np.testing.assert_array_equal(
        shared,
        [
            [2.0, 0.0, 4.0],  # robot 0 sees 1, (2 out of range), 3
            [1.0, 0.0, 4.0],  # robot 1 sees 0, (2), 3 (|0.5 - 0.9| = 0.4)
            [0.0, 0.0, 0.0],  # robot 2 is 2.1 from the nearest
            [1.0, 2.0, 0.0],  # robot 3 sees 0 (0.9), 1, (2)
        ],
    )


# ---------------------------------------------------------------- dynamics model
def test_features_and_discrete_commands():
    x = jnp.asarray([2.0, 3.0, 5.0, 7.0])[None, :, None]
    features = np.asarray(polynomial_features(x, 2))[0, :, 0]
    np.testing.assert_array_equal(
        features, [1, 2, 3, 5, 7, 4, 6, 10, 14, 9, 15, 21, 25, 35, 49]
    )
    assert polynomial_features(x, 5).shape == (1, 126, 1)
    # Discrete commands are the action set's entries in {-1, 0, 1}^2: the default box9...
    command = np.asarray(command_vector(jnp.arange(9, dtype=jnp.int32)[None], True))
    np.testing.assert_array_equal(command[0].T, [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1],
                                                 [-1, -1], [-1, 1], [1, -1], [1, 1]])
    # ... or the MPE's five: none, -x, +x, -y, +y.
    command = np.asarray(command_vector(jnp.arange(5, dtype=jnp.int32)[None], True, "mpe5"))
    np.testing.assert_array_equal(command[0].T, [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]])
    # Continuous commands are clipped like the simulator clips them.
    clipped = command_vector(jnp.asarray([[[2.0], [-0.5]]]), False)
    np.testing.assert_array_equal(clipped[0, :, 0], [1.0, -0.5])


def test_fit_recovers_a_quadratic_law_and_means_accumulate_in_any_order():
    rng = np.random.default_rng(0)
    inputs = jnp.asarray(rng.uniform(-1, 1, (4, 4, 50)), jnp.float32)
    x = np.asarray(inputs)
    targets = np.stack(
        [0.1 * x[:, 0], 0.1 * x[:, 1] + 0.3 * x[:, 0] * x[:, 2],
         0.75 * x[:, 0] + 0.5 * x[:, 2], 0.75 * x[:, 1] + 0.5 * x[:, 3] - 0.2],
        axis=1,
    )
    targets = jnp.asarray(targets, jnp.float32)

    @jax.jit
    def statistics_and_fit(inputs, targets):
        coefficients = init_coefficients(2)
        together = accumulate(init_statistics(2), coefficients, inputs, targets, 1e-3)
        first = accumulate(
            init_statistics(2), coefficients, inputs[..., :20], targets[..., :20], 1e-3
        )
        both = accumulate(first, coefficients, inputs[..., 20:], targets[..., 20:], 1e-3)
        fitted = fit(together, 1e-6)
        return together, both, predict_targets(fitted, inputs), fit(init_statistics(2), 1e-4)

    together, both, predicted, unfitted = statistics_and_fit(inputs, targets)
    for a, b in zip(jax.tree.leaves(together), jax.tree.leaves(both), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(predicted, targets, atol=2e-3)
    np.testing.assert_array_equal(unfitted, 0.0)  # no data: no model


FIT_ENVS, FIT_LENGTH, FIT_EPISODES = 16, 30, 4


def drift_actions(obs, key):
    """Uniform random forces with +0.6 added along x (clipped), so that robots reach the
    hazard, which lies about one unit ahead, within an episode."""
    num_envs, num_robots, _ = obs.shape
    u = jax.random.uniform(key, (num_envs, num_robots, 2), minval=-1.0, maxval=1.0)
    return jnp.clip(u + jnp.asarray([0.6, 0.0]), -1.0, 1.0)


def random_actions(obs, key):
    """Uniform random forces: the learners' warm-up, on which training first fits the model."""
    num_envs, num_robots, _ = obs.shape
    return jax.random.uniform(key, (num_envs, num_robots, 2), minval=-1.0, maxval=1.0)


@pytest.fixture(scope="module")
def fitted_rollouts():
    """Per scenario: the model fitted on FIT_EPISODES episodes of the scenario's own
    random-action transitions (as in training, whose first transitions are the warm-up's
    random actions), then one episode of random-drift transitions, which reach the hazard,
    and its raw scores (window m = 0)."""
    results = {}
    for scenario in ("nominal", "turbulence", "strong_wind", "hidden_obstacle"):
        env = EmergencyEnv(scenario, num_envs=FIT_ENVS, episode_length=FIT_LENGTH)
        transform = CCR(CCRConfig(window=0))
        state = transform.init(env)
        episode_fn = jax.jit(
            lambda state, key, act, env=env, transform=transform: run_episode(
                env, transform, state, act, False, key
            ),
            static_argnums=2,
        )
        keys = jax.random.split(jax.random.PRNGKey(0), FIT_EPISODES + 1)
        for key in keys[:-1]:
            state, _ = episode_fn(state, key, random_actions)
        state, episode = episode_fn(state, keys[-1], drift_actions)
        raw = np.asarray(episode.info["emergency_score"])  # [T, N, E]: transition t -> t+1
        position = np.asarray(episode.position)  # [T + 1, N, 2, E]
        gap = np.linalg.norm(position[:-1, None] - position[:-1, :, None], axis=3)
        gap = gap + 10.0 * np.eye(env.num_robots)[None, :, :, None]
        contact_free = gap.min(axis=2) > 2 * env.robot_radius + 0.02  # at t, no neighbour near
        danger_after = np.asarray(episode.danger) > 0  # at t + 1
        danger_before = np.concatenate([np.zeros_like(danger_after[:1]), danger_after[:-1]])
        results[scenario] = {
            "raw": raw,
            # The hazard acts on a robot at its position at t: in danger before and after.
            "hazard": danger_before & danger_after,
            "safe": contact_free & ~danger_before & ~danger_after,
        }
    return results


def test_fitted_model_predicts_nominal_motion(fitted_rollouts):
    nominal = fitted_rollouts["nominal"]
    errors = nominal["raw"][nominal["safe"]]
    assert errors.size > 1000
    assert errors.mean() < 1e-5, errors.mean()
    assert np.quantile(errors, 0.99) < 1e-4


@pytest.mark.parametrize("scenario", ["turbulence", "strong_wind", "hidden_obstacle"])
def test_hazards_stand_out(fitted_rollouts, scenario):
    rollout = fitted_rollouts[scenario]
    nominal = fitted_rollouts["nominal"]
    hazard = rollout["raw"][rollout["hazard"]]
    assert hazard.size > 50, "the rollout should reach the hazard"
    assert hazard.mean() > 100 * nominal["raw"][nominal["safe"]].mean()
    # The robust weights keep the hazards out of the fit: safe robots of the same scenario
    # stay predictable (with plain least squares, wind and obstacle fail this).
    assert hazard.mean() > 1000 * rollout["raw"][rollout["safe"]].mean()


# ---------------------------------------------------------------- the transform
def fake_state(position, velocity, num_envs=4):
    """An env state with only what CCR reads: obs [N, F, E] of the nominal 2-robot env
    (F = 10: position and velocity in features 0:4, the other robot's distance and
    direction in 4:7), the same in every environment, and a zero reward."""
    obs = np.zeros((2, 10, num_envs), np.float32)
    position = np.asarray(position, np.float32)
    obs[:, 0:2] = position[:, :, None]
    obs[:, 2:4] = np.asarray(velocity, np.float32)[:, :, None]
    for i, j in ((0, 1), (1, 0)):  # the other robot's distance and direction (features 4:7)
        rel = position[j] - position[i]
        distance = float(np.linalg.norm(rel))
        obs[i, 4] = distance
        obs[i, 5:7] = (rel / distance if distance > 0 else 0.0)[:, None]
    return State(pipeline_state=None, obs=jnp.asarray(obs), reward=jnp.zeros((2, num_envs)),
                 done=jnp.zeros((num_envs,)), metrics={}, info={})


def test_rolling_mean_restarts_with_each_episode():
    env = EmergencyEnv("nominal", num_robots=2, num_envs=4, discrete_actions=True)
    transform = CCR(CCRConfig(window=2, comm_range=1.0))  # mean over m + 1 = 3 steps
    position = [[0.0, 0.0], [0.5, 0.0]]  # in range of each other, never moving
    action = jnp.zeros((2, 4), jnp.int32)  # "none"

    def episode(state, speeds):
        # With no statistics the fitted model is C = 0: it predicts s_hat = (p_t, 0), so
        # robot 0's raw score is its observed speed squared (robot 1 stays at rest).
        state = state.replace(statistics=init_statistics(2))
        env_state = fake_state(position, [[0.0, 0.0], [0.0, 0.0]])
        state, obs = transform.start_episode(state, env_state)
        np.testing.assert_array_equal(obs[:, 10:], 0.0)  # no transition yet: score 0
        smoothed, shown = [], []
        for speed in speeds:
            next_env_state = fake_state(position, [[speed, 0.0], [0.0, 0.0]])
            state, obs, _, info = transform.step(state, env_state, action, next_env_state)
            smoothed.append(float(info["emergency_score"][0, 0]))
            assert float(info["emergency_score"][1, 0]) == 0.0
            shown.append(float(obs[1, 10, 0]))  # robot 1's only other robot is robot 0
            env_state = next_env_state
        return transform.end_episode(state), smoothed, shown

    state = transform.init(env)
    state, smoothed, shown = episode(state, [1.0, 2.0, 3.0, 4.0, 5.0])  # raw 1, 4, 9, 16, 25
    expected = [1.0, (1 + 4) / 2, (1 + 4 + 9) / 3, (4 + 9 + 16) / 3, (9 + 16 + 25) / 3]
    np.testing.assert_allclose(smoothed, expected, rtol=1e-6)
    np.testing.assert_allclose(shown, expected, rtol=1e-6)
    # The next episode's window holds nothing of the last one (16, 25 would leak in).
    state, smoothed, _ = episode(state, [10.0, 1.0, 2.0, 0.0])  # raw 100, 1, 4, 0
    np.testing.assert_allclose(
        smoothed, [100.0, (100 + 1) / 2, (100 + 1 + 4) / 3, (1 + 4 + 0) / 3], rtol=1e-6
    )
    assert isinstance(state, CCRState)  # the state between episodes, one structure


# 48 transitions per episode: enough that the fit is well posed (15 features), so that
# float32 rounding differences between jit and no jit are not amplified by the solve.
TINY_ENV = dict(num_robots=2, num_envs=4, episode_length=6, discrete_actions=True)


def random_discrete_actions(obs, key):
    return jax.random.randint(key, obs.shape[:2], 0, 9, jnp.int32)


def unjitted_episode(env, transform, state, act, key):
    """:func:`ccrjax.training.acting.run_episode` written out step by step: the transform runs
    op by op (no jit), the environment through its own jitted reset and transition."""
    reset, transition = jax.jit(env.reset), jax.jit(env.transition)
    reset_key, key = jax.random.split(key)
    env_state = reset(reset_key)
    state, obs = transform.start_episode(state, env_state)
    steps = []
    for step_key in jax.random.split(key, env.episode_length):
        action = act(to_batch_major_obs(obs), step_key)
        env_action = to_env_action(action, env.discrete_actions)
        next_env_state = transition(env_state, env_action)
        state, next_obs, reward, info = transform.step(
            state, env_state, env_action, next_env_state
        )
        steps.append({"obs": obs, "next_obs": next_obs, "reward": reward, "info": info})
        env_state, obs = next_env_state, next_obs
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *steps)
    return transform.end_episode(state), stacked


@pytest.fixture(scope="module")
def discrete_episodes():
    """Two episodes of a tiny discrete-action env through CCR, jitted and without jit;
    the first trains the model, the second runs with the fitted model."""
    env = EmergencyEnv("nominal", **TINY_ENV)
    # Thresholds low enough that the well-fitted second episode (scores ~1e-7) shows
    # every colour.
    transform = CCR(CCRConfig(sensing_threshold=1e-7, activation_threshold=1e-7))

    @jax.jit
    def two_episodes(key):
        first_key, second_key = jax.random.split(key)
        state, first = run_episode(
            env, transform, transform.init(env), random_discrete_actions, True, first_key
        )
        state, second = run_episode(
            env, transform, state, random_discrete_actions, True, second_key
        )
        return state, (first, second)

    # On the CPU, where op by op and jitted agree to rounding: on a GPU the moment sums
    # may be summed in another order alone than fused, and the model's solve amplifies a
    # 1-ulp difference in the statistics past these tolerances. What is tested is jit.
    with jax.default_device(jax.devices("cpu")[0]):
        key = jax.random.PRNGKey(3)
        jitted = two_episodes(key)
        first_key, second_key = jax.random.split(key)
        state, first = unjitted_episode(
            env, transform, transform.init(env), random_discrete_actions, first_key
        )
        state, second = unjitted_episode(env, transform, state, random_discrete_actions,
                                         second_key)
    return env, transform, jitted, (state, (first, second))


def test_jit_equals_no_jit(discrete_episodes):
    _, _, (state, episodes), (reference_state, reference_episodes) = discrete_episodes
    # Statistics agree to float32 rounding; the solve amplifies that to ~1e-6 on the
    # coefficients (of order 1), the well-fitted scores (~1e-7) differ by ~3e-9.
    for a, b in zip(
        jax.tree.leaves(state), jax.tree.leaves(reference_state), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)
    for episode, reference in zip(episodes, reference_episodes, strict=True):
        for name in ("emergency_score", "intrinsic_reward"):
            np.testing.assert_allclose(
                episode.info[name], reference["info"][name], rtol=1e-4, atol=1e-8
            )
        for name in ("obs", "next_obs"):
            np.testing.assert_allclose(
                getattr(episode.transitions, name),
                np.transpose(reference[name], (0, 3, 1, 2)), rtol=1e-4, atol=1e-8,
            )
        np.testing.assert_allclose(
            episode.transitions.reward, np.transpose(reference["reward"], (0, 2, 1)),
            rtol=1e-4, atol=1e-6,
        )
    assert isinstance(state, CCRState)  # what is kept between episodes does not depend on E
    assert float(state.statistics.total_weight) > 0
    assert np.any(np.asarray(state.coefficients) != 0)


@pytest.mark.parametrize("which", [0, 1])
def test_transform_wires_scores_rewards_and_states(discrete_episodes, which):
    env, transform, (_, episodes), _ = discrete_episodes
    episode = episodes[which]
    config = transform.config
    info = {name: np.asarray(value) for name, value in episode.info.items()}
    score = info["emergency_score"]  # [T, N, E]: E_{t+1}
    previous = np.concatenate([np.zeros_like(score[:1]), score[:-1]])  # E_t, 0 at reset
    position = episode.position  # [T + 1, N, 2, E]
    for t in range(env.episode_length):
        expected = intrinsic_reward(
            previous[t], position[t], position[t + 1], config.comm_range, config.lam
        )
        np.testing.assert_allclose(info["intrinsic_reward"][t], expected, rtol=1e-5, atol=1e-6)
        shared = shared_scores(score[t], position[t + 1], config.comm_range)
        next_obs = np.asarray(episode.transitions.next_obs[t])  # [E, N, F + N - 1]
        np.testing.assert_allclose(
            np.moveaxis(next_obs[:, :, env.observation_size:], 0, -1), shared, rtol=1e-6
        )
    reward = np.asarray(episode.transitions.reward)  # [T, E, N]
    np.testing.assert_allclose(
        np.moveaxis(reward, 1, 2), np.asarray(episode.env_reward) + info["intrinsic_reward"],
        rtol=1e-5, atol=1e-6,
    )
    sensing = score > config.sensing_threshold
    activated = ~sensing & (np.abs(info["intrinsic_reward"]) > config.activation_threshold)
    expected_state = np.where(sensing, 1, np.where(activated, 2, 0))
    np.testing.assert_array_equal(info["ccr_state"], expected_state)
    assert info["ccr_state"].dtype == np.int32
    if which == 1:
        assert set(np.unique(expected_state)) == {0, 1, 2}, "every colour should occur"


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    "changes, field",
    [
        ({"lam": -1.0}, "lam"),
        ({"lam": float("nan")}, "lam"),
        ({"lam": float("inf")}, "lam"),
        ({"lam": True}, "lam"),
        ({"window": -1}, "window"),
        ({"window": 2.0}, "window"),
        ({"window": True}, "window"),
        ({"comm_range": -0.5}, "comm_range"),
        ({"comm_range": float("nan")}, "comm_range"),
        ({"degree": 0}, "degree"),
        ({"degree": 6}, "degree"),
        ({"degree": True}, "degree"),
        ({"ridge": 0.0}, "ridge"),
        ({"ridge": float("inf")}, "ridge"),
        ({"tolerance": 0.0}, "tolerance"),
        ({"sensing_threshold": -1.0}, "sensing_threshold"),
        ({"activation_threshold": 0.0}, "activation_threshold"),
    ],
)
def test_bad_ccr_config_is_refused(changes, field):
    with pytest.raises(ValueError, match=f"CCRConfig.{field} "):
        CCRConfig(**changes)


def test_ccr_config_in_training_config_and_vmapped_lambdas():
    config = TrainConfig(variant="ccr", transform=CCR(CCRConfig(window=2)))
    program = make_train(config)
    assert isinstance(program.transform, CCR) and program.transform.config.window == 2
    assert program.obs_size == program.env.observation_size + config.num_robots - 1
    with pytest.raises(ValueError, match="transform of variant 'ccr' must be a CCR"):
        TrainConfig(variant="ccr", transform={"lam": 1.0})
    with pytest.raises(ValueError, match="learner of algo 'maddpg' must be a DDPGConfig"):
        TrainConfig(variant="ccr", learner=CCRConfig())
    env = program.env
    lams = jnp.asarray([0.0, 10.0, 30.0])
    states = jax.vmap(lambda lam: program.transform.init(env, {"lam": lam}))(lams)
    np.testing.assert_array_equal(states.params["lam"], lams)
    assert states.statistics.feature_moment.shape == (3, 15, 15)
    assert states.statistics.target_moment.shape == (3, 15, 4)
    assert states.coefficients.shape == (3, 15, 4)
    with pytest.raises(ValueError, match="unknown transform parameter"):
        program.transform.init(env, {"penalty": 1.0})


TINY_CCR = TrainConfig(
    algo="maddpg",
    scenario="strong_wind",
    variant="ccr",
    num_robots=3,
    num_envs=2,
    episode_length=10,
    total_env_steps=60,
    eval_every=20,
    eval_episodes=3,
    learning_starts=20,
    learner=DDPGConfig(batch_size=16, actor_hidden=(8,), critic_hidden=(8,), update_every=10),
)


def test_training_with_ccr_end_to_end():
    program = make_train(TINY_CCR)
    train = jax.jit(program.train)
    key = jax.random.PRNGKey(0)
    results = {lam: train(key, {"lam": lam}) for lam in (0.0, 30.0)}
    for state, history in results.values():
        assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(history))
        assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.transform))
        assert isinstance(state.transform, CCRState)
        assert float(state.transform.statistics.total_weight) > 0
        program.raise_if_nonfinite(state)

    def stored_and_env_rewards(state):
        # The env reward is -|p - destination|, which is also an observation feature
        # (the destination distance, after position, velocity and the other robots).
        buffer, held = state.buffer, int(state.buffer.episodes)
        goal_distance = 4 + 3 * (TINY_CCR.num_robots - 1)
        next_obs = np.asarray(buffer.obs[:held, 1:])  # [episodes, T, N, F]
        return np.asarray(buffer.reward[:held]), -next_obs[..., goal_distance]

    stored, env_reward = stored_and_env_rewards(results[0.0][0])
    np.testing.assert_allclose(stored, env_reward, rtol=1e-6, atol=1e-6)
    stored, env_reward = stored_and_env_rewards(results[30.0][0])
    assert not np.allclose(stored, env_reward, atol=1e-4), "lam = 30 should shape rewards"
