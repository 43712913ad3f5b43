"""Emergency 1, turbulence: a circular area on the way shakes robots at random.

Paper: "A circular turbulence area will appear on their way and apply forces with
random directions on them. Coordinates of the turbulence area is only observable
for robots inside the area. The task is considered successful for each robot that
arrives in the target area."

Each step, each robot whose centre is inside the area receives a force of
uniformly random direction and uniformly random magnitude in ``[0, max_force]``,
drawn fresh. The area is large (radius 0.9 to 1.0 by default, on a 3-unit trip) so
that a robot crossing it spends a large share of its trip inside, as the paper's
plain learners do (about half their steps in danger); ``experiments/calibrate.py``
shows the defaults' effect on reference controllers.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ccrjax.checks import check_number, check_range
from ccrjax.envs.scenarios.base import (
    Hazard,
    Scenario,
    area_features,
    distance_to_centre,
    hashed_bits,
    unit_vector,
)
from ccrjax.envs.scenarios.layout import Layout, sample_centre


@dataclasses.dataclass(frozen=True)
class Turbulence(Scenario):
    """Circular turbulence area of random radius at a random place on the way."""

    name = "turbulence"
    hazard_feature_size = 4
    needs_step_noise = True

    radius_range: tuple[float, float] = (0.9, 1.0)
    max_force: float = 10.0

    def __post_init__(self) -> None:
        check_range("Turbulence", "radius_range", self.radius_range, positive=True)
        check_number("Turbulence", "max_force", self.max_force, positive=False)

    def max_half_extent(self) -> tuple[float, float]:
        return (float(self.radius_range[1]),) * 2

    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        centre_key, radius_key = jax.random.split(key)
        radius = jax.random.uniform(
            radius_key, (batch,), minval=self.radius_range[0], maxval=self.radius_range[1]
        )
        return Hazard(
            centre=sample_centre(centre_key, layout, batch),
            half_extent=jnp.stack([radius, radius]),
            direction=jnp.zeros((2, batch)),
        )

    def step_noise(self, key: jax.Array, num_robots: int, batch: int) -> jax.Array:
        """``float32[N, 2, B]``: a direction and a magnitude fraction in ``[0, 1)`` per robot.

        Both come from one 32-bit word per robot (16 bits each, 65536 levels). The
        words come from :func:`hashed_bits`, seeded by one draw from ``key``: JAX's
        threefry on every word cost a sixth of a whole step on CPU.
        """
        bits = hashed_bits(key, (num_robots, batch))
        high = (bits >> 16).astype(jnp.float32)
        low = (bits & 0xFFFF).astype(jnp.float32)
        return jnp.stack([high, low], axis=1) * (1.0 / 65536.0)

    def _inside(self, hazard: Hazard, position: jax.Array) -> jax.Array:
        return distance_to_centre(position, hazard) < hazard.half_extent[None, 0]

    def hazard_force(self, hazard, position, noise):
        magnitude = self.max_force * noise[:, 1]
        force = magnitude[:, None] * unit_vector(noise[:, 0])
        return jnp.where(self._inside(hazard, position)[:, None], force, 0.0)

    def in_danger(self, hazard, position, radius):
        return self._inside(hazard, position)

    def hazard_features(self, hazard, position, radius):
        return area_features(self._inside(hazard, position), position, hazard)
