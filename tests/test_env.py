"""Tests of :class:`ccrjax.envs.env.EmergencyEnv`: registry, batching, determinism, auto-reset,
start positions and targets, success, observation layout, jit, and input validation.

Arrays are batch-last: obs ``[N, F, B]``, reward ``[N, B]``, continuous action ``[N, 2, B]``.

Compiling a step costs seconds on a 2-core CPU, so the tests share a few compiled
functions (module-scoped) and build worlds with numpy where no draw is being tested.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ccrjax.agents.types import Transition
from ccrjax.envs.env import EmergencyEnv, WorldState
from ccrjax.envs.scenarios import Hazard, Layout
from ccrjax.envs.scenarios.layout import target_positions
from ccrjax.envs.world import rectangle_distance
from ccrjax.training.acting import Episode, episode_metrics

NAMES = ["turbulence", "strong_wind", "hidden_obstacle", "nominal"]
METRICS = ("danger", "success", "target_distance", "hazard_distance")
N, B, EPISODE = 3, 4, 4  # robots, environments, steps per episode: few shapes, few compiles
STEPS = 3 * EPISODE  # every rollout has this length: one compilation per environment

# The rollouts (reset, step, transition compiled once, for the hidden obstacle) use JAX's
# "rbg" keys: the environment only splits and draws from the key it is given, and "rbg"
# keys compile, and run without jit, several times faster than the default threefry keys.
# The tests of single transitions use the default keys.
ROLLOUT = "hidden_obstacle"


def rollout_key(seed: int) -> jax.Array:
    return jax.random.key(seed, impl="rbg")


def random_actions(seed: int, steps: int, n: int = N, batch: int = B) -> jax.Array:
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform(-1.0, 1.0, (steps, n, 2, batch)), jnp.float32)


def assert_trees_equal(a, b, atol=0.0):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


def at(tree, t):
    """Element ``t`` of a tree stacked over time."""
    return jax.tree.map(lambda x: x[t], tree)


class Compiled:
    """One environment with ``reset`` and a rollout, each compiled once.

    ``run(state, actions)`` scans ``env.step`` over ``actions`` and returns, stacked over
    time: the states ``step`` gave, the states ``transition`` (the same step without the
    reset) gave from the same state, and ``env.observe`` of each stepped world.
    """

    def __init__(self, env: EmergencyEnv):
        self.env = env
        self.reset = jax.jit(env.reset)

        def run(state, actions):
            def body(state, action):
                stepped = env.step(state, action)
                terminal = env.transition(state, action)
                return stepped, (stepped, terminal, env.observe(stepped.pipeline_state))

            return jax.lax.scan(body, state, actions)[1]

        self.run = jax.jit(run)


@pytest.fixture(scope="module")
def compiled():
    cache: dict[str, Compiled] = {}

    def get(name: str) -> Compiled:
        if name not in cache:
            cache[name] = Compiled(EmergencyEnv(name, num_robots=N, num_envs=B,
                                                episode_length=EPISODE))
        return cache[name]

    return get


def hand_batch_world(env: EmergencyEnv, key=None) -> WorldState:
    """A world of ``B`` environments built with numpy (no random draws): hazards of each
    scenario's shape, robot 0 inside the hazard area (on the obstacle's -x face, touching
    it), robot 1 overlapping robot 0 (a contact), robot 2 well outside, random velocities."""
    rng = np.random.default_rng(0)
    centre = rng.uniform(-0.3, 0.3, (2, B))
    if env.scenario.name == "hidden_obstacle":
        half = np.stack([np.full(B, 0.2), rng.uniform(0.3, 0.7, B)])
        offset = np.array([[-0.25], [0.02]])  # on the grown -x face
    elif env.scenario.name == "nominal":
        half = np.zeros((2, B))
        offset = np.array([[0.05], [0.02]])
    else:
        half = np.tile(rng.uniform(0.3, 0.5, B), (2, 1))
        offset = np.array([[0.05], [0.02]])
    direction = np.stack([np.zeros(B), np.where(rng.random(B) < 0.5, -1.0, 1.0)])
    position = np.stack(
        [centre + offset, centre + offset - [[0.07], [0.0]], centre - [[0.75], [0.0]]]
    )
    hazard = Hazard(
        centre=jnp.asarray(centre, jnp.float32),
        half_extent=jnp.asarray(half, jnp.float32),
        direction=jnp.asarray(direction, jnp.float32),
    )
    position = jnp.asarray(position, jnp.float32)
    return WorldState(
        position=position,
        velocity=jnp.asarray(rng.normal(size=(N, 2, B)), jnp.float32),
        hazard=hazard,
        target=target_positions(position, env.layout),
        time=jnp.zeros((), jnp.int32),
        key=jax.random.key(0) if key is None else key,
    )


def hand_state(env: EmergencyEnv, key) -> State:
    """A brax State around :func:`hand_batch_world` (what ``step`` reads of it is the world)."""
    zeros = jnp.zeros((N, B), jnp.float32)
    return State(
        pipeline_state=hand_batch_world(env, key),
        obs=jnp.zeros((N, env.observation_size, B), jnp.float32),
        reward=zeros,
        done=jnp.zeros((B,), jnp.float32),
        metrics={name: zeros for name in METRICS},
        info={},
    )


# --------------------------------------------------------------------------- registry


def test_brax_registry():
    import brax.envs

    env = brax.envs.get_environment("ccr_hidden_obstacle", num_envs=4)
    assert isinstance(env, EmergencyEnv)
    assert env.scenario.name == "hidden_obstacle" and env.num_envs == 4
    state = jax.eval_shape(env.reset, jax.random.key(0))  # shapes only, nothing compiled
    n = env.num_robots
    assert state.obs.shape == (n, env.observation_size, 4)
    assert env.observation_size == 4 + 3 * (n - 1) + 3 + 1
    assert env.action_size == 2
    assert state.reward.shape == (n, 4) and state.done.shape == (4,)
    env.check_action(jnp.zeros((n, env.action_size, 4)))  # the documented action layout
    for name in NAMES:
        env = brax.envs.get_environment(f"ccr_{name}", num_robots=2, discrete_actions=True)
        assert isinstance(env, EmergencyEnv) and env.scenario.name == name
        assert env.action_size == 9
        assert env.observation_size == 4 + 3 + 3 + env.scenario.hazard_feature_size


# --------------------------------------------------------------------------- batch = one by one


def slice_env(world: WorldState, b: int) -> WorldState:
    """Environment ``b`` of a batched world as a batch of one (time and key are shared)."""
    time, key = world.time, world.key
    sliced = jax.tree.map(lambda x: x[..., b : b + 1], world.replace(time=None, key=None))
    return sliced.replace(time=time, key=key)


@pytest.mark.parametrize("name", NAMES)
def test_batch_equals_environments_stepped_one_by_one(name):
    batched_env = EmergencyEnv(name, num_robots=N, num_envs=B)
    single_env = EmergencyEnv(name, num_robots=N, num_envs=1)

    def advance_and_read(env, world, action, noise):
        world = env.advance(world, action, noise)
        return world, env.observe(world), env.reward(world), env.metrics(world)

    @jax.jit
    def batched_and_singles(world, singles, action, key, noise_scale):
        """One step of the batch; and of each environment alone, one after the other
        (``lax.map`` over a stack of single-environment worlds), with slices of the same
        actions and hazard noise."""
        noise = batched_env.scenario.step_noise(key, N, B) * noise_scale
        slices = (
            jnp.moveaxis(action, -1, 0)[..., None],  # [B, N, 2, 1]
            jnp.moveaxis(noise, -1, 0)[..., None],
        )
        one_by_one = jax.lax.map(
            lambda args: advance_and_read(single_env, *args), (singles, *slices)
        )
        before = batched_env.metrics(world)["danger"]
        return advance_and_read(batched_env, world, action, noise), one_by_one, before

    def stack_slices(world):
        return jax.tree.map(lambda *x: jnp.stack(x), *[slice_env(world, b) for b in range(B)])

    world = hand_batch_world(batched_env)
    singles = stack_slices(world)
    actions = random_actions(12, 3)
    keys = [jax.random.key(100 + t, impl="rbg") for t in range(3)]
    for t in range(3):
        (world, obs, reward, metrics), stacked, danger = batched_and_singles(
            world, singles, actions[t], keys[t], 1.0
        )
        if t == 0 and name != "nominal":  # the setup put robot 0 in danger everywhere
            np.testing.assert_array_equal(danger[0], np.ones(B))
        if t == 0 and name == "turbulence":  # and the noise pushed it: without, it differs
            start = hand_batch_world(batched_env)
            quiet = batched_and_singles(start, stack_slices(start), actions[0], keys[0], 0.0)
            assert not np.allclose(world.velocity[0], quiet[0][0].velocity[0])
        singles = stacked[0]
        assert obs.shape == (N, batched_env.observation_size, B)
        for b in range(B):
            world_b, obs_b, reward_b, metrics_b = at(stacked, b)
            assert_trees_equal(slice_env(world, b), world_b, atol=1e-6)
            np.testing.assert_allclose(obs[..., b : b + 1], obs_b, rtol=0, atol=1e-6)
            np.testing.assert_allclose(reward[..., b : b + 1], reward_b, rtol=0, atol=1e-6)
            for metric in METRICS:
                np.testing.assert_allclose(
                    metrics[metric][..., b : b + 1], metrics_b[metric], rtol=0, atol=1e-6
                )


# --------------------------------------------------------------------------- determinism


def test_same_key_same_episode_different_key_different_episode(compiled):
    c = compiled(ROLLOUT)
    actions = random_actions(5, STEPS)

    def episode(seed):
        start = c.reset(rollout_key(seed))
        return start, c.run(start, actions)

    first, second, other = episode(1), episode(1), episode(2)
    assert_trees_equal(first, second)
    assert not np.allclose(first[0].obs, other[0].obs)
    assert not np.allclose(
        first[0].pipeline_state.hazard.half_extent, other[0].pipeline_state.hazard.half_extent
    )
    for t in range(STEPS):  # every step, across the automatic resets
        assert not np.allclose(at(first[1][0], t).obs, at(other[1][0], t).obs)


def test_turbulence_pushes_come_from_the_state_key():
    # The turbulence draws fresh pushes from the state's key every step. Robots 0 and 1 are
    # inside the area in every environment (hand-built world), robot 2 is outside.
    env = EmergencyEnv("turbulence", num_robots=N, num_envs=B)
    transition = jax.jit(env.transition)
    state = hand_state(env, jax.random.key(0))
    zero = jnp.zeros((N, 2, B))
    pushed = transition(state, zero)
    assert_trees_equal(pushed, transition(state, zero))  # same key, same pushes
    reseeded = state.replace(pipeline_state=state.pipeline_state.replace(key=jax.random.key(9)))
    otherwise = transition(reseeded, zero)
    assert not np.allclose(pushed.pipeline_state.velocity[0], otherwise.pipeline_state.velocity[0])
    # robot 2 is outside the area: no push, the same either way
    np.testing.assert_array_equal(
        pushed.pipeline_state.velocity[2], otherwise.pipeline_state.velocity[2]
    )
    # the key moves on, so the next step's pushes are new ones
    again = transition(pushed, zero)
    key_data = [np.asarray(jax.random.key_data(s.pipeline_state.key)) for s in
                (state, pushed, again)]
    assert len({k.tobytes() for k in key_data}) == 3


# --------------------------------------------------------------------------- auto-reset


def in_start_box(env: EmergencyEnv, position) -> bool:
    centre = np.array(env.layout.start_centre)[None, :, None]
    half = np.array(env.layout.start_half_extent)[None, :, None]
    return bool(np.all(np.abs(np.asarray(position) - centre) <= half + 1e-6))


def test_auto_reset_draws_a_new_episode(compiled):
    # The hidden obstacle draws no noise, so its key does not move during an episode: each
    # reset must still draw a new episode from it.
    c = compiled(ROLLOUT)
    env = c.env
    state = hand_state(env, rollout_key(3))  # any state will do: the resets are under test
    steps, terminals, observed = c.run(state, random_actions(7, STEPS))
    hazards = [state.pipeline_state.hazard]
    starts = [state.pipeline_state.position]
    for t in range(1, STEPS + 1):
        state, terminal = at(steps, t - 1), at(terminals, t - 1)
        world = state.pipeline_state
        end = t % EPISODE == 0
        np.testing.assert_array_equal(state.done, np.full(B, float(end)))
        np.testing.assert_array_equal(terminal.done, np.full(B, float(end)))
        # reward and metrics describe the step just taken, also at the episode's end
        np.testing.assert_allclose(state.reward, terminal.reward, rtol=0, atol=1e-6)
        assert_trees_equal(state.metrics, terminal.metrics, atol=1e-6)
        # obs is always the observation of the world in the state (the new one after a reset)
        np.testing.assert_allclose(state.obs, observed[t - 1], rtol=0, atol=1e-6)
        if not end:
            assert int(world.time) == t % EPISODE
            assert_trees_equal(world, terminal.pipeline_state, atol=1e-6)
            continue
        assert int(terminal.pipeline_state.time) == EPISODE
        assert int(world.time) == 0
        assert in_start_box(env, world.position)
        assert np.all(np.asarray(world.velocity) == 0.0)
        assert not np.allclose(world.position, terminal.pipeline_state.position)
        # the targets are handed out afresh, for the new start positions
        np.testing.assert_array_equal(
            world.target, target_positions(world.position, env.layout)
        )
        hazards.append(world.hazard)
        starts.append(world.position)
    assert len(hazards) == 4  # the first state and three automatic resets
    for i in range(len(hazards)):
        for j in range(i):  # every episode new: not the previous one's, not a cached first one
            assert not np.allclose(hazards[i].centre, hazards[j].centre), (i, j)
            assert not np.allclose(hazards[i].half_extent, hazards[j].half_extent), (i, j)
            assert not np.allclose(starts[i], starts[j]), (i, j)


def test_transition_never_resets(compiled):
    c = compiled(ROLLOUT)
    zero = jnp.zeros((STEPS, N, 2, B))
    _, terminals, _ = c.run(hand_state(c.env, rollout_key(4)), zero)
    # transition from each state step gave: the clock restarts only through step
    np.testing.assert_array_equal(terminals.pipeline_state.time, [1, 2, 3, 4] * 3)
    np.testing.assert_array_equal(terminals.done[:, 0], [0, 0, 0, 1] * 3)
    # transition from a state already at the episode's end runs the clock on; done stays 1
    _, later, _ = c.run(at(terminals, EPISODE - 1), zero)
    assert int(later.pipeline_state.time[0]) == EPISODE + 1
    np.testing.assert_array_equal(later.done[0], np.ones(B))


# --------------------------------------------------------------------------- starts, targets


@pytest.mark.parametrize(
    ("num_robots", "layout"),
    [
        (5, Layout()),
        # 16 of the default start box's 3 x 6 cells; slots 0.1 apart in a larger area.
        (16, Layout(target_spacing=0.1, goal_radius=0.8)),
    ],
    ids=["5_robots", "16_robots"],
)
def test_starts_are_separated_and_targets_are_slots_by_height(num_robots, layout):
    batch = 4096
    env = EmergencyEnv("nominal", num_robots=num_robots, num_envs=batch, layout=layout)
    world = jax.jit(env.reset)(jax.random.key(11)).pipeline_state
    position, target = np.asarray(world.position), np.asarray(world.target)
    # Every pair at least min_separation apart, every robot inside the start box.
    gap = np.linalg.norm(position[:, None] - position[None], axis=2)  # [N, N, B]
    gap[np.arange(num_robots), np.arange(num_robots)] = np.inf
    assert gap.min() >= layout.min_separation - 1e-6, gap.min()
    centre = np.array(layout.start_centre)[None, :, None]
    half = np.array(layout.start_half_extent)[None, :, None]
    assert np.all(np.abs(position - centre) <= half + 1e-6)
    # Starts are spread over the whole box (every cell is drawn), and differ between envs.
    for axis in range(2):
        spread = position[:, axis].max() - position[:, axis].min()
        assert spread > 2 * layout.start_half_extent[axis] - layout.min_separation - 0.02
    assert not np.allclose(position[..., 0], position[..., 1])
    # Targets: on the target area's vertical diameter, target_spacing apart, centred on
    # the goal, each robot's disc inside the area, distinct ...
    np.testing.assert_allclose(target[:, 0], layout.goal[0], atol=1e-6)
    slots = np.sort(target[:, 1], axis=0)  # [N, B]
    np.testing.assert_allclose(np.diff(slots, axis=0), layout.target_spacing, atol=1e-5)
    np.testing.assert_allclose(slots.mean(axis=0), layout.goal[1], atol=1e-5)
    reach = np.hypot(target[:, 0] - layout.goal[0], target[:, 1] - layout.goal[1])
    assert np.all(reach + env.robot_radius <= layout.goal_radius + 1e-6)
    # ... and handed out in the order of the robots' starting heights.
    np.testing.assert_array_equal(
        np.argsort(position[:, 1], axis=0, kind="stable"),
        np.argsort(target[:, 1], axis=0, kind="stable"),
    )


def test_success_is_where_the_robot_is_now(compiled):
    # Success is read at each step, not remembered. In every environment, robot 0 starts
    # left of the goal (1.5, 0) at full speed along +x and keeps pushing: it is in the
    # target area (radius 0.4) for two steps (x = 1.55, 1.75), then out (1.95, 2.15);
    # robot 1 rests inside; robot 2 drives in from outside. (The hazard is far away.)
    c = compiled(ROLLOUT)
    state = hand_state(c.env, rollout_key(5))
    world = state.pipeline_state
    start = np.array([[1.35, 0.0], [1.5, 0.1], [0.75, 0.0]], np.float32)
    speed = np.array([[2.0, 0.0], [0.0, 0.0], [2.0, 0.0]], np.float32)
    world = world.replace(
        position=jnp.asarray(np.repeat(start[..., None], B, axis=2)),
        velocity=jnp.asarray(np.repeat(speed[..., None], B, axis=2)),
        hazard=world.hazard.replace(centre=world.hazard.centre - 3.0),
    )
    actions = np.zeros((STEPS, N, 2, B), np.float32)
    actions[:, 0, 0] = 1.0
    actions[:, 2, 0] = 1.0
    _, terminals, _ = c.run(state.replace(pipeline_state=world), jnp.asarray(actions))
    position = np.asarray(terminals.pipeline_state.position[:EPISODE])  # [T, N, 2, B]
    success = np.asarray(terminals.metrics["success"][:EPISODE])  # [T, N, B]
    inside = np.hypot(position[:, :, 0] - 1.5, position[:, :, 1]) < 0.4
    np.testing.assert_array_equal(success, inside)
    np.testing.assert_array_equal(success[:, 0], np.tile([[1], [1], [0], [0]], (1, B)))
    assert np.all(success[:, 1] == 1.0)
    assert np.all(success[0, 2] == 0.0) and np.all(success[-1, 2] == 1.0)


def test_episode_metrics_hand_built():
    # T = 3 steps, N = 2 robots, E = 2 episodes. Success and the target distance are read
    # at the last step only; danger and the hazard distance are means over robot-steps;
    # the return is the sum of the rewards over steps, averaged over robots and episodes.
    success = np.array([
        [[1, 1], [0, 1]],  # robot 0 succeeds at step 0 in both episodes ...
        [[1, 0], [0, 1]],
        [[0, 0], [1, 1]],  # ... but ends outside: only robot 1's ends count, 2 of 4
    ], np.float32)
    danger = np.array([[[1, 0], [0, 0]], [[1, 1], [0, 0]], [[0, 0], [0, 1]]], np.float32)
    target_distance = np.array([
        [[3.0, 3.0], [3.0, 3.0]], [[0.0, 0.0], [0.0, 0.0]], [[0.5, 1.5], [0.0, 2.0]],
    ], np.float32)
    hazard_distance = np.arange(12, dtype=np.float32).reshape(3, 2, 2)
    env_reward = -target_distance
    # What a learner was trained on (a transform's shaped reward, [T, E, N]): not the return.
    shaped = Transition(obs=None, action=None, reward=jnp.asarray(env_reward.transpose(0, 2, 1)
                                                                  - 10.0),
                        next_obs=None, done=None)
    episode = Episode(
        transitions=shaped, env_reward=jnp.asarray(env_reward), danger=jnp.asarray(danger),
        success=jnp.asarray(success), target_distance=jnp.asarray(target_distance),
        hazard_distance=jnp.asarray(hazard_distance), position=jnp.zeros((4, 2, 2, 2)),
        hazard=None, info={},
    )
    metrics = {name: float(value) for name, value in episode_metrics(episode).items()}
    assert metrics == pytest.approx({
        "success_rate": 0.5,
        "target_distance": 1.0,  # (0.5 + 1.5 + 0 + 2) / 4
        "danger_frequency": 4 / 12,
        "hazard_distance": 5.5,  # mean of 0..11
        "return": -4.0,  # sums per robot and episode: -3.5, -4.5, -3, -5
    })


# --------------------------------------------------------------------------- solid obstacle


PILE_ROBOTS, PILE_ENVS, PILE_STEPS = 12, 16, 40


@pytest.fixture(scope="module")
def pile_env():
    """12 robots (a target area that holds them) in 16 environments of the hidden obstacle,
    and a rollout of ``env.transition`` with full action towards an aim point ``[2, B]``."""
    layout = Layout(target_spacing=0.1, goal_radius=0.8)
    env = EmergencyEnv("hidden_obstacle", num_robots=PILE_ROBOTS, num_envs=PILE_ENVS, layout=layout)

    def run(state, aim):
        def body(state, _):
            heading = aim[None] - state.pipeline_state.position
            norm = jnp.sqrt(jnp.sum(heading * heading, axis=1, keepdims=True))
            action = jnp.clip(2.0 * heading / jnp.maximum(norm, 1e-6), -1.0, 1.0)
            state = env.transition(state, action)
            return state, (state.pipeline_state.position, state.metrics["danger"])

        return jax.lax.scan(body, state, None, length=PILE_STEPS)[1]

    return env, jax.jit(env.reset)(jax.random.key(0)), jax.jit(run)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1))
def test_obstacle_is_solid_through_the_environment(pile_env, seed):
    # Piles of 12 robots, thrown at the obstacle at up to 10 units/s from in front of it and
    # off its corners, all driving at full action towards its centre (even environments)
    # or a point behind it (odd ones) for 40 steps, through env.transition: after every
    # step no robot's disc overlaps the obstacle, and every robot touching it is in danger.
    env, start, run = pile_env
    rng = np.random.default_rng(seed)
    centre = np.stack([rng.uniform(-0.1, 0.1, PILE_ENVS), rng.uniform(-0.25, 0.25, PILE_ENVS)])
    half = np.stack([np.full(PILE_ENVS, 0.2), rng.uniform(0.6, 1.0, PILE_ENVS)])
    position = np.zeros((PILE_ROBOTS, 2, PILE_ENVS))
    for b in range(PILE_ENVS):
        placed = []
        while len(placed) < PILE_ROBOTS:
            p = centre[:, b] + [rng.uniform(-1.2, 0.0) - half[0, b] - 0.05,
                                rng.uniform(-1.3, 1.3) * (half[1, b] + 0.05)]
            if all(np.linalg.norm(p - q) > 0.1 for q in placed):
                placed.append(p)
        position[:, :, b] = placed
    heading = centre[None] - position
    velocity = heading / np.linalg.norm(heading, axis=1, keepdims=True)
    velocity *= rng.uniform(0.0, 10.0, (PILE_ROBOTS, 1, PILE_ENVS))
    aim = centre + np.stack([np.where(np.arange(PILE_ENVS) % 2 == 0, 0.0, 1.0),
                             np.zeros(PILE_ENVS)])
    hazard = Hazard(centre=jnp.asarray(centre, jnp.float32),
                    half_extent=jnp.asarray(half, jnp.float32),
                    direction=jnp.zeros((2, PILE_ENVS), jnp.float32))
    world = start.pipeline_state.replace(
        position=jnp.asarray(position, jnp.float32), velocity=jnp.asarray(velocity, jnp.float32),
        hazard=hazard,
    )
    positions, danger = run(start.replace(pipeline_state=world), jnp.asarray(aim, jnp.float32))
    distance = np.asarray(jax.vmap(
        lambda p: rectangle_distance(p, hazard.centre, hazard.half_extent))(positions))
    assert distance.min() >= env.robot_radius - 1e-5, distance.min() - env.robot_radius
    # Touching: the centre within the tolerance of the obstacle grown by the radius.
    p = np.asarray(positions, np.float64)  # [T, N, 2, B]
    out = np.maximum(np.abs(p - centre[None, None]) - (half + env.robot_radius)[None, None], 0.0)
    touching = np.hypot(out[:, :, 0], out[:, :, 1]) <= env.scenario.touch_tolerance
    np.testing.assert_array_equal(np.asarray(danger), touching)
    assert touching[-1][:, ::2].sum() >= PILE_ENVS  # the piles press against the face


# --------------------------------------------------------------------------- observations


# Robots 0 and 2 start at the same height, robot 1 above them: slots (target_spacing 0.15
# apart, centred on the goal (1.5, 0)) by height, ties by index: robot 0 the lowest.
HAND_TARGETS = np.array([[1.5, -0.15], [1.5, 0.15], [1.5, 0.0]], np.float32)


def hand_world(env: EmergencyEnv, hazard: Hazard) -> WorldState:
    position = np.array([[0.0, 0.0], [0.3, 0.4], [-1.0, 0.0]], np.float32)[:, :, None]
    velocity = np.array([[0.1, -0.2], [0.0, 0.5], [-1.0, 0.0]], np.float32)[:, :, None]
    return WorldState(
        position=jnp.asarray(position),
        velocity=jnp.asarray(velocity),
        hazard=hazard,
        target=jnp.asarray(HAND_TARGETS[:, :, None]),
        time=jnp.zeros((), jnp.int32),
        key=jax.random.key(0),
    )


def test_targets_by_starting_height_hand_computed():
    position = jnp.asarray(np.array([[0.0, 0.0], [0.3, 0.4], [-1.0, 0.0]], np.float32)[:, :, None])
    np.testing.assert_allclose(
        target_positions(position, Layout())[:, :, 0], HAND_TARGETS, atol=1e-7
    )
    # Another layout: slots 0.3 apart around (1.0, 1.0).
    layout = Layout(goal=(1.0, 1.0), target_spacing=0.3, goal_radius=0.5)
    np.testing.assert_allclose(
        target_positions(position, layout)[:, :, 0], [[1.0, 0.7], [1.0, 1.3], [1.0, 1.0]],
        atol=1e-6,
    )


def column(*values):
    return jnp.asarray(np.array(values, np.float32)[:, None])


def test_observation_layout_hand_placed():
    env = EmergencyEnv("turbulence", num_robots=3, num_envs=1)
    # Turbulence circle centred at (0.1, 0) with radius 0.5; the targets are HAND_TARGETS.
    hazard = Hazard(centre=column(0.1, 0.0), half_extent=column(0.5, 0.5),
                    direction=column(0.0, 0.0))
    world = hand_world(env, hazard)
    obs, reward, metrics = jax.jit(lambda w: (env.observe(w), env.reward(w), env.metrics(w)))(
        world
    )
    assert obs.shape == (3, env.observation_size, 1) == (3, 17, 1)
    d12 = math.sqrt(1.3**2 + 0.4**2)  # |p2 - p1| = |(-1.3, -0.4)| = 1.36015
    g0 = math.sqrt(1.5**2 + 0.15**2)  # |target0 - p0| = |(1.5, -0.15)| = 1.50748
    g1 = math.sqrt(1.2**2 + 0.25**2)  # |target1 - p1| = |(1.2, -0.25)| = 1.22577
    expected = np.array(
        [
            # own p,   own v,      robot 1: d, dir        robot 2: d, dir
            [0, 0, 0.1, -0.2, 0.5, 0.6, 0.8, 1.0, -1.0, 0.0,
             # target: d, dir      hazard: inside, centre - p, radius  (|c - p0| = 0.1 < 0.5)
             g0, 1.5 / g0, -0.15 / g0, 1.0, 0.1, 0.0, 0.5],
            # robot 1 sees robot 0, then robot 2
            [0.3, 0.4, 0.0, 0.5, 0.5, -0.6, -0.8, d12, -1.3 / d12, -0.4 / d12,
             g1, 1.2 / g1, -0.25 / g1, 1.0, -0.2, -0.4, 0.5],  # |c - p1| = 0.447 < 0.5
            # robot 2 sees robot 0, then robot 1
            [-1.0, 0.0, -1.0, 0.0, 1.0, 1.0, 0.0, d12, 1.3 / d12, 0.4 / d12,
             2.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # outside: hazard features all zero
        ]
    )
    np.testing.assert_allclose(obs[:, :, 0], expected, atol=1e-6)
    # reward and target_distance: the distance to the robot's own target
    np.testing.assert_allclose(reward[:, 0], [-g0, -g1, -2.5], atol=1e-6)
    np.testing.assert_allclose(metrics["target_distance"][:, 0], [g0, g1, 2.5], atol=1e-6)
    np.testing.assert_array_equal(metrics["success"][:, 0], [0, 0, 0])
    np.testing.assert_array_equal(metrics["danger"][:, 0], [1, 1, 0])
    np.testing.assert_allclose(
        metrics["hazard_distance"][:, 0], [0.1, math.sqrt(0.2), 1.1], atol=1e-6
    )


def test_observation_of_obstacle_nominal_and_coincident_robots():
    obstacle_env = EmergencyEnv("hidden_obstacle", num_robots=3, num_envs=1)
    # Obstacle x in [0.2, 0.4], y in [-0.5, 0.5]: robot 1 at (0.3, 0.4) is inside (touching).
    hazard = Hazard(centre=column(0.3, 0.0), half_extent=column(0.1, 0.5),
                    direction=column(0.0, 0.0))
    world = hand_world(obstacle_env, hazard)
    nominal_env = EmergencyEnv("nominal", num_robots=3, num_envs=1)
    stacked = world.replace(position=world.position.at[1].set(world.position[0]))
    observe = jax.jit(lambda w, s: (obstacle_env.observe(w), nominal_env.observe(w),
                                    nominal_env.observe(s)))
    obs, nominal, stacked_obs = (np.asarray(x) for x in observe(world, stacked))
    assert obs.shape == (3, 14, 1)
    np.testing.assert_array_equal(obs[:, -1, 0], [0, 1, 0])  # the touching flag only
    assert nominal.shape == (3, 13, 1)
    np.testing.assert_allclose(nominal, obs[:, :13], atol=1e-7)  # same layout, no hazard
    # Robots exactly on top of each other: distance 0, direction (0, 0), nothing NaN.
    assert np.all(np.isfinite(stacked_obs))
    np.testing.assert_array_equal(stacked_obs[0, 4:7, 0], [0, 0, 0])
    np.testing.assert_array_equal(stacked_obs[1, 4:7, 0], [0, 0, 0])


# --------------------------------------------------------------------------- jit


def test_jit_equals_no_jit(compiled):
    # reset, then EPISODE + 1 steps, which cross an automatic reset (a lax.cond; without jit
    # it runs one Python branch), compiled and without jit. Hidden obstacle: contacts.
    c = compiled(ROLLOUT)
    key = rollout_key(21)
    actions = random_actions(22, STEPS)
    jitted_reset = c.reset(key)
    start = hand_state(c.env, key)  # robots in contact with the obstacle and each other
    jitted_steps = c.run(start, actions)[0]
    with jax.disable_jit():
        assert_trees_equal(jitted_reset, c.env.reset(key), atol=1e-6)
        eager = start
        for t in range(EPISODE + 1):
            eager = c.env.step(eager, actions[t])
            assert_trees_equal(at(jitted_steps, t), eager, atol=1e-5)


@pytest.mark.parametrize("action_set", ["box9", "mpe5"])
def test_discrete_actions_are_their_continuous_commands(action_set):
    # Discrete action a moves a robot exactly as the continuous action DIRECTIONS[a].
    continuous = EmergencyEnv("hidden_obstacle", num_robots=N, num_envs=B)
    discrete = EmergencyEnv("hidden_obstacle", num_robots=N, num_envs=B, discrete_actions=True,
                      discrete_action_set=action_set)
    directions = {"box9": [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1],
                           [-1, -1], [-1, 1], [1, -1], [1, 1]],
                  "mpe5": [[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]]}[action_set]
    assert discrete.action_size == len(directions) and continuous.action_size == 2
    action = jnp.array([[0, 1, 2, 3], [4, 0, 1, 2], [3, 4, 0, 1]], jnp.int32)
    action = (action + jnp.array([[0], [0], [4]], jnp.int32)) % len(directions)
    directions = jnp.array(directions, jnp.float32)
    as_force = jnp.moveaxis(directions[action], -1, 1)  # [N, 2, B]

    @jax.jit
    def both(world):
        noise = jnp.zeros((N, 0, B))
        return discrete.advance(world, action, noise), continuous.advance(world, as_force, noise)

    world = hand_batch_world(continuous)
    moved_discrete, moved_continuous = both(world)
    assert_trees_equal(moved_discrete, moved_continuous, atol=1e-6)
    assert not np.allclose(moved_discrete.velocity, world.velocity)


def test_random_actions_helper():
    from ccrjax.envs.env import random_actions as env_random_actions

    env = EmergencyEnv("nominal", num_robots=N, num_envs=64)
    action = np.asarray(env_random_actions(jax.random.key(0, impl="rbg"), env))
    assert action.shape == (N, 2, 64) and action.dtype == np.float32
    assert action.min() >= -1.0 and action.max() < 1.0
    assert action.max() - action.min() > 1.8 and abs(action.mean()) < 0.1
    assert not np.allclose(action[:, 0], action[:, 1])  # the two halves are independent
    discrete = EmergencyEnv("nominal", num_robots=N, num_envs=64, discrete_actions=True)
    choice = np.asarray(env_random_actions(jax.random.key(0, impl="rbg"), discrete))
    assert choice.shape == (N, 64) and np.issubdtype(choice.dtype, np.integer)
    assert set(np.unique(choice)) == set(range(9))  # box9, the default set


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"scenario": "blizzard"}, r"scenario must be one of \[.*'turbulence'.*\].*'blizzard'"),
        ({"scenario": 3}, r"scenario must be one of"),
        ({"num_robots": 1}, r"num_robots must be an integer in \[2, 64\], got 1"),
        ({"num_robots": 65}, r"num_robots must be an integer in \[2, 64\], got 65"),
        ({"num_robots": 2.5}, r"num_robots must be an integer in \[2, 64\]"),
        ({"num_envs": 0}, r"num_envs must be an integer >= 1, got 0"),
        ({"num_envs": -3}, r"num_envs must be an integer >= 1, got -3"),
        ({"episode_length": 0}, r"episode_length must be an integer >= 1, got 0"),
        ({"robot_radius": -0.05}, r"robot_radius must be a finite number > 0, got -0.05"),
        ({"robot_radius": 0.0}, r"robot_radius must be a finite number > 0, got 0.0"),
        ({"robot_radius": float("nan")}, r"robot_radius must be a finite number > 0"),
        ({"sensitivity": 0}, r"sensitivity must be a finite number > 0"),
        ({"discrete_actions": "yes"}, r"discrete_actions must be True or False"),
        ({"scenario_params": {"max_force": -1.0}}, r"max_force"),
        ({"layout": {"goal": (0, 0)}}, r"layout must be"),
    ],
)
def test_bad_arguments_raise_value_error(kwargs, pattern):
    kwargs = {"scenario": "turbulence", **kwargs}
    with pytest.raises(ValueError, match=pattern):
        EmergencyEnv(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        # A start box of one cell at min_separation 0.15 cannot hold 5 robots.
        ({"layout": Layout(start_half_extent=(0.1, 0.1))},
         r"Layout.start_half_extent .* holds 1 robots at min_separation 0.15, fewer than "
         r"num_robots 5"),
        # Nor can the default box (3 x 6 cells) hold 20 robots.
        ({"num_robots": 20, "layout": Layout(target_spacing=0.1, goal_radius=1.0)},
         r"Layout.start_half_extent .* holds 18 robots"),
        ({"layout": Layout(min_separation=0.08)}, r"Layout.min_separation must be at least"),
        # Five targets 0.15 apart need 0.35 of the target area's radius.
        ({"layout": Layout(goal_radius=0.3)}, r"Layout.goal_radius 0.3 is too small for 5"),
        ({"num_robots": 6}, r"Layout.goal_radius 0.4 is too small for 6"),
        ({"layout": Layout(target_spacing=0.05)}, r"Layout.target_spacing must be at least"),
        # A target area smaller than a robot.
        ({"num_robots": 2, "layout": Layout(goal_radius=0.04)},
         r"Layout.goal_radius must be larger than a robot's radius"),
        # A wind area wider than the arena.
        ({"scenario": "strong_wind", "scenario_params": {"side_range": (1.2, 6.0)}},
         r"StrongWind: hazards reach .* beyond the arena .*Layout.arena_half_extent"),
        # An obstacle that blocks every way past it.
        ({"scenario": "hidden_obstacle", "scenario_params": {"length_range": (1.0, 3.9)},
          "layout": Layout(hazard_y_range=(0.0, 0.0))},
         r"HiddenObstacle.length_range .* can block every way"),
        # A hazard that overlaps the start box.
        ({"layout": Layout(start_centre=(-0.9, 0.0))},
         r"Turbulence: hazards .* overlapping the start box .*start_centre, start_half_extent"),
        ({"scenario_params": {"radius_range": (0.9, 1.5)}},
         r"Turbulence: hazards .* overlapping the start box"),
        # ... or the target area.
        ({"scenario": "hidden_obstacle", "layout": Layout(goal=(0.6, 0.0))},
         r"HiddenObstacle: hazards .* overlapping the target area .*Layout.goal, goal_radius"),
    ],
)
def test_layouts_that_cannot_hold_the_task_raise_value_error(kwargs, pattern):
    kwargs = {"scenario": "turbulence", **kwargs}
    with pytest.raises(ValueError, match=pattern):
        EmergencyEnv(**kwargs)


def test_bad_arguments_through_the_registry():
    import brax.envs

    with pytest.raises(ValueError, match=r"num_robots must be an integer in \[2, 64\], got 1"):
        brax.envs.get_environment("ccr_nominal", num_robots=1)


def test_wrong_action_shape_raises_value_error():
    env = EmergencyEnv("nominal", num_robots=N, num_envs=B)
    state = jax.eval_shape(env.reset, jax.random.key(0))  # check_action runs before any math
    for action in (
        jnp.zeros((N, 2, B + 1)),  # wrong batch
        jnp.zeros((N, B, 2)),  # batch-first by mistake
        jnp.zeros((N + 1, 2, B)),  # wrong team size
        jnp.zeros((N, 2)),  # no batch axis
    ):
        with pytest.raises(ValueError, match=r"action must be float\[3, 2, 4\]"):
            env.step(state, action)
        with pytest.raises(ValueError, match=r"action must be float\[3, 2, 4\]"):
            jax.eval_shape(env.step, state, action)  # raised while tracing under jit
        with pytest.raises(ValueError, match=r"action must be float\[3, 2, 4\]"):
            env.transition(state, action)
    discrete = EmergencyEnv("nominal", num_robots=N, num_envs=B, discrete_actions=True)
    for action in (jnp.zeros((N, B)), jnp.zeros((N, B + 1), jnp.int32)):
        with pytest.raises(ValueError, match=r"action must be int\[3, 4\]"):
            discrete.step(state, action)
