"""A replay buffer that lives on the device, inside the compiled training program.

A ring of fixed ``capacity`` holding :class:`~ccrjax.learners.base.Transition`
arrays with a leading ``[capacity]`` axis. Transitions arrive in blocks of one
fixed size (one training iteration's worth), and the capacity is a multiple of
that size, so a block is always one contiguous ``dynamic_update_slice``: no
scatter, no wrap-around split. Sampling is uniform over what has been written.

It also keeps running per-robot sums of the stored rewards, which MAAC uses to
normalise rewards as the original implementation does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ccrjax.learners.base import Transition


@struct.dataclass
class ReplayBuffer:
    data: Transition  # leaves [capacity, ...]
    position: jax.Array  # int32[]: where the next block goes
    size: jax.Array  # int32[]: transitions held
    reward_sum: jax.Array  # float32[N]: sums over every reward ever added
    reward_sq_sum: jax.Array  # float32[N]
    reward_count: jax.Array  # float32[]

    @property
    def capacity(self) -> int:
        return self.data.reward.shape[0]

    def reward_mean_std(self) -> tuple[jax.Array, jax.Array]:
        """Per-robot mean and standard deviation of the rewards added so far."""
        count = jnp.maximum(self.reward_count, 1.0)
        mean = self.reward_sum / count
        var = jnp.maximum(self.reward_sq_sum / count - mean * mean, 0.0)
        return mean, jnp.sqrt(var)


def replay_capacity(requested: int, block: int) -> int:
    """The largest multiple of ``block`` not above ``requested`` (at least one block)."""
    return max(block, (requested // block) * block)


def init_replay(example: Transition, capacity: int) -> ReplayBuffer:
    """An empty buffer for transitions shaped like ``example`` (one transition, no batch axis)."""
    data = jax.tree_util.tree_map(
        lambda x: jnp.zeros((capacity,) + x.shape, x.dtype), example
    )
    num_robots = example.reward.shape[0]
    return ReplayBuffer(
        data=data,
        position=jnp.zeros((), jnp.int32),
        size=jnp.zeros((), jnp.int32),
        reward_sum=jnp.zeros((num_robots,), jnp.float32),
        reward_sq_sum=jnp.zeros((num_robots,), jnp.float32),
        reward_count=jnp.zeros((), jnp.float32),
    )


def add_block(buffer: ReplayBuffer, block: Transition) -> ReplayBuffer:
    """Writes a block of transitions (leading axis = block size, dividing the capacity)."""
    block_size = block.reward.shape[0]
    capacity = buffer.capacity
    if capacity % block_size:
        raise ValueError(f"replay capacity {capacity} is not a multiple of the block {block_size}")
    data = jax.tree_util.tree_map(
        lambda store, new: jax.lax.dynamic_update_slice_in_dim(store, new, buffer.position, 0),
        buffer.data,
        block,
    )
    return buffer.replace(
        data=data,
        position=(buffer.position + block_size) % capacity,
        size=jnp.minimum(buffer.size + block_size, capacity),
        reward_sum=buffer.reward_sum + jnp.sum(block.reward, axis=0),
        reward_sq_sum=buffer.reward_sq_sum + jnp.sum(block.reward * block.reward, axis=0),
        reward_count=buffer.reward_count + block_size,
    )


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Transition:
    """``batch_size`` transitions drawn uniformly, with replacement, from those held."""
    index = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree_util.tree_map(lambda x: jnp.take(x, index, axis=0), buffer.data)
