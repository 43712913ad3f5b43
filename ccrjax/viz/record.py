"""One environment's episode as numpy arrays (:class:`EpisodeRecord`), what the pictures
draw (:mod:`ccrjax.viz.render`): from a policy's rollout (:func:`record_episode`, through
:func:`ccrjax.training.acting.plain_episode`) or from a batched episode
(:func:`episode_record`). Robots carry a per-step *state* index: by default every robot is
in the single state ``"robot"``; CCR passes its three states (:data:`CCR_STATE_NAMES`,
:data:`CCR_STATE_COLOURS`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from matplotlib import colors as mcolors

from ccrjax.training.acting import plain_episode

__all__ = ["CCR_STATE_COLOURS", "CCR_STATE_NAMES", "DEFAULT_STATE_COLOURS",
           "DEFAULT_STATE_NAMES", "EpisodeRecord", "Policy", "episode_record", "record_episode"]

# A policy maps the batch's observations ``float[N, F, B]`` and a key to an action.
Policy = Callable[[jax.Array, jax.Array], jax.Array]

BLUE = "#1f6fd1"
YELLOW = "#f2c500"
PINK = "#ff5fa2"
DEFAULT_STATE_NAMES: tuple[str, ...] = ("robot",)
DEFAULT_STATE_COLOURS: tuple[str, ...] = (BLUE,)
# The CCR robot states of the paper, in the order of their state index.
CCR_STATE_NAMES: tuple[str, ...] = ("standby", "sensing danger", "activated")
CCR_STATE_COLOURS: tuple[str, ...] = (BLUE, YELLOW, PINK)


def _pair(name: str, value: Any) -> np.ndarray:
    array = np.array(value, dtype=np.float64)
    if array.shape != (2,) or not np.all(np.isfinite(array)):
        raise ValueError(f"EpisodeRecord.{name} must be a finite (x, y) pair, got {value!r}")
    array.setflags(write=False)
    return array


@dataclasses.dataclass(frozen=True, eq=False)
class EpisodeRecord:
    """One environment's episode, as numpy arrays with the time axis first.

    Attributes:
      scenario: the scenario's name (``turbulence``, ``strong_wind``,
        ``hidden_obstacle`` or ``nominal``; other names draw no hazard).
      positions: ``float[T + 1, N, 2]``: every robot's position at every step,
        the reset's first.
      robot_radius: disc radius of the robots.
      goal: the centre of the target area ``(x, y)``.
      goal_radius: radius of the target area around ``goal``: a robot whose
        centre is inside it at the last step succeeded.
      hazard_centre: ``float[2]``.
      hazard_half_extent: ``float[2]`` (a circle's radius twice; a rectangle's
        half width and half height).
      hazard_direction: ``float[2]`` unit wind direction (zero elsewhere).
      states: ``int[T + 1, N]``: each robot's state index at each step, an index
        into ``state_names`` and ``state_colours``.
      state_names: the legend's name of every state.
      state_colours: a matplotlib colour for every state.
      danger: ``bool[T + 1, N]`` or ``None``: each robot in a dangerous state at each
        step (the reset's row first), marked on its path whatever the transform.
      caption: what the episode is (``"seed 0, evaluation episode 1 of 1"``), in the title.

    Arrays are copied and made read-only; a malformed record raises ``ValueError``.
    """

    scenario: str
    positions: np.ndarray
    robot_radius: float
    goal: tuple[float, float]
    goal_radius: float
    hazard_centre: np.ndarray
    hazard_half_extent: np.ndarray
    hazard_direction: np.ndarray
    states: np.ndarray
    state_names: tuple[str, ...] = DEFAULT_STATE_NAMES
    state_colours: tuple[str, ...] = DEFAULT_STATE_COLOURS
    danger: np.ndarray | None = None
    caption: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.scenario, str) or not self.scenario:
            raise ValueError(f"EpisodeRecord.scenario must be a name, got {self.scenario!r}")
        positions = np.array(self.positions, dtype=np.float64)
        if positions.ndim != 3 or positions.shape[2] != 2 or positions.shape[0] < 1:
            raise ValueError(
                "EpisodeRecord.positions must be float[T + 1, N, 2], "
                f"got shape {list(positions.shape)}"
            )
        if positions.shape[1] < 1:
            raise ValueError("EpisodeRecord.positions must hold at least one robot")
        if not np.all(np.isfinite(positions)):
            raise ValueError("EpisodeRecord.positions must be finite")
        positions.setflags(write=False)
        for name in ("robot_radius", "goal_radius"):
            value = getattr(self, name)
            if not (isinstance(value, int | float | np.floating) and math.isfinite(value)
                    and value > 0):
                raise ValueError(f"EpisodeRecord.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        goal = _pair("goal", self.goal)
        centre = _pair("hazard_centre", self.hazard_centre)
        half_extent = _pair("hazard_half_extent", self.hazard_half_extent)
        if np.any(half_extent < 0):
            raise ValueError(
                f"EpisodeRecord.hazard_half_extent must be >= 0, got {self.hazard_half_extent!r}"
            )
        direction = _pair("hazard_direction", self.hazard_direction)

        names, colours = tuple(self.state_names), tuple(self.state_colours)
        if not names or not all(isinstance(n, str) for n in names):
            raise ValueError(f"EpisodeRecord.state_names must be non-empty strings, got {names!r}")
        if len(colours) != len(names):
            raise ValueError(
                f"EpisodeRecord.state_colours must have one colour per state ({len(names)}), "
                f"got {len(colours)}"
            )
        for colour in colours:
            if not mcolors.is_color_like(colour):
                raise ValueError(f"EpisodeRecord.state_colours: {colour!r} is not a colour")

        states = np.asarray(self.states)
        if states.shape != positions.shape[:2]:
            raise ValueError(
                f"EpisodeRecord.states must be int[T + 1, N] = {list(positions.shape[:2])} "
                f"like positions, got shape {list(states.shape)}"
            )
        if states.dtype == bool or not np.issubdtype(states.dtype, np.integer):
            raise ValueError(f"EpisodeRecord.states must be integers, got {states.dtype}")
        if states.size and (states.min() < 0 or states.max() >= len(names)):
            raise ValueError(
                f"EpisodeRecord.states must lie in [0, {len(names) - 1}] (one per state name), "
                f"got values in [{states.min()}, {states.max()}]"
            )
        states = states.astype(np.int32)
        states.setflags(write=False)
        if self.danger is not None:
            danger = np.asarray(self.danger)
            if danger.shape != positions.shape[:2]:
                raise ValueError(
                    f"EpisodeRecord.danger must be bool[T + 1, N] = {list(positions.shape[:2])} "
                    f"like positions, got shape {list(danger.shape)}"
                )
            danger = danger.astype(bool)
            danger.setflags(write=False)
            object.__setattr__(self, "danger", danger)
        if not isinstance(self.caption, str):
            raise ValueError(f"EpisodeRecord.caption must be a string, got {self.caption!r}")

        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "goal", (float(goal[0]), float(goal[1])))
        object.__setattr__(self, "hazard_centre", centre)
        object.__setattr__(self, "hazard_half_extent", half_extent)
        object.__setattr__(self, "hazard_direction", direction)
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "state_names", names)
        object.__setattr__(self, "state_colours", colours)

    @property
    def num_steps(self) -> int:
        """``T``, the number of steps taken (``positions`` holds ``T + 1``)."""
        return self.positions.shape[0] - 1

    @property
    def num_robots(self) -> int:
        """``N``."""
        return self.positions.shape[1]

    @property
    def succeeded(self) -> np.ndarray:
        """``bool[N]``: each robot ends inside the target area (the task's success)."""
        offset = self.positions[-1] - np.asarray(self.goal)
        return np.hypot(offset[:, 0], offset[:, 1]) < self.goal_radius


StatesArg = np.ndarray | jax.Array | None


def record_episode(
    env: Any,
    policy: Policy,
    key: jax.Array,
    env_index: int = 0,
    states: StatesArg = None,
    *,
    state_names: Sequence[str] = DEFAULT_STATE_NAMES,
    state_colours: Sequence[str] = DEFAULT_STATE_COLOURS,
    optimize: bool = False,
    caption: str = "",
) -> EpisodeRecord:
    """Resets ``env``, runs one episode of ``policy``, and records environment ``env_index``.

    The episode is :func:`ccrjax.training.acting.run_episode`'s, the loop that training,
    evaluation and the sweeps run (plain rewards, no transform), compiled once.

    Args:
      env: a :class:`ccrjax.envs.env.EmergencyEnv`.
      policy: a pure function ``(obs float[N, F, B], key) -> action float[N, 2, B]`` of the
        env's layout; it is traced once.
      key: PRNG key for the reset and the policy.
      env_index: which environment of the batch to record.
      states: the robots' state indices: ``None`` (all 0), or an int array ``[T + 1, N]``
        or ``[T + 1, N, B]`` (the reset's first).
      state_names: legend names of the states.
      state_colours: matplotlib colours of the states.
      optimize: compile the rollout with XLA's full backend optimisation. By
        default it is compiled at optimisation level 0, which on CPU halves the
        compile time (most of a recording's cost); positions may then differ from
        an optimised rollout's by float32 rounding (about 1e-7 relative).
      caption: what the episode is, for the pictures' title.

    Returns:
      The :class:`EpisodeRecord` of environment ``env_index``, with every robot's danger
      at every step.
    """
    num_envs = int(env.num_envs)
    if isinstance(env_index, bool) or not isinstance(env_index, int | np.integer) or not (
        0 <= env_index < num_envs
    ):
        raise ValueError(f"env_index must be an integer in [0, {num_envs - 1}], got {env_index!r}")
    env_index = int(env_index)
    hazard, positions, steps_danger = plain_episode(env, policy, key, optimize)
    if states is not None:
        states = np.asarray(states)
        if states.ndim == 3:
            if states.shape[2] != num_envs:
                raise ValueError(
                    f"states must be int[T + 1, N] or int[T + 1, N, {num_envs}], "
                    f"got shape {list(states.shape)}"
                )
            states = states[..., env_index]
    return episode_record(env, hazard, positions, steps_danger, env_index, states,
                          state_names, state_colours, caption)


def episode_record(env: Any, hazard: Any, positions: Any, steps_danger: Any, env_index: int,
                   states: np.ndarray | None, state_names: Sequence[str],
                   state_colours: Sequence[str], caption: str) -> EpisodeRecord:
    """The :class:`EpisodeRecord` of environment ``env_index`` from a batched episode of
    :func:`ccrjax.training.acting.run_episode` (its hazard, positions ``[T + 1, N, 2, B]`` and
    per-step danger ``[T, N, B]``); the reset is recorded as safe, and with ``states``
    (``[T + 1, N]``; ``None``: all 0)."""
    positions = np.asarray(positions)[..., env_index]  # [T + 1, N, 2]
    steps_danger = np.asarray(steps_danger)[..., env_index] > 0  # [T, N]
    danger = np.concatenate([np.zeros_like(steps_danger[:1]), steps_danger])
    layout = env.layout
    return EpisodeRecord(
        scenario=env.scenario.name,
        positions=positions,
        robot_radius=float(env.robot_radius),
        goal=tuple(float(v) for v in layout.goal),
        goal_radius=float(layout.goal_radius),
        hazard_centre=np.asarray(hazard.centre)[:, env_index],
        hazard_half_extent=np.asarray(hazard.half_extent)[:, env_index],
        hazard_direction=np.asarray(hazard.direction)[:, env_index],
        states=np.zeros(positions.shape[:2], np.int32) if states is None else states,
        state_names=tuple(state_names),
        state_colours=tuple(state_colours),
        danger=danger,
        caption=caption,
    )
