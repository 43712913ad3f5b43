"""Tests of :mod:`ccrjax.envs.world`: hand-computed steps, agreement with the maintained MPE
(``mpe2``), properties (no NaN/inf) of the contact laws, and the solid rectangle
(:func:`rectangle_distance`, :func:`rectangle_stop`).

Every array is batch-last: positions ``[K, 2, B]``.
"""

from __future__ import annotations

import math
import types

import hypothesis.extra.numpy as hnp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ccrjax.envs.world import (
    DISCRETE_ACTION_DIRECTIONS,
    DISCRETE_ACTION_SETS,
    PhysicsParams,
    action_to_force,
    contact_penetration,
    disc_contact_forces,
    physics_step,
    rectangle_distance,
    rectangle_stop,
)

PROPERTY = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

# physics_step with params as a static argument, compiled once per shape.
physics_step_jit = jax.jit(physics_step, static_argnames="params")


def batched(*rows: list[list[float]]) -> jnp.ndarray:
    """``float32[K, 2, 1]`` from K ``[x, y]`` rows."""
    return jnp.asarray(np.array(rows, np.float32)[:, :, None])


def step_fn(use_jit: bool):
    return physics_step_jit if use_jit else physics_step


# --------------------------------------------------------------------------- hand-computed


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_two_overlapping_discs_hand_computed(use_jit):
    # Disc a at (0, 0) moving (1, 0.5); disc b at (0.08, 0) at rest; radii 0.05.
    # dist = 0.08, dist_min = 0.1, gap = -0.02, x = -gap / k = 20,
    # penetration = k * softplus(20) = 1e-3 * (20 + log(1 + e^-20)) = 0.02 (+2e-12).
    # f_a = 100 * (p_a - p_b) / dist * 0.02 = 100 * (-1, 0) * 0.02 = (-2, 0); f_b = (+2, 0).
    # a: p' = (0, 0) + (1, 0.5) * 0.1 = (0.1, 0.05)
    #    v' = (1, 0.5) * 0.75 + (-2, 0) * 0.1 = (0.55, 0.375)
    # b: p' = (0.08, 0);  v' = (0, 0) * 0.75 + (2, 0) * 0.1 = (0.2, 0)
    position = batched([0.0, 0.0], [0.08, 0.0])
    velocity = batched([1.0, 0.5], [0.0, 0.0])
    radius = jnp.array([0.05, 0.05], jnp.float32)
    p, v = step_fn(use_jit)(position, velocity, radius, jnp.zeros_like(position), PhysicsParams())
    np.testing.assert_allclose(p[:, :, 0], [[0.1, 0.05], [0.08, 0.0]], atol=1e-6)
    np.testing.assert_allclose(v[:, :, 0], [[0.55, 0.375], [0.2, 0.0]], atol=1e-6)


def test_contact_force_hand_computed():
    radius = jnp.array([0.05, 0.05, 0.05], jnp.float32)
    # Pair (0, 1) exactly touching along y: gap 0, penetration = k * log 2 = 6.9315e-4,
    # force = 100 * 6.9315e-4 = 0.069315 on 0 along (0, -1), on 1 along (0, +1).
    # Disc 2 at (5, 5) is far from both: gap ~ 7, softplus(-7000) = 0, no force.
    position = batched([0.0, 0.0], [0.0, 0.1], [5.0, 5.0])
    force = jax.jit(disc_contact_forces, static_argnames="params")(
        position, radius, PhysicsParams()
    )
    f = 100 * 1e-3 * math.log(2.0)
    np.testing.assert_allclose(
        force[:, :, 0], [[0.0, -f], [0.0, f], [0.0, 0.0]], rtol=1e-5, atol=1e-7
    )
    # Well separated (gap 0.1 = 100 margins): softplus(-100) ~ 3.7e-44, zero in float32.
    far = physics_step_jit(
        batched([0.0, 0.0], [0.2, 0.0]),
        jnp.zeros((2, 2, 1)),
        radius[:2],
        jnp.zeros((2, 2, 1)),
        PhysicsParams(),
    )[1]
    assert float(jnp.max(jnp.abs(far))) < 1e-12


def test_contact_penetration_values():
    # k * softplus(-gap / k) with k = 1e-3.
    gaps = jnp.array([-0.05, -0.001, 0.0, 0.001, 0.01, 1.0], jnp.float32)
    expected = [
        0.05,  # deep overlap: ~ -gap
        1e-3 * math.log1p(math.e),  # softplus(1)
        1e-3 * math.log(2.0),  # softplus(0)
        1e-3 * math.log1p(math.exp(-1.0)),
        1e-3 * math.log1p(math.exp(-10.0)),
        0.0,
    ]
    # atol 1e-10: log(1 + e^-10) rounds in float32 (a force error of 2e-9).
    np.testing.assert_allclose(contact_penetration(gaps, 1e-3), expected, rtol=1e-5, atol=1e-10)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_integration_order_position_before_velocity(use_jit):
    # One free disc, v = (1, -2), force (5, 0) (action +x at sensitivity 5).
    # Maintained MPE order: p' = p + v dt = (0.1, -0.2);
    #                      v' = v * 0.75 + F dt = (0.75 + 0.5, -1.5) = (1.25, -1.5).
    # (The 2017 order would give p' = p + v' dt = (0.125, -0.15).)
    position = batched([0.0, 0.0], [10.0, 10.0])
    velocity = batched([1.0, -2.0], [0.0, 0.0])
    force = batched([5.0, 0.0], [0.0, 0.0])
    radius = jnp.array([0.05, 0.05], jnp.float32)
    p, v = step_fn(use_jit)(position, velocity, radius, force, PhysicsParams())
    np.testing.assert_allclose(p[0, :, 0], [0.1, -0.2], atol=1e-6)
    np.testing.assert_allclose(v[0, :, 0], [1.25, -1.5], atol=1e-6)
    np.testing.assert_allclose(p[1, :, 0], [10.0, 10.0], atol=1e-6)
    np.testing.assert_allclose(v[1, :, 0], [0.0, 0.0], atol=1e-7)


def test_terminal_speed_under_full_action_is_two():
    # v* = 0.75 v* + 5 * 0.1  =>  v* = 2: the MPE's top speed under full action.
    position = batched([0.0, 0.0], [0.0, 50.0])
    velocity = jnp.zeros_like(position)
    force = action_to_force(batched([1.0, 0.0], [0.0, 0.0]), 5.0, discrete=False)
    radius = jnp.array([0.05, 0.05], jnp.float32)
    for _ in range(80):
        position, velocity = physics_step_jit(position, velocity, radius, force, PhysicsParams())
    np.testing.assert_allclose(velocity[0, :, 0], [2.0, 0.0], atol=1e-5)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_max_speed_clamp(use_jit):
    params = PhysicsParams(max_speed=1.0)
    # Disc 0: v = (1, 1), F = (5, 5): v' = (1.25, 1.25), |v'| = 1.7678 > 1
    #   -> v' = (1, 1) / sqrt(2) = (0.70711, 0.70711); p' = p + v dt = (0.1, 0.1) (old v).
    # Disc 1: v = (0.4, 0), F = 0: v' = (0.3, 0), below the limit, unchanged by the clamp.
    position = batched([0.0, 0.0], [3.0, 3.0])
    velocity = batched([1.0, 1.0], [0.4, 0.0])
    force = batched([5.0, 5.0], [0.0, 0.0])
    radius = jnp.array([0.05, 0.05], jnp.float32)
    p, v = step_fn(use_jit)(position, velocity, radius, force, params)
    s = 1.0 / math.sqrt(2.0)
    np.testing.assert_allclose(v[:, :, 0], [[s, s], [0.3, 0.0]], atol=1e-6)
    np.testing.assert_allclose(p[:, :, 0], [[0.1, 0.1], [3.04, 3.0]], atol=1e-6)
    # Without a limit the same step keeps |v'| = 1.7678.
    _, v_free = step_fn(use_jit)(position, velocity, radius, force, PhysicsParams())
    np.testing.assert_allclose(v_free[0, :, 0], [1.25, 1.25], atol=1e-6)


def test_coincident_discs_get_no_force_but_others_still_push():
    # Discs 0 and 1 exactly on top of each other (the MPE gives NaN there; ccrjax: no force
    # between them). Disc 2 overlaps both by 0.02 from +x: each gets (-2, 0) from it.
    position = batched([0.0, 0.0], [0.0, 0.0], [0.08, 0.0])
    velocity = jnp.zeros_like(position)
    radius = jnp.array([0.05, 0.05, 0.05], jnp.float32)
    p, v = physics_step_jit(position, velocity, radius, jnp.zeros_like(position))
    np.testing.assert_allclose(p, position)
    np.testing.assert_allclose(v[:, :, 0], [[-0.2, 0.0], [-0.2, 0.0], [0.4, 0.0]], atol=1e-6)


def test_action_to_force_continuous_scales_and_clips():
    action = batched([0.5, -1.0], [2.0, -3.0], [0.0, 0.25])
    force = action_to_force(action, 5.0, discrete=False)
    assert force.dtype == jnp.float32
    np.testing.assert_allclose(force[:, :, 0], [[2.5, -5.0], [5.0, -5.0], [0.0, 1.25]])


def test_physics_params_validation():
    for field, value in [
        ("dt", 0.0),
        ("dt", float("nan")),
        ("contact_force", -1.0),
        ("contact_margin", 0.0),
        ("mass", float("inf")),
        ("damping", 1.0),
        ("damping", -0.1),
        ("max_speed", 0.0),
    ]:
        with pytest.raises(ValueError, match=rf"PhysicsParams\.{field}"):
            PhysicsParams(**{field: value})


# --------------------------------------------------------------------------- versus mpe2


def mpe_world(position, velocity, force, sizes, max_speed):
    """An mpe2 World of silent, movable, colliding agents, in float64."""
    from mpe2._mpe_utils.core import Agent, World

    world = World()
    for i in range(position.shape[0]):
        agent = Agent()
        agent.name = f"agent_{i}"
        agent.size = float(sizes[i])
        agent.movable = True
        agent.collide = True
        agent.silent = True
        agent.max_speed = max_speed
        agent.state.p_pos = position[i].astype(np.float64)
        agent.state.p_vel = velocity[i].astype(np.float64)
        agent.action.u = force[i].astype(np.float64)
        world.agents.append(agent)
    return world


def random_state(rng, n, batch):
    """Positions in [-1, 1]^2 with overlapping (never coincident) pairs, float32 ``[n, 2, B]``."""
    position = rng.uniform(-1.0, 1.0, (n, 2, batch))
    for b in range(batch):
        # Pairs (0, 1), (3, 4), (5, 6), ... overlap by 0.005 to 0.08; disc 2 touches disc 0
        # from the side opposite disc 1 (so it is well clear of disc 1).
        for first in [0, *range(3, n - 1, 2)]:
            angle = rng.uniform(0.0, 2 * math.pi)
            direction = np.array([math.cos(angle), math.sin(angle)])
            position[first + 1, :, b] = position[first, :, b] + rng.uniform(0.02, 0.095) * direction
            if first == 0 and n >= 3:
                position[2, :, b] = position[0, :, b] - 0.099 * direction
    velocity = rng.uniform(-2.0, 2.0, (n, 2, batch))
    action = rng.uniform(-1.0, 1.0, (n, 2, batch))
    return (
        position.astype(np.float32),
        velocity.astype(np.float32),
        action.astype(np.float32),
    )


@pytest.mark.parametrize("n", [2, 5, 8])
@pytest.mark.parametrize("max_speed", [None, 1.0], ids=["no_clamp", "max_speed_1"])
def test_physics_step_matches_mpe2(n, max_speed):
    # Compiled; the hand-computed tests above also run without jit.
    batch = 4  # four random worlds (seeds) side by side in one batch
    rng = np.random.default_rng(1000 * n + (0 if max_speed is None else 1))
    position, velocity, action = random_state(rng, n, batch)
    sizes = np.full(n, 0.05)
    params = PhysicsParams(max_speed=max_speed)
    force = action_to_force(jnp.asarray(action), 5.0, discrete=False)
    p, v = physics_step_jit(
        jnp.asarray(position), jnp.asarray(velocity), jnp.asarray(sizes, jnp.float32), force, params
    )
    contact_seen = 0.0
    for b in range(batch):
        world = mpe_world(
            position[:, :, b], velocity[:, :, b], action[:, :, b] * 5.0, sizes, max_speed
        )
        world.step()
        mpe_p = np.stack([agent.state.p_pos for agent in world.agents])
        mpe_v = np.stack([agent.state.p_vel for agent in world.agents])
        np.testing.assert_allclose(np.asarray(p[:, :, b]), mpe_p, rtol=0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(v[:, :, b]), mpe_v, rtol=0, atol=1e-5)
        if max_speed is None:
            # How much of the velocity change the contacts made: the test must exercise them.
            no_contact = velocity[:, :, b] * 0.75 + action[:, :, b] * 5.0 * 0.1
            contact_seen = max(contact_seen, float(np.abs(mpe_v - no_contact).max()))
        else:
            assert np.all(np.linalg.norm(mpe_v, axis=1) <= 1.0 + 1e-9)
    if max_speed is None:
        assert contact_seen > 0.1


def test_physics_step_matches_mpe2_with_mixed_radii():
    n, batch = 5, 4
    rng = np.random.default_rng(7)
    position, velocity, action = random_state(rng, n, batch)
    sizes = rng.uniform(0.03, 0.1, n)
    force = action_to_force(jnp.asarray(action), 5.0, discrete=False)
    p, v = physics_step_jit(
        jnp.asarray(position),
        jnp.asarray(velocity),
        jnp.asarray(sizes, jnp.float32),
        force,
        PhysicsParams(),
    )
    for b in range(batch):
        world = mpe_world(position[:, :, b], velocity[:, :, b], action[:, :, b] * 5.0, sizes, None)
        world.step()
        mpe_p = np.stack([agent.state.p_pos for agent in world.agents])
        mpe_v = np.stack([agent.state.p_vel for agent in world.agents])
        np.testing.assert_allclose(np.asarray(p[:, :, b]), mpe_p, rtol=0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(v[:, :, b]), mpe_v, rtol=0, atol=1e-5)


def mpe_set_action(action, continuous):
    """Runs mpe2's own ``SimpleEnv._set_action`` for one silent agent; returns ``action.u``."""
    from mpe2._mpe_utils.core import Agent
    from mpe2._mpe_utils.simple_env import SimpleEnv

    agent = Agent()
    agent.silent = True
    owner = types.SimpleNamespace(
        world=types.SimpleNamespace(dim_p=2, dim_c=0), continuous_actions=continuous
    )
    SimpleEnv._set_action(owner, [action], agent, None)
    return np.asarray(agent.action.u, np.float64)


def test_discrete_actions_match_mpe2():
    fn = jax.jit(action_to_force, static_argnums=(1, 2, 3))
    # All five actions for 5 robots, in 2 environments (second one reversed).
    action = jnp.array([[0, 4], [1, 3], [2, 2], [3, 1], [4, 0]], jnp.int32)
    force = np.asarray(fn(action, 5.0, True, "mpe5"))
    assert force.shape == (5, 2, 2)
    for i in range(5):
        for b in range(2):
            expected = mpe_set_action(int(action[i, b]), continuous=False)
            np.testing.assert_allclose(force[i, :, b], expected, atol=0)
    # The table itself: {none, -x, +x, -y, +y}.
    np.testing.assert_array_equal(
        DISCRETE_ACTION_SETS["mpe5"], [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]]
    )
    # The default box9 holds mpe5's five first, then the box's corners, each the sum of
    # two of mpe5's forces (what mpe2 makes of a 5-way action with two entries set).
    box9 = np.asarray(fn(jnp.arange(9, dtype=jnp.int32)[:, None], 5.0, True))[:, :, 0]
    np.testing.assert_array_equal(box9[:5], force[:, :, 0])
    for a, (x, y) in zip(range(5, 9), [(1, 3), (1, 4), (2, 3), (2, 4)], strict=True):
        np.testing.assert_array_equal(box9[a], box9[x] + box9[y])
    np.testing.assert_array_equal(DISCRETE_ACTION_DIRECTIONS, DISCRETE_ACTION_SETS["box9"])


def test_continuous_action_matches_mpe2_five_way_encoding():
    # mpe2's continuous action is [noop, -x, +x, -y, +y]; u = (a2 - a1, a4 - a3) * 5.
    # ccrjax's 2-D action (ux, uy) is that same u / 5.
    rng = np.random.default_rng(3)
    for _ in range(5):
        ux, uy = rng.uniform(-1.0, 1.0, 2)
        mpe_action = np.array([0.0, max(-ux, 0), max(ux, 0), max(-uy, 0), max(uy, 0)])
        expected = mpe_set_action(mpe_action, continuous=True)
        ours = action_to_force(batched([ux, uy]), 5.0, discrete=False)[0, :, 0]
        np.testing.assert_allclose(np.asarray(ours), expected, atol=1e-6)


# --------------------------------------------------------------------------- rectangle


def test_rectangle_distance_hand_computed():
    # Rectangle centred at (1, 2), half extent (0.5, 0.25): x in [0.5, 1.5], y in [1.75, 2.25].
    centre = jnp.array([[1.0], [2.0]], jnp.float32)
    half = jnp.array([[0.5], [0.25]], jnp.float32)
    points = batched(
        [2.0, 2.0],  # right of it by 0.5
        [1.0, 1.5],  # below by 0.25
        [1.8, 2.65],  # off the top-right corner by (0.3, 0.4): 0.5
        [1.4, 2.0],  # inside, 0.1 from the right face (0.25 from top and bottom): -0.1
        [0.7, 2.2],  # inside, 0.2 from the left face, 0.05 from the top: -0.05
        [1.0, 2.0],  # the centre: 0.25 below the top and bottom faces
        [1.5, 2.25],  # exactly on the corner
    )
    distance = jax.jit(rectangle_distance)(points, centre, half)
    assert distance.shape == (7, 1)
    np.testing.assert_allclose(
        distance[:, 0], [0.5, 0.25, 0.5, -0.1, -0.05, -0.25, 0.0], atol=1e-6
    )


rectangle_stop_jit = jax.jit(rectangle_stop)


def test_rectangle_stop_hand_computed():
    # Rectangle at the origin, half extent (0.2, 0.5); discs of radius 0.05: a centre may not
    # enter the grown rectangle x in [-0.25, 0.25], y in [-0.55, 0.55].
    centre = jnp.zeros((2, 1), jnp.float32)
    half = jnp.array([[0.2], [0.5]], jnp.float32)
    cases = [
        # (previous, after the physics step, velocity) -> (position, velocity)
        # Into the -x face: stopped on it, x velocity zeroed, the new y kept (it slides).
        ([-0.4, 0.1], [-0.2, 0.15], [2.0, 0.5], [-0.25, 0.15], [0.0, 0.5]),
        # At 10 units/s, 1.0 in one step, through the whole rectangle: stopped at the entry.
        ([-0.4, 0.0], [0.6, 0.0], [10.0, 0.0], [-0.25, 0.0], [0.0, 0.0]),
        # The same, at an angle: entry face -x, the new y kept.
        ([-0.4, -0.1], [0.6, 0.3], [10.0, 4.0], [-0.25, 0.3], [0.0, 4.0]),
        # Sliding along the -x face: untouched.
        ([-0.25, 0.0], [-0.25, 0.2], [0.0, 2.0], [-0.25, 0.2], [0.0, 2.0]),
        # Moving away from the -x face: untouched.
        ([-0.25, 0.1], [-0.45, 0.1], [-2.0, 0.0], [-0.45, 0.1], [-2.0, 0.0]),
        # Into the top face from above: stopped on it (y = 0.55), y velocity zeroed.
        ([0.1, 0.7], [0.05, 0.5], [-0.5, -2.0], [0.05, 0.55], [-0.5, 0.0]),
        # Past the top-left corner, into the y slab first (t = 1/3), then the x slab
        # (t = 1/2): it hit the -x face (at y = 0.5), where it is stopped.
        ([-0.35, 0.65], [-0.15, 0.35], [2.0, -3.0], [-0.25, 0.35], [0.0, -3.0]),
        # Past the same corner, into the x slab first (t = 1/4), the y slab last (t = 2/3):
        # it hit the top face.
        ([-0.3, 0.75], [-0.1, 0.45], [2.0, -3.0], [-0.1, 0.55], [2.0, 0.0]),
        # Close by the corner, but the segment ends before it enters: untouched.
        ([-0.4, 0.7], [-0.1, 0.6], [3.0, -1.0], [-0.1, 0.6], [3.0, -1.0]),
        # Resting on the face: untouched.
        ([-0.25, 0.3], [-0.25, 0.3], [0.0, 0.0], [-0.25, 0.3], [0.0, 0.0]),
    ]
    previous, moved, velocity, want_position, want_velocity = (
        batched(*column) for column in zip(*cases, strict=True)
    )
    radius = jnp.full((len(cases),), 0.05, jnp.float32)
    position, velocity = rectangle_stop_jit(previous, moved, velocity, radius, centre, half)
    np.testing.assert_allclose(position, want_position, atol=1e-6)
    np.testing.assert_allclose(velocity, want_velocity, atol=1e-6)


finite32 = st.floats(-10.0, 10.0, width=32)


@st.composite
def robot_configurations(draw):
    """Positions ``[4, 2, 3]`` in which some robots sit exactly on top of each other."""
    position = draw(hnp.arrays(np.float32, (4, 2, 3), elements=st.floats(-50, 50, width=32)))
    copies = draw(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 3)), max_size=4))
    for src, dst in copies:
        position[dst] = position[src]
    if draw(st.booleans()):  # all four in one spot in the first environment
        position[:, :, 0] = position[0, :, 0]
    # And some barely apart (tiny but non-zero distances).
    tiny = draw(st.sampled_from([0.0, 1e-30, 1e-20, 1e-7, 1e-3]))
    position[3, 0, 1] = position[2, 0, 1] + np.float32(tiny)
    velocity = draw(hnp.arrays(np.float32, (4, 2, 3), elements=finite32))
    action = draw(hnp.arrays(np.float32, (4, 2, 3), elements=st.floats(-1, 1, width=32)))
    return position, velocity, action


@PROPERTY
@given(robot_configurations(), st.sampled_from([None, 2.0]))
def test_physics_step_never_produces_nan_or_inf(config, max_speed):
    position, velocity, action = config
    radius = jnp.full((4,), 0.05, jnp.float32)
    force = action_to_force(jnp.asarray(action), 5.0, discrete=False)
    params = PhysicsParams(max_speed=max_speed)
    p, v = physics_step_jit(jnp.asarray(position), jnp.asarray(velocity), radius, force, params)
    assert np.all(np.isfinite(np.asarray(p)))
    assert np.all(np.isfinite(np.asarray(v)))
    if max_speed is not None:
        assert np.all(np.linalg.norm(np.asarray(v), axis=1) <= max_speed * (1 + 1e-5))



def reference_signed_distance(point, centre, half):
    """float64 signed distance of one point to an axis-aligned rectangle."""
    rel = np.abs(point.astype(np.float64) - centre.astype(np.float64))
    excess = rel - half.astype(np.float64)
    if np.all(excess <= 0):
        return float(np.max(excess))
    return float(np.linalg.norm(np.maximum(excess, 0.0)))


@st.composite
def rectangle_cases(draw):
    """A rectangle ``[2, 1]`` and 6 points: centre, boundary, corner, inside, outside, any."""
    centre = np.array(draw(st.tuples(finite32, finite32)), np.float32)
    half = np.array(
        draw(st.tuples(st.floats(0.015625, 2.0, width=32), st.floats(0.015625, 2.0, width=32))),
        np.float32,
    )
    sx, sy = draw(st.sampled_from([-1.0, 1.0])), draw(st.sampled_from([-1.0, 1.0]))
    u = np.array(draw(st.tuples(st.floats(-1, 1), st.floats(-1, 1))))
    points = [
        centre,  # exactly at the centre
        centre + np.array([sx * half[0], u[1] * half[1]]),  # on a vertical face
        centre + np.array([sx * half[0], sy * half[1]]),  # on a corner
        centre + 0.999 * u * half,  # inside
        centre + np.array([sx * (half[0] + 1.0 + abs(u[0])), u[1] * 3.0]),  # outside
        np.array(draw(st.tuples(finite32, finite32))),  # anywhere
    ]
    return centre, half, np.stack(points).astype(np.float32)


@PROPERTY
@given(rectangle_cases())
def test_rectangle_distance_is_finite_and_correct(case):
    centre, half, points = case
    distance = np.asarray(
        jax.jit(rectangle_distance)(
            jnp.asarray(points[:, :, None]), jnp.asarray(centre[:, None]),
            jnp.asarray(half[:, None]),
        )
    )
    assert np.all(np.isfinite(distance))
    for k in range(6):
        expected = reference_signed_distance(points[k], centre, half)
        assert abs(distance[k, 0] - expected) <= 1e-5 * (1 + abs(expected) + np.abs(centre).max())


def segment_meets_box(start, end, centre, half):
    """float64 slab test: whether the segment ``start -> end`` meets the closed box."""
    low, high = 0.0, 1.0
    for axis in range(2):
        s, d = start[axis] - centre[axis], end[axis] - start[axis]
        if d == 0.0:
            if abs(s) > half[axis]:
                return False
            continue
        t_a, t_b = (-half[axis] - s) / d, (half[axis] - s) / d
        low, high = max(low, min(t_a, t_b)), min(high, max(t_a, t_b))
    return low <= high


@st.composite
def approaches(draw):
    """A rectangle, and 16 discs that approach it, then move on from where they were stopped.

    The first segment of each disc starts outside the grown rectangle (on any side, also
    off the corners, up to 1.5 away) and heads at up to 15 units/s (1.5 per 0.1 s step) for
    a random point of the rectangle or near it; the second one starts where the first was
    stopped and moves at any speed in any direction, often along one axis only (sliding
    along a face, or pushing straight into it).
    """
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-3.0, 3.0, 2)
    half = rng.uniform(0.05, 1.5, 2)
    radius = draw(st.sampled_from([0.05, 0.05, 0.01, 0.2]))
    grown = half + radius
    k = 16
    # Start: a point of the grown boundary (corners included), pushed out by a gap that is
    # sometimes zero.
    side = rng.integers(0, 4, k)
    along = rng.uniform(-1.0, 1.0, k)
    corner = rng.random(k) < 0.25
    along[corner] = rng.choice([-1.0, 1.0], int(corner.sum()))
    unit = np.where(side[:, None] < 2, np.stack([np.where(side == 0, -1.0, 1.0), along], 1),
                    np.stack([along, np.where(side == 2, -1.0, 1.0)], 1))
    gap = np.where(rng.random(k) < 0.3, 0.0, rng.uniform(0.0, 1.5, k))
    outward = np.where(side[:, None] < 2, [[1.0, 0.0]], [[0.0, 1.0]]) * np.sign(unit)
    start = centre + unit * grown + gap[:, None] * outward
    aim = centre + rng.uniform(-1.3, 1.3, (k, 2)) * grown
    heading = aim - start
    heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
    first = heading * rng.uniform(0.0, 1.5, (k, 1))
    angle = rng.uniform(0.0, 2 * np.pi, k)
    second = np.stack([np.cos(angle), np.sin(angle)], 1) * rng.uniform(0.0, 1.5, (k, 1))
    only = rng.integers(0, 3, k)  # 0: both axes; 1: x only; 2: y only
    second[only == 1, 1] = 0.0
    second[only == 2, 0] = 0.0
    return (centre.astype(np.float32), half.astype(np.float32), np.float32(radius),
            start.astype(np.float32), first.astype(np.float32), second.astype(np.float32))


def check_stop(previous, moved, velocity, position, new_velocity, centre, half, radius):
    """The invariants of one :func:`rectangle_stop` of discs ``[K, 2]`` (numpy, one env)."""
    distance = np.asarray(
        rectangle_distance(jnp.asarray(position[:, :, None]), jnp.asarray(centre[:, None]),
                           jnp.asarray(half[:, None]))
    )[:, 0]
    assert np.all(distance >= radius - 1e-5), distance.min() - radius
    changed = position != moved
    # Both coordinates change only for a disc that clipped a corner: it stops at the corner.
    both = changed.all(axis=1)
    corner_gap = np.abs(np.abs(position[both] - centre) - (half + radius))
    assert np.all(corner_gap < 1e-5), "both coordinates changed away from a corner"
    # A stopped disc stays on its path: the corrected coordinate lies between where it was
    # and where it would have gone (no jump to another face, no push back past its start).
    low, high = np.minimum(previous, moved), np.maximum(previous, moved)
    assert np.all(position >= low - 1e-5) and np.all(position <= high + 1e-5), (
        previous[np.any((position < low - 1e-5) | (position > high + 1e-5), axis=1)]
    )
    # Its velocity loses (at most) the component of the stopped axis.
    np.testing.assert_array_equal(np.where(changed, velocity, new_velocity), velocity)
    assert np.all((new_velocity == velocity) | (new_velocity == 0.0))
    # A disc whose path clearly misses the grown rectangle is untouched.
    grown = half.astype(np.float64) + radius + 1e-4
    for k in range(len(previous)):
        if not segment_meets_box(previous[k].astype(np.float64), moved[k].astype(np.float64),
                                 centre.astype(np.float64), grown):
            np.testing.assert_array_equal(position[k], moved[k])
            np.testing.assert_array_equal(new_velocity[k], velocity[k])


@PROPERTY
@given(approaches())
def test_rectangle_stop_never_lets_a_disc_in(case):
    centre, half, radius, start, first, second = case
    k = len(start)
    radii = jnp.full((k,), radius, jnp.float32)
    c, h = jnp.asarray(centre[:, None]), jnp.asarray(half[:, None])
    previous = start
    for displacement in (first, second):
        moved = (previous + displacement).astype(np.float32)
        velocity = (10.0 * displacement).astype(np.float32)
        position, new_velocity = (
            np.asarray(x)[:, :, 0]
            for x in rectangle_stop_jit(
                jnp.asarray(previous[:, :, None]), jnp.asarray(moved[:, :, None]),
                jnp.asarray(velocity[:, :, None]), radii, c, h,
            )
        )
        check_stop(previous, moved, velocity, position, new_velocity, centre, half, radius)
        previous = position
