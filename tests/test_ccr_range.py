"""CCR in the code path training runs (:meth:`ccrjax.transforms.ccr.CCR.step`), robots placed
by hand.

Four robots in two environments, some pairs within communication range and some out of it
(robot 3 of environment 0 is out of everyone's range). The model is unfitted (no
statistics: coefficients 0), so it predicts ``s_hat_{t+1} = (p_t, 0)`` and the raw score of
a transition is ``|p_{t+1} - p_t|^2 + |v_{t+1}|^2``: by choosing the states we choose scores
of order one. Three steps through the transform are compared with hand-computed smoothed
scores and with the reference definitions :func:`ccrjax.transforms.ccr.shared_scores` and
:func:`ccrjax.transforms.ccr.intrinsic_reward` (from positions), at a tolerance relative to the
values.
Each step also checks that the fixture is sensitive: the same references with the range
ignored give clearly different numbers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.envs.env import EmergencyEnv
from ccrjax.transforms.ccr import CCR, CCRConfig, intrinsic_reward, shared_scores

COMM_RANGE = 1.0
WINDOW = 1  # the rolling mean runs over m + 1 = 2 transitions
LAM = 20.0
RTOL = 1e-5

# Positions at t = 0, [N, 2, E]. Environment 0: robots 0, 1, 2 close (0-1 at 0.7, 0-2 at 0.78),
# 1-2 at 1.34 (out of range), robot 3 far from everyone. Environment 1: 0-1, 0-3, 1-3 in
# range, robot 2 out of everyone's range.
START = np.array(
    [
        [[0.0, 1.0], [0.0, 1.0]],
        [[0.7, 1.2], [0.0, 1.5]],
        [[-0.5, 3.0], [0.6, 1.0]],
        [[2.5, 1.5], [-0.4, 0.6]],
    ],
    np.float64,
)
# Per-step displacement p_{t+1} - p_t, and the velocity observed at t + 1 ([N, 2, E]).
DISPLACEMENT = np.array(
    [
        [[0.20, -0.10], [0.05, 0.10]],
        [[-0.10, 0.05], [0.15, -0.20]],
        [[0.05, 0.10], [-0.20, 0.05]],
        [[0.10, -0.15], [0.10, 0.15]],
    ],
    np.float64,
)
VELOCITY = np.array(
    [
        [[1.0, -0.4], [0.0, 0.6]],
        [[0.0, 0.9], [-0.5, 0.3]],
        [[0.3, 0.2], [0.3, -1.1]],
        [[-0.8, 0.5], [0.2, 0.7]],
    ],
    np.float64,
)
STEPS = 3
STEP_SCALE = (1.0, -0.6, 1.4)  # displacement and velocity of step t are scaled by this


def trajectory():
    """Positions ``[STEPS + 1, N, 2, E]`` and velocities (``[STEPS + 1]``, zero at t = 0)."""
    position, velocity = [START], [np.zeros_like(START)]
    for scale in STEP_SCALE:
        position.append(position[-1] + scale * DISPLACEMENT)
        velocity.append(scale * VELOCITY)
    return np.stack(position), np.stack(velocity)


@pytest.fixture(scope="module")
def stepped():
    """The transform's outputs for the three steps: next observations, rewards, info."""
    env = EmergencyEnv("nominal", num_robots=4, num_envs=2, episode_length=10)
    transform = CCR(CCRConfig(window=WINDOW, comm_range=COMM_RANGE, lam=LAM))
    reset = env.reset(jax.random.PRNGKey(0))
    position, velocity = trajectory()

    def env_state(t: int):
        world = reset.pipeline_state.replace(
            position=jnp.asarray(position[t], jnp.float32),
            velocity=jnp.asarray(velocity[t], jnp.float32),
        )
        return reset.replace(pipeline_state=world, obs=env.observe(world),
                             reward=env.reward(world))

    states = [env_state(t) for t in range(STEPS + 1)]
    ccr_state, first_obs = jax.jit(transform.start_episode)(transform.init(env), states[0])
    step = jax.jit(transform.step)
    action = jnp.zeros((4, 2, 2), jnp.float32)
    outputs = []
    for t in range(STEPS):
        ccr_state, obs, reward, info = step(ccr_state, states[t], action, states[t + 1])
        outputs.append({"obs": np.asarray(obs), "reward": np.asarray(reward),
                        "env_reward": np.asarray(states[t + 1].reward),
                        "info": {k: np.asarray(v) for k, v in info.items()}})
    return env, np.asarray(first_obs), outputs, position


def smoothed_scores_by_hand():
    """``E_{t+1}`` for t = 0, 1, 2: the mean of the last ``m + 1 = 2`` raw scores."""
    position, velocity = trajectory()
    raw = [
        np.sum((position[t + 1] - position[t]) ** 2, axis=1)
        + np.sum(velocity[t + 1] ** 2, axis=1)
        for t in range(STEPS)
    ]
    return [np.mean(raw[max(0, t - WINDOW): t + 1], axis=0) for t in range(STEPS)]


def test_fixture_has_pairs_in_and_out_of_range():
    position, _ = trajectory()
    for t in range(STEPS + 1):
        gap = np.linalg.norm(position[t][:, None] - position[t][None], axis=2)  # [N, N, E]
        off = ~np.eye(4, dtype=bool)[:, :, None] & np.ones((1, 1, 2), bool)
        # Clearly in or out (never within 0.05 of the range), and both kinds present.
        assert np.all(np.abs(gap[off] - COMM_RANGE) > 0.05), t
        assert np.any(gap[off] < COMM_RANGE) and np.any(gap[off] > COMM_RANGE)
        assert np.all(gap[3, :3, 0] > COMM_RANGE)  # robot 3 of env 0 talks to nobody


def test_smoothed_scores_are_the_rolling_mean_of_raw_scores(stepped):
    _, first_obs, outputs, _ = stepped
    np.testing.assert_array_equal(first_obs[:, -3:], 0.0)  # no transition yet: nothing shared
    for t, expected in enumerate(smoothed_scores_by_hand()):
        assert np.all(expected > 0.1)  # scores of order one
        np.testing.assert_allclose(outputs[t]["info"]["emergency_score"], expected,
                                   rtol=RTOL, atol=0)


def test_shared_scores_follow_the_range(stepped):
    env, _, outputs, position = stepped
    for t, score in enumerate(smoothed_scores_by_hand()):
        shared = outputs[t]["obs"][:, env.observation_size:]  # [N, N - 1, E]
        reference = np.asarray(shared_scores(jnp.asarray(score, jnp.float32),
                                             jnp.asarray(position[t + 1], jnp.float32),
                                             COMM_RANGE))
        np.testing.assert_allclose(shared, reference, rtol=RTOL, atol=0)
        # By hand: entry [i, k] is robot j's score (j the k-th other robot) or 0.
        for i in range(4):
            others = [j for j in range(4) if j != i]
            for k, j in enumerate(others):
                gap = np.linalg.norm(position[t + 1][i] - position[t + 1][j], axis=0)  # [E]
                np.testing.assert_allclose(shared[i, k], np.where(gap <= COMM_RANGE,
                                                                  score[j], 0.0),
                                           rtol=RTOL, atol=0)
        ignoring_range = np.asarray(shared_scores(jnp.asarray(score, jnp.float32),
                                                  jnp.asarray(position[t + 1], jnp.float32),
                                                  np.inf))
        assert np.max(np.abs(ignoring_range - shared)) > 0.1
        np.testing.assert_array_equal(shared[3, :, 0], 0.0)  # robot 3 of env 0 hears nothing


def test_intrinsic_reward_counts_only_robots_in_range(stepped):
    _, _, outputs, position = stepped
    scores = [np.zeros((4, 2))] + smoothed_scores_by_hand()  # E_t: 0 before any transition
    np.testing.assert_array_equal(outputs[0]["info"]["intrinsic_reward"], 0.0)
    for t in range(1, STEPS):
        got = outputs[t]["info"]["intrinsic_reward"]
        args = (jnp.asarray(scores[t], jnp.float32), jnp.asarray(position[t], jnp.float32),
                jnp.asarray(position[t + 1], jnp.float32))
        reference = np.asarray(intrinsic_reward(*args, COMM_RANGE, LAM))
        np.testing.assert_allclose(got, reference, rtol=RTOL, atol=0)
        # Values of order one where a neighbour is in range, exactly 0 for robot 3 of env 0.
        assert np.sum(np.abs(got) > 0.1) >= 5, got
        np.testing.assert_array_equal(got[3, 0], 0.0)
        ignoring_range = np.asarray(intrinsic_reward(*args, np.inf, LAM))
        assert np.max(np.abs(ignoring_range - got)) > 0.3
        # The learner's reward is the environment's plus the intrinsic reward.
        np.testing.assert_allclose(outputs[t]["reward"], outputs[t]["env_reward"] + got,
                                   rtol=RTOL, atol=0)
