"""What every emergency scenario shares: the hazard and the interface.

The paper (section Evaluation) gives every scenario the same task (the layout of
:mod:`ccrjax.envs.scenarios.layout`): a team travels from a start region to a target area,
and a hazard lies on its way, drawn at random every episode. A :class:`Scenario` says how
its hazard is drawn, pushes, constrains and is seen; the paper gives no sizes, so ccrjax
chooses them, calibrates them on hand-written reference controllers
(``experiments/calibrate.py``), and keeps every one a parameter of the scenario classes.

Array layout follows :mod:`ccrjax.envs.world`: batch axis last.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
from flax import struct

from ccrjax.envs.scenarios.layout import (
    Layout,
    add_pairs,
    boxes_overlap,
    inside_arena,
    sub_pairs,
)


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


def distance_to_centre(position: jax.Array, hazard: Hazard) -> jax.Array:
    """``|p_i - c|``: each robot's distance to the hazard's centre, ``float[N, B]``."""
    rel_x = position[:, 0] - hazard.centre[0][None]
    rel_y = position[:, 1] - hazard.centre[1][None]
    return jnp.sqrt(rel_x * rel_x + rel_y * rel_y)


class Scenario(abc.ABC):
    """An emergency: how its hazard is drawn, pushes, constrains and is seen.

    Subclasses are frozen dataclasses of their parameters, validated on
    construction; :meth:`check_layout` validates them against a layout when an
    environment is built. All methods are pure functions of arrays with the batch
    axis last; ``position`` is ``float[N, 2, B]`` and ``radius`` is ``float[N]``.
    Success is the same in every scenario (the robot is in the target area at the
    end of the episode) and lives in the environment, not here.
    """

    name: ClassVar[str]
    # Number of hazard features appended to each robot's observation.
    hazard_feature_size: ClassVar[int]
    # Whether :meth:`hazard_force` consumes fresh random numbers every step.
    needs_step_noise: ClassVar[bool] = False

    @abc.abstractmethod
    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        """Draws a fresh hazard for each of ``batch`` environments."""

    @abc.abstractmethod
    def max_half_extent(self) -> tuple[float, float]:
        """The largest half extents ``(x, y)`` a drawn hazard can have (for validation)."""

    def check_layout(self, layout: Layout, robot_radius: float) -> None:
        """Raises ``ValueError`` if this scenario's hazards make the task meaningless.

        Every hazard the layout can draw must lie inside the arena, keep clear of
        the start box (robots would start in danger) and of the target area.
        """
        half_x, half_y = self.max_half_extent()
        low = (layout.hazard_x_range[0] - half_x, layout.hazard_y_range[0] - half_y)
        high = (layout.hazard_x_range[1] + half_x, layout.hazard_y_range[1] + half_y)
        owner = type(self).__name__
        if not inside_arena(low, high, layout.arena_half_extent):
            raise ValueError(
                f"{owner}: hazards reach x in [{low[0]:.3g}, {high[0]:.3g}], y in "
                f"[{low[1]:.3g}, {high[1]:.3g}], beyond the arena |x| <= "
                f"{layout.arena_half_extent[0]}, |y| <= {layout.arena_half_extent[1]} "
                "(Layout.arena_half_extent): shrink the hazard or the hazard ranges"
            )
        start_low, start_high = layout.start_region()
        where = "column's start region" if layout.formation == "column" else "start box"
        pad = (robot_radius, robot_radius)
        if boxes_overlap(low, high, sub_pairs(start_low, pad), add_pairs(start_high, pad)):
            raise ValueError(
                f"{owner}: hazards may reach x in [{low[0]:.3g}, {high[0]:.3g}], y in "
                f"[{low[1]:.3g}, {high[1]:.3g}], overlapping the {where} x in "
                f"[{start_low[0]:.3g}, {start_high[0]:.3g}], y in [{start_low[1]:.3g}, "
                f"{start_high[1]:.3g}] (Layout.hazard_x_range, hazard_y_range, start_centre, "
                "start_half_extent): robots would start in danger"
            )
        goal_low = sub_pairs(layout.goal, (layout.goal_radius,) * 2)
        goal_high = add_pairs(layout.goal, (layout.goal_radius,) * 2)
        if boxes_overlap(low, high, goal_low, goal_high):
            raise ValueError(
                f"{owner}: hazards may reach x up to {high[0]:.3g}, overlapping the target "
                f"area x in [{goal_low[0]:.3g}, {goal_high[0]:.3g}] (Layout.goal, goal_radius)"
            )

    def step_noise(self, key: jax.Array, num_robots: int, batch: int) -> jax.Array:
        """Random numbers :meth:`hazard_force` needs this step (none by default)."""
        del key
        return jnp.zeros((num_robots, 0, batch), jnp.float32)

    def hazard_force(self, hazard: Hazard, position: jax.Array, noise: jax.Array) -> jax.Array:
        """Force ``float[N, 2, B]`` the hazard exerts on each robot at ``position`` (none)."""
        del hazard, noise
        return jnp.zeros_like(position)

    def constrain(
        self, hazard: Hazard, previous: jax.Array, position: jax.Array, velocity: jax.Array,
        radius: jax.Array,
    ) -> tuple[jax.Array, jax.Array]:
        """Position and velocity after the physics step, corrected if the hazard forbids them.

        ``previous`` is every robot's position before the step. Nothing by default;
        the hidden obstacle stops robots at its surface.
        """
        del hazard, previous, radius
        return position, velocity

    @abc.abstractmethod
    def in_danger(self, hazard: Hazard, position: jax.Array, radius: jax.Array) -> jax.Array:
        """``bool[N, B]``: the paper's unsafe state (inside the area, touching the obstacle)."""

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
