"""Hand-written reference controllers that read the environment's state.

They are the *control* on which the scenarios are calibrated (never CCR or the
pessimistic baseline) and the rows that bound what a learner can reach:

* ``go_to_goal``: hazard-blind, drives each robot to its own target with a
  saturated per-axis PD law, ``u = clip(kp (target - p) - kd v, -1, 1)``; the
  paper's plain learners head for the target in the same way;
* ``oracle``: knows the hazard (centre, size, shape) and detours around it with a
  clearance margin, passing on the side of the hazard's centre the robot is on; it
  shows the task can be done safely;
* gaming policies that ignore the task and must score (near) zero success:
  ``stand_still``, ``flee_sideways`` (full speed away from the mid-line),
  ``overshoot`` (full speed along the way, forever) and ``dash_away`` (full speed
  along the way while steering away from the mid-line: with a "far side of the
  hazard" success rule it scored 100% success and 0% danger).

Every controller is ``(world, key) -> action float32[N, 2, B]`` (continuous
actions), or a :class:`ccrjax.training.acting.StatefulController` when it needs memory
across steps (``self_reactive`` and ``team_informed`` of ``information_controllers.py``,
which :func:`evaluate_controller` runs too, with its ``memoriser``), and runs through
:func:`ccrjax.training.acting.run_episode`, the loop and metrics that evaluate the learners.
In an environment with discrete actions (MAAC's), each command is snapped to the nearest
action of the environment's set (:func:`snap_to_action_set`): what the same controller can
do with those actions.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from ccrjax.envs.env import EmergencyEnv, WorldState
from ccrjax.envs.world import DISCRETE_ACTION_SETS
from ccrjax.training.acting import StatefulController, episode_metrics, run_episode
from ccrjax.transforms import Plain

# The PD gains: about the fastest arrival from 3 units away (19 steps) with an overshoot
# of 0.02 under the MPE's damping 0.25 and sensitivity 5 (v' = 0.75 v + 0.5 u per step).
KP, KD = 10.0, 2.0
# How far the oracle keeps a robot's disc from a hazard's boundary.
CLEARANCE = 0.1

Controller = Callable[[WorldState, jax.Array], jax.Array]


def _pd(position: jax.Array, velocity: jax.Array, aim: jax.Array) -> jax.Array:
    return jnp.clip(KP * (aim - position) - KD * velocity, -1.0, 1.0)


def go_to_goal(env: EmergencyEnv) -> Controller:
    """Hazard-blind: every robot straight to its own target."""
    del env

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        return _pd(world.position, world.velocity, world.target)

    return act


def _toward(velocity: jax.Array, heading: jax.Array) -> jax.Array:
    """The action that brings the velocity to full speed along ``heading`` (``[N, 2, B]``).

    Full speed is the largest velocity along ``heading`` inside the action box (2 units/s
    on the larger axis), reached through ``v' = 0.75 v + 0.5 u``.
    """
    scale = 1.0 / jnp.maximum(jnp.max(jnp.abs(heading), axis=1, keepdims=True), 1e-6)
    desired = 2.0 * heading * scale
    return jnp.clip((desired - 0.75 * velocity) / 0.5, -1.0, 1.0)


def _segment_hits_box(start, end, centre, half):
    """``bool[N, B]``: the segment ``start -> end`` (``[N, 2, B]``) meets the open box."""
    lows, highs = [], []
    for axis in range(2):
        s = start[:, axis] - centre[:, axis]
        d = end[:, axis] - start[:, axis]
        moving = d != 0.0
        safe = jnp.where(moving, d, 1.0)
        t_a, t_b = (-half[:, axis] - s) / safe, (half[:, axis] - s) / safe
        inside = jnp.abs(s) < half[:, axis]
        lows.append(jnp.where(moving, jnp.minimum(t_a, t_b), jnp.where(inside, -jnp.inf, jnp.inf)))
        highs.append(jnp.where(moving, jnp.maximum(t_a, t_b), jnp.where(inside, jnp.inf, -jnp.inf)))
    low, high = jnp.maximum(lows[0], lows[1]), jnp.minimum(highs[0], highs[1])
    return (low < high) & (low < 1.0) & (high > 0.0)


def _segment_hits_circle(start, end, centre, radius):
    """``bool[N, B]``: the segment ``start -> end`` comes closer than ``radius`` to ``centre``."""
    d = end - start
    f = centre - start
    length2 = jnp.maximum(jnp.sum(d * d, axis=1), 1e-12)
    t = jnp.clip(jnp.sum(f * d, axis=1) / length2, 0.0, 1.0)
    closest = start + t[:, None] * d
    gap = closest - centre
    return jnp.sum(gap * gap, axis=1) < radius * radius


def oracle(env: EmergencyEnv) -> Controller:
    """Knows the hazard; goes around it, ``CLEARANCE`` away from its boundary.

    While the straight line to its target meets the hazard grown by the margin, a
    robot heads at full speed along the tangent to the grown circle (turbulence) or
    for the next corner of the grown box (wind, obstacle) on its own side of the
    hazard's centre; once the line is free it drives to its target like
    :func:`go_to_goal`.
    """
    circle = env.scenario.name == "turbulence"
    blind = env.scenario.name == "nominal"
    margin = CLEARANCE + env.robot_radius

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        home = _pd(world.position, world.velocity, world.target)
        if blind:
            return home
        p = world.position
        centre = world.hazard.centre[None]  # [1, 2, B]
        half = world.hazard.half_extent[None] + margin
        side = jnp.where(p[:, 1] >= centre[:, 1], 1.0, -1.0)  # [N, B]
        if circle:
            radius = half[:, 0]
            blocked = _segment_hits_circle(p, world.target, centre, radius)
            to_centre = centre - p
            distance = jnp.sqrt(jnp.sum(to_centre * to_centre, axis=1))
            u = to_centre / jnp.maximum(distance, 1e-6)[:, None]
            angle = jnp.arcsin(jnp.clip(radius / jnp.maximum(distance, 1e-6), 0.0, 1.0))
            cos, sin = jnp.cos(angle), side * jnp.sin(angle)
            # The centre's direction turned by the tangent angle towards the robot's side.
            heading = jnp.stack(
                [u[:, 0] * cos - u[:, 1] * sin, u[:, 1] * cos + u[:, 0] * sin], axis=1
            )
        else:
            blocked = _segment_hits_box(p, world.target, centre, half)
            before = p[:, 0] < centre[:, 0] - half[:, 0]
            corner_x = centre[:, 0] + jnp.where(before, -1.0, 1.0) * half[:, 0]
            corner_y = centre[:, 1] + side * half[:, 1]
            # Beyond the corner along the way, so the robot does not slow down at it.
            aim = jnp.stack([corner_x + jnp.where(before, 0.0, 0.2), corner_y], axis=1)
            heading = aim - p
            heading = heading / jnp.maximum(
                jnp.sqrt(jnp.sum(heading * heading, axis=1, keepdims=True)), 1e-6
            )
        return jnp.where(blocked[:, None], _toward(world.velocity, heading), home)

    return act


def stand_still(env: EmergencyEnv) -> Controller:
    """Gaming: never moves (never in danger, never arrives)."""
    del env

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        return jnp.zeros_like(world.position)

    return act


def _fixed_x_away_in_y(env: EmergencyEnv, along: float) -> Controller:
    """Action ``along`` on x, full action away from the mid-line on y."""

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        away = jnp.where(world.position[:, 1] >= env.layout.goal[1], 1.0, -1.0)
        return jnp.stack([jnp.full_like(away, along), away], axis=1)

    return act


def flee_sideways(env: EmergencyEnv) -> Controller:
    """Gaming: full speed away from the mid-line, never towards the target."""
    return _fixed_x_away_in_y(env, 0.0)


def overshoot(env: EmergencyEnv) -> Controller:
    """Gaming: the constant action (1, 0), full speed along the way forever."""
    del env

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        del key
        ones = jnp.ones_like(world.position[:, 0])
        return jnp.stack([ones, jnp.zeros_like(ones)], axis=1)

    return act


def dash_away(env: EmergencyEnv) -> Controller:
    """Gaming: full speed along the way while steering away from the mid-line."""
    return _fixed_x_away_in_y(env, 1.0)


CONTROLLERS: dict[str, Callable[[EmergencyEnv], Controller]] = {
    "go_to_goal": go_to_goal,
    "oracle": oracle,
    "stand_still": stand_still,
    "flee_sideways": flee_sideways,
    "overshoot": overshoot,
    "dash_away": dash_away,
}
GAMING = ("stand_still", "flee_sideways", "overshoot", "dash_away")


def snap_to_action_set(controller: Controller | StatefulController, action_set: str
                       ) -> Controller | StatefulController:
    """``controller`` with each command replaced by the nearest (Euclidean; ties to the
    lower index) action of the discrete ``action_set``: ``int32[N, B]`` actions."""
    directions = jnp.asarray(DISCRETE_ACTION_SETS[action_set])  # [A, 2]

    def snap(command: jax.Array) -> jax.Array:  # [N, 2, B] -> [N, B]
        gap = command[:, None] - directions[None, :, :, None]  # [N, A, 2, B]
        return jnp.argmin(jnp.sum(gap * gap, axis=2), axis=1).astype(jnp.int32)

    if isinstance(controller, StatefulController):
        def remember(world: WorldState, memory, key: jax.Array):
            command, memory = controller.act(world, memory, key)
            return snap(command), memory

        return StatefulController(init=controller.init, act=remember)

    def act(world: WorldState, key: jax.Array) -> jax.Array:
        return snap(controller(world, key))

    return act


def evaluate_controller(env: EmergencyEnv, name: str, key: jax.Array, **params
                        ) -> dict[str, jax.Array]:
    """The learners' evaluation metrics of controller ``name`` over ``env.num_envs`` episodes
    (snapped to the environment's discrete actions if it has them): one of
    :data:`CONTROLLERS` or of ``information_controllers.INFORMATION_CONTROLLERS``, built
    with ``params`` (the memoriser needs its height ``y_w``)."""
    # Imported here: information_controllers imports this module.
    from experiments.information_controllers import INFORMATION_CONTROLLERS

    known = {**CONTROLLERS, **INFORMATION_CONTROLLERS}
    if name not in known:
        raise ValueError(f"controller must be one of {sorted(known)}, got {name!r}")
    controller = known[name](env, **params)
    if env.discrete_actions:
        controller = snap_to_action_set(controller, env.discrete_action_set)
    transform = Plain()
    _, episode = run_episode(
        env, transform, transform.init(env), None, env.discrete_actions, key,
        controller=controller,
    )
    return episode_metrics(episode)
