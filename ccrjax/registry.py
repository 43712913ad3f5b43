"""The three extension points: reward transforms (safety methods), learners and scenarios.

A method defined outside ccrjax registers here and then trains through
:func:`ccrjax.training.make_train`, ``python -m ccrjax.train --plugin MODULE`` and the
experiments, with nothing in ccrjax edited::

    from ccrjax.registry import register_learner, register_scenario, register_transform

    register_transform("my_method", MyMethod, option_prefix="my")   # a Transform dataclass
    register_scenario(MyScenario)                                    # a Scenario subclass
    register_learner("my_learner", MyLearnerConfig, MyLearner, default_budget=400_000)

A transform is a frozen dataclass implementing :class:`ccrjax.transforms.Transform`, built
with no arguments for its defaults; its instance holds the run's parameters and is written
to ``config.json`` as its fields. A learner is a frozen config dataclass and a function
building a :class:`ccrjax.agents.Learner` from it. A scenario is a frozen dataclass
subclass of :class:`ccrjax.envs.Scenario` with a ``name`` (its registry is
:data:`ccrjax.envs.scenarios.SCENARIOS`). With ``option_prefix``, the command line gets an
option ``--<prefix>-<field>`` for each of the dataclass's fields.

The built-in methods are registered the same way, at the end of this module.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from ccrjax.agents.ddpg import DDPG, DDPGConfig
from ccrjax.agents.maac import MAAC, MAACConfig
from ccrjax.agents.ppo import PPO, PPOConfig
from ccrjax.agents.types import Learner
from ccrjax.envs.scenarios import SCENARIOS, make_scenario, register_scenario
from ccrjax.transforms.base import Pessimistic, Plain
from ccrjax.transforms.ccr import (
    CCR,
    CCRConfig,
    CCRPerfect,
    CCRReward,
    CCRScores,
    DangerFlags,
)
from ccrjax.transforms.lagrangian import Lagrangian


@dataclasses.dataclass(frozen=True)
class TransformEntry:
    """A registered transform: its class (whose instance is the run's parameters), how a
    ``config.json`` record becomes one, and the prefix of its command-line options."""

    name: str
    type: type
    from_record: Callable[[dict[str, Any]], Any]
    option_prefix: str | None = None
    # The transform of a run that names none, from the run's TrainConfig (None: type()).
    defaults: Callable[[Any], Any] | None = None


@dataclasses.dataclass(frozen=True)
class LearnerEntry:
    """A registered learner: its config class, the function that builds it, the budget a
    run takes when none is given, whether it acts in a discrete action set (the config's
    ``action_set``), a function completing its config for this name (MADDPG: a centralised
    critic), the prefix of its command-line options, whether it learns on-policy (its
    ``update`` takes each iteration's rollout, not replayed batches: IPPO, MAPPO), and the
    training environments per seed of a run that names none."""

    name: str
    config_type: type
    build: Callable[[Any], Learner]
    default_budget: int
    discrete_actions: bool = False
    configure: Callable[[Any], Any] | None = None
    option_prefix: str | None = None
    on_policy: bool = False
    default_num_envs: int = 8


_TRANSFORMS: dict[str, TransformEntry] = {}
_LEARNERS: dict[str, LearnerEntry] = {}


def same_definition(a: type, b: type) -> bool:
    """Whether two classes are one definition (the same module and name): a module imported
    again (a notebook's reload, a plugin file loaded twice) registers again quietly."""
    return (a.__module__, a.__qualname__) == (b.__module__, b.__qualname__)


def _check_new(kind: str, name: Any, old: type | None, cls: type, replace: bool) -> None:
    """Refuses a name that is not an identifier, or one registered (as ``old``) by another
    definition than ``cls`` unless ``replace``."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"a {kind}'s name must be an identifier, got {name!r}")
    if old is not None and not replace and not same_definition(old, cls):
        raise ValueError(f"{kind} {name!r} is already registered (replace=True replaces it)")


def _check_dataclass(kind: str, name: str, cls: Any) -> None:
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ValueError(f"{kind} {name!r} must be registered with a dataclass type, "
                         f"got {cls!r}")


def register_transform(name: str, transform_type: type, *,
                       from_record: Callable[[dict[str, Any]], Any] | None = None,
                       option_prefix: str | None = None,
                       defaults: Callable[[Any], Any] | None = None,
                       replace: bool = False) -> type:
    """Registers ``transform_type`` as variant ``name``; ``from_record`` rebuilds it from its
    ``config.json`` fields (default: ``transform_type(**fields)``); ``defaults(config)`` is
    the transform of a run that names none (default: ``transform_type()``). Returns the
    type."""
    old = _TRANSFORMS[name].type if isinstance(name, str) and name in _TRANSFORMS else None
    _check_new("transform", name, old, transform_type, replace)
    _check_dataclass("transform", name, transform_type)
    _TRANSFORMS[name] = TransformEntry(
        name, transform_type, from_record or (lambda fields: transform_type(**fields)),
        option_prefix, defaults)
    return transform_type


def register_learner(name: str, config_type: type, build: Callable[[Any], Learner], *,
                     default_budget: int, discrete_actions: bool = False,
                     configure: Callable[[Any], Any] | None = None,
                     option_prefix: str | None = None, on_policy: bool = False,
                     default_num_envs: int = 8, replace: bool = False) -> None:
    """Registers learner ``name``: ``build(config)`` makes it from a ``config_type``."""
    old = _LEARNERS[name].config_type if isinstance(name, str) and name in _LEARNERS else None
    _check_new("learner", name, old, config_type, replace)
    _check_dataclass("learner", name, config_type)
    if not isinstance(default_budget, int) or default_budget < 1:
        raise ValueError(f"learner {name!r}: default_budget must be a positive int, "
                         f"got {default_budget!r}")
    if not isinstance(default_num_envs, int) or default_num_envs < 1:
        raise ValueError(f"learner {name!r}: default_num_envs must be a positive int, "
                         f"got {default_num_envs!r}")
    _LEARNERS[name] = LearnerEntry(name, config_type, build, default_budget,
                                   discrete_actions, configure, option_prefix, on_policy,
                                   default_num_envs)


def transform_entry(name: str) -> TransformEntry:
    """The transform registered as ``name``; unknown names raise ``ValueError``."""
    if name not in _TRANSFORMS:
        raise ValueError(f"variant must be one of {list(_TRANSFORMS)}, got {name!r}")
    return _TRANSFORMS[name]


def learner_entry(name: str) -> LearnerEntry:
    """The learner registered as ``name``; unknown names raise ``ValueError``."""
    if name not in _LEARNERS:
        raise ValueError(f"algo must be one of {list(_LEARNERS)}, got {name!r}")
    return _LEARNERS[name]


def transform_names() -> tuple[str, ...]:
    """Every registered variant, the built-in ones first."""
    return tuple(_TRANSFORMS)


def learner_names() -> tuple[str, ...]:
    """Every registered learner, the built-in ones first."""
    return tuple(_LEARNERS)


def scenario_names() -> tuple[str, ...]:
    """Every registered scenario, the built-in ones first."""
    return tuple(SCENARIOS)


def _ccr_family(cls: type) -> Callable[[dict[str, Any]], Any]:
    """CCR and its parts are written as the fields of their :class:`CCRConfig`."""
    return lambda fields: cls(CCRConfig(**fields.get("config", {})))


def _centralised(centralised: bool) -> Callable[[Any], Any]:
    """Completes a DDPG or PPO config for its name: the critic centralised or not."""
    return lambda config: dataclasses.replace(config, centralised_critic=centralised)


# The built-in methods. Default budgets: what each learner needs to solve `nominal`
# (success >= 90%, experiments/sanity.py); MAAC makes 4 heavier updates per 100 steps.
register_transform("plain", Plain)
register_transform("pessimistic", Pessimistic)
for _name, _cls in (("ccr", CCR), ("ccr_scores", CCRScores), ("ccr_reward", CCRReward),
                    ("ccr_perfect", CCRPerfect)):
    register_transform(_name, _cls, from_record=_ccr_family(_cls))
register_transform("danger_flags", DangerFlags)
register_transform("lagrangian", Lagrangian, option_prefix="lagrange",
                   defaults=Lagrangian.for_run)
register_learner("iddpg", DDPGConfig, DDPG, default_budget=400_000,
                 configure=_centralised(False), option_prefix="ddpg")
register_learner("maddpg", DDPGConfig, DDPG, default_budget=400_000,
                 configure=_centralised(True), option_prefix="ddpg")
register_learner("maac", MAACConfig, MAAC, default_budget=200_000, discrete_actions=True,
                 option_prefix="maac")
# IPPO and MAPPO: many training environments per seed, as on-policy learning wants; 160
# makes a rollout (one episode of each) 4,000 steps, which divides the evaluation intervals
# (20k by default, the protocol's 100k). On `nominal` both pass 96% success from 200k steps on
# 3 seeds and 99% by 400k (sanity.py).
PPO_NUM_ENVS = 160
for _name, _centralised_value in (("ippo", False), ("mappo", True)):
    register_learner(_name, PPOConfig, PPO, default_budget=300_000,
                     configure=_centralised(_centralised_value), option_prefix="ppo",
                     on_policy=True, default_num_envs=PPO_NUM_ENVS)

__all__ = ["LearnerEntry", "TransformEntry", "learner_entry", "learner_names",
           "make_scenario", "register_learner", "register_scenario", "register_transform",
           "scenario_names", "transform_entry", "transform_names"]
