"""The regime's two knobs (issue "CCR's premise, part 1"): the hazard placement and the team
formation (:class:`ccrjax.envs.scenarios.Layout`), their validation, and the command line."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax import train
from ccrjax.envs.env import EmergencyEnv
from ccrjax.envs.scenarios import Layout
from ccrjax.envs.scenarios.layout import (
    abreast_positions,
    column_positions,
    sample_centre,
    start_positions,
    steps_to_cover,
)
from ccrjax.training import TrainConfig
from ccrjax.training.config import config_from_dict, config_to_dict, make_env
from tests.test_train_command import assert_usage_error, run_main

COLUMN = Layout(formation="column", column_spacing=0.6, arena_half_extent=(4.0, 2.0))


def test_a_column_starts_one_robot_behind_another_at_the_spacing():
    position = np.asarray(column_positions(jax.random.PRNGKey(1), COLUMN, 5, 64))  # [N, 2, B]
    x = np.sort(position[:, 0], axis=0)[::-1]  # leader first
    np.testing.assert_allclose(x[0], COLUMN.front, atol=1e-6)
    np.testing.assert_allclose(x[:-1] - x[1:], 0.6, atol=1e-5)
    assert np.all(np.abs(position[:, 1] - COLUMN.start_centre[1]) <= COLUMN.column_lateral)
    # The order is drawn every episode: every robot leads in some environment.
    leader = np.argmax(position[:, 0], axis=0)
    assert set(leader.tolist()) == set(range(5))


def test_the_abreast_default_draws_what_it_drew_before_the_column_existed():
    # Layout() and an explicit abreast layout with other column numbers start the same.
    key = jax.random.PRNGKey(3)
    a = start_positions(key, Layout(), 5, 4)
    b = start_positions(key, Layout(column_spacing=0.9, column_lateral=0.2), 5, 4)
    np.testing.assert_array_equal(a, abreast_positions(key, Layout(), 5, 4))
    np.testing.assert_array_equal(a, b)
    assert "formation" not in Layout().record() and Layout(formation="column").record()[
        "formation"] == "column"


def test_a_column_meets_the_obstacle_in_order_one_spacing_apart():
    spacing = 0.6
    env = EmergencyEnv("hidden_obstacle", num_envs=16, episode_length=40, layout=COLUMN)
    state = env.reset(jax.random.PRNGKey(0))
    rank = np.argsort(np.argsort(-np.asarray(state.pipeline_state.position[:, 0]), axis=0),
                      axis=0)  # 0 = leader
    ahead = jnp.zeros((5, 2, 16)).at[:, 0].set(1.0)  # full speed along the way

    def step(state, _):
        state = env.transition(state, ahead)
        return state, state.metrics["danger"]

    _, danger = jax.lax.scan(step, state, None, length=30)
    danger = np.asarray(danger) > 0  # [T, N, B]
    assert danger.any(axis=0).all(), "every robot runs into the obstacle"
    first = np.argmax(danger, axis=0)  # [N, B]: first step in danger
    order = np.take_along_axis(first, np.argsort(rank, axis=0), axis=0)  # by rank
    gaps = np.diff(order, axis=0)
    # At the top speed of 0.2 a step, one spacing is 3 steps; the leader, still
    # accelerating when it arrives, may be a step later.
    steps = round(spacing / 0.2)
    assert np.all(gaps >= steps) and np.all(gaps <= steps + 1), gaps
    assert np.all(gaps[1:] == steps), gaps


@pytest.mark.parametrize("scenario", ["turbulence", "strong_wind", "hidden_obstacle"])
def test_wide_placements_stay_in_range_and_off_the_start_and_target_areas(scenario):
    layout = Layout(hazard_x_range=(-0.2, 0.1), hazard_y_range=(-1.0, 1.0))
    env = EmergencyEnv(scenario, num_envs=512, layout=layout)
    world = env.reset(jax.random.PRNGKey(2)).pipeline_state
    centre = np.asarray(world.hazard.centre)
    assert centre[0].min() >= -0.2 and centre[0].max() <= 0.1
    assert centre[1].min() >= -1.0 and centre[1].max() <= 1.0
    assert centre[1].min() < -0.8 and centre[1].max() > 0.8  # the whole range is used
    metrics = env.metrics(world)
    assert float(jnp.max(metrics["danger"])) == 0.0  # nobody starts in danger
    near = np.asarray(centre[0] - world.hazard.half_extent[0])
    assert near.min() > layout.front  # every hazard lies ahead of the start box
    reach = np.asarray(centre[0] + world.hazard.half_extent[0])
    assert reach.max() < layout.goal[0] - layout.goal_radius


def test_sample_centre_is_uniform_over_the_placement_range():
    layout = Layout(hazard_y_range=(-1.0, 1.0))
    centre = np.asarray(sample_centre(jax.random.PRNGKey(0), layout, 20000))
    np.testing.assert_allclose(np.mean(centre[1]), 0.0, atol=0.03)
    np.testing.assert_allclose(np.var(centre[1]), 1.0 / 3.0, atol=0.02)


@pytest.mark.parametrize("make, fragment", [
    (lambda: Layout(formation="line"), "Layout.formation must be one of"),
    (lambda: Layout(column_spacing=0.0), "Layout.column_spacing must be a finite number > 0"),
    (lambda: Layout(formation="column", column_lateral=2.5), "Layout.column_lateral"),
    (lambda: EmergencyEnv("nominal", layout=Layout(formation="column", column_spacing=0.1)),
     "column_spacing must be at least min_separation"),
    (lambda: EmergencyEnv("nominal", layout=Layout(formation="column", column_spacing=0.5)),
     "beyond the arena |x| <= 2.5; allowed: column_spacing <= 0.3"),
    (lambda: EmergencyEnv("nominal", episode_length=21, layout=Layout(formation="column")),
     "episode_length 21 is too short for a column"),
    (lambda: EmergencyEnv("turbulence", layout=Layout(hazard_y_range=(-1.5, 1.5))),
     "beyond the arena"),
    (lambda: EmergencyEnv("turbulence", layout=Layout(hazard_x_range=(-0.5, 0.1))),
     "overlapping the start box"),
    (lambda: EmergencyEnv("turbulence", layout=Layout(hazard_x_range=(-0.1, 0.3))),
     "overlapping the target area"),
    (lambda: EmergencyEnv("hidden_obstacle", layout=Layout(formation="column",
                                                     hazard_x_range=(-1.2, 0.1))),
     "overlapping the column's start region"),
])
def test_bad_knobs_are_refused_naming_the_parameter(make, fragment):
    with pytest.raises(ValueError) as error:
        make()
    assert fragment in str(error.value)


def test_a_hazard_behind_the_start_box_is_refused_only_where_a_column_starts():
    # A short obstacle drawn behind the start box: clear of the box, in the column's way.
    behind = {"hazard_x_range": (-2.2, -2.1)}
    short = {"length_range": (0.2, 0.3)}
    EmergencyEnv("hidden_obstacle", scenario_params=short, layout=Layout(**behind))
    with pytest.raises(ValueError, match="overlapping the column's start region"):
        EmergencyEnv("hidden_obstacle", scenario_params=short,
               layout=Layout(formation="column", **behind))


def test_steps_to_cover_is_the_full_speed_arrival_time():
    # v: 0, 0.5, 0.875, ... -> 2; the first step moves nothing (position before velocity).
    assert steps_to_cover(0.0) == 0
    assert steps_to_cover(0.05) == 2
    travelled, velocity = 0.0, 0.0
    for _ in range(steps_to_cover(3.0)):
        travelled, velocity = travelled + 0.1 * velocity, 0.75 * velocity + 0.5
    assert travelled >= 3.0 and travelled - 0.1 * 2.0 < 3.0


def test_a_training_config_carries_the_layout_into_its_environments_and_json():
    config = TrainConfig(scenario="hidden_obstacle", episode_length=40, layout_params={
        "formation": "column", "column_spacing": 0.6, "arena_half_extent": (4.0, 2.0),
        "hazard_y_range": (-1.0, 1.0)})
    assert make_env(config, 2).layout == dataclasses.replace(COLUMN, hazard_y_range=(-1.0, 1.0))
    record = config_to_dict(config)
    assert config_from_dict(record) == config
    # Today's layout writes no layout_params: records made before it existed stay equal.
    assert "layout_params" not in config_to_dict(TrainConfig())
    with pytest.raises(ValueError, match="unknown layout parameter"):
        TrainConfig(layout_params={"spacing": 0.6})
    with pytest.raises(ValueError, match="too short for a column"):
        TrainConfig(layout_params={"formation": "column"}, episode_length=20)


@pytest.mark.parametrize("argv, fragments", [
    (["--layout-formation", "line"], ["--layout-formation must be one of"]),
    (["--layout-formation", "column", "--layout-column-spacing", "0.1"],
     ["--layout-column-spacing must be at least min_separation"]),
    (["--layout-hazard-y-range=-1.5,1.5", "--scenario", "turbulence"], ["beyond the arena"]),
    (["--layout-hazard-y-range", "a,b"], ["--layout-hazard-y-range", "comma-separated"]),
])
def test_the_train_command_refuses_bad_knobs_in_one_line(argv, fragments, capsys, tmp_path):
    status, _, err = run_main(train, [*argv, "--out", tmp_path / "run"], capsys)
    assert_usage_error(status, err, *fragments)
    assert not (tmp_path / "run" / "config.json").exists()


def test_the_train_command_takes_the_knobs(tmp_path):
    parser = train.build_parser()
    args = parser.parse_args(["--layout-formation", "column", "--layout-column-spacing", "0.6",
                              "--layout-arena-half-extent", "4,2", "--episode-length", "40",
                              "--layout-hazard-y-range=-1,1"])
    spec = train.resolve(args, None)
    assert spec.train.layout == dataclasses.replace(COLUMN, hazard_y_range=(-1.0, 1.0))
