"""The controllers that measure what the team's information is worth
(``experiments/information_controllers.py``), the stateful controllers of
:func:`ccrjax.training.acting.run_episode`, and the information regimes of
``experiments/calibrate.py --regimes`` (``experiments/regimes.py``).

Hand-built worlds check what each controller may and may not react to; short batched
episodes (several controllers in blocks of one batch, one compilation) check their
behaviour; the regimes run once at a tiny size.
"""

from __future__ import annotations

import importlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.envs.env import EmergencyEnv
from ccrjax.envs.scenarios import Layout
from ccrjax.training.acting import Episode, StatefulController, episode_metrics, run_episode
from ccrjax.transforms import Plain

SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle")


@pytest.fixture(scope="module")
def info():
    return importlib.import_module("experiments.information_controllers")


@pytest.fixture(scope="module")
def reference():
    return importlib.import_module("experiments.reference_controllers")


def play(env, controller, seed=0):
    transform = Plain()
    return jax.jit(lambda key: run_episode(env, transform, transform.init(env), None,
                                           env.discrete_actions, key,
                                           controller=controller)[1])(jax.random.key(seed))


def blocks_metrics(info, env_of, factories, episodes, seed=0):
    """Each controller's metrics, ``episodes`` environments each, in one program."""
    env = env_of(len(factories) * episodes)
    episode = play(env, info.in_blocks([f(env) for f in factories.values()], episodes), seed)
    out = {}
    for k, name in enumerate(factories):
        part = slice(k * episodes, (k + 1) * episodes)
        out[name] = {m: float(v) for m, v in episode_metrics(Episode(
            transitions=None, env_reward=episode.env_reward[..., part],
            danger=episode.danger[..., part], success=episode.success[..., part],
            target_distance=episode.target_distance[..., part],
            hazard_distance=episode.hazard_distance[..., part],
            position=episode.position[..., part], hazard=None, info={})).items()}
    return out


def world_with(env, positions, centre, half, velocity=None):
    """``env``'s first world with the robots at ``positions`` ``[N, 2]`` (one environment),
    robot ``i``'s target the ``i``-th slot of the target area (whatever the positions), and
    the hazard at ``centre`` with half extents ``half``."""
    world = env.reset(jax.random.key(0)).pipeline_state
    position = jnp.asarray(positions, jnp.float32)[:, :, None]
    hazard = world.hazard.replace(centre=jnp.asarray(centre, jnp.float32)[:, None],
                                  half_extent=jnp.asarray(half, jnp.float32)[:, None])
    layout, robots = env.layout, len(positions)
    slots = [(layout.goal[0], layout.goal[1] + (i - 0.5 * (robots - 1)) * layout.target_spacing)
             for i in range(robots)]
    return world.replace(position=position, hazard=hazard,
                         target=jnp.asarray(slots, jnp.float32)[:, :, None],
                         velocity=jnp.zeros_like(position) if velocity is None
                         else jnp.asarray(velocity, jnp.float32)[:, :, None])


# Robot 0 on its way at the mid-line; robot 1 in a turbulence area of radius 0.5 at the
# origin, 0.8 ahead of robot 0; the others far off, never in danger.
FAR = [(-2.0, 1.8), (-2.0, -1.8), (-2.2, 1.5)]
CENTRE, HALF = (0.0, 0.0), (0.5, 0.5)


def act_once(controller, world):
    memory = jax.jit(controller.init)(world)
    action, memory = jax.jit(controller.act)(world, memory, jax.random.key(0))
    return np.asarray(action), memory


def test_team_informed_reacts_only_to_teammates_in_range(info):
    env = EmergencyEnv("turbulence")
    own = info.self_reactive(env)
    team = info.team_informed(env)
    # In range (0.8 <= comm_range 1.0): robot 0 turns off its straight way.
    near = world_with(env, [(-1.2, 0.0), (-0.4, 0.0), *FAR], CENTRE, HALF)
    assert bool(env.scenario.in_danger(near.hazard, near.position, env.radius)[1, 0])
    warned, _ = act_once(team, near)
    alone, _ = act_once(own, near)
    assert not np.allclose(warned[0], alone[0])
    assert abs(warned[0, 1, 0]) > 0.5  # it steers sideways, round the teammate's disc
    # Out of range (1.2 > 1.0): robot 0 does what it would do on its own.
    far = world_with(env, [(-1.6, 0.0), (-0.4, 0.0), *FAR], CENTRE, HALF)
    warned, _ = act_once(team, far)
    alone, _ = act_once(own, far)
    np.testing.assert_array_equal(warned[0], alone[0])
    # The same teammate in range with a range of 0.5 is out of range.
    short, _ = act_once(info.team_informed(env, comm_range=0.5), near)
    np.testing.assert_array_equal(short[0], act_once(own, near)[0][0])


def test_team_informed_remembers_a_warning_for_memory_steps(info):
    env = EmergencyEnv("turbulence")
    memory = 3
    team, own = info.team_informed(env, memory=memory), info.self_reactive(env)
    warning = world_with(env, [(-1.2, 0.0), (-0.4, 0.0), *FAR], CENTRE, HALF)
    # The teammate leaves danger (far off); robot 0 stays where it was.
    quiet = world_with(env, [(-1.2, 0.0), (-2.3, 0.0), *FAR], CENTRE, HALF)
    alone = act_once(own, quiet)[0][0]
    step = jax.jit(team.act)
    state = team.init(warning)
    action, state = step(warning, state, jax.random.key(0))
    reacted = [not np.allclose(np.asarray(action)[0], alone)]
    for _ in range(memory + 2):
        action, state = step(quiet, state, jax.random.key(0))
        reacted.append(not np.allclose(np.asarray(action)[0], alone))
    # Warned at the step of the danger and the memory steps after it, then no longer.
    assert reacted == [True] * (memory + 1) + [False] * 2


def test_team_informed_out_of_range_is_self_reactive(info):
    """With a range shorter than robots ever come to each other, every teammate is out of
    range all the time: the whole episode is the self-reactive one (up to the float
    rounding of two differently fused programs)."""
    def env_of(batch):
        return EmergencyEnv("turbulence", num_envs=batch, layout=Layout(
            formation="column", column_spacing=0.3), episode_length=30)

    env = env_of(32)
    team = play(env, info.team_informed(env, comm_range=0.01))
    own = play(env, info.self_reactive(env))
    np.testing.assert_allclose(np.asarray(team.position), np.asarray(own.position), atol=1e-4)
    # ... and in range, the warnings change the column's paths.
    warned = play(env, info.team_informed(env))
    assert not np.array_equal(np.asarray(warned.position), np.asarray(own.position))


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_self_reactive_never_reacts_to_a_teammate(info, reference, scenario):
    env = EmergencyEnv(scenario)
    own = info.self_reactive(env)
    # Robot 0 senses the hazard itself: inside the area, or pressed against the obstacle.
    mine = (-0.555, 0.1) if scenario == "hidden_obstacle" else (-0.4, 0.1)
    base = [mine, (-0.9, 0.0), *FAR]
    velocity = [(0.0, 0.0)] * 5
    world = world_with(env, base, CENTRE, HALF, velocity)
    assert bool(env.scenario.in_danger(world.hazard, world.position, env.radius)[0, 0])
    mine_alone, _ = act_once(own, world)
    home = np.asarray(reference.go_to_goal(env)(world, None))
    assert not np.allclose(mine_alone[0], home[0])  # it reacts to its own sensing
    rng = np.random.default_rng(0)
    for _ in range(5):  # teammates anywhere: in the hazard, touching it, beside robot 0
        moved = [base[0], *(rng.uniform(-1.0, 1.0, size=(4, 2)) * [0.6, 0.6])]
        action, _ = act_once(own, world_with(env, moved, CENTRE, HALF, velocity))
        np.testing.assert_array_equal(action[0], mine_alone[0])
    # Robot 0 away from the hazard, teammates in it: it drives home as if alone.
    for _ in range(3):
        moved = [(-1.2, 0.1), (-0.4, 0.0), (0.0, 0.3), (-0.555, -0.2), (0.2, -0.1)]
        world = world_with(env, moved, CENTRE, HALF, velocity)
        assert bool(env.scenario.in_danger(world.hazard, world.position, env.radius)[1:].any())
        action, _ = act_once(own, world)
        home = np.asarray(reference.go_to_goal(env)(world, None))
        np.testing.assert_array_equal(action[0], home[0])


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_go_round_with_the_true_hazard_is_the_oracle(info, reference, scenario):
    """The self-reactive robot that knows the hazard steers as the oracle does."""
    env = EmergencyEnv(scenario, num_envs=64)
    world = env.reset(jax.random.key(1)).pipeline_state
    world = world.replace(position=world.position + jax.random.uniform(
        jax.random.key(2), world.position.shape, minval=-0.2, maxval=3.0) * jnp.array(
        [1.0, 0.4])[None, :, None])
    margin = reference.CLEARANCE + env.robot_radius
    centre = jnp.broadcast_to(world.hazard.centre[None], world.position.shape)
    half = jnp.broadcast_to(world.hazard.half_extent[None], world.position.shape) + margin
    blocked, heading = info.go_round(world.position, world.target, centre, half,
                                     scenario == "turbulence")
    expected = jnp.where(blocked[:, None], reference._toward(world.velocity, heading),
                         reference._pd(world.position, world.velocity, world.target))
    assert 0.2 < float(jnp.mean(blocked)) < 0.9  # both branches
    np.testing.assert_allclose(np.asarray(expected),
                               np.asarray(reference.oracle(env)(world, None)), atol=1e-6)


@pytest.mark.slow  # whole episodes of several controllers: make test-slow
def test_team_informed_is_no_less_safe_than_go_to_goal_on_the_obstacle(info, reference):
    rows = blocks_metrics(info, lambda b: EmergencyEnv("hidden_obstacle", num_envs=b), {
        "go_to_goal": reference.go_to_goal, "team_informed": info.team_informed,
        "self_reactive": info.self_reactive}, episodes=128)
    assert rows["team_informed"]["danger_frequency"] <= rows["go_to_goal"]["danger_frequency"]
    assert rows["self_reactive"]["danger_frequency"] < rows["go_to_goal"]["danger_frequency"]


@pytest.mark.slow  # whole episodes of several controllers: make test-slow
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_gaming_policies_fail_in_the_new_regimes(info, reference, scenario):
    """A column 0.6 apart (the longest of the grid, 40 steps) and the widest placement."""
    layout = Layout(formation="column", column_spacing=0.6, hazard_y_range=(-1.0, 1.0),
                    arena_half_extent=(3.75, 2.0))
    rows = blocks_metrics(
        info, lambda b: EmergencyEnv(scenario, num_envs=b, layout=layout, episode_length=40),
        {name: reference.CONTROLLERS[name] for name in (*reference.GAMING, "oracle")},
        episodes=64)
    for name in reference.GAMING:
        assert rows[name]["success_rate"] <= 0.05, (name, rows[name])
    assert rows["oracle"]["success_rate"] >= 0.8


@pytest.mark.parametrize("kwargs, message", [
    ({"comm_range": 0.0}, r"team_informed.comm_range must be a finite number in \(0.0, 6.4"),
    ({"comm_range": -1.0}, r"team_informed.comm_range .* got -1.0"),
    ({"comm_range": 7.0}, r"team_informed.comm_range .*6.40.*got 7.0"),
    ({"comm_range": float("nan")}, r"team_informed.comm_range"),
    ({"memory": -1}, r"team_informed.memory must be an integer in \[0, 25\], got -1"),
    ({"memory": 26}, r"team_informed.memory must be an integer in \[0, 25\], got 26"),
    ({"memory": 2.0}, r"team_informed.memory .* got 2.0"),
])
def test_team_informed_refuses_bad_parameters_when_built(info, kwargs, message):
    with pytest.raises(ValueError, match=message):
        info.team_informed(EmergencyEnv("turbulence"), **kwargs)


def test_team_informed_accepts_the_bounds(info):
    env = EmergencyEnv("turbulence", episode_length=25)
    info.team_informed(env, comm_range=2.0 * float(np.hypot(2.5, 2.0)), memory=25)
    info.team_informed(env, comm_range=1e-3, memory=0)


def test_choose_height(info):
    heights = [-1.0, -0.5, 0.0, 0.5, 1.0]
    # Success within 10 points of the oracle's (0.95): the last four; lowest danger 0.1.
    assert int(info.choose_height(heights, [0.5, 0.9, 0.99, 0.86, 0.9],
                                  [0.0, 0.1, 0.4, 0.1, 0.2], 0.95)) == 1
    # Ties in danger: the higher success; then the height nearer the middle.
    assert int(info.choose_height(heights, [0.9, 0.95, 0.99, 0.95, 0.9],
                                  [0.0, 0.0, 0.4, 0.0, 0.0], 0.95)) in (1, 3)
    assert int(info.choose_height(heights, [0.9, 0.96, 0.99, 0.95, 0.9],
                                  [0.0, 0.0, 0.4, 0.0, 0.0], 0.95)) == 1
    # None within 10 points: the highest success.
    assert int(info.choose_height(heights, [0.1, 0.3, 0.2, 0.3, 0.0],
                                  [0.0, 0.2, 0.1, 0.1, 0.0], 0.95)) == 3


def test_memoriser_height_is_chosen_on_the_selection_seed(monkeypatch):
    regimes = importlib.import_module("experiments.regimes")
    calls, programs = [], {}
    real = regimes.regime_program

    def spy(*args):
        if args not in programs:
            programs[args] = real(*args)
        heights, program = programs[args]

        def recorded(eval_key, select_key, grid):
            calls.append((np.asarray(eval_key), np.asarray(select_key)))
            return program(eval_key, select_key, grid)

        return heights, recorded

    monkeypatch.setattr(regimes, "regime_program", spy)
    layout = regimes.regime_layout(0.5, "abreast", None)

    def measured(seed, selection_seed):
        return regimes.measure_regime("hidden_obstacle", layout, 25, episodes=8, seed=seed,
                                      selection_seed=selection_seed, select_episodes=8)

    first, other_eval, other_selection = measured(0, 5), measured(3, 5), measured(0, 6)
    assert len(programs) == 1  # one compilation
    for (eval_key, select_key), (seed, selection_seed) in zip(calls, [(0, 5), (3, 5), (0, 6)],
                                                              strict=True):
        np.testing.assert_array_equal(eval_key, np.asarray(jax.random.PRNGKey(seed)))
        np.testing.assert_array_equal(select_key, np.asarray(jax.random.PRNGKey(selection_seed)))
    # The selection depends on the selection seed only; the evaluation on the other.
    assert first["memoriser"] == other_eval["memoriser"]
    assert first["memoriser"] != other_selection["memoriser"]
    assert first["rows"]["go_to_goal"] != other_eval["rows"]["go_to_goal"]
    assert first["rows"]["go_to_goal"] == other_selection["rows"]["go_to_goal"]


def test_run_episode_carries_a_stateful_controllers_memory():
    env = EmergencyEnv("nominal", num_envs=2, episode_length=6)

    def act(world, count, key):  # a push along x at the third step only
        push = jnp.where(count == 2, 1.0, 0.0)
        action = jnp.zeros_like(world.position).at[:, 0].set(push)
        return action, count + 1

    episode = play(env, StatefulController(init=lambda world: jnp.int32(0), act=act))
    x = np.asarray(episode.position)[:, :, 0]  # [T + 1, N, E]
    np.testing.assert_array_equal(x[:4], np.broadcast_to(x[0], x[:4].shape))
    assert np.all(x[4] > x[3])


@pytest.mark.slow  # whole episodes of several controllers: make test-slow
def test_evaluate_controller_runs_the_information_controllers(reference):
    """By name, with parameters, snapped to discrete actions (memory and all)."""
    env = EmergencyEnv("hidden_obstacle", num_envs=4, discrete_actions=True)
    metrics = reference.evaluate_controller(env, "team_informed", jax.random.key(0), memory=2)
    assert 0.0 < float(metrics["danger_frequency"]) < 1.0
    with pytest.raises(ValueError, match="controller must be one of .*'memoriser'"):
        reference.evaluate_controller(env, "psychic", jax.random.key(0))


@pytest.mark.slow
def test_calibrate_regimes_at_a_tiny_size(tmp_path):
    calibrate = importlib.import_module("experiments.calibrate")
    assert calibrate.main(["--regimes", "--episodes", "8", "--select-episodes", "4",
                           "--scenarios", "hidden_obstacle", "--placements", "0.25",
                           "--spacings", "0", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "regimes.json").read_text())
    assert result["grid"]["lengths"]["abreast"] == {"go_to_goal_steps": 19,
                                                    "episode_length": 25}
    (regime,) = result["grid"]["regimes"]
    assert set(regime["rows"]) == {"go_to_goal", "self_reactive", "team_informed", "oracle",
                                   "memoriser"}
    assert regime["episode_length"] == 25 and regime["placement"] == 0.25
    assert isinstance(regime["informative"], bool)
    assert regime["memoriser"]["y_w"] in regime["memoriser"]["heights"]
    text = (tmp_path / "regimes.md").read_text()
    assert "| hidden_obstacle | 0.25 | abreast | 25 |" in text and "Made by" in text
    with pytest.raises(SystemExit):
        calibrate.main(["--regimes", "--selection-seed", "0", "--out", str(tmp_path / "x")])
