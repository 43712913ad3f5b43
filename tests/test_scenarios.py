"""Tests of the emergency scenarios (:mod:`ccrjax.scenarios`).

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

from ccrjax.scenarios import (
    SCENARIOS,
    Hazard,
    HiddenObstacle,
    Layout,
    Nominal,
    StrongWind,
    Turbulence,
    make_scenario,
)
from ccrjax.world import PhysicsParams, action_to_force, physics_step

PHYSICS = PhysicsParams()
NAMES = ["turbulence", "strong_wind", "hidden_obstacle", "nominal"]


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
def jitted(scenario, method: str, layout: Layout | None = None):
    """A scenario method compiled once (physics / layout bound as constants)."""
    fn = getattr(scenario, method)
    if method == "hazard_force":
        fn = functools.partial(fn, physics=PHYSICS)
    if method == "reached":
        fn = functools.partial(fn, layout=layout or Layout())
    if method == "step_noise":
        return jax.jit(fn, static_argnums=(1, 2))
    return jax.jit(fn)


def call(scenario, method, *args, layout=None):
    return np.asarray(jitted(scenario, method, layout)(*args))


# --------------------------------------------------------------------------- hazard forces

# Hazard centred at (0.2, -0.1) with half extent 0.4 (the turbulence circle's radius, the
# wind square's half side); wind along (0.6, 0.8).
CENTRE, HALF, WIND = (0.2, -0.1), (0.4, 0.4), (0.6, 0.8)
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
    force = call(scenario, "hazard_force", hazard, PLACED, radii(n), noise)
    expected = np.where(IN_CIRCLE[:, None], 5.0 / math.sqrt(2.0), 0.0)
    np.testing.assert_allclose(force[:, :, 0], np.tile(expected, (1, 2)), atol=1e-5)
    assert np.all(force[~IN_CIRCLE] == 0.0)


def test_strong_wind_force_acts_inside_the_square_only():
    scenario = StrongWind()
    hazard = make_hazard(CENTRE, HALF, WIND)
    n = PLACED.shape[0]
    force = call(scenario, "hazard_force", hazard, PLACED, radii(n), jnp.zeros((n, 0, 1)))
    expected = np.where(IN_SQUARE[:, None], 4.0 * np.array(WIND), 0.0)
    np.testing.assert_allclose(force[:, :, 0], expected, atol=1e-6)
    assert np.all(force[~IN_SQUARE] == 0.0)


@pytest.mark.parametrize("name", ["turbulence", "strong_wind"])
def test_area_force_uses_each_environments_own_hazard(name):
    # Two environments: the hazard of the first covers robot 0, that of the second is far away.
    scenario = make_scenario(name)
    hazard = make_hazard([(0.0, 0.0), (5.0, 5.0)], [(0.5, 0.5), (0.5, 0.5)], [(1, 0), (1, 0)])
    position = jnp.zeros((2, 2, 2)).at[1].set(3.0)  # robot 0 at the origin, robot 1 at (3, 3)
    noise = jnp.full((2, 2, 2), 0.5, jnp.float32)
    noise = noise[:, :0] if not scenario.needs_step_noise else noise
    force = call(scenario, "hazard_force", hazard, position, radii(2), noise)
    assert np.linalg.norm(force[0, :, 0]) > 1.0
    assert np.all(force[1] == 0.0)
    assert np.all(force[:, :, 1] == 0.0)


def test_hidden_obstacle_force_acts_only_on_contact():
    scenario = HiddenObstacle()
    # Obstacle: x in [-0.2, 0.2], y in [-0.5, 0.5]; robot radius 0.05.
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))
    placed = positions(
        (-0.23, 0.0),  # overlaps the left face by 0.02: force 100 * 0.02 = 2 along -x
        (0.0, 0.53),  # overlaps the top face by 0.02: (0, +2)
        (0.23, -0.4),  # overlaps the right face by 0.02: (+2, 0)
        (-0.27, 0.0),  # 0.02 clear of the left face: 100 * 1e-3 * softplus(-20) = 2e-10
        (-0.75, 0.0),  # 0.5 clear
        (3.0, 3.0),  # far away
    )
    force = call(scenario, "hazard_force", hazard, placed, radii(6), jnp.zeros((6, 0, 1)))
    np.testing.assert_allclose(force[:3, :, 0], [[-2, 0], [0, 2], [2, 0]], atol=1e-4)
    assert np.all(np.abs(force[3]) < 1e-8)
    assert np.all(force[4:] == 0.0)


def test_nominal_exerts_no_force():
    scenario = Nominal()
    hazard = make_hazard(CENTRE, (0.0, 0.0))
    n = PLACED.shape[0]
    force = call(scenario, "hazard_force", hazard, PLACED, radii(n), jnp.zeros((n, 0, 1)))
    assert np.all(force == 0.0)


def test_turbulence_force_matches_its_formula():
    # force = max_force * m * (cos 2 pi u, sin 2 pi u) for noise (u, m).
    scenario = Turbulence(max_force=7.0)
    u = np.array([0.0, 0.1, 0.2499, 0.25, 0.3, 0.5, 0.6, 0.75, 0.9, 65535 / 65536], np.float32)
    m = np.linspace(0.1, 1.0, len(u)).astype(np.float32)
    noise = jnp.asarray(np.stack([u, m], axis=1)[:, :, None])
    hazard = make_hazard((0.0, 0.0), (100.0, 100.0))  # everyone inside
    n = len(u)
    force = call(scenario, "hazard_force", hazard, jnp.zeros((n, 2, 1)), radii(n), noise)
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
        forces.append(call(scenario, "hazard_force", hazard, position, radii(n), noise))
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


# --------------------------------------------------------------------------- the obstacle


def obstacle_rollout(position, velocity, action, hazard, steps):
    """Centres ``[T, N, 2, B]`` of robots driven by ``action`` against the hidden obstacle.

    One step as :meth:`ccrjax.env.CCREnv.advance` takes it: action and obstacle forces
    (the obstacle's force reads its per-robot memory), the MPE step, the obstacle's
    constraint (a robot that crossed it in one step goes back), the memory update.
    """
    scenario = HiddenObstacle()
    radius = jnp.full((position.shape[0],), 0.05, jnp.float32)
    applied = action_to_force(action, 5.0, discrete=False)

    def body(carry, _):
        p, v, memory = carry
        force = applied + scenario.hazard_force(hazard, p, radius, None, PHYSICS, memory)
        p, v = physics_step(p, v, radius, force, PHYSICS)
        p, v = scenario.constrain(hazard, memory, p, v, radius)
        return (p, v, scenario.update_memory(hazard, memory, p)), p

    start = (position, velocity, scenario.init_memory(hazard, position))
    return jax.lax.scan(body, start, None, length=steps)[1]


obstacle_rollout_jit = jax.jit(obstacle_rollout, static_argnames="steps")


def passed_through(trajectory, centre, half):
    """Whether a robot ever went through the obstacle from its near (-x) face, ``[N, B]``.

    Passing through: a step that crosses the far (+x) face's line level with the obstacle
    (``|y| < half length``) while the last point where the centre was outside the
    obstacle lay beyond its near face. With the obstacle's entry memory a robot may get
    past the mid-line, up to about 0.35 deep, and still be pushed back out the way it
    came; a robot squeezed over a corner (in through the top or bottom face, out through
    the far one) clips the corner, which a soft wall allows: neither passes through.
    """
    x = trajectory[:, :, 0] - centre[0]  # [T, N, B]
    y = trajectory[:, :, 1] - centre[1]
    x0, x1, y0, y1 = x[:-1], x[1:], y[:-1], y[1:]
    crosses = (x0 <= half[0]) & (x1 > half[0])
    step = np.where(crosses, x1 - x0, 1.0)
    y_at_face = y0 + (half[0] - x0) * (y1 - y0) / step
    exits = crosses & (np.abs(y_at_face) < half[1])
    outside = (np.abs(x) > half[0]) | (np.abs(y) > half[1])
    result = np.zeros(x.shape[1:], bool)
    for t, n, b in zip(*np.nonzero(exits), strict=True):
        before = np.nonzero(outside[: t + 1, n, b])[0]
        last = before[-1] if len(before) else 0
        # Came from the near side (not from above or below the obstacle).
        if x[last, n, b] < -half[0] and abs(y[last, n, b]) - half[1] < -half[0] - x[last, n, b]:
            result[n, b] = True
    return result


DEFAULT_HALF_THICKNESS = HiddenObstacle().thickness / 2


@pytest.mark.parametrize(
    "half_thickness", [DEFAULT_HALF_THICKNESS, 0.2], ids=["default_thickness", "thickness_0.4"]
)
def test_obstacle_stops_robots_at_terminal_speed(half_thickness):
    # Obstacle of length 1.0 at the origin: x in [-half_thickness, half_thickness].
    centre, half = (0.0, 0.0), (half_thickness, 0.5)
    offsets = np.linspace(-0.45, 0.45, 7)  # y of the approach
    slopes = np.array([-0.5, -0.25, 0.0, 0.25, 0.5])  # action (1, s): approach angles
    phases = np.linspace(0.0, 0.2, 8, endpoint=False)  # where within one step contact starts
    y, s, phase = (a.ravel() for a in np.meshgrid(offsets, slopes, phases, indexing="ij"))
    batch = len(y)
    action = np.stack([np.ones(batch), s])[None].astype(np.float32)  # [1, 2, B]
    velocity = 2.0 * action  # terminal velocity under that action
    # Start 0.33 + phase clear of the face, so contact comes within the first three steps.
    position = np.stack([-half_thickness - 0.05 - 0.33 - phase, y])[None].astype(np.float32)
    hazard = make_hazard([centre] * batch, [half] * batch)
    trajectory = np.asarray(
        obstacle_rollout_jit(
            jnp.asarray(position), jnp.asarray(velocity), jnp.asarray(action), hazard, steps=60
        )
    )
    through = passed_through(trajectory, centre, half)[0]
    assert not through.any(), (
        f"{through.sum()} of {batch} approaches passed through, e.g. y={y[through][:3]}, "
        f"s={s[through][:3]}, phase={phase[through][:3]}"
    )
    # Head-on, the robots end up back on the side they came from.
    head_on = s == 0.0
    assert np.all(trajectory[-1, 0, 0, head_on] < -half_thickness)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    y=st.floats(-0.6, 0.6),
    slope=st.floats(-1.0, 1.0),
    start_gap=st.floats(0.0, 0.5),
    speed_fraction=st.floats(0.0, 1.0),
    half_length=st.floats(0.3, 0.7),
)
def test_obstacle_is_never_crossed_property(y, slope, start_gap, speed_fraction, half_length):
    # A robot pushes at full force along (1, slope) into a default-thickness obstacle,
    # starting start_gap clear of its face at up to the terminal speed.
    centre, half = (0.0, 0.0), (DEFAULT_HALF_THICKNESS, half_length)
    action = jnp.array([[[1.0], [slope]]], jnp.float32)
    velocity = 2.0 * speed_fraction * action
    start_x = -DEFAULT_HALF_THICKNESS - 0.05 - start_gap
    position = jnp.array([[[start_x], [y * half_length / 0.5]]], jnp.float32)
    trajectory = np.asarray(
        obstacle_rollout_jit(position, velocity, action, make_hazard(centre, half), steps=60)
    )
    assert not passed_through(trajectory, centre, half).any()


@pytest.mark.parametrize("team", [2, 4, 6])
def test_obstacle_stops_a_column_of_robots(team):
    # Robots in a row, at rest, the front one touching the face of a default obstacle, all
    # pushing +x at full force: the ones behind push the front one through their contacts.
    centre, half = (0.0, 0.0), (DEFAULT_HALF_THICKNESS, 0.5)
    x = -DEFAULT_HALF_THICKNESS - 0.05 - 0.1 * np.arange(team)
    position = jnp.asarray(np.stack([x, np.zeros(team)], axis=1)[:, :, None], jnp.float32)
    action = jnp.tile(jnp.array([[[1.0], [0.0]]], jnp.float32), (team, 1, 1))
    trajectory = np.asarray(
        obstacle_rollout_jit(
            position, jnp.zeros_like(position), action, make_hazard(centre, half), steps=150
        )
    )
    assert not passed_through(trajectory, centre, half).any()


def test_obstacle_returns_a_robot_that_jumps_over_it_in_one_step():
    # 9 units/s: 0.9 per step, more than the 0.6-thick wall; the contact force never acts.
    centre, half = (0.0, 0.0), (DEFAULT_HALF_THICKNESS, 0.5)
    position = jnp.array([[[-DEFAULT_HALF_THICKNESS - 0.1], [0.0]]], jnp.float32)
    velocity = jnp.array([[[9.0], [0.0]]], jnp.float32)
    action = jnp.zeros_like(position)
    trajectory = np.asarray(
        obstacle_rollout_jit(position, velocity, action, make_hazard(centre, half), steps=5)
    )
    assert not passed_through(trajectory, centre, half).any()
    assert np.all(trajectory[:, 0, 0, 0] < -DEFAULT_HALF_THICKNESS)


def test_obstacle_stops_a_pile_of_robots():
    # 64 environments of 16 robots (the environment allows 2 to 64), at rest, not touching,
    # 0.5 to 1.0 in front of a default obstacle, all driving +x at full force for 20 s.
    centre, half = (0.0, 0.0), (DEFAULT_HALF_THICKNESS, 0.5)
    rng = np.random.default_rng(1)
    team, batch = 16, 64
    position = np.zeros((team, 2, batch), np.float32)
    for b in range(batch):
        placed = []
        while len(placed) < team:
            p = np.array([-DEFAULT_HALF_THICKNESS - 0.05 - rng.uniform(0.5, 1.0),
                          rng.uniform(-0.4, 0.4)])
            if all(np.linalg.norm(p - q) > 0.1 for q in placed):
                placed.append(p)
        position[:, :, b] = np.array(placed)
    action = np.zeros_like(position)
    action[:, 0] = 1.0
    trajectory = np.asarray(
        obstacle_rollout_jit(
            jnp.asarray(position),
            jnp.zeros((team, 2, batch), jnp.float32),
            jnp.asarray(action),
            make_hazard([centre] * batch, [half] * batch),
            steps=200,
        )
    )
    through = passed_through(trajectory, centre, half)
    assert not through.any(), f"robots through in {through.any(axis=0).sum()} of {batch} envs"


def test_obstacle_memory_of_a_robot_last_on_the_face():
    # A point exactly on a face is not an entry point: the memory keeps the last point
    # strictly outside, so the robot is still pushed back out the way it came.
    scenario = HiddenObstacle()
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))  # x in [-0.2, 0.2]
    update = jitted(scenario, "update_memory")
    before = positions((-0.5, 0.0))
    on_face = positions((-0.2, 0.0))  # exactly on the left face
    memory = update(hazard, before, on_face)
    np.testing.assert_array_equal(memory, before)
    past_mid_line = positions((0.05, 0.0))  # came in from the left, 0.25 deep
    memory = update(hazard, memory, past_mid_line)
    force = np.asarray(
        jax.jit(functools.partial(scenario.hazard_force, physics=PHYSICS))(
            hazard, past_mid_line, radii(1), None, memory=memory
        )
    )
    assert force[0, 0, 0] < 0.0, f"pushed along +x, out of the far side: {force[0, :, 0]}"


def test_obstacle_remembers_where_robots_came_from():
    scenario = HiddenObstacle()
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))  # x in [-0.2, 0.2], y in [-0.5, 0.5]
    outside = positions((-0.5, 0.1), (0.1, 0.9))  # left of it; above it
    memory = call(scenario, "init_memory", hazard, outside)
    np.testing.assert_array_equal(memory, outside)
    # Both robots are now at (0.1, 0.1), past the mid-line, 0.1 below the right face.
    inside = positions((0.1, 0.1), (0.1, 0.1))
    np.testing.assert_array_equal(call(scenario, "update_memory", hazard, memory, inside), memory)
    force = np.asarray(
        jax.jit(functools.partial(scenario.hazard_force, physics=PHYSICS))(
            hazard, inside, radii(2), None, memory=memory
        )
    )
    # Robot 0 came from the left: out through the left face, 0.3 below it, plus its
    # radius: 100 * 0.35 = 35 along -x. Robot 1 came from above: 0.4 below the top face:
    # 100 * 0.45 = 45 along +y. (The nearest face would have been the right one.)
    np.testing.assert_allclose(force[:, :, 0], [[-35.0, 0.0], [0.0, 45.0]], atol=1e-3)
    # Once outside again, the memory follows the robot.
    out_again = positions((-0.6, 0.0), (2.0, 2.0))
    np.testing.assert_array_equal(
        call(scenario, "update_memory", hazard, memory, out_again), out_again
    )
    # The other scenarios remember nothing.
    for other in (Turbulence(), StrongWind(), Nominal()):
        assert call(other, "init_memory", hazard, outside).shape == (2, 0, 1)


def test_obstacle_pushes_a_resting_robot_out_of_the_near_face():
    # A robot at rest overlapping the left face by 0.03, no action: pushed back to -x,
    # and it ends clear of the obstacle, never having moved towards the mid-line.
    centre, half = (0.0, 0.0), (0.2, 0.5)
    position = jnp.array([[[-0.22], [0.1]]], jnp.float32)
    zero = jnp.zeros((1, 2, 1), jnp.float32)
    trajectory = np.asarray(
        obstacle_rollout_jit(position, zero, zero, make_hazard(centre, half), steps=60)
    )
    assert np.all(trajectory[:, 0, 0, 0] <= -0.22 + 1e-6)
    assert trajectory[-1, 0, 0, 0] < -0.25
    np.testing.assert_allclose(trajectory[:, 0, 1, 0], 0.1, atol=1e-6)


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
    scenario = HiddenObstacle()
    hazard = make_hazard((0.0, 0.0), (0.2, 0.5))  # x in [-0.2, 0.2], y in [-0.5, 0.5]
    placed = positions(
        (-0.3, 0.0),  # 0.05 clear: not touching
        (-0.26, 0.0),  # 0.01 clear: not touching
        (-0.24, 0.0),  # 0.01 overlap: touching
        (0.0, 0.54),  # 0.01 overlap with the top: touching
        (0.0, 0.0),  # centre inside: touching
        (0.24, 0.54),  # off the corner by (0.04, 0.04), 0.0566 > 0.05: not touching
        (0.23, 0.53),  # off the corner by (0.03, 0.03), 0.0424 < 0.05: touching
        (1.0, 1.0),  # far: not touching
    )
    touching = [0, 0, 1, 1, 1, 0, 1, 0]
    features = call(scenario, "hazard_features", hazard, placed, radii(8))
    assert features.shape == (8, 1, 1)
    np.testing.assert_array_equal(features[:, 0, 0], touching)
    np.testing.assert_array_equal(call(scenario, "in_danger", hazard, placed, radii(8))[:, 0],
                                  touching)


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


@pytest.mark.parametrize("name", ["turbulence", "nominal"])
def test_success_in_target_area(name):
    scenario = make_scenario(name)
    hazard = make_hazard(CENTRE, HALF)
    # Default goal (1.5, 0), radius 0.3.
    placed = positions((1.5, 0.0), (1.79, 0.0), (1.5, -0.29), (1.5, 0.31), (1.0, 0.0), (2.0, 0))
    np.testing.assert_array_equal(
        call(scenario, "reached", hazard, placed)[:, 0], [1, 1, 1, 0, 0, 0]
    )
    # A different layout moves the target area.
    layout = Layout(goal=(0.0, 1.0), goal_radius=0.1)
    placed = positions((0.0, 1.0), (0.0, 1.09), (0.0, 1.11), (1.5, 0.0))
    np.testing.assert_array_equal(
        call(scenario, "reached", hazard, placed, layout=layout)[:, 0], [1, 1, 0, 0]
    )


@pytest.mark.parametrize("name", ["strong_wind", "hidden_obstacle"])
def test_success_past_the_far_side(name):
    scenario = make_scenario(name)
    # Far side at x = 0.2 + 0.3 = 0.5 (wind square half side 0.3; obstacle half thickness 0.3).
    hazard = make_hazard((0.2, 0.1), (0.3, 0.3), (1.0, 0.0))
    placed = positions((0.51, 0.1), (0.49, 0.1), (0.2, 0.1), (-1.0, 0.0), (1.5, 0.0), (0.6, 0.3))
    np.testing.assert_array_equal(
        call(scenario, "reached", hazard, placed)[:, 0], [1, 0, 0, 0, 1, 1]
    )


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
    cx, cy = hazard.centre
    assert cx.min() >= -0.3 and cx.max() <= 0.3 and cx.max() - cx.min() > 0.5
    assert cy.min() >= -0.25 and cy.max() <= 0.25 and cy.max() - cy.min() > 0.4
    assert not np.allclose(hazard.centre, other.centre)  # a new draw for a new key
    hx, hy = hazard.half_extent
    if name == "turbulence":
        np.testing.assert_array_equal(hx, hy)
        assert hx.min() >= 0.3 and hx.max() <= 0.5 and hx.max() - hx.min() > 0.15
        assert not np.allclose(hazard.half_extent, other.half_extent)
    elif name == "strong_wind":
        np.testing.assert_array_equal(hx, hy)  # a square
        assert hx.min() >= 0.25 and hx.max() <= 0.5 and hx.max() - hx.min() > 0.2
        np.testing.assert_allclose(np.linalg.norm(hazard.direction, axis=0), 1.0, atol=1e-6)
        angle = np.arctan2(hazard.direction[1], hazard.direction[0])
        assert np.histogram(angle, bins=4, range=(-np.pi, np.pi))[0].min() > 30
    elif name == "hidden_obstacle":
        np.testing.assert_allclose(hx, HiddenObstacle().thickness / 2)  # fixed
        assert hy.min() >= 0.3 and hy.max() <= 0.7 and hy.max() - hy.min() > 0.3
    else:
        assert np.all(hazard.half_extent == 0.0)


def test_hazard_ranges_are_configurable():
    layout = Layout(hazard_x_range=(1.0, 1.5), hazard_y_range=(-2.0, -1.0))
    cases = [
        (Turbulence(radius_range=(0.1, 0.2)), (0.1, 0.2), (0.1, 0.2)),
        (StrongWind(side_range=(0.2, 0.4), angle=1.0), (0.1, 0.2), (0.1, 0.2)),
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
        if isinstance(scenario, StrongWind):  # a fixed angle: the same wind in every episode
            np.testing.assert_allclose(
                np.asarray(hazard.direction), np.tile([[math.cos(1.0)], [math.sin(1.0)]], 256),
                atol=1e-6,
            )


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
        (lambda: StrongWind(angle=float("nan")), "angle"),
        (lambda: StrongWind(angle="north"), "angle"),
        (lambda: HiddenObstacle(thickness=0.0), "thickness"),
        (lambda: HiddenObstacle(thickness=-0.4), "thickness"),
        (lambda: HiddenObstacle(length_range=(1.4, 0.6)), "length_range"),
        (lambda: Layout(goal_radius=0.0), "goal_radius"),
        (lambda: Layout(goal=(float("nan"), 0.0)), "goal"),
        (lambda: Layout(start_half_extent=(-0.1, 0.5)), "start_half_extent"),
        (lambda: Layout(hazard_x_range=(0.3, -0.3)), "hazard_x_range"),
        (lambda: Layout(hazard_y_range=(0.0, float("nan"))), "hazard_y_range"),
        (lambda: make_scenario("turbulence", max_force=-2.0), "max_force"),
        (lambda: make_scenario("strong_wind", strength=3.0), "strength"),
        (lambda: make_scenario("blizzard"), "blizzard"),
    ],
)
def test_bad_parameters_raise_value_error_naming_the_field(build, field):
    with pytest.raises(ValueError, match=field):
        build()


def test_registry_names():
    assert sorted(SCENARIOS) == sorted(NAMES)
    for name in NAMES:
        assert make_scenario(name).name == name
