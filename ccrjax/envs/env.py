"""The multi-robot emergency environment, batched, behind brax's ``Env`` interface.

One :class:`EmergencyEnv` holds ``num_envs`` environments of one scenario and steps
them all in one call. Following :mod:`ccrjax.envs.world`, every array has the
environment batch as its **last** axis, and every per-robot array has the robot
axis first:

=================================  =========================================
``state.obs``                      ``float32[N, observation_size, B]``
``state.reward``                   ``float32[N, B]``: ``-|p_i - target_i|``
``state.done``                     ``float32[B]``: the episode ended this step
``state.metrics["danger"]``        ``float32[N, B]``: 1 while in danger
``state.metrics["success"]``       ``float32[N, B]``: 1 while in the target area
``state.metrics["target_distance"]`` ``float32[N, B]``: ``|p_i - target_i|``
``state.metrics["hazard_distance"]`` ``float32[N, B]``: ``|p_i - hazard centre|``
continuous action                  ``float[N, 2, B]`` in ``[-1, 1]^2``
discrete action                    ``int[N, B]``, an index into the action set
=================================  =========================================

Robot ``i`` observes, in this order (``observation_size = 4 + 3 (N - 1) + 3 + H``):
its position and velocity (4); for every other robot ``j`` in increasing index
order, the distance ``|p_j - p_i|`` and the unit direction ``(p_j - p_i) / |p_j - p_i|``
(3 each); the distance and unit direction to its own target point in the target
area (3); the ``H`` hazard features its scenario allows (:mod:`ccrjax.envs.scenarios`).

A robot succeeds when it is in the target area at the end of the episode
(``metrics["success"]`` of the last step): the paper's robots "navigate to a
target point", so reaching the far side of a hazard and then wandering off, or
passing through the area and overshooting, is no success.

Episodes have a fixed length and all ``B`` environments run in lockstep, so the
episode clock is one scalar. :meth:`EmergencyEnv.step` resets every environment when
the clock reaches ``episode_length``: positions *and hazards* are drawn anew
from the state's key (never a cached first episode). :meth:`EmergencyEnv.transition`
is the same step without the reset, for learners that handle episode boundaries
themselves and need the terminal observation.

The environments are registered in brax's registry as ``ccr_<scenario>``::

    env = brax.envs.get_environment("ccr_hidden_obstacle", num_envs=1024)
"""

from __future__ import annotations

import contextlib
import functools
import io
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ccrjax.checks import check_choice, check_int, check_number
from ccrjax.envs.scenarios import SCENARIOS, Hazard, Layout, Scenario, make_scenario
from ccrjax.envs.scenarios.base import distance_to_centre
from ccrjax.envs.scenarios.layout import (
    distance_to,
    in_target_area,
    start_positions,
    target_positions,
)
from ccrjax.envs.world import (
    DEFAULT_DISCRETE_ACTION_SET,
    DISCRETE_ACTION_SETS,
    PhysicsParams,
    action_to_force,
    physics_step,
)

# brax pulls in MuJoCo's MJX, which prints to stdout when the optional NVIDIA Warp
# is missing; keep our commands' output clean.
with contextlib.redirect_stdout(io.StringIO()):
    from brax import envs as brax_envs
    from brax.envs.base import Env, State

MIN_ROBOTS, MAX_ROBOTS = 2, 64
ROBOT_RADIUS = 0.05  # the MPE's agent size


def check_team(scenario: Scenario, num_robots: int, episode_length: int,
               robot_radius: float = ROBOT_RADIUS, layout: Layout | None = None) -> None:
    """Refuses a team and episode the environment cannot run (the checks that need no
    environment: a training configuration makes them when it is built)."""
    check_int("", "num_robots", num_robots, MIN_ROBOTS, MAX_ROBOTS)
    check_int("", "episode_length", episode_length, 1)
    layout = layout or Layout()
    layout.check_team(num_robots, robot_radius)
    layout.check_episode(num_robots, episode_length)
    scenario.check_layout(layout, robot_radius)


@struct.dataclass
class WorldState:
    """Everything that evolves in a batch of environments (brax's ``pipeline_state``)."""

    position: jax.Array  # float32[N, 2, B]
    velocity: jax.Array  # float32[N, 2, B]
    hazard: Hazard  # arrays [2, B]
    target: jax.Array  # float32[N, 2, B]: each robot's own destination in the target area
    time: jax.Array  # int32[]: steps since the episode started (shared by the batch)
    key: jax.Array  # PRNG key for hazard noise and the next reset


class EmergencyEnv(Env):
    """A batch of ``num_envs`` multi-robot environments of one emergency scenario (the
    world with its hazard; CCR itself is a transform, :mod:`ccrjax.transforms.ccr`).

    Args:
      scenario: a name in ``ccrjax.envs.scenarios.SCENARIOS`` or a ``Scenario`` object.
      num_robots: team size ``N``, 2 to 64 (default 5).
      num_envs: environments ``B`` stepped together.
      episode_length: steps per episode: the MPE's 25 by default (2.5 simulated
        seconds; the straight trip at full speed takes about 18 of them).
      robot_radius: disc radius (the MPE's default 0.05).
      sensitivity: force per unit action (the MPE's default 5).
      discrete_actions: discrete actions instead of a 2-D continuous force.
      discrete_action_set: which discrete actions: ``"box9"`` (default: ``{-1, 0, 1}^2``,
        every speed the continuous force reaches) or ``"mpe5"`` (the MPE's none, -x, +x,
        -y, +y); :data:`ccrjax.envs.world.DISCRETE_ACTION_SETS` says why.
      layout: where robots start and go (:class:`ccrjax.envs.scenarios.Layout`).
      physics: physics constants (:class:`ccrjax.envs.world.PhysicsParams`).
      scenario_params: keyword parameters of the scenario, e.g. ``{"max_force": 5.0}``.
    """

    def __init__(
        self,
        scenario: str | Scenario = "nominal",
        *,
        num_robots: int = 5,
        num_envs: int = 1,
        episode_length: int = 25,
        robot_radius: float = ROBOT_RADIUS,
        sensitivity: float = 5.0,
        discrete_actions: bool = False,
        discrete_action_set: str = DEFAULT_DISCRETE_ACTION_SET,
        layout: Layout | None = None,
        physics: PhysicsParams | None = None,
        scenario_params: dict[str, Any] | None = None,
    ) -> None:
        if isinstance(scenario, Scenario):
            if scenario_params:
                raise ValueError("scenario_params must be empty when scenario is a Scenario object")
            self.scenario = scenario
        elif isinstance(scenario, str):
            self.scenario = make_scenario(scenario, **(scenario_params or {}))
        else:
            raise ValueError(
                f"scenario must be one of {sorted(SCENARIOS)} or a Scenario, got {scenario!r}"
            )
        check_int("", "num_envs", num_envs, 1)
        check_number("", "robot_radius", robot_radius, positive=True)
        check_number("", "sensitivity", sensitivity, positive=True)
        if not isinstance(discrete_actions, bool):
            raise ValueError(f"discrete_actions must be True or False, got {discrete_actions!r}")
        check_choice("", "discrete_action_set", discrete_action_set, DISCRETE_ACTION_SETS)
        if layout is not None and not isinstance(layout, Layout):
            raise ValueError(f"layout must be a ccrjax.envs.scenarios.Layout, got {layout!r}")
        if physics is not None and not isinstance(physics, PhysicsParams):
            raise ValueError(f"physics must be a ccrjax.envs.world.PhysicsParams, got {physics!r}")
        check_team(self.scenario, num_robots, episode_length, float(robot_radius), layout)
        self.num_robots = int(num_robots)
        self.num_envs = int(num_envs)
        self.episode_length = int(episode_length)
        self.robot_radius = float(robot_radius)
        self.sensitivity = float(sensitivity)
        self.discrete_actions = discrete_actions
        self.discrete_action_set = discrete_action_set
        self.layout = layout or Layout()
        self.physics = physics or PhysicsParams()
        # For robot i, the indices of the other robots in increasing order: [N, N - 1].
        self._others = np.array(
            [[j for j in range(self.num_robots) if j != i] for i in range(self.num_robots)],
            dtype=np.int32,
        )

    # ------------------------------------------------------------------ sizes
    @property
    def observation_size(self) -> int:
        """Features per robot: ``4 + 3 (N - 1) + 3 + hazard features``."""
        return 4 + 3 * (self.num_robots - 1) + 3 + self.scenario.hazard_feature_size

    @property
    def action_size(self) -> int:
        """2 for the continuous force, else the number of discrete choices."""
        return self.num_discrete_actions if self.discrete_actions else 2

    @property
    def num_discrete_actions(self) -> int:
        """How many actions the discrete action set holds (whichever space is in use)."""
        return len(DISCRETE_ACTION_SETS[self.discrete_action_set])

    @property
    def backend(self) -> str:
        return "ccrjax"

    @property
    def radius(self) -> jax.Array:
        """``float32[N]``: every robot's disc radius (the team is homogeneous)."""
        return jnp.full((self.num_robots,), self.robot_radius, jnp.float32)

    @property
    def goal(self) -> jax.Array:
        """``float32[2]``: the centre of the target area."""
        return jnp.asarray(self.layout.goal, jnp.float32)

    # ------------------------------------------------------------------ pieces
    def initial_world(self, key: jax.Array) -> WorldState:
        """Draws start positions and hazards for every environment of the batch."""
        key, position_key, hazard_key = jax.random.split(key, 3)
        position = start_positions(position_key, self.layout, self.num_robots, self.num_envs)
        hazard = self.scenario.sample_hazard(hazard_key, self.layout, self.num_envs)
        return WorldState(
            position=position,
            velocity=jnp.zeros_like(position),
            hazard=hazard,
            target=target_positions(position, self.layout),
            time=jnp.zeros((), jnp.int32),
            key=key,
        )

    def observe(self, world: WorldState) -> jax.Array:
        """Each robot's observation, ``float32[N, observation_size, B]``."""
        position = world.position
        rel_x = position[None, :, 0] - position[:, None, 0]  # [i, j, B]: p_j - p_i
        rel_y = position[None, :, 1] - position[:, None, 1]
        rows = np.arange(self.num_robots)[:, None]
        rel_x = rel_x[rows, self._others]  # [N, N - 1, B]
        rel_y = rel_y[rows, self._others]
        distance = jnp.sqrt(rel_x * rel_x + rel_y * rel_y)
        inverse = jnp.where(distance > 0.0, 1.0 / jnp.where(distance > 0.0, distance, 1.0), 0.0)
        others = jnp.stack([distance, rel_x * inverse, rel_y * inverse], axis=2)
        others = others.reshape(self.num_robots, 3 * (self.num_robots - 1), self.num_envs)

        to_goal_x = world.target[:, 0] - position[:, 0]  # [N, B]
        to_goal_y = world.target[:, 1] - position[:, 1]
        goal_distance = jnp.sqrt(to_goal_x * to_goal_x + to_goal_y * to_goal_y)
        inverse_goal = jnp.where(
            goal_distance > 0.0, 1.0 / jnp.where(goal_distance > 0.0, goal_distance, 1.0), 0.0
        )
        goal_features = jnp.stack(
            [goal_distance, to_goal_x * inverse_goal, to_goal_y * inverse_goal], axis=1
        )
        hazard = self.scenario.hazard_features(world.hazard, position, self.radius)
        return jnp.concatenate(
            [position, world.velocity, others, goal_features, hazard], axis=1
        )

    def reward(self, world: WorldState) -> jax.Array:
        """``-|p_i - target_i|`` per robot, ``float32[N, B]``: the paper's distance reward."""
        return -distance_to(world.position, world.target)

    def metrics(self, world: WorldState) -> dict[str, jax.Array]:
        """Per robot and environment, at this step: in danger, in the target area (a
        success if it is the episode's last step), the distance to its target and to
        the hazard's centre."""
        return {
            "danger": self.scenario.in_danger(world.hazard, world.position, self.radius).astype(
                jnp.float32
            ),
            "success": in_target_area(world.position, self.layout).astype(jnp.float32),
            "target_distance": distance_to(world.position, world.target),
            "hazard_distance": distance_to_centre(world.position, world.hazard),
        }

    def check_action(self, action: jax.Array) -> None:
        """Raises ``ValueError`` (at trace time) unless ``action`` has this env's layout."""
        if self.discrete_actions:
            expected = (self.num_robots, self.num_envs)
            ok = action.shape == expected and jnp.issubdtype(action.dtype, jnp.integer)
            what = (f"int[{expected[0]}, {expected[1]}] (robots, envs) with values "
                    f"0..{self.num_discrete_actions - 1}")
        else:
            expected = (self.num_robots, 2, self.num_envs)
            ok = action.shape == expected
            what = f"float[{expected[0]}, 2, {expected[2]}] (robots, xy, envs)"
        if not ok:
            raise ValueError(f"action must be {what}, got {action.dtype}{list(action.shape)}")

    def advance(self, world: WorldState, action: jax.Array, noise: jax.Array) -> WorldState:
        """The deterministic part of a step, given this step's hazard noise.

        Forces (actions, hazard), MPE physics, the hazard's constraint (the solid
        obstacle) and the clock; ``noise`` comes from ``scenario.step_noise``.
        """
        force = action_to_force(action, self.sensitivity, self.discrete_actions,
                                self.discrete_action_set)
        force = force + self.scenario.hazard_force(world.hazard, world.position, noise)
        position, velocity = physics_step(
            world.position, world.velocity, self.radius, force, self.physics
        )
        # Materialised once: otherwise XLA fuses the physics into each use the constraint
        # makes of it, recomputing the contact forces several times (a 4x slower step).
        position, velocity = jax.lax.optimization_barrier((position, velocity))
        position, velocity = self.scenario.constrain(
            world.hazard, world.position, position, velocity, self.radius
        )
        position, velocity = jax.lax.optimization_barrier((position, velocity))
        return world.replace(position=position, velocity=velocity, time=world.time + 1)

    def _state(self, world: WorldState, reward: jax.Array, done: jax.Array) -> State:
        return State(
            pipeline_state=world,
            obs=self.observe(world),
            reward=reward,
            done=done,
            metrics=self.metrics(world),
            info={},
        )

    # ------------------------------------------------------------------ brax API
    def reset(self, rng: jax.Array) -> State:
        """Starts ``num_envs`` fresh episodes drawn from ``rng``."""
        world = self.initial_world(rng)
        zeros = jnp.zeros((self.num_robots, self.num_envs), jnp.float32)
        return self._state(world, zeros, jnp.zeros((self.num_envs,), jnp.float32))

    def transition(self, state: State, action: jax.Array) -> State:
        """One step of every environment, without the automatic reset."""
        self.check_action(action)
        world = state.pipeline_state
        if self.scenario.needs_step_noise:
            key, noise_key = jax.random.split(world.key)
            world = world.replace(key=key)
            noise = self.scenario.step_noise(noise_key, self.num_robots, self.num_envs)
        else:
            noise = self.scenario.step_noise(world.key, self.num_robots, self.num_envs)
        world = self.advance(world, action, noise)
        done = jnp.broadcast_to(world.time >= self.episode_length, (self.num_envs,))
        return self._state(world, self.reward(world), done.astype(jnp.float32))

    def step(self, state: State, action: jax.Array) -> State:
        """One step of every environment; at the episode's end, all reset together.

        ``reward``, ``done`` and ``metrics`` describe the step just taken; after a
        reset, ``obs`` and ``pipeline_state`` are the new episode's first.
        """
        stepped = self.transition(state, action)
        world = stepped.pipeline_state

        def start_new_episode(world: WorldState) -> tuple[WorldState, jax.Array]:
            fresh = self.initial_world(world.key)
            return fresh, self.observe(fresh)

        def carry_on(world: WorldState) -> tuple[WorldState, jax.Array]:
            return world, stepped.obs

        world, obs = jax.lax.cond(
            world.time >= self.episode_length, start_new_episode, carry_on, world
        )
        return stepped.replace(pipeline_state=world, obs=obs)


OTHER_ROBOTS_START = 4  # observation features 4 .. 4 + 3 (N - 1): the other robots


def other_robot_features(obs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """From observations ``[N, F, B]``: each robot's distance and unit direction ``(ux, uy)``
    to every other robot (increasing index order), each ``[N, N - 1, B]``."""
    num_robots, _, batch = obs.shape
    block = obs[:, OTHER_ROBOTS_START:OTHER_ROBOTS_START + 3 * (num_robots - 1)]
    block = block.reshape(num_robots, num_robots - 1, 3, batch)
    return block[:, :, 0], block[:, :, 1], block[:, :, 2]


def of_other_robots(values: jax.Array) -> jax.Array:
    """``values`` ``[N, B]`` (one per robot) as each robot sees the others': ``[N, N - 1, B]``,
    entry ``[i, k]`` the value of the ``k``-th other robot of ``i`` in increasing index order.

    Slices and reshapes only (no gather): the ``N x N`` broadcast, its diagonal dropped.
    """
    num_robots, batch = values.shape
    full = jnp.broadcast_to(values[None], (num_robots, num_robots, batch))
    flat = full.reshape(num_robots * num_robots, batch)[1:]
    return flat.reshape(num_robots - 1, num_robots + 1, batch)[:, :num_robots].reshape(
        num_robots, num_robots - 1, batch
    )


def random_actions(key: jax.Array, env: EmergencyEnv) -> jax.Array:
    """Uniformly random actions for every robot of every environment of ``env``.

    Continuous: ``float32[N, 2, B]`` uniform in ``[-1, 1)`` at 16-bit resolution,
    both components of a robot's force cut from one 32-bit random word (random
    numbers are a large share of a cheap step on CPU, so we draw half as many).
    Discrete: ``int32[N, B]`` uniform over the action set.
    """
    shape = (env.num_robots, env.num_envs)
    if env.discrete_actions:
        return jax.random.randint(key, shape, 0, env.num_discrete_actions, jnp.int32)
    bits = jax.random.bits(key, shape, jnp.uint32)
    halves = jnp.stack([bits >> 16, bits & 0xFFFF], axis=1).astype(jnp.float32)
    return halves * (2.0 / 65536.0) - 1.0


def batch_major(x: jax.Array) -> jax.Array:
    """Moves the batch axis (last) to the front, e.g. obs ``[N, F, B] -> [B, N, F]``."""
    return jnp.moveaxis(x, -1, 0)


def batch_minor(x: jax.Array) -> jax.Array:
    """Inverse of :func:`batch_major`: ``[B, ...] -> [..., B]``."""
    return jnp.moveaxis(x, 0, -1)


def registered_name(scenario: str) -> str:
    """The brax registry name of a scenario: ``ccr_<scenario>``."""
    return f"ccr_{scenario}"


for _name in SCENARIOS:
    brax_envs.register_environment(
        registered_name(_name), functools.partial(EmergencyEnv, scenario=_name)
    )

