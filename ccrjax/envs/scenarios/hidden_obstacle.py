"""Emergency 3, hidden obstacle: a solid rectangle on the way that robots cannot see.

Paper: "A rectangular solid obstacle with random lengths is located on their way.
Robots can only sense whether they are in collision with the obstacle, but not the
coordinates of the obstacle. The task is considered successful for each robot that
arrives at the other side of the obstacle."

The obstacle is an axis-aligned rectangle across the way: ``thickness`` along the
direction of travel (x) and a random ``length`` across it (y, uniform in
``length_range``); its centre's height is drawn from the layout's hazard range, so
the shorter way round is above in some episodes and below in others. It is
**solid**: after the physics step, a robot whose motion would take its disc into the
obstacle is stopped at the obstacle's surface and loses its velocity into it
(:func:`ccrjax.envs.world.rectangle_stop`), at any speed, angle, corner or pile; robots
still collide with each other through the MPE's contact law. A robot observes one
feature: whether it touches the obstacle (its disc within ``touch_tolerance`` of the
surface, or stopped at a corner), which is also the paper's dangerous state ("colliding
with the obstacle").
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ccrjax.checks import check_number, check_range
from ccrjax.envs.scenarios.base import Hazard, Scenario
from ccrjax.envs.scenarios.layout import Layout, sample_centre
from ccrjax.envs.world import rectangle_stop


@dataclasses.dataclass(frozen=True)
class HiddenObstacle(Scenario):
    """Solid rectangle of random length across the way."""

    name = "hidden_obstacle"
    hazard_feature_size = 1

    thickness: float = 0.4
    length_range: tuple[float, float] = (1.2, 2.0)
    touch_tolerance: float = 0.01

    def __post_init__(self) -> None:
        check_number("HiddenObstacle", "thickness", self.thickness, positive=True)
        check_range("HiddenObstacle", "length_range", self.length_range, positive=True)
        check_number("HiddenObstacle", "touch_tolerance", self.touch_tolerance, positive=False)

    def max_half_extent(self) -> tuple[float, float]:
        return (0.5 * float(self.thickness), 0.5 * float(self.length_range[1]))

    def check_layout(self, layout: Layout, robot_radius: float) -> None:
        """Also refuses an obstacle that can block every way past it.

        Robots are not walled in, but the arena frames the task: between the
        longest obstacle, drawn nearest the middle, and the arena's edge there must be
        room for two robots side by side on its longer side. (Drawn at height ``y``, an
        obstacle of half length ``L`` leaves ``A - L + |y|`` on its longer side.)
        """
        super().check_layout(layout, robot_radius)
        half_length = 0.5 * float(self.length_range[1])
        low_y, high_y = layout.hazard_y_range
        arena_y = layout.arena_half_extent[1]
        nearest = 0.0 if low_y <= 0.0 <= high_y else min(abs(low_y), abs(high_y))
        if arena_y - half_length + nearest < 4 * robot_radius:
            raise ValueError(
                f"HiddenObstacle.length_range {self.length_range} with Layout.hazard_y_range "
                f"{layout.hazard_y_range} can block every way past the obstacle inside the "
                f"arena |y| <= {arena_y}: shorten the obstacle"
            )

    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        centre_key, length_key = jax.random.split(key)
        half_length = 0.5 * jax.random.uniform(
            length_key, (batch,), minval=self.length_range[0], maxval=self.length_range[1]
        )
        half_thickness = jnp.full((batch,), 0.5 * self.thickness, jnp.float32)
        return Hazard(
            centre=sample_centre(centre_key, layout, batch),
            half_extent=jnp.stack([half_thickness, half_length]),
            direction=jnp.zeros((2, batch)),
        )

    def touching(self, hazard: Hazard, position: jax.Array, radius: jax.Array) -> jax.Array:
        """``bool[N, B]``: the robot's centre is within ``touch_tolerance`` of the obstacle
        grown by its radius, the region :meth:`constrain` keeps it out of.

        Along a face this is the disc within ``touch_tolerance`` of the obstacle; at a
        corner the grown rectangle is square where the disc's reach is round, so a disc
        stopped there counts as touching up to ``(sqrt(2) - 1) r`` (0.02) early: every
        robot the obstacle stops is in contact with it.
        """
        grown = hazard.half_extent[None] + radius[:, None, None]  # [N, 2, B]
        rel_x = jnp.abs(position[:, 0] - hazard.centre[0][None]) - grown[:, 0]
        rel_y = jnp.abs(position[:, 1] - hazard.centre[1][None]) - grown[:, 1]
        out_x, out_y = jnp.maximum(rel_x, 0.0), jnp.maximum(rel_y, 0.0)
        return out_x * out_x + out_y * out_y <= self.touch_tolerance**2

    def constrain(self, hazard, previous, position, velocity, radius):
        """Stops robots at the obstacle's surface (:func:`ccrjax.envs.world.rectangle_stop`)."""
        return rectangle_stop(
            previous, position, velocity, radius, hazard.centre, hazard.half_extent
        )

    def in_danger(self, hazard, position, radius):
        return self.touching(hazard, position, radius)

    def hazard_features(self, hazard, position, radius):
        return self.touching(hazard, position, radius)[:, None].astype(jnp.float32)
