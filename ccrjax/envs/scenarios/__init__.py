"""The emergency scenarios, one module each, and their registry by name (:data:`SCENARIOS`;
:func:`register_scenario` adds one defined elsewhere)."""

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


def register_scenario(cls: type[Scenario], *, replace: bool = False) -> type[Scenario]:
    """Registers a :class:`Scenario` subclass under its ``name`` (usable as a decorator);
    a name already taken is refused unless ``replace``."""
    if not (isinstance(cls, type) and issubclass(cls, Scenario)):
        raise ValueError(f"a scenario must be a Scenario subclass, got {cls!r}")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"scenario {cls.__name__} needs a class attribute name, an "
                         f"identifier; got {name!r}")
    old = SCENARIOS.get(name)
    same = old is not None and (old.__module__, old.__qualname__) == (cls.__module__,
                                                                      cls.__qualname__)
    if old is not None and not same and not replace:
        raise ValueError(f"scenario {name!r} is already registered (replace=True replaces it)")
    SCENARIOS[name] = cls
    return cls


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
    "register_scenario",
]
