"""A scenario defined outside ccrjax, for tests/test_registry.py: a square that nobody sees
or feels, where every step is dangerous. Loaded with ``--plugin tests/plugins/dead_zone.py``."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ccrjax.envs.scenarios import Hazard, Scenario
from ccrjax.envs.scenarios.layout import sample_centre
from ccrjax.registry import register_scenario


@register_scenario
@dataclasses.dataclass(frozen=True)
class DeadZone(Scenario):
    """A hidden square of side ``2 * half_size``, dangerous inside, with no force."""

    half_size: float = 0.2  # half the square's side
    name = "dead_zone"
    hazard_feature_size = 0

    def max_half_extent(self) -> tuple[float, float]:
        return (self.half_size, self.half_size)

    def sample_hazard(self, key, layout, batch):
        return Hazard(centre=sample_centre(key, layout, batch),
                      half_extent=jnp.full((2, batch), self.half_size),
                      direction=jnp.zeros((2, batch)))

    def in_danger(self, hazard, position, radius):
        inside = jnp.abs(position - hazard.centre[None]) <= hazard.half_extent[None]
        return inside.all(axis=1)

    def hazard_features(self, hazard, position, radius):
        return jnp.zeros((position.shape[0], 0, position.shape[2]), jnp.float32)
