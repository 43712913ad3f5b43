"""What every emergency scenario shares: the task layout, the hazard, the interface.

The paper (section Evaluation) gives every scenario the same task: a homogeneous
team starts on one side of the arena and travels to a target area on the other
side; a hazard lies on its way, drawn at random every episode. The paper gives no
sizes, so ccrjax chooses them (in MPE units, with the MPE's robot radius 0.05 and a
top speed of 2 units/s per axis under full action), calibrates them on hand-written
reference controllers (``experiments/calibrate.py``), and keeps every one a parameter
of :class:`Layout` or of the scenario classes:

* robots start inside a box centred at ``(-1.5, 0)`` with half extent ``(0.25, 0.5)``,
  at least ``min_separation`` apart (centre to centre): the box is cut into square
  cells of that side, each robot takes a different cell drawn at random and a uniform
  point of it, shrunk so that robots in neighbouring cells never come closer;
* the target area is the disc of radius ``goal_radius`` around ``goal = (1.5, 0)``.
  It holds the whole team: robot ``i``'s own destination (its *target*) is a slot on
  the area's vertical diameter, ``target_spacing`` apart, slots handed out in the
  order of the robots' starting heights, so that the team arrives side by side
  instead of piling onto one point;
* the hazard's centre is drawn uniformly in ``hazard_x_range x hazard_y_range``,
  across the straight way.

Array layout follows :mod:`ccrjax.envs.world`: batch axis last.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import ClassVar

import jax
import jax.numpy as jnp
from flax import struct

from ccrjax.checks import check_number, check_pair, check_range


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the team starts, where it goes, and where hazards may appear.

    ``arena_half_extent`` is the half size of the arena around the origin: robots are
    not walled in, but the start box, the target area and every hazard must lie
    inside it (it also frames the pictures).
    """

    start_centre: tuple[float, float] = (-1.5, 0.0)
    start_half_extent: tuple[float, float] = (0.25, 0.5)
    min_separation: float = 0.15
    goal: tuple[float, float] = (1.5, 0.0)
    goal_radius: float = 0.4
    target_spacing: float = 0.15
    hazard_x_range: tuple[float, float] = (-0.1, 0.1)
    hazard_y_range: tuple[float, float] = (-0.25, 0.25)
    arena_half_extent: tuple[float, float] = (2.5, 2.0)

    def __post_init__(self) -> None:
        for name in ("start_centre", "goal", "start_half_extent", "arena_half_extent"):
            check_pair("Layout", name, getattr(self, name))
        if min(self.start_half_extent) < 0:
            raise ValueError(
                f"Layout.start_half_extent must be >= 0, got {self.start_half_extent!r}"
            )
        check_number("Layout", "arena_half_extent", min(self.arena_half_extent), positive=True)
        check_number("Layout", "min_separation", self.min_separation, positive=True)
        check_number("Layout", "goal_radius", self.goal_radius, positive=True)
        check_number("Layout", "target_spacing", self.target_spacing, positive=True)
        check_range("Layout", "hazard_x_range", self.hazard_x_range, positive=False)
        check_range("Layout", "hazard_y_range", self.hazard_y_range, positive=False)
        for name, low, high in (
            ("start box", _sub(self.start_centre, self.start_half_extent),
             _add(self.start_centre, self.start_half_extent)),
            ("target area", _sub(self.goal, (self.goal_radius,) * 2),
             _add(self.goal, (self.goal_radius,) * 2)),
        ):
            if not _inside_arena(low, high, self.arena_half_extent):
                raise ValueError(
                    f"Layout: the {name} must lie inside the arena |x| <= "
                    f"{self.arena_half_extent[0]}, |y| <= {self.arena_half_extent[1]}"
                )

    def start_cells(self) -> tuple[int, int]:
        """``(columns, rows)`` of the start box's cells of side ``min_separation``."""
        columns = max(1, int(math.floor(2 * self.start_half_extent[0] / self.min_separation)))
        rows = max(1, int(math.floor(2 * self.start_half_extent[1] / self.min_separation)))
        return columns, rows

    def check_team(self, num_robots: int, robot_radius: float) -> None:
        """Raises ``ValueError`` unless the start box and the target area hold the team."""
        if self.min_separation < 2 * robot_radius:
            raise ValueError(
                f"Layout.min_separation must be at least a robot's diameter ({2 * robot_radius}) "
                f"so that robots never start overlapping, got {self.min_separation}"
            )
        columns, rows = self.start_cells()
        if columns * rows < num_robots:
            raise ValueError(
                f"Layout.start_half_extent {self.start_half_extent} holds {columns * rows} "
                f"robots at min_separation {self.min_separation}, fewer than num_robots "
                f"{num_robots}: enlarge the start box or lower min_separation"
            )
        if self.target_spacing < 2 * robot_radius:
            raise ValueError(
                f"Layout.target_spacing must be at least a robot's diameter ({2 * robot_radius}) "
                f"so that robots at their targets do not overlap, got {self.target_spacing}"
            )
        if self.goal_radius <= robot_radius:
            raise ValueError(
                f"Layout.goal_radius must be larger than a robot's radius ({robot_radius}), "
                f"got {self.goal_radius}"
            )
        reach = 0.5 * (num_robots - 1) * self.target_spacing + robot_radius
        if reach > self.goal_radius:
            raise ValueError(
                f"Layout.goal_radius {self.goal_radius} is too small for {num_robots} robots' "
                f"targets {self.target_spacing} apart (they need {reach:.3g}): enlarge "
                "goal_radius or lower target_spacing"
            )


def _add(a, b) -> tuple[float, float]:
    return (float(a[0]) + float(b[0]), float(a[1]) + float(b[1]))


def _sub(a, b) -> tuple[float, float]:
    return (float(a[0]) - float(b[0]), float(a[1]) - float(b[1]))


def _inside_arena(low, high, arena) -> bool:
    return all(-arena[k] <= low[k] and high[k] <= arena[k] for k in range(2))


def _boxes_overlap(low_a, high_a, low_b, high_b) -> bool:
    return all(low_a[k] < high_b[k] and low_b[k] < high_a[k] for k in range(2))


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


def start_positions(key: jax.Array, layout: Layout, num_robots: int, batch: int) -> jax.Array:
    """Start positions ``float32[N, 2, B]``, every pair at least ``min_separation`` apart.

    The start box is cut into ``columns x rows`` square cells of side ``s =
    min_separation`` (centred in the box); each robot gets a different cell, chosen
    uniformly at random among all of them, and a uniform point within ``(cell side -
    s) / 2`` of the cell's centre. Two robots in different cells are then at least
    ``s`` apart along the axis on which their cells differ. The cells are chosen by
    ranking one uniform number per cell (comparisons only, no sort).
    """
    columns, rows = layout.start_cells()
    cells = columns * rows
    s = layout.min_separation
    cell_w = 2 * layout.start_half_extent[0] / columns
    cell_h = 2 * layout.start_half_extent[1] / rows
    cell_key, jitter_key = jax.random.split(key)
    score = jax.random.uniform(cell_key, (cells, batch))
    # rank[c]: how many cells score below cell c (ties have probability zero).
    rank = jnp.sum(score[None, :, :] < score[:, None, :], axis=1)  # [C, B]
    index = jnp.arange(cells, dtype=jnp.float32)
    # Robot i takes the cell of rank i.
    chosen = jnp.sum(
        jnp.where(rank[None] == jnp.arange(num_robots)[:, None, None], index[None, :, None], 0.0),
        axis=1,
    )  # [N, B]
    column = jnp.floor(chosen / rows)
    row = chosen - column * rows
    low_x = layout.start_centre[0] - 0.5 * columns * cell_w
    low_y = layout.start_centre[1] - 0.5 * rows * cell_h
    centre_x = low_x + (column + 0.5) * cell_w
    centre_y = low_y + (row + 0.5) * cell_h
    jitter = jax.random.uniform(jitter_key, (num_robots, 2, batch), minval=-1.0, maxval=1.0)
    jitter_x = jitter[:, 0] * 0.5 * max(cell_w - s, 0.0)
    jitter_y = jitter[:, 1] * 0.5 * max(cell_h - s, 0.0)
    return jnp.stack([centre_x + jitter_x, centre_y + jitter_y], axis=1).astype(jnp.float32)


def target_positions(position: jax.Array, layout: Layout) -> jax.Array:
    """Each robot's own destination ``float32[N, 2, B]``: a slot of the target area.

    Slots lie on the target area's vertical diameter, ``target_spacing`` apart and
    centred on ``goal``; the robot that starts lowest gets the lowest slot (ties
    broken by index), so the team's paths need not cross.
    """
    num_robots = position.shape[0]
    y = position[:, 1]  # [N, B]
    index = jnp.arange(num_robots)
    below = (y[None, :, :] < y[:, None, :]) | (
        (y[None, :, :] == y[:, None, :]) & (index[None, :, None] < index[:, None, None])
    )  # [i, j, B]: robot j is ranked below robot i
    rank = jnp.sum(below, axis=1).astype(jnp.float32)  # [N, B]
    slot_y = layout.goal[1] + (rank - 0.5 * (num_robots - 1)) * layout.target_spacing
    slot_x = jnp.full_like(slot_y, layout.goal[0])
    return jnp.stack([slot_x, slot_y], axis=1)


def in_target_area(position: jax.Array, layout: Layout) -> jax.Array:
    """``bool[N, B]``: the robot's centre is inside the target area (the success region)."""
    rel_x = position[:, 0] - layout.goal[0]
    rel_y = position[:, 1] - layout.goal[1]
    return rel_x * rel_x + rel_y * rel_y < layout.goal_radius**2


def distance_to(position: jax.Array, point: jax.Array) -> jax.Array:
    """``|p_i - q_i|`` per robot ``float[N, B]``, for points ``q`` of shape ``[N, 2, B]``."""
    rel_x = position[:, 0] - point[:, 0]
    rel_y = position[:, 1] - point[:, 1]
    return jnp.sqrt(rel_x * rel_x + rel_y * rel_y)


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
        if not _inside_arena(low, high, layout.arena_half_extent):
            raise ValueError(
                f"{owner}: hazards reach x in [{low[0]:.3g}, {high[0]:.3g}], y in "
                f"[{low[1]:.3g}, {high[1]:.3g}], beyond the arena |x| <= "
                f"{layout.arena_half_extent[0]}, |y| <= {layout.arena_half_extent[1]} "
                "(Layout.arena_half_extent): shrink the hazard or the hazard ranges"
            )
        start_low = _sub(layout.start_centre, layout.start_half_extent)
        start_high = _add(layout.start_centre, layout.start_half_extent)
        pad = (robot_radius, robot_radius)
        if _boxes_overlap(low, high, _sub(start_low, pad), _add(start_high, pad)):
            raise ValueError(
                f"{owner}: hazards may reach x in [{low[0]:.3g}, {high[0]:.3g}], overlapping "
                f"the start box x in [{start_low[0]:.3g}, {start_high[0]:.3g}] "
                "(Layout.start_centre, start_half_extent): robots would start in danger"
            )
        goal_low = _sub(layout.goal, (layout.goal_radius,) * 2)
        goal_high = _add(layout.goal, (layout.goal_radius,) * 2)
        if _boxes_overlap(low, high, goal_low, goal_high):
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
