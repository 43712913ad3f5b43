"""Emergency 3, hidden obstacle: a solid rectangle on the way that robots cannot see.

Paper: "A rectangular solid obstacle with random lengths is located on their way.
Robots can only sense whether they are in collision with the obstacle, but not the
coordinates of the obstacle. The task is considered successful for each robot that
arrives at the other side of the obstacle."

The obstacle is an axis-aligned rectangle across the way: ``thickness`` along the
direction of travel (x, fixed, 0.4 by default) and a random ``length`` across it
(y, uniform in ``length_range``). Robots collide with it through the MPE's soft
contact law (:func:`ccrjax.world.rectangle_contact_force`). The default thickness
is what keeps a robot at full speed (about 0.2 per step) from tunnelling through
the soft wall; ``tests/test_scenarios.py`` pushes robots into it to check.
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
from ccrjax.world import rectangle_contact_force, rectangle_signed_distance


@dataclasses.dataclass(frozen=True)
class HiddenObstacle(Scenario):
    """Solid rectangle of random length across the way."""

    name = "hidden_obstacle"
    hazard_feature_size = 1

    thickness: float = 0.4
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
        distance, _ = rectangle_signed_distance(position, hazard.centre, hazard.half_extent)
        return distance < radius[:, None]

    def hazard_force(self, hazard, position, radius, noise, physics):
        return rectangle_contact_force(
            position, radius, hazard.centre, hazard.half_extent, physics
        )

    def in_danger(self, hazard, position, radius):
        return self.touching(hazard, position, radius)

    def reached(self, hazard, position, layout):
        far_side = hazard.centre[0] + hazard.half_extent[0]  # [B]
        return position[:, 0] > far_side[None]

    def hazard_features(self, hazard, position, radius):
        return self.touching(hazard, position, radius)[:, None].astype(jnp.float32)
