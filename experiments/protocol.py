"""The experimental protocol of the tables and the searches, in one place (docs/protocol.md).

Fixed before any search or table run: the seeds of each purpose (disjoint), the budgets
(chosen on the plain learners only), the searched values, the selection rule, and the
evaluation settings. ``experiments/search.py`` and ``experiments/tables.py`` read them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.agents.maac import MAACConfig
from ccrjax.agents.ppo import PPOConfig
from ccrjax.training import ALGOS, TrainConfig
from experiments.paper import PAPER_SCENARIOS
from experiments.selection import SelectionRule

# Seeds: the tables' seeds never select a hyperparameter and never choose a budget.
TABLE_SEEDS = tuple(range(0, 10))
SELECTION_SEEDS = (100, 101, 102)
BUDGET_SEED_OFFSET = 200  # experiments/budgets.py
BUDGET_SEEDS = tuple(range(BUDGET_SEED_OFFSET, BUDGET_SEED_OFFSET + 3))
# The on-policy learners (amendment of 2026-12-02, "the on-policy learners"): a family of
# their own, with its own budget, searches' selection and tables, beside the paper's three.
ON_POLICY_ALGOS = ("ippo", "mappo")
EXPERIMENT_ALGOS = (*ALGOS, *ON_POLICY_ALGOS)
FAMILIES = {"off-policy": ALGOS, "on-policy": ON_POLICY_ALGOS}


def family(algos: Sequence[str]) -> tuple[str, ...]:
    """Every learner of the family that ``algos`` belong to: a search's rule and a table's
    aggregates run over that family's pairs (raises ``ValueError`` if ``algos`` mix
    families)."""
    found = {name for name, members in FAMILIES.items() if set(algos) & set(members)}
    if len(found) != 1:
        raise ValueError(
            "--algos " + " ".join(algos) + " mixes the off-policy learners ("
            + ", ".join(ALGOS) + ") with the on-policy ones (" + ", ".join(ON_POLICY_ALGOS)
            + "): each family has its own searches and tables (docs/protocol.md, amendment "
            "of 2026-12-02); name one family's learners")
    return FAMILIES[found.pop()]


SEED_SETS = {"the tables'": TABLE_SEEDS, "the selection": SELECTION_SEEDS,
             "the budgets'": BUDGET_SEEDS}


def seed_overlap(seeds: Sequence[int], offset: int, against: Sequence[str]) -> str | None:
    """Why ``seeds`` (from ``--seed-offset offset``) may not be used (``None`` if they
    may): they overlap one of the seed sets named in ``against`` (keys of
    :data:`SEED_SETS`). Each purpose keeps seeds of its own."""
    for name in against:
        taken = SEED_SETS[name]
        if set(seeds) & set(taken):
            return (f"--seed-offset {offset} overlaps {name} seeds {taken[0]}-{taken[-1]}: "
                    "each purpose of docs/protocol.md keeps seeds of its own")
    return None

# Environment steps per run, per learner, chosen on the plain learners only
# (experiments/budgets.py, seeds 200-202; docs/protocol.md tells the history): the re-check
# on the current scenarios (experiments/results/budgets/, CPU, 3M) found IDDPG levelled in
# all three scenarios and MADDPG on the obstacle, MADDPG still creeping up in turbulence and
# strong wind; MAAC's (box9, 1 x 256, this CPU, 2026-11-25) on the obstacle, still creeping up in
# turbulence and the wind (docs/protocol.md says how its check was read).
# Every table cell records whether its plain learner's return plateaued at this budget on
# the tables' seeds, and the results report (experiments/results/README.md) says where it did not.
BUDGETS = {"iddpg": 3_000_000, "maddpg": 3_000_000, "maac": 3_000_000}
# The longer budget (docs/protocol.md, amendments of 2026-11-26 and 2026-11-27): the
# longer-budget check's rule, on the plain learners alone, gave 6M steps for every learner.
# Both searches and all 18 table programs at it are the protocol's too, reported beside the
# 3M tables (not instead of them); the tables at one budget take the searches at the same.
LONGER_BUDGETS = {"iddpg": 6_000_000, "maddpg": 6_000_000, "maac": 6_000_000}
# The constrained baseline's budget (docs/protocol.md, amendment of 2026-12-02): chosen on
# the plain learners' budgets curves (90% of their mean success at 3M over the 9 pairs), for
# every learner; above the replay capacity, so the other variants' cells at it are the 6M
# runs' evaluations there.
LAGRANGIAN_BUDGET = 2_000_000
# The on-policy learners' budget (amendment of 2026-12-02, "the on-policy learners"): the
# largest budget proposed by their six plain cells of the budgets run (4M steps, seeds
# 200-202, experiments/results/budgets_on_policy/), for IPPO and MAPPO alike.
ON_POLICY_BUDGET = 3_000_000
EVAL_EVERY = 100_000
EVAL_EPISODES = 64
QUICK_EPISODE_LENGTH = 10  # --quick's episodes (the tables' regime)


@dataclasses.dataclass(frozen=True)
class Regime:
    """Where the hazards are and how the team meets them (amendment of 2026-12-01, "CCR's
    premise, the regimes"), and the evaluation interval and candidate budgets its episode
    length allows in whole iterations (its addition of 2026-12-02)."""

    layout_params: dict[str, Any]  # TrainConfig.layout_params: the Layout fields it changes
    episode_length: int  # go-to-goal's steps to 95% success on nominal, times 1.3
    eval_every: int  # environment steps between evaluations, whole iterations
    budget_candidates: tuple[int, ...]  # the budgets run's candidates on the plain learner
    # --quick's episodes, and the factor on its steps and intervals (quick_scale): 10
    # steps for the tables' regime; a column's last robot needs 22 to arrive
    quick_episode_length: int = QUICK_EPISODE_LENGTH

    @property
    def quick_scale(self) -> int:
        """What --quick's steps, evaluation interval and candidate spacing are multiplied
        by in this regime, so that they stay whole iterations of its quick episodes."""
        return self.quick_episode_length // QUICK_EPISODE_LENGTH


# The study's regimes (experiments/regimes.py chose `column` on the reference controllers
# alone: experiments/results/regimes/). An iteration of 8 environments of 30 steps (240
# steps; IPPO's and MAPPO's 4,800) divides neither 100,000 nor 1M or 2M, so `column`
# evaluates every 120,000 steps (500 iterations) and its candidate budgets are 1.2M, 2.4M
# and 3M, the nearest whole multiples of that interval to the amendment's 1M, 2M and 3M.
REGIMES = {
    "today": Regime(layout_params={}, episode_length=25, eval_every=EVAL_EVERY,
                    budget_candidates=(1_000_000, 2_000_000, 3_000_000)),
    "column": Regime(layout_params={"hazard_y_range": (-1.0, 1.0), "formation": "column",
                                    "column_spacing": 0.3, "column_lateral": 0.05,
                                    "arena_half_extent": (2.55, 2.0)},
                     episode_length=30, eval_every=120_000,
                     budget_candidates=(1_200_000, 2_400_000, 3_000_000),
                     quick_episode_length=30),
}
DEFAULT_REGIME = "today"  # the paper's tables and searches; not written in their records
# The study's scenario x learner pairs (the amendment of 2026-12-01): a regime's budget is
# the largest of their proposed budgets (each the smallest candidate from which on plain's
# return stays level; the addition of 2026-12-03).
STUDY_SCENARIOS = ("hidden_obstacle", "turbulence")
STUDY_ALGOS = ("maddpg",)
# A regime's budget per learner, once its budgets run has chosen it; until then its runs
# train the largest candidate and a selection made there is provisional. The column's:
# experiments/results/study/budgets_column/ (the obstacle's proposal, 3M; turbulence's 1.2M).
REGIME_BUDGETS: dict[str, dict[str, int]] = {"column": {"maddpg": 3_000_000}}

# The learners' hyperparameters where the protocol departs from their defaults
# (TrainConfig's). MAAC: 1 update of batch 256 every 100 environment steps, not the
# original's 4 of batch 1024 (its default). Amendment of 2026-11-25 (docs/protocol.md),
# made before any MAAC search or table cell existed and from cost alone: at the original's
# settings a MAAC run of 3M steps costs this project's 2-core CPU about 20 times a MADDPG
# run, and the GPU the protocol was waiting for is lent to about 5% of sessions; halving the
# update arithmetic from the original's, 1 x 256 is the first setting at which a MAAC run
# costs about what a MADDPG run does (0.80 times MADDPG's steps per second, 1 x 512 0.41).
# The budgets run at this setting (seeds 200-202) checks that plain MAAC still levels off.
LEARNERS = {"maac": MAACConfig(gradient_steps=1, batch_size=256)}

# The searches: the same number of values, spanning more than two orders of magnitude,
# the same seeds and budgets; 0 (the plain learner) is trained beside them as the
# rule's reference.
LAMBDAS = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
PENALTIES = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
# The Lagrangian's cost limits (amendment of 2026-12-02); its reference, trained beside them
# as value 0, is the multiplier held at 0: exactly the plain learner.
COST_LIMITS = (0.003, 0.01, 0.02, 0.05, 0.1, 0.3)
SEARCHED = {"ccr": ("lam", LAMBDAS), "pessimistic": ("penalty", PENALTIES),
            "lagrangian": ("cost_limit", COST_LIMITS),
            # CCR's parts with an intrinsic reward (the study, amendment of 2026-12-01):
            # lambda over the same values, on the study's pairs alone
            "ccr_reward": ("lam", LAMBDAS), "ccr_perfect": ("lam", LAMBDAS)}
PART_VARIANTS = ("ccr_reward", "ccr_perfect")
RULE = SelectionRule(objective="danger_frequency", constraint="success_rate", tolerance=0.05)


def budgets_text() -> str:
    """The protocol's budgets in words, for ``--help``: ``"3,000,000 for every learner"``."""
    if len(set(BUDGETS.values())) == 1:
        return f"{next(iter(BUDGETS.values())):,} for every learner"
    return ", ".join(f"{steps:,} for {algo}" for algo, steps in BUDGETS.items())


def budget(algo: str, steps: int | None, regime: str = DEFAULT_REGIME) -> int:
    """Environment steps per run: ``steps`` if given, else the protocol's budget of ``algo``
    in ``regime`` (another regime's: :data:`REGIME_BUDGETS`, its largest candidate until
    chosen)."""
    if steps is not None:
        return steps
    if regime != DEFAULT_REGIME:
        return REGIME_BUDGETS[regime].get(algo, max(REGIMES[regime].budget_candidates))
    return ON_POLICY_BUDGET if algo in ON_POLICY_ALGOS else BUDGETS[algo]


def regime_text(record: dict[str, Any]) -> str:
    """The regime a summary's cells were trained in (settings ``record``), as a clause to
    follow its seeds; nothing for the tables' regime."""
    regime = record.get("regime", DEFAULT_REGIME)
    if regime == DEFAULT_REGIME:
        return ""
    spec = REGIMES[regime]
    return (f"; regime `{regime}` (docs/protocol.md, amendment of 2026-12-01: "
            f"{spec.episode_length}-step episodes, layout "
            + ", ".join(f"{k} {v}" for k, v in spec.layout_params.items()) + ")")


def study_pairs(algos: Sequence[str]) -> list[tuple[str, str]]:
    """The study's scenario x learner pairs of the family of ``algos`` (the amendment of
    2026-12-01): its scenarios with MADDPG, or with IPPO and MAPPO."""
    learners = STUDY_ALGOS if family(algos) == ALGOS else ON_POLICY_ALGOS
    return [(scenario, algo) for scenario in STUDY_SCENARIOS for algo in learners]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings:
    """The settings every experiment trains its cells with (``budgets.py``, ``search.py``
    and ``tables.py`` each add their own fields and default seeds). They are stored in
    every cell; a cell made with other settings is trained again
    (``cell_identity.cell_is_current``)."""

    seeds: tuple[int, ...]
    steps: int | None = None  # None: the protocol's budget of each learner
    eval_every: int = EVAL_EVERY
    eval_episodes: int = EVAL_EPISODES
    quick: bool = False  # tiny sizes (:func:`quick`): the pipeline, not the learning
    # Which programs an invocation trains, not what a cell holds (cell_identity.NOT_IN_CELLS):
    # a grid can be split over invocations.
    scenarios: tuple[str, ...] = PAPER_SCENARIOS
    algos: tuple[str, ...] = ALGOS
    regime: str = DEFAULT_REGIME  # a key of REGIMES: the layout and episode length

    def __post_init__(self) -> None:
        if self.regime not in REGIMES:
            raise ValueError(f"--regime {self.regime!r} is not a regime of the protocol; "
                             f"choose from {', '.join(REGIMES)}")

    def budget(self, algo: str) -> int:
        """Environment steps per run of learner ``algo``."""
        return budget(algo, self.steps, self.regime)


def run_config(settings: Settings, scenario: str, algo: str, variant: str,
               **fields: Any) -> TrainConfig:
    """One run's configuration under an experiment's ``settings``: :func:`budget` steps,
    its evaluation interval and episodes, the protocol's learner settings (:data:`LEARNERS`),
    the regime's layout and episode length, tiny sizes if ``quick``; ``fields`` set the rest
    (the transform). A budget or evaluation interval that would be rounded to whole
    iterations is refused (``ValueError``): an experiment's cells and tables record the
    budget asked for, so it must be the one that runs."""
    regime = REGIMES[settings.regime]
    base = TrainConfig(algo=algo, scenario=scenario, variant=variant,
                       learner=LEARNERS.get(algo), episode_length=regime.episode_length,
                       layout_params=dict(regime.layout_params))
    if settings.quick:
        base = quick(base, regime.quick_episode_length)
    config = dataclasses.replace(base, total_env_steps=settings.budget(algo),
                                 eval_every=settings.eval_every,
                                 eval_episodes=settings.eval_episodes, **fields)
    notes = config.schedule()["notes"]
    if notes:
        raise ValueError("; ".join(notes) + " (an experiment runs exactly what it records: "
                         "give whole evaluation intervals)")
    return config


def quick(config: TrainConfig, episode_length: int = QUICK_EPISODE_LENGTH) -> TrainConfig:
    """``config`` at a tiny size (2 environments of ``episode_length`` steps, 10 unless a
    regime needs more, 8-unit networks, learning from the 40th transition, an on-policy
    learner from its first rollout, in 2 minibatches): the pipeline of an experiment in
    minutes, not its learning."""
    if config.on_policy:
        learner = PPOConfig(actor_hidden=(8,), critic_hidden=(8,), minibatches=2)
    elif config.algo == "maac":
        learner = MAACConfig(batch_size=32, policy_hidden=(8,), critic_hidden=8,
                             attention_heads=2, update_every=20, gradient_steps=1)
    else:
        learner = DDPGConfig(batch_size=32, actor_hidden=(8,), critic_hidden=(8,),
                             update_every=20)
    return dataclasses.replace(config, num_envs=2, episode_length=episode_length,
                               learning_starts=40, learner=learner)


# Whether a plain learner's return plateaued (ccrjax.run.stats.plateau), as the summaries say it.
PLATEAU_WORDS = {True: "yes", False: "**no**",
                 None: "undetermined (too few evaluations or seeds, or a NaN return)"}
# The learners as the experiments' outputs name them; IDDPG is the paper's "DDPG" (one DDPG
# per robot, its critic seeing only its own observation and action).
LEARNER_NAMES = {"iddpg": "IDDPG", "maddpg": "MADDPG", "maac": "MAAC", "ippo": "IPPO",
                 "mappo": "MAPPO"}


def quick_note(variants: bool = True, regime: str = DEFAULT_REGIME) -> str:
    """The quick mode's warning atop a summary; ``variants``: whether it compares them
    (the budgets train plain learners only); ``regime``: the one its cells trained in."""
    tail = (", and the variants barely train, so their rows can coincide: pessimistic equal "
            "to plain to the digits shown" if variants else "")
    length = REGIMES[regime].quick_episode_length
    return (f"**Quick mode**: tiny networks, 2 environments of {length}-step episodes, a few "
            "hundred to a few thousand steps per run, 4 evaluation episodes. It checks the "
            "pipeline; no number here measures learning or the scenarios (the reference "
            f"controllers run {length}-step episodes too, the plateau checks see a handful of "
            f"evaluations{tail}).")


def quick_help(seeds: str = "2 seeds unless --seeds") -> str:
    """The ``--quick`` option's help text; ``seeds``: how many seeds the quick mode runs."""
    return ("the pipeline at a toy size, in minutes (tiny networks, 2 environments of 10-step "
            "episodes, a few hundred to a few thousand steps per run, 4 evaluation episodes, "
            f"{seeds}): its numbers measure nothing")


# Before every figure's title in quick mode, so a figure copied out alone still says so.
QUICK_FIGURE = "[quick mode: measures nothing] "
QUICK_STEPS = 400
QUICK_EVAL_EVERY = 200
QUICK_EVAL_EPISODES = 4
