"""What every learner shares: the transition it learns from and the interface it offers.

Learners work in the usual *batch-major* layout of neural-network code
(``[batch, robot, feature]``); the training loop moves the environment's
batch-last arrays into this layout once, when transitions are stored.

A learner never knows which reward or observation transform (plain, pessimistic,
CCR) produced its transitions: it sees observations of some width and rewards.
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import jax
from flax import struct


@struct.dataclass
class Transition:
    """A batch of multi-robot transitions, batch-major.

    ``obs``/``next_obs``: ``float32[batch, N, F]``; ``action``: ``float32[batch, N, 2]``
    (continuous) or ``int32[batch, N]`` (discrete); ``reward``: ``float32[batch, N]``;
    ``done``: ``float32[batch]``, 1 only where the episode *terminated* (the
    particle tasks end by time limit only, which is not a termination, so
    targets bootstrap through it, as in the original MADDPG and MAAC code).
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    done: jax.Array


class Learner(Protocol):
    """A multi-agent learner: pure functions over an immutable learner state."""

    name: str
    # True for a discrete action space (5 choices), False for continuous 2-D forces.
    discrete: bool

    def init(self, key: jax.Array, num_robots: int, obs_size: int) -> Any:
        """Fresh parameters, target parameters and optimiser states."""

    def act(self, state: Any, obs: jax.Array, key: jax.Array, explore: bool) -> jax.Array:
        """Actions for ``obs`` ``float[batch, N, F]``.

        Returns ``float32[batch, N, 2]`` in ``[-1, 1]`` or ``int32[batch, N]``;
        ``explore=False`` is the deterministic evaluation policy (argmax for MAAC).
        """

    def update(self, state: Any, batch: Transition, key: jax.Array) -> tuple[Any, dict]:
        """One update of every robot's networks from ``batch``; returns scalar metrics."""

    def flops_per_update(self, num_robots: int, obs_size: int) -> float:
        """Floating-point operations of one :meth:`update` (multiply-adds count 2)."""


def check_positive_int(owner: str, name: str, value: Any) -> None:
    """``ValueError`` naming the field unless ``value`` is an integer > 0."""
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{owner}.{name} must be an integer > 0, got {value!r}")


def in_interval(value: float, low: float, high: float | None, low_open: bool,
                high_open: bool) -> bool:
    """Whether ``value`` lies in the interval (``high=None``: unbounded above)."""
    ok = value > low if low_open else value >= low
    if high is not None:
        ok = ok and (value < high if high_open else value <= high)
    return ok


def interval_text(low: float, high: float | None, low_open: bool, high_open: bool) -> str:
    """The interval written out, e.g. ``(0.0, 1.0]`` or ``[0.0, inf)``."""
    left = "(" if low_open else "["
    right = (")" if high_open else "]") if high is not None else ")"
    return f"{left}{low}, {high if high is not None else 'inf'}{right}"


def check_finite(
    owner: str, name: str, value: Any, *, low: float = 0.0, low_open: bool = True,
    high: float | None = None, high_open: bool = False,
) -> None:
    """``ValueError`` naming the field unless ``value`` is a finite number in range."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and in_interval(value, low, high, low_open, high_open)):
        raise ValueError(
            f"{owner}.{name} must be a finite number in "
            f"{interval_text(low, high, low_open, high_open)}, got {value!r}"
        )


def check_hidden(owner: str, name: str, value: Any) -> None:
    """``ValueError`` unless ``value`` is a non-empty tuple of positive layer widths."""
    if not isinstance(value, tuple | list) or not value or any(
        isinstance(v, bool) or not isinstance(v, int) or v <= 0 for v in value
    ):
        raise ValueError(f"{owner}.{name} must be a non-empty tuple of integers > 0, got {value!r}")


def soft_update(target: Any, online: Any, tau: float) -> Any:
    """Polyak averaging ``target <- (1 - tau) target + tau online``, leaf by leaf."""
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)
