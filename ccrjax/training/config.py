"""A training run's configuration (:class:`TrainConfig`) and the pieces it builds.

:class:`TrainConfig` holds everything that defines the training run of one seed; it is
validated once, when built, without building anything. :func:`make_env`, :func:`make_learner`
and :func:`make_transform` build the environment, the learner and the reward transform it
names; :func:`config_to_dict` and :func:`config_from_dict` write and read it as JSON.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from ccrjax.agents.replay import replay_capacity
from ccrjax.agents.types import Learner
from ccrjax.checks import check_int, check_positive_int
from ccrjax.envs.env import EmergencyEnv, check_team
from ccrjax.envs.scenarios import SCENARIOS, Layout, make_scenario
from ccrjax.envs.world import DEFAULT_DISCRETE_ACTION_SET
from ccrjax.registry import learner_entry, learner_names, transform_entry
from ccrjax.transforms import Transform

# Learning starts after this many transitions per seed, whatever the learner and episode
# length: the original MADDPG's 1024 x 25 (its batch size times its episode length).
LEARNING_STARTS = 25_600


def default_budgets() -> dict[str, int]:
    """Environment steps per seed of a run that names none, by learner (the registry's)."""
    return {name: learner_entry(name).default_budget for name in learner_names()}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run of one seed.

    ``algo`` and ``variant`` name the learner and the transform; ``learner`` and
    ``transform`` hold their parameters (``None``: that learner's or variant's defaults,
    :attr:`resolved_learner` and :attr:`resolved_transform`). Sizes the paper leaves open are
    chosen here and documented in the README: 8 training environments per seed (IPPO and MAPPO
    160: :attr:`num_envs`), episodes of
    25 steps (the MPE's), and the environment-step budget per seed (:attr:`budget`; every
    environment step of every training environment counts). Validated when built, without
    building an environment; nothing is rewritten.
    """

    algo: str = "maddpg"  # learner: iddpg, maddpg, maac, or one registered (ccrjax.registry)
    scenario: str = "nominal"  # emergency scenario, built in or registered
    variant: str = "plain"  # plain, pessimistic, ccr, one of ccr's parts, or one registered
    # The variant's transform and its parameters: Plain(), Pessimistic(penalty),
    # CCR(CCRConfig) (and its parts CCRScores, CCRReward, CCRPerfect), or
    # DangerFlags(comm_range), or a registered transform; None: the variant's defaults.
    transform: Transform | None = None
    # The learner's hyperparameters: a DDPGConfig (iddpg, maddpg), a MAACConfig (maac), or
    # a registered learner's config; None: the learner's defaults.
    learner: Any = None
    num_robots: int = 5  # team size
    episode_length: int = 25  # steps per episode
    # training environments per seed; None: the learner's default (8; IPPO and MAPPO 160),
    # filled in when the configuration is built, so the field always holds a number.
    num_envs: int | None = None
    total_env_steps: int | None = None  # environment steps per seed; None: the learner's default
    eval_every: int = 20_000  # environment steps per seed between evaluations
    eval_episodes: int = 64  # fresh episodes per evaluation and seed
    learning_starts: int = LEARNING_STARTS  # transitions per seed before the first update
    scenario_params: dict[str, Any] = dataclasses.field(default_factory=dict)
    # Layout fields that differ from ccrjax.envs.scenarios.Layout's defaults: the hazard
    # placement (hazard_x_range, hazard_y_range) and the team formation (formation,
    # column_spacing, column_lateral), the two knobs of a regime; {}: today's layout.
    layout_params: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        learner_type = learner_entry(self.algo).config_type  # unknown names: ValueError
        if self.num_envs is None:
            object.__setattr__(self, "num_envs", learner_entry(self.algo).default_num_envs)
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {list(SCENARIOS)}, got {self.scenario!r}")
        transform_type = transform_entry(self.variant).type
        if self.transform is not None and type(self.transform) is not transform_type:
            raise ValueError(f"TrainConfig.transform of variant {self.variant!r} must be a "
                             f"{transform_type.__name__} or None, got {self.transform!r}")
        if self.learner is not None and type(self.learner) is not learner_type:
            raise ValueError(f"TrainConfig.learner of algo {self.algo!r} must be a "
                             f"{learner_type.__name__} or None, got {self.learner!r}")
        if self.total_env_steps is not None:
            check_positive_int("TrainConfig", "total_env_steps", self.total_env_steps)
        for name in ("num_envs", "eval_every", "eval_episodes"):
            check_positive_int("TrainConfig", name, getattr(self, name))
        check_int("TrainConfig", "learning_starts", self.learning_starts, 0)
        rollout_problem = getattr(self.resolved_learner, "rollout_problem", None)
        problem = rollout_problem and rollout_problem(self.num_envs, self.episode_length)
        if problem:  # an on-policy learner's minibatches must cut the rollout evenly
            raise ValueError(problem)
        scenario = make_scenario(self.scenario, **self.scenario_params)  # checks its params
        check_team(scenario, self.num_robots, self.episode_length, layout=self.layout)
        if self.budget < self.min_total_env_steps:
            why = ("one rollout of every training environment" if self.on_policy else
                   f"learning_starts {self.learning_starts:,} transitions")
            raise ValueError(
                f"total_env_steps (--steps) {self.budget:,} ends before learning "
                f"starts: at least {self.min_total_env_steps:,} environment steps are needed "
                f"({why}, collected {self.steps_per_iteration:,} per iteration)"
            )

    @property
    def layout(self) -> Layout:
        """The environment's layout: :class:`Layout`'s defaults with ``layout_params`` on top
        (lists, as JSON gives them, become pairs); unknown names raise ``ValueError``."""
        if not isinstance(self.layout_params, dict):
            raise ValueError(f"TrainConfig.layout_params must be a dict, got "
                             f"{self.layout_params!r}")
        unknown = sorted(set(self.layout_params) - {f.name for f in dataclasses.fields(Layout)})
        if unknown:
            raise ValueError(f"unknown layout parameter(s) {unknown}; Layout takes "
                             f"{[f.name for f in dataclasses.fields(Layout)]}")
        return Layout(**{name: tuple(value) if isinstance(value, list) else value
                         for name, value in self.layout_params.items()})

    @property
    def budget(self) -> int:
        """Environment steps per seed: ``total_env_steps``, or the learner's default."""
        if self.total_env_steps is None:
            return learner_entry(self.algo).default_budget
        return self.total_env_steps

    @property
    def resolved_transform(self) -> Transform:
        """The transform the run uses: ``transform``, or the variant's defaults for this run
        (its registry entry's ``defaults(config)``, else its type's defaults)."""
        if self.transform is not None:
            return self.transform
        entry = transform_entry(self.variant)
        return entry.type() if entry.defaults is None else entry.defaults(self)

    @property
    def resolved_learner(self) -> Any:
        """The learner's hyperparameters: ``learner``, or the learner's defaults, completed
        for the learner's name (iddpg's and maddpg's critic centralised or not as it says)."""
        entry = learner_entry(self.algo)
        config = entry.config_type() if self.learner is None else self.learner
        return config if entry.configure is None else entry.configure(config)

    @property
    def steps_per_iteration(self) -> int:
        """Environment steps of one iteration: one episode of every training env."""
        return self.num_envs * self.episode_length

    @property
    def iterations_per_eval(self) -> int:
        return max(1, round(self.eval_every / self.steps_per_iteration))

    @property
    def num_iterations(self) -> int:
        """Iterations of the run: :attr:`budget` rounded up to whole evaluation intervals
        (one compiled chunk of iterations serves the whole run)."""
        iterations = math.ceil(self.budget / self.steps_per_iteration)
        return self.iterations_per_eval * math.ceil(iterations / self.iterations_per_eval)

    @property
    def eval_every_run(self) -> int:
        """The evaluation interval that runs: ``eval_every`` in whole iterations."""
        return self.iterations_per_eval * self.steps_per_iteration

    @property
    def total_env_steps_run(self) -> int:
        """The budget that runs: :attr:`budget` in whole evaluation intervals."""
        return self.num_iterations * self.steps_per_iteration

    def schedule(self) -> dict[str, Any]:
        """What was asked and what runs, and why they differ (empty ``notes`` if not)."""
        notes = []
        if self.eval_every_run != self.eval_every:
            notes.append(f"--eval-every {self.eval_every:,} runs as {self.eval_every_run:,} "
                         f"environment steps: whole iterations of {self.steps_per_iteration:,} "
                         "(num_envs x episode_length)")
        if self.total_env_steps_run != self.budget:
            notes.append(f"--steps {self.budget:,} runs as "
                         f"{self.total_env_steps_run:,} environment steps per seed: whole "
                         f"evaluation intervals of {self.eval_every_run:,}")
        return {"requested": {"total_env_steps": self.budget,
                              "eval_every": self.eval_every},
                "ran": {"total_env_steps": self.total_env_steps_run,
                        "eval_every": self.eval_every_run},
                "notes": notes}

    @property
    def on_policy(self) -> bool:
        """Whether the learner learns from each iteration's rollout (IPPO, MAPPO) instead
        of a replay buffer."""
        return learner_entry(self.algo).on_policy

    @property
    def updates_per_iteration(self) -> int:
        """``gradient_steps`` updates every ``update_every`` environment steps (at least 1);
        an on-policy learner's one update per rollout (its epochs are inside it)."""
        if self.on_policy:
            return 1
        learner = self.resolved_learner
        return max(
            1, round(self.steps_per_iteration * learner.gradient_steps / learner.update_every)
        )

    @property
    def replay_capacity(self) -> int:
        """The learner's buffer size, a multiple of one iteration's transitions, and no
        larger than all the transitions the run will ever collect; an on-policy learner
        replays nothing (one episode's slot keeps the training state's structure)."""
        if self.on_policy:
            return self.episode_length
        collected = self.num_iterations * self.steps_per_iteration
        wanted = min(self.resolved_learner.buffer_size, collected)
        return replay_capacity(wanted, self.steps_per_iteration)

    @property
    def learning_starts_transitions(self) -> int:
        """Transitions collected before the first update: ``learning_starts``; 0 for an
        on-policy learner, which learns from its first rollout."""
        return 0 if self.on_policy else self.learning_starts

    @property
    def min_total_env_steps(self) -> int:
        """The smallest budget that reaches the first learning iteration: the first whole
        iteration after which the buffer holds ``learning_starts`` transitions."""
        first = max(1, math.ceil(self.learning_starts_transitions / self.steps_per_iteration))
        return first * self.steps_per_iteration


def config_to_dict(config: TrainConfig) -> dict[str, Any]:
    """Every field of ``config``, nested configurations included, as JSON-ready values
    (``transform`` and ``learner`` as the fields of their dataclass, or ``None``).
    ``layout_params`` is written only when it holds something, so that a run of today's
    layout has the record (and checkpoint fingerprint) it had before layouts were options."""
    record = dataclasses.asdict(config)
    if not record["layout_params"]:
        del record["layout_params"]
    return record


def _tuples(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """The inverse of :func:`config_to_dict` (JSON lists become tuples); validates."""
    names = {field.name for field in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown TrainConfig field(s) {unknown}")
    values = {name: _tuples(value) for name, value in data.items()}
    variant, algo = values.get("variant", "plain"), values.get("algo", "maddpg")
    if isinstance(values.get("transform"), dict):
        values["transform"] = transform_entry(variant).from_record(values["transform"])
    if isinstance(values.get("learner"), dict):
        values["learner"] = learner_entry(algo).config_type(**values["learner"])
    return TrainConfig(**values)


def make_env(config: TrainConfig, num_envs: int) -> EmergencyEnv:
    """``num_envs`` environments of the run's scenario, team, episode length and layout, in
    the learner's action space (a discrete learner's ``action_set``, if its config has one)."""
    discrete = (learner_entry(config.algo).discrete_actions
                or getattr(config.resolved_learner, "discrete", False))
    return EmergencyEnv(
        config.scenario,
        num_robots=config.num_robots,
        num_envs=num_envs,
        episode_length=config.episode_length,
        discrete_actions=discrete,
        discrete_action_set=(getattr(config.resolved_learner, "action_set",
                                     DEFAULT_DISCRETE_ACTION_SET)
                             if discrete else DEFAULT_DISCRETE_ACTION_SET),
        scenario_params=dict(config.scenario_params),
        layout=config.layout,
    )


def make_learner(config: TrainConfig) -> Learner:
    """The run's learner, built by its registry entry from :attr:`TrainConfig.resolved_learner`."""
    return learner_entry(config.algo).build(config.resolved_learner)


def make_transform(config: TrainConfig) -> Transform:
    """The run's transform: :attr:`TrainConfig.resolved_transform`."""
    return config.resolved_transform
