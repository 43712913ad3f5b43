"""Emergency 2, strong wind: a square area on the way where a steady force blows.

Paper: "A square strong wind area with random sizes will appear on their way and
apply force with a fixed direction. Coordinates of the strong wind area is only
observable for robots inside the area. The task is considered successful for each
robot that arrives at the other side of the strong wind area."

The wind's direction is fixed within an episode. By default it is drawn uniformly
at random for every episode (``angle=None``); pass an angle in radians to fix it
for all episodes. Its strength, 4 by default, is 80% of a robot's full actuation
force (5): a robot can fight it, but not ignore it.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from ccrjax.scenarios.base import (
    Hazard,
    Layout,
    Scenario,
    area_features,
    check_positive,
    check_range,
    sample_centre,
)


@dataclasses.dataclass(frozen=True)
class StrongWind(Scenario):
    """Square wind area of random side at a random place on the way."""

    name = "strong_wind"
    hazard_feature_size = 4

    side_range: tuple[float, float] = (0.5, 1.0)
    force: float = 4.0
    angle: float | None = None

    def __post_init__(self) -> None:
        check_range("StrongWind", "side_range", self.side_range, positive=True)
        check_positive("StrongWind", "force", self.force, allow_zero=True)
        if self.angle is not None and not (
            isinstance(self.angle, int | float) and math.isfinite(self.angle)
        ):
            raise ValueError(f"StrongWind.angle must be None or finite radians, got {self.angle!r}")

    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        centre_key, side_key, angle_key = jax.random.split(key, 3)
        half = 0.5 * jax.random.uniform(
            side_key, (batch,), minval=self.side_range[0], maxval=self.side_range[1]
        )
        if self.angle is None:
            angle = jax.random.uniform(angle_key, (batch,), maxval=2.0 * math.pi)
        else:
            angle = jnp.full((batch,), self.angle, jnp.float32)
        return Hazard(
            centre=sample_centre(centre_key, layout, batch),
            half_extent=jnp.stack([half, half]),
            direction=jnp.stack([jnp.cos(angle), jnp.sin(angle)]),
        )

    def _inside(self, hazard: Hazard, position: jax.Array) -> jax.Array:
        inside_x = jnp.abs(position[:, 0] - hazard.centre[0][None]) < hazard.half_extent[0][None]
        inside_y = jnp.abs(position[:, 1] - hazard.centre[1][None]) < hazard.half_extent[1][None]
        return inside_x & inside_y

    def hazard_force(self, hazard, position, radius, noise, physics, memory=None):
        wind = self.force * hazard.direction[None]  # [1, 2, B]
        return jnp.where(self._inside(hazard, position)[:, None], wind, 0.0)

    def in_danger(self, hazard, position, radius):
        return self._inside(hazard, position)

    def reached(self, hazard, position, layout):
        far_side = hazard.centre[0] + hazard.half_extent[0]  # [B]
        return position[:, 0] > far_side[None]

    def hazard_features(self, hazard, position, radius):
        return area_features(self._inside(hazard, position), position, hazard)
