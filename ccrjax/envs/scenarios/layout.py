"""The task's layout: where the team starts (abreast or in a column), where it goes, and
where hazards may appear.

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
  point of it, shrunk so that robots in neighbouring cells never come closer (the
  ``"abreast"`` formation, the default);
* or, in the ``"column"`` formation, one behind another along the way: the leader at
  the start box's front edge, each next robot ``column_spacing`` further back (x), each
  at a uniform height within ``column_lateral`` of the start box's centre line, the
  order drawn at random every episode, so that the robots meet a hazard on the way one
  after another (the leader ``column_spacing / 0.2`` steps before the next at top
  speed) and a teammate's trouble can reach the robots behind it;
* the target area is the disc of radius ``goal_radius`` around ``goal = (1.5, 0)``.
  It holds the whole team: robot ``i``'s own destination (its *target*) is a slot on
  the area's vertical diameter, ``target_spacing`` apart, slots handed out in the
  order of the robots' starting heights, so that the team arrives side by side
  instead of piling onto one point;
* the hazard's centre is drawn uniformly in ``hazard_x_range x hazard_y_range``,
  across the straight way: by default almost in the same place every episode; a wide
  ``hazard_y_range`` is the placement knob that makes it impossible to memorise.

The hazards themselves are the scenarios' (:mod:`ccrjax.envs.scenarios.base`). Array
layout follows :mod:`ccrjax.envs.world`: batch axis last.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp

from ccrjax.checks import check_choice, check_number, check_pair, check_range


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the team starts, where it goes, and where hazards may appear.

    ``arena_half_extent`` is the half size of the arena around the origin: robots are
    not walled in, but the start box, the target area and every hazard must lie
    inside it (it also frames the pictures).
    """

    start_centre: tuple[float, float] = (-1.5, 0.0)  # centre of the start box
    start_half_extent: tuple[float, float] = (0.25, 0.5)  # half size of the start box
    min_separation: float = 0.15  # least distance between robots' centres at the start
    goal: tuple[float, float] = (1.5, 0.0)  # centre of the target area
    goal_radius: float = 0.4  # radius of the target area
    target_spacing: float = 0.15  # distance between robots' own targets in the target area
    hazard_x_range: tuple[float, float] = (-0.1, 0.1)  # range of the hazard centre's x
    hazard_y_range: tuple[float, float] = (-0.25, 0.25)  # range of the hazard centre's y
    arena_half_extent: tuple[float, float] = (2.5, 2.0)  # half size of the arena
    formation: str = "abreast"  # abreast (the start box) or column (one behind another)
    column_spacing: float = 0.3  # column: distance along the way between consecutive robots
    column_lateral: float = 0.05  # column: largest offset of a robot across the way

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
        check_choice("Layout", "formation", self.formation, FORMATIONS)
        check_number("Layout", "column_spacing", self.column_spacing, positive=True)
        check_number("Layout", "column_lateral", self.column_lateral, positive=False)
        if self.formation == "column":
            centre_y = self.start_centre[1]
            if abs(centre_y) + self.column_lateral > self.arena_half_extent[1]:
                raise ValueError(
                    f"Layout.column_lateral {self.column_lateral} takes the column beyond the "
                    f"arena |y| <= {self.arena_half_extent[1]} (start_centre y {centre_y})"
                )
        for name, low, high in (
            ("start box", sub_pairs(self.start_centre, self.start_half_extent),
             add_pairs(self.start_centre, self.start_half_extent)),
            ("target area", sub_pairs(self.goal, (self.goal_radius,) * 2),
             add_pairs(self.goal, (self.goal_radius,) * 2)),
        ):
            if not inside_arena(low, high, self.arena_half_extent):
                raise ValueError(
                    f"Layout: the {name} must lie inside the arena |x| <= "
                    f"{self.arena_half_extent[0]}, |y| <= {self.arena_half_extent[1]}"
                )

    def start_cells(self) -> tuple[int, int]:
        """``(columns, rows)`` of the start box's cells of side ``min_separation``."""
        columns = max(1, int(math.floor(2 * self.start_half_extent[0] / self.min_separation)))
        rows = max(1, int(math.floor(2 * self.start_half_extent[1] / self.min_separation)))
        return columns, rows

    def record(self) -> dict[str, Any]:
        """The parameters as a dict, the column's own ones (``formation``, ``column_spacing``,
        ``column_lateral``) only for a column: abreast they change nothing, and an abreast
        layout's record stays what it was before the column existed (records of committed
        results compare equal)."""
        record = dataclasses.asdict(self)
        if self.formation == "abreast":
            for name in COLUMN_FIELDS:
                del record[name]
        return record

    @property
    def front(self) -> float:
        """x of the start box's front edge (towards the target): where a column's leader starts."""
        return float(self.start_centre[0]) + float(self.start_half_extent[0])

    def start_region(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``(low, high)`` corners of the region robots may start in, whatever the team size:
        the start box abreast; in a column, from the arena's back edge to the box's front,
        within ``column_lateral`` of its centre line."""
        if self.formation == "column":
            centre_y = float(self.start_centre[1])
            return ((-float(self.arena_half_extent[0]), centre_y - self.column_lateral),
                    (self.front, centre_y + self.column_lateral))
        return (sub_pairs(self.start_centre, self.start_half_extent),
                add_pairs(self.start_centre, self.start_half_extent))

    def check_team(self, num_robots: int, robot_radius: float) -> None:
        """Raises ``ValueError`` unless the start region and the target area hold the team."""
        if self.min_separation < 2 * robot_radius:
            raise ValueError(
                f"Layout.min_separation must be at least a robot's diameter ({2 * robot_radius}) "
                f"so that robots never start overlapping, got {self.min_separation}"
            )
        if self.formation == "column":
            self._check_column(num_robots, robot_radius)
        columns, rows = self.start_cells()
        if self.formation == "abreast" and columns * rows < num_robots:
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

    def _check_column(self, num_robots: int, robot_radius: float) -> None:
        if self.column_spacing < self.min_separation:
            raise ValueError(
                f"Layout.column_spacing must be at least min_separation ({self.min_separation}) "
                f"so that robots never start closer, got {self.column_spacing}"
            )
        last = self.front - (num_robots - 1) * self.column_spacing
        if last - robot_radius < -self.arena_half_extent[0]:
            longest = (self.front - robot_radius + self.arena_half_extent[0]) / (num_robots - 1)
            raise ValueError(
                f"Layout.column_spacing {self.column_spacing}: a column of {num_robots} robots "
                f"reaches x = {last:.3g}, beyond the arena |x| <= {self.arena_half_extent[0]}; "
                f"allowed: column_spacing <= {longest:.3g} (or a larger arena_half_extent)"
            )

    def check_episode(self, num_robots: int, episode_length: int) -> None:
        """Raises ``ValueError`` if a column is longer than the episode allows: its last robot
        could not reach the target area even at full speed along the way
        (:func:`steps_to_cover`). The abreast start box is the task's own and is not checked
        (short episodes are a legitimate test size there)."""
        if self.formation != "column":
            return
        last = self.front - (num_robots - 1) * self.column_spacing
        distance = (self.goal[0] - self.goal_radius) - last
        needed = steps_to_cover(distance)
        if needed > episode_length:
            raise ValueError(
                f"episode_length {episode_length} is too short for a column of {num_robots} "
                f"robots {self.column_spacing} apart: its last robot needs at least {needed} "
                "steps at full speed to reach the target area; allowed: episode_length >= "
                f"{needed} (or a shorter column_spacing)"
            )


FORMATIONS = ("abreast", "column")
COLUMN_FIELDS = ("formation", "column_spacing", "column_lateral")


def steps_to_cover(distance: float, sensitivity: float = 5.0, damping: float = 0.25,
                   dt: float = 0.1) -> int:
    """Steps a robot starting at rest needs to travel ``distance`` at full action along one axis
    under the MPE's integration (``p += v dt``, then ``v = (1 - damping) v + sensitivity dt``):
    a lower bound on any policy's arrival time."""
    travelled, velocity, steps = 0.0, 0.0, 0
    while travelled < distance:
        travelled += velocity * dt
        velocity = (1.0 - damping) * velocity + sensitivity * dt
        steps += 1
    return steps


def add_pairs(a, b) -> tuple[float, float]:
    return (float(a[0]) + float(b[0]), float(a[1]) + float(b[1]))


def sub_pairs(a, b) -> tuple[float, float]:
    return (float(a[0]) - float(b[0]), float(a[1]) - float(b[1]))


def inside_arena(low, high, arena) -> bool:
    return all(-arena[k] <= low[k] and high[k] <= arena[k] for k in range(2))


def boxes_overlap(low_a, high_a, low_b, high_b) -> bool:
    return all(low_a[k] < high_b[k] and low_b[k] < high_a[k] for k in range(2))


def sample_centre(key: jax.Array, layout: Layout, batch: int) -> jax.Array:
    """Draws hazard centres ``float[2, B]`` uniformly in the layout's hazard box."""
    low = jnp.array([layout.hazard_x_range[0], layout.hazard_y_range[0]])[:, None]
    high = jnp.array([layout.hazard_x_range[1], layout.hazard_y_range[1]])[:, None]
    return jax.random.uniform(key, (2, batch), minval=low, maxval=high)


def start_positions(key: jax.Array, layout: Layout, num_robots: int, batch: int) -> jax.Array:
    """Start positions ``float32[N, 2, B]`` of the layout's formation (abreast or a column)."""
    if layout.formation == "column":
        return column_positions(key, layout, num_robots, batch)
    return abreast_positions(key, layout, num_robots, batch)


def _rank(score: jax.Array) -> jax.Array:
    """``rank[c, b]``: how many entries of ``score[:, b]`` lie below ``score[c, b]`` (a random
    permutation for uniform scores: ties have probability zero; comparisons only, no sort)."""
    return jnp.sum(score[None, :, :] < score[:, None, :], axis=1)


def column_positions(key: jax.Array, layout: Layout, num_robots: int, batch: int) -> jax.Array:
    """A column along the way, ``float32[N, 2, B]``: the robot of rank ``r`` (a random order
    every episode) at ``x = front - r * column_spacing``, ``y`` uniform within
    ``column_lateral`` of the start box's centre line. Consecutive robots are exactly
    ``column_spacing`` apart along x, so at least that far apart."""
    order_key, lateral_key = jax.random.split(key)
    rank = _rank(jax.random.uniform(order_key, (num_robots, batch))).astype(jnp.float32)
    x = layout.front - rank * layout.column_spacing
    offset = jax.random.uniform(lateral_key, (num_robots, batch), minval=-1.0, maxval=1.0)
    y = layout.start_centre[1] + offset * layout.column_lateral
    return jnp.stack([x, y], axis=1).astype(jnp.float32)


def abreast_positions(key: jax.Array, layout: Layout, num_robots: int, batch: int) -> jax.Array:
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
    rank = _rank(jax.random.uniform(cell_key, (cells, batch)))  # [C, B]
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
