"""A replay buffer that lives on the device, inside the compiled training program.

It stores whole episodes: a ring of ``capacity_episodes`` slots, each holding an
episode's ``T + 1`` observations (the reset's and one after every step), its ``T``
actions, rewards and termination flags. A transition ``(o_t, a_t, r_t, o_{t+1})``
is read back from its episode, so every observation is stored once instead of
twice (as ``obs`` and ``next_obs``): half the memory, half the writing, and half
the size of a checkpoint, which matter when many seeds train side by side.

Episodes arrive in blocks of one fixed size (one training iteration's worth) and
the capacity is a multiple of it, so a block is one contiguous
``dynamic_update_slice``. Sampling is uniform over the transitions held.

It also keeps running per-robot sums of the stored rewards, which MAAC uses to
normalise rewards as the original implementation does. A buffer whose transitions carry a
cost channel (:class:`ccrjax.agents.types.Transition`) stores it beside the reward, with
the sums that give the mean and spread of any weighted sum of the two
(:meth:`ReplayBuffer.combined_mean_std`): the weights change while the transitions stay.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

from ccrjax.agents.types import Transition


@struct.dataclass
class ReplayBuffer:
    obs: jax.Array  # [C, T + 1, N, F]
    action: jax.Array  # [C, T, N, 2] or int [C, T, N]
    reward: jax.Array  # [C, T, N]
    done: jax.Array  # [C, T]
    position: jax.Array  # int32[]: the slot the next block starts at
    episodes: jax.Array  # int32[]: episodes held
    reward_sum: jax.Array  # float32[N]: sums over every reward ever added
    reward_sq_sum: jax.Array  # float32[N]
    reward_count: jax.Array  # float32[]
    cost: jax.Array | None = None  # [C, T, N], or None without a cost channel
    cost_sum: jax.Array | None = None  # float32[N]
    cost_sq_sum: jax.Array | None = None  # float32[N]
    reward_cost_sum: jax.Array | None = None  # float32[N]: sums of reward x cost

    @property
    def capacity_episodes(self) -> int:
        return self.reward.shape[0]

    @property
    def episode_length(self) -> int:
        return self.reward.shape[1]

    @property
    def capacity(self) -> int:
        """Transitions the buffer can hold."""
        return self.capacity_episodes * self.episode_length

    @property
    def size(self) -> jax.Array:
        """Transitions held (int32[])."""
        return self.episodes * self.episode_length

    def reward_mean_std(self) -> tuple[jax.Array, jax.Array]:
        """Per-robot mean and standard deviation of the rewards added so far."""
        count = jnp.maximum(self.reward_count, 1.0)
        mean = self.reward_sum / count
        var = jnp.maximum(self.reward_sq_sum / count - mean * mean, 0.0)
        return mean, jnp.sqrt(var)

    def combined_mean_std(self, reward_weight: jax.Array, cost_weight: jax.Array
                          ) -> tuple[jax.Array, jax.Array]:
        """Per-robot mean and standard deviation of ``reward_weight r + cost_weight c`` over
        every transition added so far, from the running sums (exact for any weights):
        ``var = a^2 var(r) + b^2 var(c) + 2 a b cov(r, c)``."""
        count = jnp.maximum(self.reward_count, 1.0)
        mean_r, mean_c = self.reward_sum / count, self.cost_sum / count
        var_r = self.reward_sq_sum / count - mean_r * mean_r
        var_c = self.cost_sq_sum / count - mean_c * mean_c
        cov = self.reward_cost_sum / count - mean_r * mean_c
        a, b = reward_weight, cost_weight
        mean = a * mean_r + b * mean_c
        var = jnp.maximum(a * a * var_r + b * b * var_c + 2.0 * a * b * cov, 0.0)
        return mean, jnp.sqrt(var)


def replay_capacity(requested: int, block: int) -> int:
    """The largest multiple of ``block`` not above ``requested`` (at least one block)."""
    return max(block, (requested // block) * block)


def init_replay(example: Transition, capacity_episodes: int, episode_length: int) -> ReplayBuffer:
    """An empty buffer of ``capacity_episodes`` episodes of ``episode_length`` steps, for
    transitions shaped like ``example`` (one transition, no batch axis)."""
    c, t = capacity_episodes, episode_length

    def zeros(x: jax.Array, steps: int) -> jax.Array:
        return jnp.zeros((c, steps) + x.shape, x.dtype)

    num_robots = example.reward.shape[0]
    return ReplayBuffer(
        obs=zeros(example.obs, t + 1),
        action=zeros(example.action, t),
        reward=zeros(example.reward, t),
        done=zeros(example.done, t),
        position=jnp.zeros((), jnp.int32),
        episodes=jnp.zeros((), jnp.int32),
        reward_sum=jnp.zeros((num_robots,), jnp.float32),
        reward_sq_sum=jnp.zeros((num_robots,), jnp.float32),
        reward_count=jnp.zeros((), jnp.float32),
        **({} if example.cost is None else {
            "cost": zeros(example.cost, t),
            **{name: jnp.zeros((num_robots,), jnp.float32)
               for name in ("cost_sum", "cost_sq_sum", "reward_cost_sum")}}),
    )


def add_episodes(buffer: ReplayBuffer, episodes: Transition) -> ReplayBuffer:
    """Writes a block of whole episodes, given step-major as the rollout makes them.

    ``episodes``: leaves ``[T, E, ...]`` (``obs``/``next_obs`` ``[T, E, N, F]``); ``E``
    must divide the capacity. ``next_obs[t]`` is ``obs[t + 1]`` within an episode, so
    only the last step's ``next_obs`` is kept beside the observations.
    """
    steps, block = episodes.reward.shape[:2]
    chex.assert_equal(steps, buffer.episode_length)
    capacity = buffer.capacity_episodes
    if capacity % block:
        raise ValueError(f"replay capacity {capacity} episodes is not a multiple of {block}")
    obs = jnp.concatenate([episodes.obs, episodes.next_obs[-1:]], axis=0)  # [T + 1, E, ...]

    def write(store: jax.Array, new: jax.Array) -> jax.Array:
        new = jnp.swapaxes(new, 0, 1)  # episode-major
        return jax.lax.dynamic_update_slice_in_dim(store, new, buffer.position, 0)

    reward = episodes.reward.reshape(steps * block, -1)
    buffer = buffer.replace(
        obs=write(buffer.obs, obs),
        action=write(buffer.action, episodes.action),
        reward=write(buffer.reward, episodes.reward),
        done=write(buffer.done, episodes.done),
        position=(buffer.position + block) % capacity,
        episodes=jnp.minimum(buffer.episodes + block, capacity),
        reward_sum=buffer.reward_sum + jnp.sum(reward, axis=0),
        reward_sq_sum=buffer.reward_sq_sum + jnp.sum(reward * reward, axis=0),
        reward_count=buffer.reward_count + steps * block,
    )
    if (buffer.cost is None) != (episodes.cost is None):
        raise ValueError("the episodes and the buffer disagree on a cost channel")
    if buffer.cost is None:
        return buffer
    cost = episodes.cost.reshape(steps * block, -1)
    return buffer.replace(
        cost=write(buffer.cost, episodes.cost),
        cost_sum=buffer.cost_sum + jnp.sum(cost, axis=0),
        cost_sq_sum=buffer.cost_sq_sum + jnp.sum(cost * cost, axis=0),
        reward_cost_sum=buffer.reward_cost_sum + jnp.sum(reward * cost, axis=0),
    )


def grow(buffer: ReplayBuffer, capacity_episodes: int) -> ReplayBuffer:
    """``buffer`` in a larger ring of ``capacity_episodes`` episodes, holding the same
    transitions in the same slots: what a longer run's buffer holds at the same step.

    Only a buffer that never wrapped can grow (a capped one keeps its capacity); its next
    block then goes after the episodes held (``position = episodes``), as in a buffer that
    was that large from the start. ``sample`` draws from ``[0, size)``, so sampling is
    unchanged too.
    """
    extra = capacity_episodes - buffer.capacity_episodes
    if extra < 0:
        raise ValueError(f"a buffer of {buffer.capacity_episodes} episodes cannot shrink to "
                         f"{capacity_episodes}")

    def pad(x: jax.Array) -> jax.Array:
        return jnp.concatenate([x, jnp.zeros((extra,) + x.shape[1:], x.dtype)])

    return buffer.replace(obs=pad(buffer.obs), action=pad(buffer.action),
                          reward=pad(buffer.reward), done=pad(buffer.done),
                          cost=None if buffer.cost is None else pad(buffer.cost),
                          position=buffer.episodes % capacity_episodes)


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Transition:
    """``batch_size`` transitions drawn uniformly, with replacement, from those held.

    Transition ``k`` is step ``k % T`` of episode slot ``k // T`` (slots fill from 0),
    so actions and rewards are read at flat index ``k`` and the two observations at
    ``(k // T) (T + 1) + k % T`` and the one after it.
    """
    steps = buffer.episode_length
    index = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    at = index + index // steps  # = episode * (T + 1) + step

    def flat(x: jax.Array) -> jax.Array:
        return x.reshape((-1,) + x.shape[2:])

    obs = flat(buffer.obs)
    return Transition(
        obs=jnp.take(obs, at, axis=0),
        action=jnp.take(flat(buffer.action), index, axis=0),
        reward=jnp.take(flat(buffer.reward), index, axis=0),
        next_obs=jnp.take(obs, at + 1, axis=0),
        done=jnp.take(flat(buffer.done), index, axis=0),
        cost=None if buffer.cost is None else jnp.take(flat(buffer.cost), index, axis=0),
    )
