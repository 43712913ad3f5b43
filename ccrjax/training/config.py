"""A training run's configuration (:class:`TrainConfig`) and the pieces it builds.

:class:`TrainConfig` holds everything that defines the training run of one seed; it is
validated once, when built. :func:`make_env`, :func:`make_learner` and
:func:`make_transform` build the environment, the learner and the reward transform it
names; :func:`config_to_dict` and :func:`config_from_dict` write and read it as JSON.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from ccrjax.agents import ALGOS
from ccrjax.agents.ddpg import DDPG, DDPGConfig
from ccrjax.agents.maac import MAAC, MAACConfig
from ccrjax.agents.replay import replay_capacity
from ccrjax.agents.types import Learner
from ccrjax.checks import check_positive_int
from ccrjax.envs.env import CCREnv
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.transforms import VARIANTS, Pessimistic, Plain, Transform
from ccrjax.transforms.ccr import CCR, CCRConfig

# Learning starts after this many transitions per seed, whatever the learner and episode
# length: the original MADDPG's 1024 x 25 (its batch size times its episode length).
LEARNING_STARTS = 25_600
# Default environment steps per seed: what each learner needs to solve `nominal` (success
# >= 90%, experiments/sanity.py). MAAC makes 4 heavier updates per 100 steps, DDPG one.
DEFAULT_BUDGET = {"iddpg": 400_000, "maddpg": 400_000, "maac": 200_000}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run of one seed.

    Sizes the paper leaves open are chosen here and documented in the README:
    8 training environments per seed, episodes of 25 steps (the MPE's), and the environment-step
    budget ``total_env_steps`` per seed (every environment step of every training
    environment counts).
    """

    algo: str = "maddpg"
    scenario: str = "nominal"
    variant: str = "plain"
    penalty: float = 1.0  # pessimistic baseline: reward lowered on danger steps
    ccr: CCRConfig = CCRConfig()  # CCR's hyperparameters (variant "ccr")
    num_robots: int = 5
    episode_length: int = 25
    num_envs: int = 8
    total_env_steps: int | None = None  # None: DEFAULT_BUDGET[algo]
    eval_every: int = 20_000  # environment steps between evaluations
    eval_episodes: int = 64
    learning_starts: int = LEARNING_STARTS  # transitions per seed before the first update
    scenario_params: dict[str, Any] = dataclasses.field(default_factory=dict)
    ddpg: DDPGConfig = DDPGConfig()
    maac: Any = None  # MAACConfig; None = its defaults

    def __post_init__(self) -> None:
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {list(ALGOS)}, got {self.algo!r}")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {sorted(SCENARIOS)}, got {self.scenario!r}")
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {list(VARIANTS)}, got {self.variant!r}")
        if self.total_env_steps is None and self.algo in ALGOS:
            object.__setattr__(self, "total_env_steps", DEFAULT_BUDGET[self.algo])
        for name in ("num_envs", "total_env_steps", "eval_every", "eval_episodes"):
            check_positive_int("TrainConfig", name, getattr(self, name))
        if isinstance(self.learning_starts, bool) or not isinstance(
            self.learning_starts, int
        ) or self.learning_starts < 0:
            raise ValueError(
                f"TrainConfig.learning_starts must be an integer >= 0, "
                f"got {self.learning_starts!r}"
            )
        if self.maac is None and self.algo == "maac":
            object.__setattr__(self, "maac", MAACConfig())
        Pessimistic(penalty=self.penalty)  # validates the penalty whatever the variant
        if not isinstance(self.ccr, CCRConfig):
            raise ValueError(f"TrainConfig.ccr must be a CCRConfig, got {self.ccr!r}")
        # Building the pieces validates the rest (env sizes, penalty, learner fields).
        make_transform(self)
        make_env(self, self.num_envs)
        if self.total_env_steps < self.min_total_env_steps:
            raise ValueError(
                f"total_env_steps (--steps) {self.total_env_steps:,} ends before learning "
                f"starts: at least {self.min_total_env_steps:,} environment steps are needed "
                f"(learning_starts {self.learning_starts:,} transitions, collected "
                f"{self.steps_per_iteration:,} per iteration)"
            )

    @property
    def learner_config(self) -> Any:
        return self.maac if self.algo == "maac" else self.ddpg

    @property
    def steps_per_iteration(self) -> int:
        """Environment steps of one iteration: one episode of every training env."""
        return self.num_envs * self.episode_length

    @property
    def iterations_per_eval(self) -> int:
        return max(1, round(self.eval_every / self.steps_per_iteration))

    @property
    def num_iterations(self) -> int:
        """Iterations of the run: ``total_env_steps`` rounded up to whole evaluation intervals
        (one compiled chunk of iterations serves the whole run)."""
        iterations = math.ceil(self.total_env_steps / self.steps_per_iteration)
        return self.iterations_per_eval * math.ceil(iterations / self.iterations_per_eval)

    @property
    def eval_every_run(self) -> int:
        """The evaluation interval that runs: ``eval_every`` in whole iterations."""
        return self.iterations_per_eval * self.steps_per_iteration

    @property
    def total_env_steps_run(self) -> int:
        """The budget that runs: ``total_env_steps`` in whole evaluation intervals."""
        return self.num_iterations * self.steps_per_iteration

    def schedule(self) -> dict[str, Any]:
        """What was asked and what runs, and why they differ (empty ``notes`` if not)."""
        notes = []
        if self.eval_every_run != self.eval_every:
            notes.append(f"--eval-every {self.eval_every:,} runs as {self.eval_every_run:,} "
                         f"environment steps: whole iterations of {self.steps_per_iteration:,} "
                         "(num_envs x episode_length)")
        if self.total_env_steps_run != self.total_env_steps:
            notes.append(f"--steps {self.total_env_steps:,} runs as "
                         f"{self.total_env_steps_run:,} environment steps per seed: whole "
                         f"evaluation intervals of {self.eval_every_run:,}")
        return {"requested": {"total_env_steps": self.total_env_steps,
                              "eval_every": self.eval_every},
                "ran": {"total_env_steps": self.total_env_steps_run,
                        "eval_every": self.eval_every_run},
                "notes": notes}

    @property
    def updates_per_iteration(self) -> int:
        """``gradient_steps`` updates every ``update_every`` environment steps (at least 1)."""
        learner = self.learner_config
        return max(
            1, round(self.steps_per_iteration * learner.gradient_steps / learner.update_every)
        )

    @property
    def replay_capacity(self) -> int:
        """The learner's buffer size, a multiple of one iteration's transitions, and no
        larger than all the transitions the run will ever collect."""
        collected = self.num_iterations * self.steps_per_iteration
        wanted = min(self.learner_config.buffer_size, collected)
        return replay_capacity(wanted, self.steps_per_iteration)

    @property
    def learning_starts_transitions(self) -> int:
        return self.learning_starts

    @property
    def min_total_env_steps(self) -> int:
        """The smallest budget that reaches the first learning iteration: the first whole
        iteration after which the buffer holds ``learning_starts`` transitions."""
        first = max(1, math.ceil(self.learning_starts / self.steps_per_iteration))
        return first * self.steps_per_iteration


def _nested_config_types() -> dict[str, type]:
    """The fields of :class:`TrainConfig` that hold a configuration dataclass, and its type."""
    types: dict[str, type] = {"maac": MAACConfig}
    for field in dataclasses.fields(TrainConfig):
        default = field.default
        if default is dataclasses.MISSING and field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        if dataclasses.is_dataclass(default):
            types[field.name] = type(default)
    return types


def config_to_dict(config: TrainConfig) -> dict[str, Any]:
    """Every field of ``config``, nested configurations included, as JSON-ready values."""
    return dataclasses.asdict(config)


def _tuples(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """The inverse of :func:`config_to_dict` (JSON lists become tuples); validates."""
    nested = _nested_config_types()
    names = {field.name for field in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown TrainConfig field(s) {unknown}")
    values = {}
    for name, value in data.items():
        value = _tuples(value)
        if name in nested and isinstance(value, dict):
            value = nested[name](**value)
        values[name] = value
    return TrainConfig(**values)


def make_env(config: TrainConfig, num_envs: int) -> CCREnv:
    return CCREnv(
        config.scenario,
        num_robots=config.num_robots,
        num_envs=num_envs,
        episode_length=config.episode_length,
        discrete_actions=config.algo == "maac",
        scenario_params=dict(config.scenario_params),
    )


def make_learner(config: TrainConfig) -> Learner:
    if config.algo == "iddpg":
        return DDPG(dataclasses.replace(config.ddpg, centralised_critic=False))
    if config.algo == "maddpg":
        return DDPG(dataclasses.replace(config.ddpg, centralised_critic=True))
    return MAAC(config.maac)


def make_transform(config: TrainConfig) -> Transform:
    if config.variant == "plain":
        return Plain()
    if config.variant == "pessimistic":
        return Pessimistic(penalty=config.penalty)
    return CCR(config.ccr)
