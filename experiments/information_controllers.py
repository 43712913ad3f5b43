"""Reference controllers that measure what a teammate's trouble is worth to a robot.

CCR's argument is about information: a teammate in danger should tell a robot something
it could not know otherwise. These hand-written controllers bracket that information, and
run through the same evaluation as the others (:func:`reference_controllers.evaluate_controller`,
:func:`ccrjax.training.acting.run_episode`, :func:`~ccrjax.training.acting.episode_metrics`):

* ``self_reactive``: detours only on what the robot itself senses. An area hazard
  (turbulence, wind) is observed only from inside, as ``[1, dx, dy, size]``: once inside,
  the robot remembers the area's centre and size for the rest of the episode and, while
  its straight line to the target meets the area grown by the oracle's clearance, steers
  exactly as the oracle does with that knowledge (:func:`go_round`: along the circle's
  tangent on its side, from inside too; for the square, to its far corner on its side,
  0.2 beyond), so it leaves the area by its side and goes round the rest. The hidden
  obstacle is felt only by touch: a robot touching it while stopped along the way (its
  velocity along x is below ``STOPPED_SPEED``: it is pressed against a face across the
  way) slides along the face at full speed towards a side fixed at its first touch (the
  **side rule**: away from the team's mid-line ``y = goal y``, upwards on it; the hazard
  is centred on the way on average, so that is the nearer end on average, and it uses
  only the robot's own height and its own target area) until it no longer touches, then
  heads for its target; touching a face while moving along the way (the obstacle's side
  face, whose thickness it does not know), it keeps heading for its target and the solid
  face slides it along.
* ``team_informed``: ``self_reactive``, plus what CCR shares, with perfect detection: a
  teammate that is in danger while within ``comm_range`` of the robot warns it (the range
  is read at the step of the danger, as CCR shares scores then), and a warning lasts
  ``memory`` steps after the teammate's last dangerous step in range (CCR's rolling
  window). While warned and ignorant of the area (it has not been inside it), the robot
  goes round a disc of radius ``warning_radius`` around where the warning teammate was
  (its latest dangerous position in range), with the oracle's clearance and tangent logic;
  of several warnings, the nearest disc that blocks its way counts. Its own knowledge
  comes first: an area it knows exactly makes warnings redundant, and touching the
  obstacle it follows the self-reactive touch rule.
* ``memoriser``: senses nothing; takes the one fixed detour that is best on average over
  the placements: every robot heads at full speed for a waypoint at ``x`` = the centre of
  the layout's hazard x range and height ``y_w`` (shifted by its own target slot's offset,
  so the team passes side by side), then drives to its target. ``y_w`` is a traced
  argument (a scalar or one per environment) and is chosen by :func:`choose_height` on
  episodes of a selection seed (``experiments/calibrate.py --regimes``): it measures what
  knowing only *where hazards usually are* is worth.

The warning disc's radius ``WARNING_RADIUS`` (0.5) is fixed a priori, not tuned: a robot in
danger is inside an area (radius 0.9-1.0, half side 0.6-0.8) or on the obstacle's face
(half length 0.6-1.0), so the hazard reaches at least about half its size around the
teammate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax.checks import check_finite, check_int
from ccrjax.envs.env import EmergencyEnv, WorldState
from ccrjax.training.acting import StatefulController
from ccrjax.transforms.ccr import CCRConfig
from experiments.reference_controllers import (
    CLEARANCE,
    Controller,
    _pd,
    _segment_hits_box,
    _segment_hits_circle,
    _toward,
)

WARNING_RADIUS = 0.5  # the disc a teammate's warning is about (module docstring)
STOPPED_SPEED = 0.1  # |v_x| below this while touching: pressed against a face across the way
MEMORISER_HEIGHT_STEP = 0.1  # the memoriser's grid of waypoint heights
SUCCESS_SLACK = 0.10  # memoriser heights considered: success within this of the oracle's


def _unit(vector: jax.Array) -> jax.Array:
    """``vector`` ``[N, 2, B]`` divided by its length (zero-safe)."""
    length = jnp.sqrt(jnp.sum(vector * vector, axis=1, keepdims=True))
    return vector / jnp.maximum(length, 1e-6)


def _side(position: jax.Array, centre: jax.Array) -> jax.Array:
    """``[N, B]``: +1 where the robot is level with or above ``centre``'s height, else -1."""
    return jnp.where(position[:, 1] >= centre[:, 1], 1.0, -1.0)


def go_round(position: jax.Array, target: jax.Array, centre: jax.Array, half: jax.Array,
             circle: bool) -> tuple[jax.Array, jax.Array]:
    """The oracle's detour (:func:`reference_controllers.oracle`), round a hazard known to
    each robot: ``centre`` ``[N, 2, B]`` and ``half`` ``[N, 2, B]``, the half extents grown
    by the clearance margin. Returns ``blocked`` ``[N, B]`` (the straight line to the
    target meets the grown hazard) and a unit ``heading`` ``[N, 2, B]`` on the robot's side
    of the centre: the tangent to a circle (from inside it, the circle's own tangent at the
    robot's point, as the oracle's formula gives), the near corner of a box the robot is
    before, else its far corner 0.2 beyond. With the true hazard it is the oracle's
    command (``tests/test_information_controllers.py``)."""
    side = _side(position, centre)
    if circle:
        radius = half[:, 0]
        blocked = _segment_hits_circle(position, target, centre, radius)
        to_centre = centre - position
        distance = jnp.sqrt(jnp.sum(to_centre * to_centre, axis=1))
        u = to_centre / jnp.maximum(distance, 1e-6)[:, None]
        angle = jnp.arcsin(jnp.clip(radius / jnp.maximum(distance, 1e-6), 0.0, 1.0))
        cos, sin = jnp.cos(angle), side * jnp.sin(angle)
        return blocked, jnp.stack(
            [u[:, 0] * cos - u[:, 1] * sin, u[:, 1] * cos + u[:, 0] * sin], axis=1)
    blocked = _segment_hits_box(position, target, centre, half)
    before = position[:, 0] < centre[:, 0] - half[:, 0]
    corner_x = centre[:, 0] + jnp.where(before, -1.0, 1.0) * half[:, 0]
    aim = jnp.stack([corner_x + jnp.where(before, 0.0, 0.2), centre[:, 1] + side * half[:, 1]],
                    axis=1)
    return blocked, _unit(aim - position)


def _kind(env: EmergencyEnv) -> str:
    """What a robot can sense of the scenario's hazard: ``area``, ``touch`` or ``none``."""
    return {4: "area", 1: "touch", 0: "none"}[env.scenario.hazard_feature_size]


class SelfMemory(NamedTuple):
    """What a robot has sensed itself: ``known`` ``[N, B]`` (it has been inside the area),
    the area's ``centre`` ``[N, 2, B]`` and ``size`` ``[N, B]`` (half extent) as it observed
    them there, and the obstacle's sliding ``side`` ``[N, B]`` (0 until the first touch)."""

    known: jax.Array
    centre: jax.Array
    size: jax.Array
    side: jax.Array


def _self_init(world: WorldState) -> SelfMemory:
    zeros = jnp.zeros_like(world.position[:, 0])
    return SelfMemory(known=zeros > 1.0, centre=jnp.zeros_like(world.position), size=zeros,
                      side=zeros)


def _self_step(env: EmergencyEnv, world: WorldState, memory: SelfMemory
               ) -> tuple[SelfMemory, jax.Array, jax.Array, jax.Array]:
    """Senses (the robot's own hazard features only), updates the memory, and returns it
    with the self-reactive command ``[N, 2, B]``, whether that command is a reaction
    (``[N, B]``: a detour or a slide, not the plain drive home) and whether the robot
    knows the area exactly (``[N, B]``)."""
    p, v = world.position, world.velocity
    home = _pd(p, v, world.target)
    kind = _kind(env)
    if kind == "none":
        return memory, home, jnp.zeros_like(memory.known), memory.known
    features = env.scenario.hazard_features(world.hazard, p, env.radius)  # [N, H, B]
    sensed = features[:, 0] > 0.5  # inside the area, or touching the obstacle
    if kind == "area":
        known = memory.known | sensed
        centre = jnp.where(sensed[:, None], p + features[:, 1:3], memory.centre)
        size = jnp.where(sensed, features[:, 3], memory.size)
        memory = memory._replace(known=known, centre=centre, size=size)
        half = jnp.stack([size, size], axis=1) + CLEARANCE + env.robot_radius
        blocked, heading = go_round(p, world.target, centre, half,
                                    env.scenario.name == "turbulence")
        react = known & blocked
        return memory, jnp.where(react[:, None], _toward(v, heading), home), react, known
    # The obstacle: pressed against a face across the way, slide along it.
    pressed = sensed & (jnp.abs(v[:, 0]) < STOPPED_SPEED)
    rule = jnp.where(p[:, 1] >= env.layout.goal[1], 1.0, -1.0)
    side = jnp.where(pressed & (memory.side == 0.0), rule, memory.side)
    memory = memory._replace(side=side)
    slide = _toward(v, jnp.stack([jnp.zeros_like(side), side], axis=1))
    return memory, jnp.where(pressed[:, None], slide, home), pressed, memory.known


def self_reactive(env: EmergencyEnv) -> StatefulController:
    """Reacts only to what the robot senses itself (module docstring)."""

    def act(world: WorldState, memory: SelfMemory, key: jax.Array):
        del key
        memory, action, _, _ = _self_step(env, world, memory)
        return action, memory

    return StatefulController(init=_self_init, act=act)


class TeamMemory(NamedTuple):
    """``own``: :class:`SelfMemory`; ``age`` ``[N, N, B]``: steps since teammate ``j`` last
    warned robot ``i`` (in danger within range; large before any warning); ``point``
    ``[N, N, 2, B]``: where ``j`` was then."""

    own: SelfMemory
    age: jax.Array
    point: jax.Array


NEVER = 1_000_000  # the age of a warning never received


def team_informed(env: EmergencyEnv, comm_range: float | None = None, memory: int | None = None,
                  warning_radius: float = WARNING_RADIUS) -> StatefulController:
    """``self_reactive`` plus detours round teammates' recent dangers in range (module
    docstring). ``comm_range`` (default CCR's, ``CCRConfig().comm_range``) must lie in
    ``(0, arena diagonal]``; ``memory`` (default CCR's window, ``CCRConfig().window``) in
    ``[0, episode_length]``; both are checked here, when the controller is built."""
    defaults = CCRConfig()
    comm_range = defaults.comm_range if comm_range is None else comm_range
    memory = defaults.window if memory is None else memory
    diagonal = 2.0 * math.hypot(*env.layout.arena_half_extent)
    check_finite("team_informed", "comm_range", comm_range, low=0.0, low_open=True,
                 high=diagonal)
    check_int("team_informed", "memory", memory, 0, env.episode_length)
    check_finite("team_informed", "warning_radius", warning_radius, low=0.0, low_open=True,
                 high=diagonal)
    num_robots = env.num_robots
    other = ~np.eye(num_robots, dtype=bool)[:, :, None]  # [i, j, 1]
    grown = warning_radius + CLEARANCE + env.robot_radius

    def init(world: WorldState) -> TeamMemory:
        shape = (num_robots, num_robots, world.position.shape[-1])
        return TeamMemory(own=_self_init(world), age=jnp.full(shape, NEVER, jnp.int32),
                          point=jnp.zeros((num_robots, *world.position.shape), jnp.float32))

    def act(world: WorldState, state: TeamMemory, key: jax.Array):
        del key
        p, v = world.position, world.velocity
        own, action, reacting, known = _self_step(env, world, state.own)
        danger = env.scenario.in_danger(world.hazard, p, env.radius)  # [N, B]: perfect
        gap = p[:, None] - p[None, :]  # [i, j, 2, B]
        distance = jnp.sqrt(jnp.sum(gap * gap, axis=2))  # [i, j, B]
        warns = danger[None] & (distance <= comm_range) & other  # [i, j, B]
        age = jnp.where(warns, 0, jnp.minimum(state.age + 1, NEVER))
        point = jnp.where(warns[:, :, None], jnp.broadcast_to(p[None], state.point.shape),
                          state.point)
        active = age <= memory
        # Every robot's line to its target against every warning disc: [i, j, B].
        start = jnp.broadcast_to(p[:, None], point.shape)
        end = jnp.broadcast_to(world.target[:, None], point.shape)
        blocked = jax.vmap(_segment_hits_circle, in_axes=(1, 1, 1, None), out_axes=1)(
            start, end, point, grown) & active
        reach = jnp.where(blocked, jnp.sqrt(jnp.sum((point - start) ** 2, axis=2)), jnp.inf)
        nearest = (jnp.arange(num_robots)[None, :, None] == jnp.argmin(reach, axis=1)[:, None])
        centre = jnp.sum(jnp.where(nearest[:, :, None], point, 0.0), axis=1)  # [N, 2, B]
        radius = jnp.full_like(p, grown)
        _, heading = go_round(p, world.target, centre, radius, circle=True)
        warned = jnp.any(blocked, axis=1) & ~known & ~reacting
        action = jnp.where(warned[:, None], _toward(v, heading), action)
        return action, TeamMemory(own=own, age=age, point=point)

    return StatefulController(init=init, act=act)


def memoriser(env: EmergencyEnv, y_w: float | jax.Array) -> Controller:
    """The one fixed detour: every robot to ``(x_w, y_w + its slot's offset)``, ``x_w`` the
    centre of the hazard x range, then to its target. ``y_w``: a number, or ``[B]`` (one
    per environment), possibly traced."""
    x_w = 0.5 * (env.layout.hazard_x_range[0] + env.layout.hazard_x_range[1])
    goal_y = env.layout.goal[1]

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        p, v, target = world.position, world.velocity, world.target
        height = jnp.broadcast_to(jnp.asarray(y_w, jnp.float32), p.shape[-1:])[None]  # [1, B]
        aim = jnp.stack([jnp.full_like(target[:, 0], x_w), height + target[:, 1] - goal_y],
                        axis=1)
        before = (p[:, 0] < x_w)[:, None]
        return jnp.where(before, _toward(v, _unit(aim - p)), _pd(p, v, target))

    return act


def memoriser_heights(env: EmergencyEnv) -> np.ndarray:
    """The grid of waypoint heights: every ``MEMORISER_HEIGHT_STEP`` from the mid-line, as
    far as the whole team's waypoints (``y_w`` plus the target slots' offsets) keep its
    discs inside the arena (up to 1.6 with 5 robots in today's arena)."""
    layout = env.layout
    slots = 0.5 * (env.num_robots - 1) * layout.target_spacing
    reach = layout.arena_half_extent[1] - abs(layout.goal[1]) - slots - env.robot_radius
    count = int(math.floor(reach / MEMORISER_HEIGHT_STEP + 1e-6))
    offsets = MEMORISER_HEIGHT_STEP * np.arange(-count, count + 1)
    return (env.layout.goal[1] + offsets).astype(np.float32)


def choose_height(heights: jax.Array, success: jax.Array, danger: jax.Array,
                  oracle_success: jax.Array) -> jax.Array:
    """Index of the memoriser's height in ``heights`` (traceable; numpy arrays work too):
    the lowest danger among the heights whose success is within ``SUCCESS_SLACK`` of the
    oracle's (ties: the higher success), else the highest success (ties: the lower
    danger); remaining ties: the height nearest the grid's middle."""
    heights, success, danger = (jnp.asarray(a, jnp.float32) for a in (heights, success, danger))
    near = jnp.abs(heights - 0.5 * (heights[0] + heights[-1]))
    eligible = success >= oracle_success - SUCCESS_SLACK - 1e-6
    some = jnp.any(eligible)
    first = jnp.where(some, jnp.where(eligible, danger, jnp.inf), -success)
    tied = first == jnp.min(first)
    second = jnp.where(some, -success, danger)
    tied = tied & (second == jnp.min(jnp.where(tied, second, jnp.inf)))
    return jnp.argmin(jnp.where(tied, near, jnp.inf))


def _slice_world(world: WorldState, start: int, stop: int) -> WorldState:
    def part(array: jax.Array) -> jax.Array:
        return array[..., start:stop]

    return world.replace(position=part(world.position), velocity=part(world.velocity),
                         target=part(world.target), hazard=jax.tree.map(part, world.hazard))


def in_blocks(controllers: Sequence[Controller | StatefulController], block: int
              ) -> StatefulController:
    """One controller for a batch of ``len(controllers) * block`` environments: controller
    ``k`` drives environments ``k * block`` to ``(k + 1) * block - 1`` (and sees only them).
    Environments of a batch never interact, so every controller is measured as if alone,
    and a program holds them all: one compilation instead of one each."""

    def init(world: WorldState) -> tuple[Any, ...]:
        return tuple(
            c.init(_slice_world(world, k * block, (k + 1) * block))
            if isinstance(c, StatefulController) else ()
            for k, c in enumerate(controllers))

    def act(world: WorldState, memory: tuple[Any, ...], key: jax.Array):
        actions, memories = [], []
        for k, (c, mine) in enumerate(zip(controllers, memory, strict=True)):
            part = _slice_world(world, k * block, (k + 1) * block)
            if isinstance(c, StatefulController):
                action, mine = c.act(part, mine, key)
            else:
                action = c(part, key)
            actions.append(action)
            memories.append(mine)
        return jnp.concatenate(actions, axis=-1), tuple(memories)

    return StatefulController(init=init, act=act)


INFORMATION_CONTROLLERS: dict[str, Callable[..., Controller | StatefulController]] = {
    "self_reactive": self_reactive,
    "team_informed": team_informed,
    "memoriser": memoriser,
}
