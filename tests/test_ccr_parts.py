"""Tests of CCR's parts taken apart (:mod:`ccrjax.transforms.ccr.parts`): ``ccr_scores``,
``ccr_reward``, ``ccr_perfect`` and ``danger_flags``, against CCR and the reference definitions.

One compiled program runs the environment (turbulence, robots drifting into it) and all five
transforms side by side on the very same transitions, for two episodes (the second with CCR's
model fitted on the first): what a part shares of CCR must be exactly CCR's. The perfect
detector and the danger flags are also checked on states built by hand.
Arrays are batch-last, as in the environment: per robot ``[N, E]``, positions ``[N, 2, E]``.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State

from ccrjax import train
from ccrjax.envs.env import EmergencyEnv
from ccrjax.training import TrainConfig
from ccrjax.training.config import config_from_dict, config_to_dict
from ccrjax.transforms import VARIANTS
from ccrjax.transforms.ccr import (
    CCR,
    CCRConfig,
    CCRPerfect,
    CCRReward,
    CCRScores,
    CCRState,
    DangerFlags,
    intrinsic_reward,
    shared_scores,
)

NUM_ROBOTS, NUM_ENVS, LENGTH = 3, 2, 12
CONFIG = CCRConfig(window=2, lam=7.0)  # the rolling mean runs over m + 1 = 3 steps
FLAGS_RANGE = 0.5  # some pairs of the rollout within it, some beyond
TRANSFORMS = {"ccr": CCR(CONFIG), "ccr_scores": CCRScores(CONFIG),
              "ccr_reward": CCRReward(CONFIG), "ccr_perfect": CCRPerfect(CONFIG),
              "danger_flags": DangerFlags(FLAGS_RANGE)}


@pytest.fixture(scope="module")
def rollouts():
    """Two episodes of every transform on the same transitions; per episode and transform
    the observations ``[T + 1, N, F', E]``, rewards and info ``[T, N, E]``, and the env's
    own observations, rewards, danger flags and positions (``[T + 1]`` where they include
    the reset), and the states between episodes."""
    env = EmergencyEnv("turbulence", num_robots=NUM_ROBOTS, num_envs=NUM_ENVS,
                       episode_length=LENGTH)

    @jax.jit
    def episode(states, key):
        reset_key, key = jax.random.split(key)
        env_state = env.reset(reset_key)
        started = {name: t.start_episode(states[name], env_state)
                   for name, t in TRANSFORMS.items()}

        def step(carry, step_key):
            env_state, inner = carry
            # Uniform forces drifting towards the hazard ahead (+x).
            force = jax.random.uniform(step_key, (NUM_ROBOTS, 2, NUM_ENVS), minval=-1.0)
            action = jnp.clip(force + jnp.asarray([0.8, 0.0])[None, :, None], -1.0, 1.0)
            next_env_state = env.transition(env_state, action)
            out, inner_next = {}, {}
            for name, t in TRANSFORMS.items():
                inner_next[name], obs, reward, info = t.step(
                    inner[name], env_state, action, next_env_state)
                out[name] = (obs, reward, info)
            seen = (next_env_state.obs, next_env_state.reward,
                    next_env_state.metrics["danger"], next_env_state.pipeline_state.position)
            return (next_env_state, inner_next), (out, seen)

        inner = {name: s for name, (s, _) in started.items()}
        (_, inner), (out, seen) = jax.lax.scan(
            step, (env_state, inner), jax.random.split(key, LENGTH))
        ends = {name: t.end_episode(inner[name]) for name, t in TRANSFORMS.items()}
        first = {name: obs for name, (_, obs) in started.items()}
        start_seen = (env_state.obs, env_state.metrics["danger"],
                      env_state.pipeline_state.position)
        return ends, first, out, seen, start_seen

    states = {name: t.init(env) for name, t in TRANSFORMS.items()}
    initial = states
    episodes = []
    for key in jax.random.split(jax.random.PRNGKey(4), 2):
        states, first, out, seen, start_seen = jax.device_get(episode(states, key))
        record = {name: {"obs": np.concatenate([first[name][None], out[name][0]]),
                         "reward": out[name][1], "info": out[name][2]} for name in out}
        record["env"] = {
            "obs": np.concatenate([start_seen[0][None], seen[0]]), "reward": seen[1],
            "danger": np.concatenate([start_seen[1][None], seen[2]]),
            "position": np.concatenate([start_seen[2][None], seen[3]]),
        }
        record["states"] = states
        episodes.append(record)
    return env, initial, episodes


@pytest.mark.parametrize("which", [0, 1])
def test_ccr_scores_observes_as_ccr_with_the_environments_reward(rollouts, which):
    env, _, episodes = rollouts
    episode = episodes[which]
    scores, ccr = episode["ccr_scores"], episode["ccr"]
    assert scores["obs"].shape[2] == env.observation_size + NUM_ROBOTS - 1
    np.testing.assert_array_equal(scores["obs"], ccr["obs"])
    assert np.any(ccr["obs"][:, :, env.observation_size:] > 0)  # scores were shared
    np.testing.assert_array_equal(scores["reward"], episode["env"]["reward"])
    assert not np.allclose(ccr["reward"], episode["env"]["reward"])  # CCR's is shaped
    np.testing.assert_array_equal(scores["info"]["emergency_score"],
                                  ccr["info"]["emergency_score"])
    np.testing.assert_array_equal(scores["info"]["intrinsic_reward"], 0.0)  # none added
    assert set(scores["info"]) == set(ccr["info"])


@pytest.mark.parametrize("which", [0, 1])
def test_ccr_reward_rewards_as_ccr_with_the_environments_observations(rollouts, which):
    _, _, episodes = rollouts
    episode = episodes[which]
    reward, ccr = episode["ccr_reward"], episode["ccr"]
    np.testing.assert_array_equal(reward["reward"], ccr["reward"])
    np.testing.assert_array_equal(reward["obs"], episode["env"]["obs"])
    assert set(reward["info"]) == set(ccr["info"])
    for name in ("emergency_score", "intrinsic_reward", "ccr_state"):
        np.testing.assert_array_equal(reward["info"][name], ccr["info"][name])


@pytest.mark.parametrize("which", [0, 1])
def test_perfect_detector_scores_danger_alone_and_rewards_as_ccr_defines(rollouts, which):
    env, _, episodes = rollouts
    episode = episodes[which]
    perfect, seen = episode["ccr_perfect"], episode["env"]
    danger = seen["danger"][1:]  # [T, N, E]: after each transition
    assert danger.any() and not danger.all(), "the rollout should reach the hazard, not only"
    score = perfect["info"]["emergency_score"]
    m1 = CONFIG.window + 1
    for t in range(LENGTH):  # the rolling mean of the flags since the episode started
        recent = danger[max(0, t + 1 - m1):t + 1]
        np.testing.assert_allclose(score[t], recent.mean(axis=0), rtol=1e-6)
        away = ~recent.any(axis=0)
        np.testing.assert_array_equal(score[t][away], 0.0)  # exactly zero away from danger
        assert np.all(score[t][danger[t] > 0] > 0)
    previous = np.concatenate([np.zeros_like(score[:1]), score[:-1]])  # E_t, 0 at reset
    position = seen["position"]
    for t in range(LENGTH):
        expected = intrinsic_reward(previous[t], position[t], position[t + 1],
                                    CONFIG.comm_range, CONFIG.lam)
        np.testing.assert_allclose(perfect["info"]["intrinsic_reward"][t], expected,
                                   rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(perfect["reward"][t], seen["reward"][t] + expected,
                                   rtol=1e-5, atol=1e-6)
        shared = shared_scores(score[t], position[t + 1], CONFIG.comm_range)
        np.testing.assert_allclose(perfect["obs"][t + 1][:, env.observation_size:], shared,
                                   rtol=1e-6)
    assert np.any(perfect["info"]["intrinsic_reward"] != 0)


def test_perfect_detector_keeps_only_lam_between_episodes(rollouts):
    env, initial, episodes = rollouts
    state = initial["ccr_perfect"]
    assert isinstance(state, CCRState) and state.statistics is None
    assert [np.shape(x) for x in jax.tree.leaves(state)] == [()]  # lam: nothing depends on E
    for episode in episodes:
        after = episode["states"]["ccr_perfect"]
        assert jax.tree.structure(after) == jax.tree.structure(state)
        np.testing.assert_array_equal(after.params["lam"], CONFIG.lam)
    lams = jnp.asarray([0.0, 30.0])  # a run parameter: several values vmap in one program
    states = jax.vmap(lambda lam: TRANSFORMS["ccr_perfect"].init(env, {"lam": lam}))(lams)
    np.testing.assert_array_equal(states.params["lam"], lams)
    assert TRANSFORMS["ccr_scores"].default_params() == {}  # no intrinsic reward: no lam
    with pytest.raises(ValueError, match="unknown transform parameter"):
        TRANSFORMS["ccr_scores"].init(env, {"lam": 1.0})


@pytest.mark.parametrize("which", [0, 1])
def test_danger_flags_are_the_teammates_flags_within_range(rollouts, which):
    env, _, episodes = rollouts
    episode = episodes[which]
    flags, seen = episode["danger_flags"], episode["env"]
    np.testing.assert_array_equal(flags["obs"][:, :, :env.observation_size], seen["obs"])
    np.testing.assert_array_equal(flags["reward"], seen["reward"])
    assert flags["info"] == {}
    position, danger = seen["position"], seen["danger"]  # [T + 1, ...]
    within = beyond = 0
    for t in range(LENGTH + 1):
        for i in range(NUM_ROBOTS):
            others = [j for j in range(NUM_ROBOTS) if j != i]
            for k, j in enumerate(others):
                near = np.linalg.norm(position[t, i] - position[t, j], axis=0) <= FLAGS_RANGE
                expected = np.where(near, danger[t, j], 0.0)
                np.testing.assert_array_equal(flags["obs"][t, i, env.observation_size + k],
                                              expected)
                within += int(np.sum(near & (danger[t, j] > 0)))
                beyond += int(np.sum(~near & (danger[t, j] > 0)))
    assert within > 0 and beyond > 0, "the rollout should share some flags and hold some back"


# ---------------------------------------------------------------- states built by hand
def hand_state(position, danger):
    """An env state with what the transforms read, one environment: observations
    ``[N, F, 1]`` (position, zero velocity, the other robots' distances and directions;
    nominal's ``F``), zero reward, the danger flags ``[N, 1]``."""
    position = np.asarray(position, np.float32)
    num_robots = len(position)
    obs = np.zeros((num_robots, 4 + 3 * (num_robots - 1) + 3, 1), np.float32)
    obs[:, 0:2, 0] = position
    for i in range(num_robots):
        for k, j in enumerate(j for j in range(num_robots) if j != i):
            rel = position[j] - position[i]
            distance = float(np.linalg.norm(rel))
            obs[i, 4 + 3 * k, 0] = distance
            obs[i, 5 + 3 * k:7 + 3 * k, 0] = rel / distance
    return State(pipeline_state=None, obs=jnp.asarray(obs),
                 reward=jnp.zeros((num_robots, 1)), done=jnp.zeros((1,)),
                 metrics={"danger": jnp.asarray(danger, jnp.float32)[:, None]}, info={})


def test_perfect_detector_by_hand():
    # Three robots: 0 and 1 within range (0.6 apart at first), 2 far away. Robot 0 is in
    # danger after the 1st and 2nd transitions only; robot 0 moves along +x, robot 1 along -y.
    env = EmergencyEnv("nominal", num_robots=3, num_envs=1)
    transform = CCRPerfect(CCRConfig(window=2, lam=5.0))
    danger = [[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]
    positions = [np.array([[0.1 * t, 0.0], [0.6, -0.05 * t], [5.0, 5.0]]) for t in range(7)]
    state, obs = transform.start_episode(transform.init(env), hand_state(positions[0], danger[0]))
    np.testing.assert_array_equal(obs[:, env.observation_size:], 0.0)
    action = jnp.zeros((3, 2, 1))
    raw = [flags[0] for flags in danger[1:]]  # robot 0's flag after each transition
    score_before = jnp.zeros((3, 1))
    step = jax.jit(transform.step)  # compiled once: op by op is slower here
    for t in range(6):
        env_state = hand_state(positions[t], danger[t])
        next_env_state = hand_state(positions[t + 1], danger[t + 1])
        state, obs, reward, info = step(state, env_state, action, next_env_state)
        score = np.asarray(info["emergency_score"])
        recent = raw[max(0, t - 2):t + 1]
        np.testing.assert_allclose(score[0, 0], sum(recent) / len(recent), rtol=1e-6)
        np.testing.assert_array_equal(score[1:], 0.0)  # never in danger: exactly zero
        expected = intrinsic_reward(score_before, jnp.asarray(positions[t])[:, :, None],
                                    jnp.asarray(positions[t + 1])[:, :, None], 1.0, 5.0)
        np.testing.assert_allclose(reward, expected, rtol=1e-5, atol=1e-7)
        np.testing.assert_array_equal(obs[1, env.observation_size], score[0, 0])  # shared
        np.testing.assert_array_equal(obs[2, env.observation_size:], 0.0)  # out of range
        score_before = info["emergency_score"]
    assert float(score[0, 0]) == 0.0  # m + 1 transitions after the danger: exactly zero
    assert isinstance(transform.end_episode(state), CCRState)


def test_danger_flags_by_hand():
    # Four robots on the x axis at 0, 0.5, 3, 0.9 (as tests/test_ccr.py's shared scores),
    # in danger: 0, 2, 3. Range 1: robots 0, 1, 3 talk, robot 2 talks to nobody.
    env = EmergencyEnv("nominal", num_robots=4, num_envs=1)
    transform = DangerFlags(comm_range=1.0)
    state = transform.init(env)
    position = [[0.0, 0.0], [0.5, 0.0], [3.0, 0.0], [0.9, 0.0]]
    env_state = hand_state(position, [1, 0, 1, 1])
    expected = [[0.0, 0.0, 1.0],  # robot 0 sees 1, (2 out of range), 3
                [1.0, 0.0, 1.0],  # robot 1 sees 0, (2), 3
                [0.0, 0.0, 0.0],  # robot 2 sees nobody
                [1.0, 0.0, 0.0]]  # robot 3 sees 0, 1, (2)
    _, obs = transform.start_episode(state, env_state)
    np.testing.assert_array_equal(obs[:, env.observation_size:, 0], expected)
    _, obs, reward, info = transform.step(state, env_state, jnp.zeros((4, 2, 1)), env_state)
    np.testing.assert_array_equal(obs[:, env.observation_size:, 0], expected)
    np.testing.assert_array_equal(obs[:, :env.observation_size], env_state.obs)
    np.testing.assert_array_equal(reward, env_state.reward)
    assert info == {} and transform.extra_obs_size(env) == 3
    _, obs = DangerFlags(comm_range=10.0).start_episode(state, env_state)  # all in range
    np.testing.assert_array_equal(obs[:, env.observation_size:, 0],
                                  [[0, 1, 1], [1, 1, 1], [1, 0, 1], [1, 0, 1]])


# ---------------------------------------------------------------- configuration, command line
NEW = {"ccr_scores": CCRScores(CCRConfig(window=3, comm_range=0.8)),
       "ccr_reward": CCRReward(CCRConfig(lam=12.0, degree=3)),
       "ccr_perfect": CCRPerfect(CCRConfig(lam=4.0, window=1)),
       "danger_flags": DangerFlags(comm_range=0.7)}


@pytest.mark.parametrize("variant", sorted(NEW))
def test_the_new_variants_round_trip_through_json(variant):
    assert variant in VARIANTS
    config = TrainConfig(variant=variant, transform=NEW[variant])
    again = config_from_dict(json.loads(json.dumps(config_to_dict(config))))
    assert again == config and type(again.transform) is type(NEW[variant])
    assert type(TrainConfig(variant=variant).resolved_transform) is type(NEW[variant])
    with pytest.raises(ValueError, match=f"transform of variant '{variant}' must be a "):
        TrainConfig(variant=variant, transform=CCR())


def resolved(*argv):
    return train.resolve(train.build_parser().parse_args([str(a) for a in argv]), None).train


def test_the_command_line_selects_and_sets_the_new_variants():
    config = resolved("--variant", "ccr_perfect", "--lam", 5, "--ccr-window", 2)
    assert config.transform == CCRPerfect(CCRConfig(lam=5.0, window=2))
    config = resolved("--variant", "ccr_reward", "--lam", 3, "--ccr-degree", 3)
    assert config.transform == CCRReward(CCRConfig(lam=3.0, degree=3))
    config = resolved("--variant", "ccr_scores", "--ccr-comm-range", 0.5)
    assert config.transform == CCRScores(CCRConfig(comm_range=0.5))
    config = resolved("--variant", "danger_flags", "--ccr-comm-range", 0.5)
    assert config.transform == DangerFlags(comm_range=0.5)
    assert resolved("--variant", "danger_flags").transform == DangerFlags()


@pytest.mark.parametrize(
    "argv, line",
    [
        (["--variant", "ccr_scores", "--lam", "3"],
         "--lam applies to --variant ccr, ccr_reward or ccr_perfect, not ccr_scores"),
        (["--variant", "danger_flags", "--lam", "3"], "--lam applies to"),
        (["--variant", "ccr_perfect", "--ccr-degree", "3"],
         "--ccr-degree applies to --variant ccr, ccr_scores or ccr_reward, not ccr_perfect"),
        (["--variant", "danger_flags", "--ccr-window", "2"],
         "--ccr-window applies to --variant ccr, ccr_scores, ccr_reward or ccr_perfect, "
         "not danger_flags"),
        (["--variant", "plain", "--ccr-comm-range", "0.5"],
         "--ccr-comm-range applies to --variant ccr, ccr_scores, ccr_reward, ccr_perfect or "
         "danger_flags, not plain"),
        (["--variant", "danger_flags", "--ccr-comm-range", "-0.5"],
         "--ccr-comm-range must be a finite number >= 0"),
        (["--variant", "ccr_reward", "--penalty", "1"],
         "--penalty applies to --variant pessimistic, not ccr_reward"),
    ],
)
def test_misused_options_get_one_line(argv, line, tmp_path, capsys):
    out = tmp_path / "never"
    try:
        status = train.main([*argv, "--out", str(out)])
    except SystemExit as exit_:
        status = exit_.code
    err = capsys.readouterr().err
    lines = [text for text in err.strip().splitlines() if text]
    assert status == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert line in lines[0], lines[0]
    assert not out.exists() or not any(out.iterdir())
