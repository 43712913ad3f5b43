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
way. That alone does not stop a disc that moves more than the whole thickness in
one step: robots piling into the wall bounce off each other at up to about 4 units/s
(0.4 per step), which carried some through a 0.4-thick wall and none through 0.6,
hence the default; ``tests/test_scenarios.py`` drives robots into it at full speed
to check.
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
