"""Pictures of an episode: recording, validation, PNG and GIF output, outcomes."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from PIL import Image

from ccrjax.envs.env import EmergencyEnv
from ccrjax.viz import render
from ccrjax.viz.record import CCR_STATE_COLOURS, CCR_STATE_NAMES, EpisodeRecord, record_episode
from ccrjax.viz.render import FAILURE_COLOUR, GOAL_COLOUR, animate_episode, draw_episode

STEPS = 5


def random_policy(obs: jax.Array, key: jax.Array) -> jax.Array:
    num_robots, _, num_envs = obs.shape
    return jax.random.uniform(key, (num_robots, 2, num_envs), minval=-1.0, maxval=1.0)


@pytest.fixture(scope="module")
def env() -> EmergencyEnv:
    return EmergencyEnv("strong_wind", num_robots=3, num_envs=2, episode_length=STEPS)


@pytest.fixture(scope="module")
def record(env: EmergencyEnv) -> EpisodeRecord:
    return record_episode(env, random_policy, jax.random.key(0), env_index=1)


def test_record_matches_the_rollout(env: EmergencyEnv, record: EpisodeRecord) -> None:
    assert record.scenario == "strong_wind"
    assert record.positions.shape == (STEPS + 1, 3, 2)
    assert record.states.shape == (STEPS + 1, 3)
    assert np.all(record.states == 0)
    assert record.state_names == ("robot",)
    # Robots start in the layout's start box; the hazard lies in its range.
    layout = env.layout
    offset = np.abs(record.positions[0] - np.array(layout.start_centre))
    assert np.all(offset <= np.array(layout.start_half_extent) + 1e-6)
    assert layout.hazard_x_range[0] <= record.hazard_centre[0] <= layout.hazard_x_range[1]
    assert record.hazard_half_extent[0] == record.hazard_half_extent[1] > 0
    assert record.goal == env.layout.goal
    assert record.goal_radius == env.layout.goal_radius
    # Robots moved, and every recorded position is finite.
    assert np.all(np.isfinite(record.positions))
    assert not np.allclose(record.positions[0], record.positions[-1])
    # Five random steps from the start box: nobody is in the target area.
    assert record.succeeded.shape == (3,) and not record.succeeded.any()


def test_draw_and_animate(record: EpisodeRecord, tmp_path) -> None:
    png, gif = tmp_path / "episode.png", tmp_path / "episode.gif"
    draw_episode(record, png)
    animate_episode(record, gif, fps=5)
    with Image.open(png) as image:
        image.verify()
    with Image.open(png) as image:
        assert image.format == "PNG" and min(image.size) > 100
    with Image.open(gif) as image:
        assert image.format == "GIF"
        assert image.n_frames == STEPS + 1
    assert gif.stat().st_size < 2_000_000


def test_state_colours_are_drawn(env: EmergencyEnv, record: EpisodeRecord, tmp_path) -> None:
    """CCR states given per step, robot and environment; their colours appear in the GIF."""
    # [T + 1, N, B]: robot i is in state i % 3, to show all three colours.
    shape = (STEPS + 1, env.num_robots, env.num_envs)
    states = np.broadcast_to(np.arange(shape[1])[None, :, None] % 3, shape)

    plain = record  # the same rollout, recorded without states
    record = record_episode(env, random_policy, jax.random.key(0), env_index=1, states=states,
                            state_names=CCR_STATE_NAMES, state_colours=CCR_STATE_COLOURS)
    np.testing.assert_array_equal(record.states[0], [0, 1, 2])
    np.testing.assert_allclose(record.positions, plain.positions)
    gif = tmp_path / "ccr.gif"
    animate_episode(record, gif, dpi=60)
    with Image.open(gif) as image:
        image.seek(STEPS)
        pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    for colour in CCR_STATE_COLOURS:
        rgb = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
        assert np.any(np.all(pixels == rgb, axis=1)), f"{colour} missing from the last frame"


def test_record_validation(record: EpisodeRecord) -> None:
    with pytest.raises(ValueError, match="states"):
        dataclasses.replace(record, states=np.zeros((STEPS, 3), np.int32))
    with pytest.raises(ValueError, match="states"):
        dataclasses.replace(record, states=np.full((STEPS + 1, 3), 1, np.int32))
    with pytest.raises(ValueError, match="state_colours"):
        dataclasses.replace(record, state_names=("a", "b"))
    with pytest.raises(ValueError, match="positions"):
        dataclasses.replace(record, positions=np.zeros((STEPS + 1, 3, 3)))
    # A valid three-state record is accepted, and its arrays are read-only.
    three = dataclasses.replace(record, states=np.full((STEPS + 1, 3), 2),
                                state_names=CCR_STATE_NAMES, state_colours=CCR_STATE_COLOURS)
    assert not three.states.flags.writeable and not three.positions.flags.writeable


def test_record_episode_rejects_bad_env_index(env: EmergencyEnv) -> None:
    with pytest.raises(ValueError, match="env_index"):
        record_episode(env, random_policy, jax.random.key(0), env_index=2)


def colour_count(pixels: np.ndarray, colour: str) -> int:
    rgb = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
    return int(np.sum(np.all(pixels == rgb, axis=1)))


def png_pixels(path) -> np.ndarray:
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB")).reshape(-1, 3)


def test_outcomes_are_read_at_the_end_and_marked(record: EpisodeRecord, tmp_path) -> None:
    # Success is the robot's centre inside the target area (radius 0.4 around the goal)
    # at the last step: robot 0 passed through the area and left it, robot 1 ends inside
    # near its edge, robot 2 ends just outside.
    goal = np.array(record.goal)
    positions = np.tile(goal - [2.0, 0.0], (STEPS + 1, 3, 1))
    positions[2, 0] = goal  # in the area earlier on: no success
    positions[-1] = goal + np.array([[1.0, 0.0], [0.39, 0.0], [0.0, 0.41]])
    ended = dataclasses.replace(record, positions=positions)
    np.testing.assert_array_equal(ended.succeeded, [False, True, False])
    positions[-1] = goal + np.array([[0.0, -0.15], [0.0, 0.0], [0.0, 0.15]])
    all_in = dataclasses.replace(record, positions=positions)
    assert all_in.succeeded.all()
    positions[-1] = goal + np.array([[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    all_out = dataclasses.replace(record, positions=positions)
    assert not all_out.succeeded.any()
    # The still marks each end: a green ring for a success, a red cross for a failure (the
    # legend shows one of each in every picture).
    red, green = {}, {}
    for name, outcome in (("ended", ended), ("all_in", all_in), ("all_out", all_out)):
        draw_episode(outcome, tmp_path / f"{name}.png", dpi=80)
        pixels = png_pixels(tmp_path / f"{name}.png")
        red[name], green[name] = colour_count(pixels, FAILURE_COLOUR), colour_count(
            pixels, GOAL_COLOUR)
    assert red["all_in"] < red["ended"] < red["all_out"]
    assert green["all_out"] < green["ended"] < green["all_in"]
    # The GIF marks the outcomes on its last frame only (its legend, on every frame, shows
    # one mark of each kind).
    gif = tmp_path / "ended.gif"
    animate_episode(ended, gif, dpi=60)
    with Image.open(gif) as image:
        first = np.asarray(image.convert("RGB")).reshape(-1, 3)
        image.seek(STEPS)
        last = np.asarray(image.convert("RGB")).reshape(-1, 3)
    assert 0 < colour_count(first, FAILURE_COLOUR) < colour_count(last, FAILURE_COLOUR)
    assert colour_count(first, GOAL_COLOUR) < colour_count(last, GOAL_COLOUR)


def test_pictures_show_each_robot_its_danger_and_the_caption(tmp_path):
    """One trajectory colour per robot, a danger mark on the steps spent in danger (a plain
    run too), and the caption in the title; the GIF the same."""
    env = EmergencyEnv("hidden_obstacle", num_robots=3, num_envs=1, episode_length=12)

    def right(obs, key):
        return jnp.ones((3, 2, 1)) * jnp.array([1.0, 0.0])[None, :, None]

    record = record_episode(env, right, jax.random.PRNGKey(0), caption="seed 7, ep 1")
    assert record.danger is not None and record.danger.shape == (13, 3)
    assert not record.danger[0].any() and record.danger.any()  # they run into the obstacle
    lines, rings, titles = [], [], []
    original_plot, original_scatter, original_title = Axes.plot, Axes.scatter, Axes.set_title

    def plot(self, *args, **kwargs):
        lines.append(kwargs.get("color"))
        return original_plot(self, *args, **kwargs)

    def scatter(self, *args, **kwargs):
        if kwargs.get("facecolors") == "none":
            rings.append(len(args[0]))
        return original_scatter(self, *args, **kwargs)

    def set_title(self, text, *args, **kwargs):
        titles.append(text)
        return original_title(self, text, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Axes, "plot", plot)
        patch.setattr(Axes, "scatter", scatter)
        patch.setattr(Axes, "set_title", set_title)
        render.draw_episode(record, tmp_path / "e.png", dpi=40)
    trajectory_colours = [c for c in lines if c in render.ROBOT_COLOURS]
    assert len(set(trajectory_colours)) == 3  # one colour per robot
    assert sum(rings) == int(record.danger.sum())  # every dangerous step marked
    assert "seed 7, ep 1" in titles[-1]
    labels = []
    original_legend = Figure.legend

    def legend(self, *args, **kwargs):
        labels.extend(h.get_label() for h in kwargs["handles"])
        return original_legend(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "legend", legend)
        render.animate_episode(dataclasses.replace(record), tmp_path / "e.gif", dpi=40)
    ok = int(record.succeeded.sum())
    assert f"succeeded ({ok})" in labels and f"failed ({3 - ok})" in labels  # the GIF's too
    with Image.open(tmp_path / "e.gif") as gif:
        assert gif.n_frames >= record.num_steps + 1  # a frame per step


def test_a_long_caption_is_wrapped_inside_the_picture(tmp_path):
    """A caption far wider than the axes is wrapped, and every line of the title stays
    inside the figure, in the PNG and in the GIF (``make train``'s once ran off the left)."""
    env = EmergencyEnv("turbulence", num_robots=2, num_envs=1, episode_length=3)

    def still(obs, key):
        return jnp.zeros((2, 2, 1))

    caption = "seed 0's policy (deterministic), an episode drawn for the picture " * 3
    record = record_episode(env, still, jax.random.PRNGKey(0), caption=caption.strip())
    titles = []
    original_title = Axes.set_title

    def set_title(self, text, *args, **kwargs):
        titles.append((self.figure, original_title(self, text, *args, **kwargs)))
        return titles[-1][1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Axes, "set_title", set_title)
        render.draw_episode(record, tmp_path / "e.png", dpi=40)
        render.animate_episode(record, tmp_path / "e.gif", dpi=40)
    assert len(titles) == 2
    for figure, text in titles:
        assert text.get_text().count("\n") >= 3  # the first line, then the caption wrapped
        figure.canvas.draw()
        box, frame = text.get_window_extent(), figure.bbox
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and box.y1 <= frame.y1
