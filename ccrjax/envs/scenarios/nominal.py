"""The task with no hazard: for calibrating dynamics models and checking that learners learn.

A *virtual* hazard centre is still drawn exactly as in the other scenarios, so
that the paper's "average distance to the hazard centre" stays comparable; it
exerts no force, is never observed and is never dangerous.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ccrjax.envs.scenarios.base import Hazard, Scenario
from ccrjax.envs.scenarios.layout import Layout, sample_centre


@dataclasses.dataclass(frozen=True)
class Nominal(Scenario):
    """No hazard at all."""

    name = "nominal"
    hazard_feature_size = 0

    def max_half_extent(self) -> tuple[float, float]:
        return (0.0, 0.0)

    def sample_hazard(self, key: jax.Array, layout: Layout, batch: int) -> Hazard:
        return Hazard(
            centre=sample_centre(key, layout, batch),
            half_extent=jnp.zeros((2, batch)),
            direction=jnp.zeros((2, batch)),
        )

    def in_danger(self, hazard, position, radius):
        return jnp.zeros(position[:, 0].shape, bool)

    def hazard_features(self, hazard, position, radius):
        return jnp.zeros((position.shape[0], 0, position.shape[2]), jnp.float32)
