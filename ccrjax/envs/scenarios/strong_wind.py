"""Emergency 2, strong wind: a square area on the way where a steady force blows across.

Paper: "A square strong wind area with random sizes will appear on their way and
apply force with a fixed direction. Coordinates of the strong wind area is only
observable for robots inside the area. The task is considered successful for each
robot that arrives at the other side of the strong wind area."

The wind blows across the way (along +y or -y, the side drawn per episode with
equal probability; the team travels along +x), with a force above a robot's full
actuation along one axis (5) by default, so a robot inside cannot hold its course
and is pushed off it; it is observable only inside the area. A wind along the way
would only speed robots up or slow them down, which is no emergency.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ccrjax.checks import check_number, check_range
from ccrjax.envs.scenarios.base import Hazard, Scenario, area_features
from ccrjax.envs.scenarios.layout import Layout, sample_centre


@dataclasses.dataclass(frozen=True)
class StrongWind(Scenario):
    """Square wind area of random side at a random place on the way, blowing across it."""

    name = "strong_wind"
    hazard_feature_size = 4

    side_range: tuple[float, float] = (1.2, 1.6)
    force: float = 10.0

    def __post_init__(self) -> None:
        check_range("StrongWind", "side_range", self.side_range, positive=True)
        check_number("StrongWind", "force", self.force, positive=False)

    def max_half_extent(self) -> tuple[float, float]:
        return (0.5 * float(self.side_range[1]),) * 2

    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        centre_key, side_key, sign_key = jax.random.split(key, 3)
        half = 0.5 * jax.random.uniform(
            side_key, (batch,), minval=self.side_range[0], maxval=self.side_range[1]
        )
        sign = jnp.where(jax.random.bernoulli(sign_key, 0.5, (batch,)), 1.0, -1.0)
        return Hazard(
            centre=sample_centre(centre_key, layout, batch),
            half_extent=jnp.stack([half, half]),
            direction=jnp.stack([jnp.zeros((batch,)), sign]),
        )

    def _inside(self, hazard: Hazard, position: jax.Array) -> jax.Array:
        inside_x = jnp.abs(position[:, 0] - hazard.centre[0][None]) < hazard.half_extent[0][None]
        inside_y = jnp.abs(position[:, 1] - hazard.centre[1][None]) < hazard.half_extent[1][None]
        return inside_x & inside_y

    def hazard_force(self, hazard, position, noise):
        wind = self.force * hazard.direction[None]  # [1, 2, B]
        return jnp.where(self._inside(hazard, position)[:, None], wind, 0.0)

    def in_danger(self, hazard, position, radius):
        return self._inside(hazard, position)

    def hazard_features(self, hazard, position, radius):
        return area_features(self._inside(hazard, position), position, hazard)
