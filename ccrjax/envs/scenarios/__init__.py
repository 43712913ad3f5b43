"""The emergency scenarios, one module each, and a registry by name."""

from __future__ import annotations

from typing import Any

from ccrjax.envs.scenarios.base import Hazard, Scenario
from ccrjax.envs.scenarios.hidden_obstacle import HiddenObstacle
from ccrjax.envs.scenarios.layout import Layout
from ccrjax.envs.scenarios.nominal import Nominal
from ccrjax.envs.scenarios.strong_wind import StrongWind
from ccrjax.envs.scenarios.turbulence import Turbulence

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls for cls in (Turbulence, StrongWind, HiddenObstacle, Nominal)
}


def make_scenario(name: str, **params: Any) -> Scenario:
    """Builds a scenario by name; unknown names and parameters raise ``ValueError``."""
    if name not in SCENARIOS:
        raise ValueError(f"scenario must be one of {sorted(SCENARIOS)}, got {name!r}")
    try:
        return SCENARIOS[name](**params)
    except TypeError as error:
        raise ValueError(f"bad parameters for scenario {name!r}: {error}") from None


__all__ = [
    "SCENARIOS",
    "Hazard",
    "HiddenObstacle",
    "Layout",
    "Nominal",
    "Scenario",
    "StrongWind",
    "Turbulence",
    "make_scenario",
]
