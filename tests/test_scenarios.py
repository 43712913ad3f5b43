"""Tests of the emergency scenarios (:mod:`ccrjax.envs.scenarios`).

Hazards and robot positions are placed by hand (batch axis last: positions ``[N, 2, B]``,
hazard arrays ``[2, B]``), so every expected value can be read off the test.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ccrjax.envs.scenarios import (
    SCENARIOS,
    Hazard,
    HiddenObstacle,
    Layout,
    Nominal,
    StrongWind,
    Turbulence,
    make_scenario,
)
from ccrjax.envs.scenarios.layout import in_target_area
from ccrjax.envs.world import PhysicsParams, action_to_force, physics_step, rectangle_distance

PHYSICS = PhysicsParams()
NAMES = ["turbulence", "strong_wind", "hidden_obstacle", "nominal"]
PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def make_hazard(centre, half, direction=(0.0, 0.0)) -> Hazard:
    """A hazard for one environment, or several if the arguments are lists of pairs."""

    def column(value):
        array = np.asarray(value, np.float32)
        return jnp.asarray(array.T if array.ndim == 2 else array[:, None])

    return Hazard(centre=column(centre), half_extent=column(half), direction=column(direction))


def positions(*points) -> jnp.ndarray:
    """``float32[N, 2, 1]`` from N ``(x, y)`` points."""
    return jnp.asarray(np.array(points, np.float32)[:, :, None])


def radii(n: int) -> jnp.ndarray:
    return jnp.full((n,), 0.05, jnp.float32)


@functools.cache
def jitted(scenario, method: str):
    """A scenario method compiled once."""
    fn = getattr(scenario, method)
    if method == "step_noise":
        return jax.jit(fn, static_argnums=(1, 2))
    return jax.jit(fn)


def call(scenario, method, *args):
    return np.asarray(jitted(scenario, method)(*args))


def no_noise(n: int, batch: int = 1) -> jnp.ndarray:
    return jnp.zeros((n, 0, batch), jnp.float32)


# --------------------------------------------------------------------------- hazard forces

# Hazard centred at (0.2, -0.1) with half extent 0.4 (the turbulence circle's radius, the
# wind square's half side); the wind blows along +y.
CENTRE, HALF, WIND = (0.2, -0.1), (0.4, 0.4), (0.0, 1.0)
PLACED = positions(
    (0.2, -0.1),  # 0: the centre                      circle: in   square: in
    (0.55, -0.1),  # 1: 0.35 right of it                circle: in   square: in
    (0.2, 0.29),  # 2: 0.39 above                      circle: in   square: in
    (-0.05, -0.35),  # 3: (-0.25, -0.25), |.| = 0.354     circle: in   square: in
    (0.55, 0.25),  # 4: (0.35, 0.35), |.| = 0.495       circle: out  square: in
    (0.65, -0.1),  # 5: 0.45 right                      circle: out  square: out
    (0.2, -0.51),  # 6: 0.41 below                      circle: out  square: out
    (2.0, 2.0),  # 7: far away                         circle: out  square: out
    (-1.5, 0.0),  # 8: the start                       circle: out  square: out
)
IN_CIRCLE = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0], bool)
IN_SQUARE = np.array([1, 1, 1, 1, 1, 0, 0, 0, 0], bool)


def test_turbulence_force_acts_inside_the_circle_only():
    scenario = Turbulence()
    hazard = make_hazard(CENTRE, HALF)
    n = PLACED.shape[0]
    # Noise (direction fraction 1/8, magnitude fraction 1/2): force = 10 * 0.5 * (cos 45, sin 45).
    noise = jnp.tile(jnp.array([0.125, 0.5], jnp.float32)[None, :, None], (n, 1, 1))
    force = call(scenario, "hazard_force", hazard, PLACED, noise)
    expected = np.where(IN_CIRCLE[:, None], 5.0 / math.sqrt(2.0), 0.0)
    np.testing.assert_allclose(force[:, :, 0], np.tile(expected, (1, 2)), atol=1e-5)
    assert np.all(force[~IN_CIRCLE] == 0.0)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_strong_wind_force_acts_inside_the_square_only(sign):
    # The default force is 10 along the episode's direction (0, +1) or (0, -1).
    scenario = StrongWind()
    hazard = make_hazard(CENTRE, HALF, (0.0, sign))
    n = PLACED.shape[0]
    force = call(scenario, "hazard_force", hazard, PLACED, no_noise(n))
    expected = np.where(IN_SQUARE[:, None], [0.0, 10.0 * sign], 0.0)
    np.testing.assert_allclose(force[:, :, 0], expected, atol=1e-6)
    assert np.all(force[~IN_SQUARE] == 0.0)


@pytest.mark.parametrize("name", ["turbulence", "strong_wind"])
def test_area_force_uses_each_environments_own_hazard(name):
    # Two environments: the hazard of the first covers robot 0, that of the second is far away.
    scenario = make_scenario(name)
    hazard = make_hazard([(0.0, 0.0), (5.0, 5.0)], [(0.5, 0.5), (0.5, 0.5)], [(0, 1), (0, 1)])
    position = jnp.zeros((2, 2, 2)).at[1].set(3.0)  # robot 0 at the origin, robot 1 at (3, 3)
    noise = jnp.full((2, 2, 2), 0.5, jnp.float32)
    noise = noise[:, :0] if not scenario.needs_step_noise else noise
    force = call(scenario, "hazard_force", hazard, position, noise)
    assert np.linalg.norm(force[0, :, 0]) > 1.0
    assert np.all(force[1] == 0.0)
    assert np.all(force[:, :, 1] == 0.0)


@pytest.mark.parametrize("scenario", [HiddenObstacle(), Nominal()], ids=["obstacle", "nominal"])
def test_obstacle_and_nominal_exert_no_force(scenario):
    # The obstacle is a constraint on positions (Scenario.constrain), not a force: robots
    # touching it, overlapping it or far away feel nothing from it.
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))
    placed = positions((-0.25, 0.0), (-0.23, 0.0), (0.0, 0.0), (0.0, 0.55), (3.0, 3.0))
    force = call(scenario, "hazard_force", hazard, placed, no_noise(5))
    assert np.all(force == 0.0)


def test_turbulence_force_matches_its_formula():
    # force = max_force * m * (cos 2 pi u, sin 2 pi u) for noise (u, m).
    scenario = Turbulence(max_force=7.0)
    u = np.array([0.0, 0.1, 0.2499, 0.25, 0.3, 0.5, 0.6, 0.75, 0.9, 65535 / 65536], np.float32)
    m = np.linspace(0.1, 1.0, len(u)).astype(np.float32)
    noise = jnp.asarray(np.stack([u, m], axis=1)[:, :, None])
    hazard = make_hazard((0.0, 0.0), (100.0, 100.0))  # everyone inside
    n = len(u)
    force = call(scenario, "hazard_force", hazard, jnp.zeros((n, 2, 1)), noise)
    angle = 2 * np.pi * u.astype(np.float64)
    expected = 7.0 * m[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    np.testing.assert_allclose(force[:, :, 0], expected, atol=1e-5)


@pytest.mark.parametrize("max_force", [10.0, 2.5])
def test_turbulence_force_is_bounded_and_random(max_force):
    scenario = Turbulence(max_force=max_force)
    n, batch = 8, 64
    hazard = make_hazard([(0.0, 0.0)] * batch, [(100.0, 100.0)] * batch)  # all inside
    position = jnp.zeros((n, 2, batch))
    forces = []
    for step in range(2):
        # The noise does not depend on max_force: one compiled step_noise serves both cases.
        noise = jitted(Turbulence(), "step_noise")(jax.random.key(step, impl="rbg"), n, batch)
        assert noise.shape == (n, 2, batch)
        assert float(noise.min()) >= 0.0 and float(noise.max()) < 1.0
        forces.append(call(scenario, "hazard_force", hazard, position, noise))
    assert not np.allclose(forces[0], forces[1])  # fresh every step
    force = forces[0].transpose(0, 2, 1).reshape(-1, 2)  # 512 samples
    magnitude = np.linalg.norm(force, axis=1)
    assert magnitude.max() <= max_force * (1 + 1e-5)
    # Magnitudes uniform in [0, max_force]: mean max_force / 2 (std of the mean 0.013 max_force).
    assert abs(magnitude.mean() - max_force / 2) < 0.08 * max_force
    assert magnitude.max() > 0.9 * max_force and magnitude.min() < 0.1 * max_force
    # Directions uniform: every octant is hit, and they do not favour one direction.
    angle = np.arctan2(force[:, 1], force[:, 0])
    counts = np.histogram(angle, bins=8, range=(-np.pi, np.pi))[0]
    assert counts.min() >= 30, counts
    unit = force / np.maximum(magnitude[:, None], 1e-12)
    assert np.linalg.norm(unit.mean(axis=0)) < 0.15


@pytest.mark.parametrize("force", [10.0, 7.0])
def test_wind_blows_across_the_way(force):
    # Over many drawn hazards, the wind blows along (0, +1) or (0, -1), each about half the
    # time; a robot in the area (here: at its centre) is pushed along that direction with
    # the configured force, and one step of it changes the velocity by force * dt along y.
    scenario = StrongWind(force=force)
    batch = 4096
    hazard = jax.jit(scenario.sample_hazard, static_argnums=(1, 2))(
        jax.random.key(5, impl="rbg"), Layout(), batch
    )
    direction = np.asarray(hazard.direction)
    np.testing.assert_array_equal(direction[0], 0.0)
    assert set(np.unique(direction[1])) == {-1.0, 1.0}
    up = np.mean(direction[1] == 1.0)
    assert abs(up - 0.5) < 0.03, up  # the std of the share is 0.008
    position = hazard.centre[None]  # one robot at each area's centre
    pushed = call(scenario, "hazard_force", hazard, position, no_noise(1, batch))[0]
    np.testing.assert_allclose(pushed, force * direction, atol=1e-6)
    _, velocity = physics_step(
        position, jnp.zeros_like(position), radii(1), jnp.asarray(pushed)[None]
    )
    np.testing.assert_allclose(velocity[0], force * PHYSICS.dt * direction, atol=1e-6)


# --------------------------------------------------------------------------- the obstacle

OBSTACLE = HiddenObstacle()
HALF_THICKNESS = OBSTACLE.thickness / 2  # 0.2
RADIUS = 0.05


def obstacle_rollout(position, velocity, action, hazard, steps, aim=None):
    """Robots driven against the hidden obstacle for ``steps`` steps.

    The action is ``action`` throughout, or, if ``aim`` (``[2, B]``) is given, full action
    towards ``aim`` from wherever the robot is. One step as
    :meth:`ccrjax.envs.env.EmergencyEnv.advance`
    takes it: the action force (the obstacle exerts none), the MPE step with the robots'
    contacts, then the obstacle's constraint. Returns positions and velocities
    ``[T + 1, N, 2, B]`` (the start included) and every robot's distance to the obstacle
    ``[T + 1, N, B]``.
    """
    radius = jnp.full((position.shape[0],), RADIUS, jnp.float32)

    def body(carry, _):
        p, v = carry
        if aim is not None:
            heading = aim[None] - p
            norm = jnp.sqrt(jnp.sum(heading * heading, axis=1, keepdims=True))
            action_now = jnp.clip(2.0 * heading / jnp.maximum(norm, 1e-6), -1.0, 1.0)
        else:
            action_now = action
        applied = action_to_force(action_now, 5.0, discrete=False)
        applied = applied + OBSTACLE.hazard_force(hazard, p, jnp.zeros((0,)))
        new_p, new_v = physics_step(p, v, radius, applied, PHYSICS)
        new_p, new_v = OBSTACLE.constrain(hazard, p, new_p, new_v, radius)
        return (new_p, new_v), (new_p, new_v)

    _, (p, v) = jax.lax.scan(body, (position, velocity), None, length=steps)
    p = jnp.concatenate([position[None], p])
    v = jnp.concatenate([velocity[None], v])
    distance = jax.vmap(lambda q: rectangle_distance(q, hazard.centre, hazard.half_extent))(p)
    return p, v, distance


obstacle_rollout_jit = jax.jit(obstacle_rollout, static_argnames="steps")


def check_solid(position, velocity, distance):
    """After every step, every robot's disc is outside the obstacle, and it never jumped:
    each coordinate lies between where it was and where its velocity would have taken it
    (the constraint only cuts motion short)."""
    position, velocity, distance = (np.asarray(x) for x in (position, velocity, distance))
    assert distance.min() >= RADIUS - 1e-5, distance.min() - RADIUS
    before, free = position[:-1], position[:-1] + velocity[:-1] * PHYSICS.dt
    low, high = np.minimum(before, free) - 1e-5, np.maximum(before, free) + 1e-5
    jumped = (position[1:] < low) | (position[1:] > high)
    assert not jumped.any(), f"{jumped.any(axis=(1, 2)).sum()} robots jumped"


def boundary_points(rng, centre, grown, count, corner_share=0.25):
    """Points on the rectangle ``centre +- grown`` (corners included) and their outward
    normals (a face's, or a corner's diagonal)."""
    side = rng.integers(0, 4, count)
    along = rng.uniform(-1.0, 1.0, count)
    corner = rng.random(count) < corner_share
    along[corner] = rng.choice([-1.0, 1.0], int(corner.sum()))
    out = np.where(side % 2 == 0, -1.0, 1.0)
    unit = np.where((side < 2)[:, None], np.stack([out, along], 1), np.stack([along, out], 1))
    normal = np.where((side < 2)[:, None], [[1.0, 0.0]], [[0.0, 1.0]]) * unit
    normal = np.where(corner[:, None], unit / np.sqrt(2.0), normal)
    return centre + unit * grown, normal


@PROPERTY
@given(
    seed=st.integers(0, 2**32 - 1),
    thickness=st.sampled_from([OBSTACLE.thickness, 0.02, 0.1, 1.0]),
    half_length=st.floats(0.1, 1.0),
)
def test_obstacle_is_solid_at_any_speed_angle_and_corner(seed, thickness, half_length):
    # 32 environments, one robot each: it starts on or near any face or corner of the
    # obstacle (up to 0.5 from the grown boundary), moving at up to 10 units/s (five times
    # the top speed under full action) towards a random point of the obstacle or beside
    # it, and pushes at full action in a random direction, mostly into the obstacle.
    rng = np.random.default_rng(seed)
    batch = 32
    centre = rng.uniform(-0.3, 0.3, 2)
    half = np.array([thickness / 2, half_length])
    grown = half + RADIUS
    start, normal = boundary_points(rng, centre, grown, batch)
    start = start + rng.uniform(0.0, 0.5, (batch, 1)) * normal * (rng.random((batch, 1)) < 0.8)
    aim = centre + rng.uniform(-1.3, 1.3, (batch, 2)) * grown
    heading = aim - start
    heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
    velocity = heading * rng.uniform(0.0, 10.0, (batch, 1))
    angle = np.arctan2(-normal[:, 1], -normal[:, 0]) + rng.uniform(-1.5, 1.5, batch)
    action = np.clip(1.5 * np.stack([np.cos(angle), np.sin(angle)], 1), -1.0, 1.0)
    as_env = lambda a: jnp.asarray(a.T[None], jnp.float32)  # noqa: E731  [B, 2] -> [1, 2, B]
    hazard = make_hazard(np.tile(centre, (batch, 1)), np.tile(half, (batch, 1)))
    check_solid(*obstacle_rollout_jit(as_env(start), as_env(velocity), as_env(action), hazard,
                                      steps=25))


def test_obstacle_stops_robots_at_terminal_speed():
    # Obstacle of length 1.0 at the origin: grown by a robot's radius, x in [-0.25, 0.25].
    offsets = np.linspace(-0.5, 0.5, 9)  # y of the approach, the corners included
    slopes = np.array([-0.5, -0.25, 0.0, 0.25, 0.5])  # action (1, s): approach angles
    phases = np.linspace(0.0, 0.2, 6, endpoint=False)  # where within one step contact starts
    y, s, phase = (a.ravel() for a in np.meshgrid(offsets, slopes, phases, indexing="ij"))
    batch = len(y)
    action = np.stack([np.ones(batch), s])[None].astype(np.float32)  # [1, 2, B]
    velocity = 2.0 * action  # terminal velocity under that action
    # Start 0.33 + phase clear of the face, so contact comes within the first three steps.
    position = np.stack([-HALF_THICKNESS - RADIUS - 0.33 - phase, y])[None].astype(np.float32)
    hazard = make_hazard([(0.0, 0.0)] * batch, [(HALF_THICKNESS, 0.5)] * batch)
    p, v, distance = obstacle_rollout_jit(
        jnp.asarray(position), jnp.asarray(velocity), jnp.asarray(action), hazard, steps=30
    )
    check_solid(p, v, distance)
    # Head-on, a robot ends on the face, touching it: in danger. (Its velocity into the face
    # is zeroed when it is stopped; the next step's push, 0.5, moves it no further.)
    head_on = s == 0.0
    np.testing.assert_allclose(p[-1, 0, 0, head_on], -HALF_THICKNESS - RADIUS, atol=1e-6)
    np.testing.assert_allclose(p[-1, 0, 1, head_on], y[head_on], atol=1e-6)
    assert np.all(np.asarray(v[-2:, 0, 0][:, head_on]) <= 0.5 + 1e-6)
    danger = call(OBSTACLE, "in_danger", hazard, p[-1], radii(1))[0]
    assert np.all(danger[head_on])
    # At an angle, a robot slides along the face and, past a corner, goes on its way.
    assert np.all(np.asarray(p[-1, 0, 0, np.abs(s) == 0.5]) > HALF_THICKNESS)


def test_obstacle_stops_a_robot_that_would_tunnel_through_it():
    # 9 units/s: 0.9 in one step, further than the obstacle (0.4) is thick. Stopped at the
    # entry face on the first step, with its velocity into the face gone.
    position = jnp.array([[[-0.4], [0.1]]], jnp.float32)
    velocity = jnp.array([[[9.0], [0.0]]], jnp.float32)
    p, v, distance = obstacle_rollout_jit(
        position, velocity, jnp.zeros_like(position), make_hazard((0.0, 0.0), (0.2, 0.5)),
        steps=5,
    )
    check_solid(p, v, distance)
    np.testing.assert_allclose(p[1:, 0, :, 0], np.tile([-0.25, 0.1], (5, 1)), atol=1e-6)
    assert np.all(np.asarray(v[1:, 0, 0, 0]) == 0.0)


@pytest.mark.parametrize("team", [2, 4, 6])
def test_obstacle_stops_a_column_of_robots(team):
    # Robots in a row, at rest, the front one on the face of a default obstacle, all
    # pushing +x at full force: the ones behind push the front one through their contacts.
    x = -HALF_THICKNESS - RADIUS - 0.1 * np.arange(team)
    position = jnp.asarray(np.stack([x, np.zeros(team)], axis=1)[:, :, None], jnp.float32)
    action = jnp.tile(jnp.array([[[1.0], [0.0]]], jnp.float32), (team, 1, 1))
    hazard = make_hazard((0.0, 0.0), (HALF_THICKNESS, 0.5))
    p, v, distance = obstacle_rollout_jit(
        position, jnp.zeros_like(position), action, hazard, steps=60
    )
    check_solid(p, v, distance)
    np.testing.assert_allclose(p[:, 0, 0, 0], -HALF_THICKNESS - RADIUS, atol=1e-6)
    assert call(OBSTACLE, "in_danger", hazard, p[-1], radii(team))[0, 0]


def test_obstacle_stops_a_pile_of_robots():
    # 32 environments of 16 robots (the environment allows 2 to 64), at rest, not touching,
    # 0.1 to 0.8 in front of an obstacle of length 1.0, spread over its height and both
    # corners, all driving at full force for 8 s: in even environments towards the
    # obstacle's centre (they pile up against its face), in odd ones towards a point behind
    # it (they squeeze round its corners).
    rng = np.random.default_rng(1)
    team, batch = 16, 32
    position = np.zeros((team, 2, batch), np.float32)
    for b in range(batch):
        placed = []
        while len(placed) < team:
            p = np.array([-HALF_THICKNESS - RADIUS - rng.uniform(0.1, 0.8),
                          rng.uniform(-0.8, 0.8)])
            if all(np.linalg.norm(p - q) > 0.11 for q in placed):
                placed.append(p)
        position[:, :, b] = np.array(placed)
    aim = np.stack([np.where(np.arange(batch) % 2 == 0, 0.0, 1.0), np.zeros(batch)])
    hazard = make_hazard([(0.0, 0.0)] * batch, [(HALF_THICKNESS, 0.5)] * batch)
    zeros = jnp.zeros((team, 2, batch), jnp.float32)
    p, v, distance = obstacle_rollout_jit(
        jnp.asarray(position), zeros, zeros, hazard, steps=80, aim=jnp.asarray(aim, jnp.float32)
    )
    check_solid(p, v, distance)
    # Robots pressed against it touch it (the paper's dangerous state).
    pressed = np.asarray(distance[-1]) <= RADIUS + 1e-5
    assert pressed[:, ::2].sum() >= batch
    danger = call(OBSTACLE, "in_danger", hazard, p[-1], radii(team))
    assert np.all(danger[pressed])


def test_obstacle_keeps_robots_on_its_face():
    # Robot 0 rests on the +x face, without action: it stays there, in danger. Robot 1
    # pushes diagonally into the -x face: it is stopped on it and slides along it, never
    # jumping to another face. (At this centre, the stopped robot's coordinate minus the
    # centre's rounds to just inside the grown rectangle in float32.)
    hazard = make_hazard((-0.08, 0.03), (HALF_THICKNESS, 0.6))
    face = -0.08 - HALF_THICKNESS - RADIUS
    far_face = -0.08 + HALF_THICKNESS + RADIUS
    position = positions((far_face, 0.1), (face - 0.1, -0.4))
    action = positions((0.0, 0.0), (1.0, 1.0))
    p, v, distance = obstacle_rollout_jit(position, jnp.zeros_like(position), action, hazard,
                                          steps=10)
    check_solid(p, v, distance)
    np.testing.assert_allclose(p[:, 0, :, 0], np.tile([far_face, 0.1], (11, 1)), atol=1e-6)
    np.testing.assert_allclose(p[3:, 1, 0, 0], face, atol=1e-6)
    assert np.all(np.diff(np.asarray(p[:, 1, 1, 0])) >= 0.0)
    # Both touch the obstacle while on it (robot 1 until it slides past the corner at
    # y = 0.68, after 9 steps).
    assert np.all(call(OBSTACLE, "in_danger", hazard, p[8], radii(2))[:, 0])
    assert p[-1, 1, 1, 0] > 0.68


# --------------------------------------------------------------------------- features


@pytest.mark.parametrize("name", ["turbulence", "strong_wind"])
def test_area_features_visible_only_inside(name):
    scenario = make_scenario(name)
    inside = IN_CIRCLE if name == "turbulence" else IN_SQUARE
    hazard = make_hazard(CENTRE, HALF, WIND)
    n = PLACED.shape[0]
    features = call(scenario, "hazard_features", hazard, PLACED, radii(n))
    assert features.shape == (n, scenario.hazard_feature_size, 1) == (n, 4, 1)
    assert np.all(features[~inside] == 0.0)
    # Inside: [1, centre_x - x, centre_y - y, half extent].
    p = np.asarray(PLACED)[inside, :, 0]
    expected = np.concatenate(
        [np.ones((len(p), 1)), np.array(CENTRE) - p, np.full((len(p), 1), HALF[0])], axis=1
    )
    np.testing.assert_allclose(features[inside, :, 0], expected, atol=1e-6)


def test_obstacle_feature_is_the_touching_flag():
    # Touching: the centre within touch_tolerance (0.01) of the obstacle grown by the radius
    # (0.05), the square-cornered region the obstacle stops robots at.
    scenario = HiddenObstacle()
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))  # x in [-0.2, 0.2], y in [-0.5, 0.5]
    placed = positions(
        (-0.3, 0.0),  # 0.1 from the left face: not touching
        (-0.265, 0.0),  # 0.065: not touching
        (-0.255, 0.0),  # 0.055: within the tolerance, touching
        (-0.25, 0.0),  # 0.05: in contact (where the obstacle stops a robot), touching
        (0.0, 0.54),  # 0.04 from the top (overlapping): touching
        (0.0, 0.0),  # centre inside: touching
        (0.24, 0.54),  # off the corner by (0.04, 0.04): inside the grown corner, touching
        (0.25, 0.55),  # off the corner by (0.05, 0.05): the grown corner, where a robot
        #                that clips it is stopped, touching
        (1.0, 1.0),  # far: not touching
    )
    touching = [0, 0, 1, 1, 1, 1, 1, 1, 0]
    features = call(scenario, "hazard_features", hazard, placed, radii(9))
    assert features.shape == (9, 1, 1)
    np.testing.assert_array_equal(features[:, 0, 0], touching)
    np.testing.assert_array_equal(call(scenario, "in_danger", hazard, placed, radii(9))[:, 0],
                                  touching)
    # The tolerance is a parameter: with none, only contact counts.
    exact = HiddenObstacle(touch_tolerance=0.0)
    np.testing.assert_array_equal(call(exact, "in_danger", hazard, placed, radii(9))[:, 0],
                                  [0, 0, 0, 1, 1, 1, 1, 1, 0])


def test_nominal_has_no_features():
    scenario = Nominal()
    assert scenario.hazard_feature_size == 0
    features = call(scenario, "hazard_features", make_hazard(CENTRE, (0, 0)), PLACED, radii(9))
    assert features.shape == (9, 0, 1)


# --------------------------------------------------------------------------- predicates


def test_area_danger_predicates():
    n = PLACED.shape[0]
    turbulence = call(Turbulence(), "in_danger", make_hazard(CENTRE, HALF), PLACED, radii(n))
    np.testing.assert_array_equal(turbulence[:, 0], IN_CIRCLE)
    wind = call(StrongWind(), "in_danger", make_hazard(CENTRE, HALF, WIND), PLACED, radii(n))
    np.testing.assert_array_equal(wind[:, 0], IN_SQUARE)
    nominal = call(Nominal(), "in_danger", make_hazard(CENTRE, HALF), PLACED, radii(n))
    assert not nominal.any()


def test_target_area():
    # Success (in every scenario) is the robot's centre inside the target area: the disc of
    # radius goal_radius (0.4) around goal (1.5, 0).
    placed = positions((1.5, 0.0), (1.89, 0.0), (1.5, -0.39), (1.5, 0.41), (1.2, 0.2),
                       (1.0, 0.0), (2.0, 0.0))
    inside = jax.jit(in_target_area, static_argnums=1)
    np.testing.assert_array_equal(inside(placed, Layout())[:, 0], [1, 1, 1, 0, 1, 0, 0])
    # A different layout moves the target area.
    layout = Layout(goal=(0.0, 1.0), goal_radius=0.1)
    placed = positions((0.0, 1.0), (0.0, 1.09), (0.0, 1.11), (1.5, 0.0))
    np.testing.assert_array_equal(inside(placed, layout)[:, 0], [1, 1, 0, 0])


# --------------------------------------------------------------------------- random hazards


@pytest.mark.parametrize("name", NAMES)
def test_hazards_are_drawn_within_their_ranges(name):
    scenario = make_scenario(name)
    layout = Layout()
    batch = 256
    sample = jax.jit(scenario.sample_hazard, static_argnums=(1, 2))
    # "rbg" keys: the scenario only draws from the key it is given, and they compile faster
    key, other_key = jax.random.key(0, impl="rbg"), jax.random.key(1, impl="rbg")
    hazard = jax.tree.map(np.asarray, sample(key, layout, batch))
    other = jax.tree.map(np.asarray, sample(other_key, layout, batch))
    for array in (hazard.centre, hazard.half_extent, hazard.direction):
        assert array.shape == (2, batch)
    # Centres: x in hazard_x_range (-0.1, 0.1), y in hazard_y_range (-0.25, 0.25).
    cx, cy = hazard.centre
    assert cx.min() >= -0.1 and cx.max() <= 0.1 and cx.max() - cx.min() > 0.18
    assert cy.min() >= -0.25 and cy.max() <= 0.25 and cy.max() - cy.min() > 0.4
    assert not np.allclose(hazard.centre, other.centre)  # a new draw for a new key
    hx, hy = hazard.half_extent
    if name == "turbulence":  # radius in (0.9, 1.0)
        np.testing.assert_array_equal(hx, hy)
        assert hx.min() >= 0.9 and hx.max() <= 1.0 and hx.max() - hx.min() > 0.08
        assert not np.allclose(hazard.half_extent, other.half_extent)
        np.testing.assert_array_equal(hazard.direction, 0.0)
    elif name == "strong_wind":  # a square of side in (1.2, 1.6), wind along (0, +-1)
        np.testing.assert_array_equal(hx, hy)
        assert hx.min() >= 0.6 and hx.max() <= 0.8 and hx.max() - hx.min() > 0.15
        np.testing.assert_array_equal(np.abs(hazard.direction), np.tile([[0.0], [1.0]], batch))
    elif name == "hidden_obstacle":  # thickness 0.4, length in (1.2, 2.0)
        np.testing.assert_allclose(hx, 0.2)
        assert hy.min() >= 0.6 and hy.max() <= 1.0 and hy.max() - hy.min() > 0.3
        np.testing.assert_array_equal(hazard.direction, 0.0)
    else:
        assert np.all(hazard.half_extent == 0.0)


def test_hazard_ranges_are_configurable():
    layout = Layout(hazard_x_range=(1.0, 1.5), hazard_y_range=(-2.0, -1.0))
    cases = [
        (Turbulence(radius_range=(0.1, 0.2)), (0.1, 0.2), (0.1, 0.2)),
        (StrongWind(side_range=(0.2, 0.4)), (0.1, 0.2), (0.1, 0.2)),
        (HiddenObstacle(thickness=0.8, length_range=(2.0, 2.0)), (0.4, 0.4), (1.0, 1.0)),
    ]
    for scenario, (hx_low, hx_high), (hy_low, hy_high) in cases:
        hazard = scenario.sample_hazard(jax.random.key(3, impl="rbg"), layout, 256)
        cx, cy = np.asarray(hazard.centre)
        assert cx.min() >= 1.0 and cx.max() <= 1.5
        assert cy.min() >= -2.0 and cy.max() <= -1.0
        hx, hy = np.asarray(hazard.half_extent)
        assert hx.min() >= hx_low - 1e-6 and hx.max() <= hx_high + 1e-6
        assert hy.min() >= hy_low - 1e-6 and hy.max() <= hy_high + 1e-6
        assert scenario.max_half_extent() == pytest.approx((hx_high, hy_high))


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: Turbulence(radius_range=(0.5, 0.3)), "radius_range"),
        (lambda: Turbulence(radius_range=(0.0, 0.3)), "radius_range"),
        (lambda: Turbulence(radius_range=(0.1, float("inf"))), "radius_range"),
        (lambda: Turbulence(radius_range=0.3), "radius_range"),
        (lambda: Turbulence(max_force=-1.0), "max_force"),
        (lambda: Turbulence(max_force=float("nan")), "max_force"),
        (lambda: StrongWind(side_range=(-1.0, 1.0)), "side_range"),
        (lambda: StrongWind(side_range=(1.0, 2.0, 3.0)), "side_range"),
        (lambda: StrongWind(force=-0.1), "force"),
        (lambda: StrongWind(force="strong"), "force"),
        (lambda: HiddenObstacle(thickness=0.0), "thickness"),
        (lambda: HiddenObstacle(thickness=-0.4), "thickness"),
        (lambda: HiddenObstacle(length_range=(1.4, 0.6)), "length_range"),
        (lambda: HiddenObstacle(touch_tolerance=-0.01), "touch_tolerance"),
        (lambda: Layout(goal_radius=0.0), "goal_radius"),
        (lambda: Layout(goal=(float("nan"), 0.0)), "goal"),
        (lambda: Layout(start_half_extent=(-0.1, 0.5)), "start_half_extent"),
        (lambda: Layout(min_separation=0.0), "min_separation"),
        (lambda: Layout(target_spacing=-0.15), "target_spacing"),
        (lambda: Layout(arena_half_extent=(2.5, 0.0)), "arena_half_extent"),
        (lambda: Layout(start_centre=(-2.4, 0.0)), "start box"),
        (lambda: Layout(goal=(1.5, 1.8)), "target area"),
        (lambda: Layout(hazard_x_range=(0.3, -0.3)), "hazard_x_range"),
        (lambda: Layout(hazard_y_range=(0.0, float("nan"))), "hazard_y_range"),
        (lambda: make_scenario("turbulence", max_force=-2.0), "max_force"),
        (lambda: make_scenario("strong_wind", strength=3.0), "strength"),
        (lambda: make_scenario("strong_wind", angle=1.0), "angle"),  # no longer a parameter
        (lambda: make_scenario("blizzard"), "blizzard"),
    ],
)
def test_bad_parameters_raise_value_error_naming_the_field(build, field):
    with pytest.raises(ValueError, match=field):
        build()


@pytest.mark.parametrize(
    ("scenario", "layout", "pattern"),
    [
        # A wind area wider than the arena.
        (StrongWind(side_range=(1.2, 6.0)), Layout(), r"StrongWind.*arena_half_extent"),
        # A turbulence area reaching into the start box.
        (Turbulence(radius_range=(0.9, 1.5)), Layout(), r"Turbulence.*start box"),
        # A start box moved next to the hazards.
        (Turbulence(), Layout(start_centre=(-0.9, 0.0)), r"start_centre, start_half_extent"),
        # A target area moved next to the hazards.
        (HiddenObstacle(), Layout(goal=(0.6, 0.0)), r"target area.*goal, goal_radius"),
        # An obstacle that leaves less than two robots' width past it on either side.
        (HiddenObstacle(length_range=(1.0, 3.9)), Layout(hazard_y_range=(0.0, 0.0)),
         r"HiddenObstacle.length_range.*block every way"),
        # The same, though one of its positions leaves a way on one side: it can block.
        (HiddenObstacle(length_range=(1.0, 3.64)), Layout(hazard_y_range=(-0.05, 0.05)),
         r"HiddenObstacle.length_range.*block every way"),
    ],
)
def test_check_layout_refuses_meaningless_hazards(scenario, layout, pattern):
    with pytest.raises(ValueError, match=pattern):
        scenario.check_layout(layout, 0.05)


@pytest.mark.parametrize("name", NAMES)
def test_check_layout_accepts_the_defaults(name):
    make_scenario(name).check_layout(Layout(), 0.05)
    # The obstacle may nearly span the arena's height, if a way remains past it.
    HiddenObstacle(length_range=(1.0, 3.5)).check_layout(Layout(hazard_y_range=(0.0, 0.0)), 0.05)


def test_registry_names():
    assert sorted(SCENARIOS) == sorted(NAMES)
    for name in NAMES:
        assert make_scenario(name).name == name
