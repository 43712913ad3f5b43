"""Emergency 3, hidden obstacle: a solid rectangle on the way that robots cannot see.

Paper: "A rectangular solid obstacle with random lengths is located on their way.
Robots can only sense whether they are in collision with the obstacle, but not the
coordinates of the obstacle. The task is considered successful for each robot that
arrives at the other side of the obstacle."

The obstacle is an axis-aligned rectangle across the way: ``thickness`` along the
direction of travel (x, fixed, 0.6 by default) and a random ``length`` across it
(y, uniform in ``length_range``). Robots collide with it through the MPE's soft
contact law (:func:`ccrjax.world.rectangle_contact_force`). A robot at full speed
(about 0.2 per step) gets up to about 0.35 deep into the soft wall before the contact
force stops it (the MPE moves bodies with their old velocity before forces act), so
the obstacle remembers where each robot last was outside and pushes it back out that
way, and a robot that crossed the whole obstacle within one step (robots piling
into it bounce off each other at up to about 8 units/s) is put back at the face it
came in through (:meth:`HiddenObstacle.constrain`). ``tests/test_scenarios.py``
drives single robots, columns and a pile of 16 into it at full speed to check.
A robot observes one feature: whether it touches the obstacle.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ccrjax.scenarios.base import (
    Hazard,
    Layout,
    Scenario,
    check_positive,
    check_range,
    sample_centre,
)
from ccrjax.world import rectangle_contact_force, rectangle_distance


@dataclasses.dataclass(frozen=True)
class HiddenObstacle(Scenario):
    """Solid rectangle of random length across the way."""

    name = "hidden_obstacle"
    hazard_feature_size = 1

    thickness: float = 0.6
    length_range: tuple[float, float] = (0.6, 1.4)

    def __post_init__(self) -> None:
        check_positive("HiddenObstacle", "thickness", self.thickness)
        check_range("HiddenObstacle", "length_range", self.length_range, positive=True)

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
        """``bool[N, B]``: the robot's disc overlaps the obstacle."""
        distance = rectangle_distance(position, hazard.centre, hazard.half_extent)
        return distance < radius[:, None]

    def init_memory(self, hazard: Hazard, position: jax.Array) -> jax.Array:
        """Where each robot's centre last was outside the obstacle: ``float32[N, 2, B]``."""
        return position

    def update_memory(self, hazard: Hazard, memory: jax.Array, position: jax.Array):
        distance = rectangle_distance(position, hazard.centre, hazard.half_extent)
        # Only points strictly outside are entry points (a point on a face is not).
        return jnp.where((distance <= 0.0)[:, None], memory, position)

    def constrain(self, hazard, memory, position, velocity, radius):
        """Returns a robot that crossed the whole obstacle in one step to its entry face.

        The soft contact force cannot stop a disc that moves further than the wall is
        thick within one step (robots piling into the wall bounce off each other fast
        enough). A robot whose last outside point (``memory``, before this step) was on
        one side and which now lies beyond the opposite face, level with the obstacle,
        went through it: it is put back just outside the face it came in through, its
        velocity along that axis set to zero. Robots that did not cross are untouched.
        """
        centre, half = hazard.centre, hazard.half_extent
        entry_x = memory[:, 0] - centre[0][None]
        entry_y = memory[:, 1] - centre[1][None]
        entry_out_x = jnp.abs(entry_x) - half[0][None]
        entry_out_y = jnp.abs(entry_y) - half[1][None]
        through_x = entry_out_x >= entry_out_y  # entered through an x face
        side_x = jnp.where(entry_x >= 0.0, 1.0, -1.0)
        side_y = jnp.where(entry_y >= 0.0, 1.0, -1.0)
        rel_x = position[:, 0] - centre[0][None]
        rel_y = position[:, 1] - centre[1][None]
        beyond_x = (side_x * rel_x < -half[0][None]) & (jnp.abs(rel_y) < half[1][None])
        beyond_y = (side_y * rel_y < -half[1][None]) & (jnp.abs(rel_x) < half[0][None])
        outside_before = (entry_out_x > 0.0) | (entry_out_y > 0.0)
        crossed_x = outside_before & through_x & beyond_x
        crossed_y = outside_before & ~through_x & beyond_y
        face_x = centre[0][None] + side_x * (half[0][None] + radius[:, None])
        face_y = centre[1][None] + side_y * (half[1][None] + radius[:, None])
        crossed = jnp.stack([crossed_x, crossed_y], axis=1)  # [N, 2, B]
        position = jnp.where(crossed, jnp.stack([face_x, face_y], axis=1), position)
        velocity = jnp.where(crossed, 0.0, velocity)
        return position, velocity

    def hazard_force(self, hazard, position, radius, noise, physics, memory=None):
        """Contact with the obstacle; a robot inside is pushed back out the way it came."""
        return rectangle_contact_force(
            position, radius, hazard.centre, hazard.half_extent, physics, entry=memory
        )

    def in_danger(self, hazard, position, radius):
        return self.touching(hazard, position, radius)

    def reached(self, hazard, position, layout):
        far_side = hazard.centre[0] + hazard.half_extent[0]  # [B]
        return position[:, 0] > far_side[None]

    def hazard_features(self, hazard, position, radius):
        return self.touching(hazard, position, radius)[:, None].astype(jnp.float32)
