"""The equations of PPO, one function each: generalised advantage estimation, the clipped
surrogate objective, the (clipped) value loss, advantage normalisation, and the log
probability and entropy of the two policy families (a diagonal Gaussian over the 2-D force,
a categorical over an action set).

Notation of Schulman et al., *Proximal Policy Optimization Algorithms* (2017), and of
*High-Dimensional Continuous Control Using Generalized Advantage Estimation* (2016);
``docs/references.md`` names the implementations read for the details (PureJaxRL's
``ppo.py``, JaxMARL's IPPO and MAPPO, the MAPPO paper's code).
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

# A Python float: computing it with jax.numpy at import would start the XLA backend before
# jax.distributed.initialize() can run.
LOG_2PI = math.log(2.0 * math.pi)


def gae(reward: jax.Array, value: jax.Array, next_value: jax.Array, terminated: jax.Array,
        episode_end: jax.Array, gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimates and the value targets of a rollout, time-major.

    ``delta_t = r_t + gamma (1 - term_t) V(s_{t+1}) - V(s_t)``;
    ``A_t = delta_t + gamma lam (1 - end_t) A_{t+1}``; the return target is ``A_t + V(s_t)``.

    ``next_value`` is the value of each step's own next observation, so an episode cut by
    its time limit (``episode_end`` 1, ``terminated`` 0) still bootstraps from the state it
    reached, and the recursion stops there; a termination bootstraps nothing. ``reward``,
    ``value``, ``next_value``: ``[T, ...]``; ``terminated``, ``episode_end``: ``[T, ...]``
    broadcastable to them (``[T, B]`` against ``[T, B, N]`` needs a trailing axis).
    """
    chex.assert_equal_shape([reward, value, next_value])
    terminated = jnp.broadcast_to(terminated, reward.shape).astype(reward.dtype)
    episode_end = jnp.broadcast_to(episode_end, reward.shape).astype(reward.dtype)
    delta = reward + gamma * (1.0 - terminated) * next_value - value

    def backwards(following, step):
        delta_t, end_t = step
        advantage = delta_t + gamma * lam * (1.0 - end_t) * following
        return advantage, advantage

    _, advantage = jax.lax.scan(backwards, jnp.zeros_like(reward[0]), (delta, episode_end),
                                reverse=True)
    return advantage, advantage + value


def normalise(advantage: jax.Array, eps: float = 1e-8) -> jax.Array:
    """``(A - mean A) / (std A + eps)`` over the whole batch (every robot's together)."""
    return (advantage - jnp.mean(advantage)) / (jnp.std(advantage) + eps)


def clipped_surrogate(log_ratio: jax.Array, advantage: jax.Array, clip: float) -> jax.Array:
    """The policy loss ``-mean min(rho A, clip(rho, 1 - eps, 1 + eps) A)`` with
    ``rho = exp(log_ratio)`` (PPO's L^CLIP, negated to be minimised). Its gradient is
    zero wherever the clipped term is the smaller: the ratio has left ``[1 - eps, 1 + eps]``
    in the direction the advantage favours."""
    chex.assert_equal_shape([log_ratio, advantage])
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantage
    clipped = jnp.clip(ratio, 1.0 - clip, 1.0 + clip) * advantage
    return -jnp.mean(jnp.minimum(unclipped, clipped))


def value_loss(value: jax.Array, old_value: jax.Array, target: jax.Array,
               clip: float | None) -> jax.Array:
    """``0.5 mean (V - target)^2``; with ``clip``, PPO2's clipped form
    ``0.5 mean max((V - target)^2, (V_old + clip(V - V_old, -eps, eps) - target)^2)``,
    which stops the value moving more than ``eps`` from the rollout's in one favourable
    step."""
    chex.assert_equal_shape([value, old_value, target])
    squared = jnp.square(value - target)
    if clip is None:
        return 0.5 * jnp.mean(squared)
    clipped = old_value + jnp.clip(value - old_value, -clip, clip)
    return 0.5 * jnp.mean(jnp.maximum(squared, jnp.square(clipped - target)))


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, action: jax.Array) -> jax.Array:
    """``log N(a; mu, diag sigma^2)`` summed over the last (action) axis."""
    chex.assert_equal_shape([mean, action])
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """The entropy of the diagonal Gaussian, ``sum (log sigma + (1 + log 2 pi) / 2)``,
    broadcast to ``shape`` (the batch's leading axes)."""
    per_dimension = log_std + 0.5 * (1.0 + LOG_2PI)
    return jnp.broadcast_to(jnp.sum(per_dimension, axis=-1), shape)


def categorical_log_prob(logits: jax.Array, action: jax.Array) -> jax.Array:
    """``log softmax(logits)[a]`` for integer actions ``a`` (``logits``: ``[..., K]``)."""
    log_p = jax.nn.log_softmax(logits, axis=-1)
    return jnp.take_along_axis(log_p, action[..., None].astype(jnp.int32), axis=-1)[..., 0]


def categorical_entropy(logits: jax.Array) -> jax.Array:
    """``-sum p log p`` over the last axis."""
    log_p = jax.nn.log_softmax(logits, axis=-1)
    return -jnp.sum(jnp.exp(log_p) * log_p, axis=-1)
