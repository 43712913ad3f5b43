"""The replay buffer (:mod:`ccrjax.agents.replay`): what goes in comes back aligned.

Every stored number encodes where it came from, ``code = 100 * episode + step``: the
observation at step ``t`` of an episode holds its code, the next observation the code of
``t + 1``, the action and reward the code of ``t``. A sampled transition is then right
only if all five fields name the same episode and step, including the last step of an
episode (whose next observation is stored apart) and after the ring has wrapped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.replay import add_episodes, init_replay, sample
from ccrjax.agents.types import Transition

T, E, N, F = 4, 2, 3, 2  # steps per episode, episodes per block, robots, features
CAPACITY = 3 * E  # episodes: three blocks


def block_of(first_episode: int, reward: np.ndarray | None = None) -> Transition:
    """``E`` episodes numbered from ``first_episode``, step-major ``[T, E, ...]``."""
    episode = first_episode + np.arange(E)[None, :]  # [1, E]
    step = np.arange(T)[:, None]  # [T, 1]
    code = (100 * episode + step).astype(np.float32)  # [T, E]
    robot = np.arange(N, dtype=np.float32)[None, None, :]  # distinguishes robots

    def per_robot(values: np.ndarray) -> np.ndarray:  # [T, E] -> [T, E, N, F]
        return np.broadcast_to((values[:, :, None] + 0.25 * robot)[..., None], (T, E, N, F))

    return Transition(
        obs=jnp.asarray(per_robot(code)),
        action=jnp.asarray(per_robot(code)),  # continuous actions: [T, E, N, 2]
        reward=jnp.asarray(code[:, :, None] + 0.25 * robot if reward is None else reward),
        next_obs=jnp.asarray(per_robot(code + 1)),
        done=jnp.asarray((step + episode) % 3 == 0, jnp.float32),
    )


def empty_buffer():
    example = jax.tree_util.tree_map(lambda x: x[0, 0], block_of(0))
    return init_replay(example, CAPACITY, T)


add = jax.jit(add_episodes)
draw = jax.jit(sample, static_argnums=2)


def decode(batch: Transition):
    """Episode and step of every sampled transition, checking that all fields agree."""
    obs = np.asarray(batch.obs)
    robot = 0.25 * np.arange(N)[None, :, None]
    code = obs[:, 0, 0]
    np.testing.assert_array_equal(obs, code[:, None, None] + robot + 0 * obs)
    np.testing.assert_array_equal(batch.action, obs)
    np.testing.assert_array_equal(batch.next_obs, obs + 1)
    np.testing.assert_array_equal(batch.reward, obs[:, :, 0])
    episode, step = np.divmod(code.astype(int), 100)
    np.testing.assert_array_equal(batch.done, ((step + episode) % 3 == 0).astype(np.float32))
    return episode, step


def test_samples_are_aligned_transitions_of_the_episodes_held():
    buffer = add(empty_buffer(), block_of(0))
    assert (int(buffer.episodes), int(buffer.position), int(buffer.size)) == (E, E, E * T)
    episode, step = decode(draw(buffer, jax.random.PRNGKey(0), 400))
    # Only what was written is drawn (slots 2.. are still zeros), every step of it,
    # the last step of every episode included.
    assert set(episode) == set(range(E))
    assert set(step) == set(range(T))
    assert {(e, s) for e, s in zip(episode, step, strict=True)} == {
        (e, s) for e in range(E) for s in range(T)
    }


def test_the_ring_wraps_over_the_oldest_block():
    buffer = empty_buffer()
    for first in range(0, 4 * E, E):  # four blocks into a ring of three
        buffer = add(buffer, block_of(first))
    assert (int(buffer.episodes), int(buffer.position)) == (CAPACITY, E)
    # The fourth block (episodes 6, 7) replaced the first (0, 1) in slots 0 and 1.
    slots = 100 * np.asarray([6, 7, 2, 3, 4, 5])
    np.testing.assert_array_equal(buffer.obs[:, 0, 0, 0], slots)
    np.testing.assert_array_equal(buffer.obs[:, T, 0, 0], slots + T)
    episode, step = decode(draw(buffer, jax.random.PRNGKey(1), 2000))
    assert set(episode) == set(range(E, 4 * E))
    # Uniform over the held transitions: every episode about 1/6 of the draws.
    counts = np.bincount(episode, minlength=4 * E)[E:]
    assert counts.min() > 2000 / CAPACITY * 0.7, counts
    # Two more blocks: slots 2..5 are overwritten in order, slots 0 and 1 kept.
    for first in range(4 * E, 6 * E, E):
        buffer = add(buffer, block_of(first))
    assert int(buffer.position) == 0
    np.testing.assert_array_equal(buffer.obs[:, 0, 0, 0], 100 * np.arange(6, 12))
    episode, _ = decode(draw(buffer, jax.random.PRNGKey(2), 600))
    assert set(episode) == set(range(6, 12))


def test_reward_statistics_are_those_of_every_reward_added():
    rng = np.random.default_rng(0)
    buffer = empty_buffer()
    added = []
    for first in range(0, 5 * E, E):  # five blocks: two were overwritten, stats keep them
        reward = (rng.normal(size=(T, E, N)) * [0.5, 1.0, 2.0] + [-2.0, 0.5, 3.0])
        reward = reward.astype(np.float32)
        added.append(reward.reshape(-1, N))
        buffer = add(buffer, block_of(first, reward))
    added = np.concatenate(added).astype(np.float64)
    mean, std = buffer.reward_mean_std()
    np.testing.assert_allclose(mean, added.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(std, added.std(axis=0), rtol=1e-4)  # population (ddof 0)
    assert float(buffer.reward_count) == 5 * T * E


def test_a_block_that_does_not_divide_the_capacity_is_refused():
    buffer = init_replay(jax.tree_util.tree_map(lambda x: x[0, 0], block_of(0)), 5, T)
    with pytest.raises(ValueError, match="not a multiple"):
        add_episodes(buffer, block_of(0))
