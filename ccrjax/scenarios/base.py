"""What every emergency scenario shares: the task layout, the hazard, the interface.

The paper (section Evaluation) gives every scenario the same task: a homogeneous
team starts on one side of the arena and travels to a destination on the other
side; a hazard lies on its way, drawn at random every episode. The paper gives no
sizes, so ccrjax chooses them here (in MPE units, with the MPE's robot radius
0.05 and top speed of about 2 units/s under full action), documents them in
the README, and keeps every one a parameter:

* robots start uniformly inside a box centred at ``(-1.5, 0)`` with half extent
  ``(0.25, 0.5)``;
* the destination is ``(1.5, 0)``; the target *area* (turbulence, nominal) is the
  disc of radius 0.3 around it;
* the hazard's centre is drawn uniformly in ``x in [-0.3, 0.3]``,
  ``y in [-0.25, 0.25]``, so it always lies across the straight way.

Array layout follows :mod:`ccrjax.world`: batch axis last.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
from flax import struct


def check_range(owner: str, name: str, value: tuple[float, float], *, positive: bool) -> None:
    """Validates a ``(low, high)`` pair; raises ``ValueError`` naming the field."""
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{name} must be a pair (low, high), got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise ValueError(f"{owner}.{name} must be finite with low <= high, got {value!r}")
    if positive and low <= 0:
        raise ValueError(f"{owner}.{name} must hold sizes > 0, got {value!r}")


def check_positive(owner: str, name: str, value: float, *, allow_zero: bool = False) -> None:
    """Validates a finite number that is > 0 (or >= 0); raises ``ValueError`` naming it."""
    ok = isinstance(value, int | float) and math.isfinite(value)
    ok = ok and (value >= 0 if allow_zero else value > 0)
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{owner}.{name} must be a finite number {bound}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the team starts, where it goes, and where hazards may appear."""

    start_centre: tuple[float, float] = (-1.5, 0.0)
    start_half_extent: tuple[float, float] = (0.25, 0.5)
    goal: tuple[float, float] = (1.5, 0.0)
    goal_radius: float = 0.3
    hazard_x_range: tuple[float, float] = (-0.3, 0.3)
    hazard_y_range: tuple[float, float] = (-0.25, 0.25)

    def __post_init__(self) -> None:
        for name in ("start_centre", "goal", "start_half_extent"):
            value = getattr(self, name)
            if len(value) != 2 or not all(math.isfinite(float(v)) for v in value):
                raise ValueError(f"Layout.{name} must be a finite (x, y) pair, got {value!r}")
        if min(self.start_half_extent) < 0:
            raise ValueError(
                f"Layout.start_half_extent must be >= 0, got {self.start_half_extent!r}"
            )
        check_positive("Layout", "goal_radius", self.goal_radius)
        check_range("Layout", "hazard_x_range", self.hazard_x_range, positive=False)
        check_range("Layout", "hazard_y_range", self.hazard_y_range, positive=False)


@struct.dataclass
class Hazard:
    """One hazard per environment (batch axis last).

    ``centre``: ``float[2, B]``; ``half_extent``: ``float[2, B]`` (a circle's
    radius in both entries; a rectangle's half width and half height);
    ``direction``: ``float[2, B]`` unit vector (the wind's; zero elsewhere).
    """

    centre: jax.Array
    half_extent: jax.Array
    direction: jax.Array


def sample_centre(key: jax.Array, layout: Layout, batch: int) -> jax.Array:
    """Draws hazard centres ``float[2, B]`` uniformly in the layout's hazard box."""
    low = jnp.array([layout.hazard_x_range[0], layout.hazard_y_range[0]])[:, None]
    high = jnp.array([layout.hazard_x_range[1], layout.hazard_y_range[1]])[:, None]
    return jax.random.uniform(key, (2, batch), minval=low, maxval=high)


def hashed_bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Uniform ``uint32`` words of ``shape``: a counter-based integer hash seeded from ``key``.

    One 32-bit seed is drawn from ``key`` with JAX's generator; element ``c`` (its
    flat index) gets ``mix(seed + c * 0x9E3779B9)``, where ``mix`` is a two-round
    multiply-xorshift finaliser (constants of the "lowbias32" hash), which passes
    the usual avalanche tests. A fresh key each step gives fresh words. It is for
    physical noise only (not for anything that needs cryptographic quality) and
    costs a few integer operations per word instead of threefry's twenty rounds.
    """
    seed = jax.random.bits(key, (), jnp.uint32)
    counter = jax.lax.iota(jnp.uint32, math.prod(shape)).reshape(shape)
    x = seed + counter * jnp.uint32(0x9E3779B9)
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def unit_vector(fraction: jax.Array) -> jax.Array:
    """``(cos 2 pi u, sin 2 pi u)`` for ``u in [0, 1)``, stacked on a new axis 1.

    XLA's ``cos``/``sin`` on CPU cost about 9 ns an element, more than the rest
    of a turbulence step; this reduces the angle to one quadrant and evaluates
    Taylor polynomials (degree 10/11, error below 5e-7), then rotates the result
    back by quarter turns with selects.
    """
    scaled = 4.0 * fraction
    quadrant = jnp.floor(scaled)
    r = (scaled - quadrant) * (0.5 * math.pi)  # in [0, pi / 2)
    r2 = r * r
    cos_r = 1.0 + r2 * (-1 / 2 + r2 * (1 / 24 + r2 * (-1 / 720 + r2 * (
        1 / 40320 + r2 * (-1 / 3628800)))))
    sin_r = r * (1.0 + r2 * (-1 / 6 + r2 * (1 / 120 + r2 * (-1 / 5040 + r2 * (
        1 / 362880 + r2 * (-1 / 39916800))))))
    q = jnp.mod(quadrant, 4.0)
    x = jnp.where(q == 0, cos_r, jnp.where(q == 1, -sin_r, jnp.where(q == 2, -cos_r, sin_r)))
    y = jnp.where(q == 0, sin_r, jnp.where(q == 1, cos_r, jnp.where(q == 2, -sin_r, -cos_r)))
    return jnp.stack([x, y], axis=1)


def in_goal_area(position: jax.Array, layout: Layout) -> jax.Array:
    """``bool[N, B]``: the robot's centre is inside the target area around the destination."""
    rel_x = position[:, 0] - layout.goal[0]
    rel_y = position[:, 1] - layout.goal[1]
    return rel_x * rel_x + rel_y * rel_y < layout.goal_radius**2


def distance_to_centre(position: jax.Array, hazard: Hazard) -> jax.Array:
    """``|p_i - c|``: each robot's distance to the hazard's centre, ``float[N, B]``."""
    rel_x = position[:, 0] - hazard.centre[0][None]
    rel_y = position[:, 1] - hazard.centre[1][None]
    return jnp.sqrt(rel_x * rel_x + rel_y * rel_y)


class Scenario(abc.ABC):
    """An emergency: how its hazard is drawn, pushes, is seen, and what counts as done.

    Subclasses are frozen dataclasses of their parameters, validated on
    construction. All methods are pure functions of arrays with the batch axis
    last; ``position`` is ``float[N, 2, B]`` and ``radius`` is ``float[N]``.
    """

    name: ClassVar[str]
    # Number of hazard features appended to each robot's observation.
    hazard_feature_size: ClassVar[int]
    # Whether :meth:`hazard_force` consumes fresh random numbers every step.
    needs_step_noise: ClassVar[bool] = False

    @abc.abstractmethod
    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        """Draws a fresh hazard for each of ``batch`` environments."""

    def step_noise(self, key: jax.Array, num_robots: int, batch: int) -> jax.Array:
        """Random numbers :meth:`hazard_force` needs this step (none by default)."""
        del key
        return jnp.zeros((num_robots, 0, batch), jnp.float32)

    def init_memory(self, hazard: Hazard, position: jax.Array) -> jax.Array:
        """Per-robot memory the hazard's physics keeps across steps (none by default).

        ``float32[N, M, B]``; the hidden obstacle remembers where each robot last
        was outside it, so that it pushes robots out the way they came in.
        """
        del hazard
        return jnp.zeros((position.shape[0], 0, position.shape[2]), jnp.float32)

    def update_memory(
        self, hazard: Hazard, memory: jax.Array, position: jax.Array
    ) -> jax.Array:
        """The memory after the robots moved to ``position``."""
        del hazard, position
        return memory

    def constrain(
        self, hazard: Hazard, memory: jax.Array, position: jax.Array, velocity: jax.Array,
        radius: jax.Array,
    ) -> tuple[jax.Array, jax.Array]:
        """Position and velocity after the physics step, corrected if the hazard forbids them.

        Nothing by default; the hidden obstacle returns a robot that crossed it in one
        step to the face it came in through. ``memory`` is the one before the step.
        """
        del hazard, memory, radius
        return position, velocity

    @abc.abstractmethod
    def hazard_force(
        self, hazard: Hazard, position: jax.Array, radius: jax.Array, noise: jax.Array,
        physics, memory: jax.Array | None = None,
    ) -> jax.Array:
        """Force ``float[N, 2, B]`` the hazard exerts on each robot at ``position``."""

    @abc.abstractmethod
    def in_danger(self, hazard: Hazard, position: jax.Array, radius: jax.Array) -> jax.Array:
        """``bool[N, B]``: the paper's unsafe state (inside the area, touching the obstacle)."""

    @abc.abstractmethod
    def reached(self, hazard: Hazard, position: jax.Array, layout: Layout) -> jax.Array:
        """``bool[N, B]``: the robot accomplishes the task at this position."""

    @abc.abstractmethod
    def hazard_features(
        self, hazard: Hazard, position: jax.Array, radius: jax.Array
    ) -> jax.Array:
        """``float[N, hazard_feature_size, B]``: what each robot may observe of the hazard."""


def area_features(inside: jax.Array, position: jax.Array, hazard: Hazard) -> jax.Array:
    """Features of an area hazard, visible only from inside: ``[inside, dx, dy, size]``.

    ``dx, dy`` is the area's centre relative to the robot and ``size`` its half
    extent along x; all four are zero for robots outside the area.
    """
    rel = hazard.centre[None] - position  # [N, 2, B]
    size = jnp.broadcast_to(hazard.half_extent[None, 0], inside.shape)
    features = jnp.concatenate(
        [jnp.ones_like(size)[:, None], rel, size[:, None]], axis=1
    )  # [N, 4, B]
    return jnp.where(inside[:, None, :], features, 0.0)
