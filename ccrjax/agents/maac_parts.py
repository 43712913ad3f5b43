"""MAAC's equations, one function each (:mod:`ccrjax.agents.maac` puts them together): the
attention of every robot over the others (:func:`attend`) and its logit regulariser, the
counterfactual baseline, Gumbel-max sampling, and the initialisation of per-robot weights.
Shapes are batch-major: ``[B, N, ...]``."""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

# Critic modules every robot's loss passes through, whose gradients the original
# scales by 1/N (its ``shared_modules``: the extractors and the state-action encoders).
SHARED_CRITIC_MODULES = ("attention", "encoder")


def leaky(x: jax.Array) -> jax.Array:
    return nn.leaky_relu(x, negative_slope=0.01)  # torch's default slope


def select(values: jax.Array, action: jax.Array) -> jax.Array:
    """``values[..., action]``: ``[B, N, A]`` and ``int[B, N]`` to ``[B, N]``."""
    return jnp.take_along_axis(values, action[..., None], axis=-1)[..., 0]


def baseline(all_q: jax.Array, probs: jax.Array) -> jax.Array:
    """Counterfactual baseline ``b_i = sum_a pi_i(a | o_i) Q_i(o, (a, a_-i))``, ``[B, N]``.

    ``all_q``: ``[B, N, A]`` from :meth:`MAAC.critic_values` (entry ``a`` of row ``i`` is
    ``Q_i`` with robot ``i``'s action replaced by ``a``); ``probs``: ``[B, N, A]``.
    """
    return jnp.sum(probs * all_q, axis=-1)


def attend(
    attention: dict, e: jax.Array, s: jax.Array, num_heads: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Multi-head attention of every robot over the others.

    ``e``: state-action encodings ``[B, N, D]``; ``s``: state encodings ``[B, N, D]``;
    ``attention``: the shared extractors, ``key``/``query``/``value`` ``[D, H d]`` (head
    ``h`` in columns ``h d .. (h + 1) d``) and ``value_bias`` ``[H d]``. Returns ``x``
    ``[B, N, H d]`` (heads concatenated in order), the attention weights
    ``[B, N(i), N(j), H]``, exactly 0 where ``j == i``, and the unscaled logits
    ``q_i . k_j``, same shape (their diagonal is computed but never used).
    """
    batch, num_robots, width = e.shape
    dim = attention["key"].shape[1] // num_heads
    # One matrix product per extractor for every head, robot and sample at once.
    keys = (e.reshape(-1, width) @ attention["key"]).reshape(batch, num_robots, num_heads, dim)
    values = leaky(e.reshape(-1, width) @ attention["value"] + attention["value_bias"])
    values = values.reshape(batch, num_robots, num_heads, dim)
    queries = (s.reshape(-1, width) @ attention["query"]).reshape(
        batch, num_robots, num_heads, dim
    )
    logits = jnp.einsum("bihd,bjhd->bijh", queries, keys)
    others = ~jnp.eye(num_robots, dtype=bool)[None, :, :, None]
    scaled = jnp.where(others, logits / math.sqrt(dim), -jnp.inf)
    weights = jax.nn.softmax(scaled, axis=2)
    x = jnp.einsum("bijh,bjhd->bihd", weights, values)
    return x.reshape(batch, num_robots, num_heads * dim), weights, logits


def attention_logit_penalty(logits: jax.Array) -> jax.Array:
    """Per robot ``sum_h mean_{b, j != i} logits^2`` (the original's regulariser), ``[N]``.

    ``logits``: ``[B, N(i), N(j), H]`` from :func:`attend`.
    """
    batch, num_robots = logits.shape[:2]
    others = ~jnp.eye(num_robots, dtype=bool)[None, :, :, None]
    squares = jnp.where(others, logits * logits, 0.0)
    return jnp.sum(squares, axis=(0, 2, 3)) / (batch * (num_robots - 1))


def sample_actions(logits: jax.Array, gumbel: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Actions ``a ~ softmax(logits)``, ``int32[B, N]``, and ``log pi(a)``, ``[B, N]``.

    ``gumbel``: standard Gumbel noise shaped like ``logits``; ``argmax(logits + gumbel)``
    is a categorical sample (the Gumbel-max trick, what ``jax.random.categorical`` does).
    Taking the noise instead of a key lets one draw serve a whole update.
    """
    action = jnp.argmax(logits + gumbel, axis=-1).astype(jnp.int32)
    return action, select(jax.nn.log_softmax(logits, axis=-1), action)


def is_bias(path: tuple) -> bool:
    return str(getattr(path[-1], "key", path[-1])).endswith("bias")


def lecun_init(key: jax.Array, shapes: Any) -> Any:
    """Parameters for a tree of shapes: weights LeCun normal (truncated at 2 standard
    deviations, fan-in = the second-to-last axis, as flax's default ``Dense``), biases
    (leaves named ``*bias``) zero.

    All weights come from one random draw: on the CPU every separate draw adds seconds
    to the compilation of the program that holds it.
    """
    flat, treedef = jax.tree_util.tree_flatten_with_path(
        shapes, is_leaf=lambda x: isinstance(x, tuple) and all(isinstance(v, int) for v in x)
    )
    sizes = [0 if is_bias(path) else math.prod(shape) for path, shape in flat]
    noise = jax.random.truncated_normal(key, -2.0, 2.0, (max(1, sum(sizes)),))
    noise = noise / 0.87962566103423978  # unit variance after truncation (flax's constant)
    leaves, offset = [], 0
    for (path, shape), size in zip(flat, sizes, strict=True):
        if is_bias(path):
            leaves.append(jnp.zeros(shape))
        else:
            weights = noise[offset : offset + size].reshape(shape)
            leaves.append(weights / math.sqrt(shape[-2]))
            offset += size
    return jax.tree_util.tree_unflatten(treedef, leaves)


def per_robot_shapes(module: nn.Module, num_robots: int, in_size: int) -> Any:
    """The shapes of ``module``'s parameters for input width ``in_size``, with a leading
    robot axis (for :func:`~ccrjax.agents.networks.apply_per_robot`)."""
    shapes = jax.eval_shape(module.init, jax.random.PRNGKey(0), jnp.zeros((1, in_size)))
    return jax.tree_util.tree_map(lambda x: (num_robots, *x.shape), shapes)
