"""The reference controllers of ``experiments/reference_controllers.py`` and the calibration
script ``experiments/calibrate.py`` (issue "A valid experiment, part 1").

Every controller of a scenario runs in one compiled episode: the batch holds
``EPISODES`` environments per controller, and each block of environments is driven by
its own controller (the environments of a batch never interact), so a scenario costs
one compilation instead of six.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.envs.env import EmergencyEnv
from ccrjax.training.acting import Episode, episode_metrics, run_episode
from ccrjax.transforms import Plain

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"
SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
EPISODES = 128  # per controller and scenario


def load_script(name: str):
    return importlib.import_module(f"experiments.{name}")


@pytest.fixture(scope="module")
def controllers():
    return load_script("reference_controllers")


def run_all_controllers(module, scenario: str, seed: int = 0):
    """Every controller's metrics and per-step success ``[T, N, EPISODES]`` in ``scenario``."""
    names = list(module.CONTROLLERS)
    env = EmergencyEnv(scenario, num_envs=EPISODES * len(names))
    policies = [module.CONTROLLERS[name](env) for name in names]
    block = np.repeat(np.arange(len(names)), EPISODES)  # which controller drives each env

    def mixed(world, key):
        action = jnp.zeros_like(world.position)
        for index, policy in enumerate(policies):
            action = jnp.where(block == index, policy(world, key), action)
        return action

    transform = Plain()

    # XLA's optimisation level 0 halves the compile time, most of this test's cost.
    @functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})
    def run(key):
        _, episode = run_episode(
            env, transform, transform.init(env), None, False, key, controller=mixed
        )
        out = {}
        for index, name in enumerate(names):
            part = slice(index * EPISODES, (index + 1) * EPISODES)
            mine = Episode(
                transitions=None,
                env_reward=episode.env_reward[..., part],
                danger=episode.danger[..., part],
                success=episode.success[..., part],
                target_distance=episode.target_distance[..., part],
                hazard_distance=episode.hazard_distance[..., part],
                position=episode.position[..., part],
                hazard=None,
                info={},
            )
            out[name] = (episode_metrics(mine), mine.success, mine.position)
        return out

    return jax.tree.map(np.asarray, run(jax.random.key(seed)))


@pytest.fixture(scope="module")
def results(controllers):
    return {scenario: run_all_controllers(controllers, scenario) for scenario in SCENARIOS}


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_gaming_policies_never_succeed(controllers, results, scenario):
    for name in controllers.GAMING:
        metrics = results[scenario][name][0]
        assert metrics["success_rate"] <= 0.05, (scenario, name, metrics)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_oracle_succeeds_safely(results, scenario):
    metrics = results[scenario]["oracle"][0]
    assert metrics["success_rate"] >= 0.8, metrics
    assert metrics["danger_frequency"] <= 0.05, metrics


def test_go_to_goal_and_oracle_succeed_without_a_hazard(results):
    for name in ("go_to_goal", "oracle"):
        metrics = results["nominal"][name][0]
        assert metrics["success_rate"] >= 0.8, (name, metrics)
        assert metrics["danger_frequency"] == 0.0


def test_success_is_read_at_the_last_step_not_sticky(controllers, results):
    layout = EmergencyEnv("nominal").layout
    # overshoot: full speed (0.2 a step) along the way, at its starting height. A robot
    # that starts within 0.3 of the goal's height crosses the target area on a chord of
    # at least 2 sqrt(0.4^2 - 0.3^2) = 0.53, so it is in the area at some step; it then
    # leaves it and fails.
    _, success, position = results["nominal"]["overshoot"]
    level = np.abs(position[0, :, 1] - layout.goal[1]) < 0.3  # [N, E]
    assert level.mean() > 0.5
    assert np.all(success.max(axis=0)[level] == 1.0)
    assert np.all(success[-1] == 0.0)
    assert np.all(position[-1, :, 0] > layout.goal[0] + layout.goal_radius)
    assert results["nominal"]["overshoot"][0]["success_rate"] == 0.0
    # go_to_goal: in the area at the end, a success.
    metrics, success, position = results["nominal"]["go_to_goal"]
    ends_inside = np.hypot(position[-1, :, 0] - layout.goal[0],
                           position[-1, :, 1] - layout.goal[1]) < layout.goal_radius
    np.testing.assert_array_equal(success[-1], ends_inside)
    assert metrics["success_rate"] == pytest.approx(success[-1].mean())


def test_evaluate_controller_rejects_bad_input(controllers):
    env = EmergencyEnv("nominal", num_envs=2)
    with pytest.raises(ValueError, match="controller must be one of"):
        controllers.evaluate_controller(env, "teleport", jax.random.key(0))


def test_snapping_to_a_discrete_action_set(controllers):
    def constant(command):
        return lambda world, key: jnp.broadcast_to(
            jnp.asarray(command, jnp.float32)[None, :, None], world.position.shape)

    world = EmergencyEnv("nominal", num_envs=1).reset(jax.random.key(0)).pipeline_state
    for command, box9, mpe5 in [((0.9, 0.8), 8, 2), ((0.2, -0.1), 0, 0), ((-0.1, -0.7), 3, 3),
                                ((-0.8, 0.9), 6, 4)]:
        for action_set, expected in (("box9", box9), ("mpe5", mpe5)):
            action = controllers.snap_to_action_set(constant(command), action_set)(world, None)
            assert action.dtype == jnp.int32 and action.shape == (5, 1)
            assert np.all(np.asarray(action) == expected), (command, action_set)


def test_the_oracle_needs_the_box_of_actions(controllers):
    """Why MAAC's actions are box9: snapped to it, the oracle still detours round the hidden
    obstacle; snapped to the MPE's five it cannot (experiments/calibrate.py measures all)."""
    def measured(action_set, name):
        env = EmergencyEnv("hidden_obstacle", num_envs=EPISODES, discrete_actions=True,
                     discrete_action_set=action_set)
        return jax.jit(lambda key: controllers.evaluate_controller(env, name, key))(
            jax.random.key(0))

    box9, mpe5 = measured("box9", "oracle"), measured("mpe5", "oracle")
    assert box9["success_rate"] >= 0.95 and box9["danger_frequency"] <= 0.01
    assert mpe5["success_rate"] <= 0.05
    assert measured("box9", "dash_away")["success_rate"] == 0.0


class QuickCompile(types.ModuleType):
    """``jax`` as the calibration script sees it, with ``jit`` compiling at XLA's
    optimisation level 0: it makes the same numbers (the script's own at 16 episodes were
    identical) and halves the script's time, nearly all of it the compilation of its
    24 programs."""

    def __getattr__(self, name):
        return getattr(jax, name)

    @staticmethod
    def jit(function, **kwargs):
        options = {"xla_backend_optimization_level": 0}
        return jax.jit(function, compiler_options=options, **kwargs)


@pytest.mark.slow
def test_calibrate_runs_at_a_small_size(controllers, tmp_path, monkeypatch):
    calibrate = load_script("calibrate")
    monkeypatch.setattr(calibrate, "jax", QuickCompile("jax"))
    assert calibrate.main(["--episodes", "16", "--no-sweeps", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "calibration.json").read_text())
    assert result["episodes"] == 16 and result["sweeps"] == []
    assert set(result["rows"]) == set(SCENARIOS)
    for scenario in SCENARIOS:
        assert set(result["rows"][scenario]) == set(controllers.CONTROLLERS)
        for row in result["rows"][scenario].values():
            assert set(row) == set(calibrate.METRICS)
            assert all(np.isfinite(value) for value in row.values())
            assert 0.0 <= row["success_rate"] <= 1.0 and 0.0 <= row["danger_frequency"] <= 1.0
    assert result["checks"] and all(isinstance(c["holds"], bool) for c in result["checks"])
    # The discrete action sets: every controller with box9 (its bands checked), the
    # go-to-goal and the oracle with the MPE's five.
    assert set(result["action_sets"]) == {"box9", "mpe5"}
    for scenario in SCENARIOS:
        assert set(result["action_sets"]["box9"][scenario]) == set(controllers.CONTROLLERS)
        assert set(result["action_sets"]["mpe5"][scenario]) == {"go_to_goal", "oracle"}
    assert any(c["check"] == "hidden_obstacle, box9: oracle success" for c in result["checks"])
    text = (tmp_path / "calibration.md").read_text()
    for scenario in SCENARIOS:
        for controller in controllers.CONTROLLERS:
            assert f"| {scenario} | {controller} |" in text
