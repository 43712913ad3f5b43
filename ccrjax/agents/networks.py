"""Small networks, one set of parameters per robot, applied to all robots in one call.

Parameters of the ``N`` robots are stacked on a leading axis and applied with
``jax.vmap``, so XLA sees one batched matrix product per layer instead of ``N``
small ones (the learner update is compute-bound; this is where its time goes).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def orthonormal_columns(matrix: jax.Array) -> jax.Array:
    """The ``Q`` of ``matrix = Q R`` with ``R``'s diagonal positive, for a tall ``matrix``
    ``[m, n]`` (``m >= n``), by classical Gram-Schmidt with one reorthogonalisation (two
    passes keep ``Q`` orthonormal to float precision for well-conditioned matrices).

    Plain matrix-vector products, no LAPACK call: under ``vmap`` (a grid of seeds), XLA on
    CPU runs a batched QR factorisation as a custom call that splits its batch over the
    intra-op thread pool from a thread of that pool, and on a 2-core machine two such
    calls at once can wait on each other forever (seen with jax 0.10.2)."""
    _, columns = matrix.shape
    index = jnp.arange(columns)

    def orthonormalise(k: int, q: jax.Array) -> jax.Array:
        earlier = (index < k).astype(q.dtype)  # the columns already orthonormal
        v = q[:, k]
        for _ in range(2):
            v = v - q @ ((q.T @ v) * earlier)
        return q.at[:, k].set(v / jnp.linalg.norm(v))

    return jax.lax.fori_loop(0, columns, orthonormalise, matrix)


def orthogonal(scale: float = 1.0) -> Callable[..., jax.Array]:
    """Orthogonal initialisation (Saxe et al. 2014) of a kernel ``[..., fan_out]``: the
    orthonormal factor of a standard normal matrix, times ``scale``. It draws the matrix
    as ``jax.nn.initializers.orthogonal`` does and returns its sign-corrected ``Q``, so the
    two agree to float rounding; :func:`orthonormal_columns` says why it is computed here."""

    def init(key: jax.Array, shape: Sequence[int], dtype: jnp.dtype = jnp.float32) -> jax.Array:
        rows, columns = math.prod(shape[:-1]), shape[-1]
        tall = (columns, rows) if rows < columns else (rows, columns)
        q = orthonormal_columns(jax.random.normal(key, tall, dtype))
        q = q.T if rows < columns else q
        return scale * q.reshape(tuple(shape))

    return init


class MLP(nn.Module):
    """Fully connected network: ``hidden`` layers with ``activation``, then a linear output."""

    hidden: Sequence[int]
    out: int
    activation: Callable[[jax.Array], jax.Array] = nn.relu

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = self.activation(nn.Dense(width)(x))
        return nn.Dense(self.out)(x)


def init_per_robot(module: nn.Module, key: jax.Array, num_robots: int, example: jax.Array):
    """Independent parameters for each robot, stacked on a leading robot axis."""
    keys = jax.random.split(key, num_robots)
    return jax.vmap(lambda k: module.init(k, example))(keys)


def apply_per_robot(module: nn.Module, params, x: jax.Array) -> jax.Array:
    """Applies robot ``i``'s parameters to ``x[:, i]`` for every ``i``.

    ``x``: ``[batch, N, ...]``; returns ``[batch, N, out]``.
    """
    out = jax.vmap(module.apply, in_axes=(0, 1), out_axes=1)(params, x)
    return out


def mlp_flops(sizes: Sequence[int]) -> int:
    """Multiply-add FLOPs (2 per weight) of one forward pass through layers ``sizes``."""
    return sum(2 * a * b for a, b in zip(sizes[:-1], sizes[1:], strict=True))


def clip_by_global_norm_per_robot(grads, max_norm: float):
    """Scales each robot's gradient (leading axis) so its global norm is at most ``max_norm``."""
    leaves = jax.tree_util.tree_leaves(grads)
    squared = sum(jnp.sum(g.reshape(g.shape[0], -1) ** 2, axis=1) for g in leaves)
    scale = jnp.minimum(1.0, max_norm / (jnp.sqrt(squared) + 1e-6))
    return jax.tree_util.tree_map(
        lambda g: g * scale.reshape((-1,) + (1,) * (g.ndim - 1)), grads
    )
