"""The study of CCR's premise, one regime's cells: ``python experiments/study.py``.

    python experiments/study.py --regime column --out experiments/results/study/column --force
    python experiments/study.py --regime today --out experiments/results/study/today --force
    python experiments/study.py --regime column --quick --out /tmp/study   # the pipeline

Under the amendment of 2026-12-01 (``docs/protocol.md``, "The study"): per study pair (the
hidden obstacle and turbulence with MADDPG; ``--algos ippo mappo`` the on-policy learners;
``--scenarios`` may add the wind, the negative control) it trains plain and pessimistic
together (plain is the penalty 0, exactly), CCR, CCR's four parts (``ccr_scores``,
``ccr_reward``, ``ccr_perfect``, ``danger_flags``) and the Lagrangian, each on the tables'
seeds (0-4 by default, the addition of 2026-12-03; up to 10) at the regime's budget, as the
tables' programs do (:mod:`experiments.tables_grid`: resumable, cells written as they
finish). Each cell also holds the study's own measures (:mod:`experiments.study_measures`:
the forewarned share, the followers' distance, danger and success), per seed; the
hypotheses and aggregates over the cells of both regimes are
:mod:`experiments.study_analysis`'s.

Each searched parameter is the regime's search's choice over the study's pairs
(:func:`chosen_value`): in ``column``, ``<searches>/<variant>`` (``search.py --variant V
--regime column``); in ``today``, the tables' 3M searches for lambda and the penalty
(re-applied to the study's pairs, no new runs) and ``<searches>/<variant>`` for the parts
and the Lagrangian. ``--variants`` trains a subset (a variant whose search is not made yet
is refused with the command that makes it); ``--value VARIANT VALUE`` sets a value by hand
(exploratory: the summary says so). A cell records only its own variant's value, so a value
chosen later trains that variant's cells alone.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/study.py")

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import write_atomic
from ccrjax.run.sweep_grid import SEARCHED_PARAMETER
from ccrjax.training import TrainConfig
from experiments import protocol, search
from experiments.cell_identity import cell_is_current, settings_record
from experiments.ledger import (
    RESULTS,
    STOPPED_KEPT,
    Partial,
    add_checkpoint_option,
    add_no_train_option,
    add_out_options,
    cell_path,
    check_quick_out,
    open_experiment,
    read_json,
    refuse_untrained,
    repo_relative,
)
from experiments.paper import PAPER_SCENARIOS
from experiments.study_measures import cell_measures
from experiments.tables_grid import Job, job_cells, run_grid, variant_cell_path

PROG = "python experiments/study.py"
# The study's variants in its programs: plain trains beside pessimistic (penalty 0).
PROGRAMS = (("plain", "pessimistic"), ("ccr",), ("ccr_scores",), ("ccr_reward",),
            ("ccr_perfect",), ("danger_flags",), ("lagrangian",))
VARIANTS = tuple(v for program in PROGRAMS for v in program)
SEARCHED = tuple(v for v in VARIANTS if v in SEARCHED_PARAMETER)
QUICK_VALUES = {"pessimistic": 3.0, "ccr": 3.0, "ccr_reward": 3.0, "ccr_perfect": 3.0,
                "lagrangian": 0.05}
# The study's seeds (docs/protocol.md, addition of 2026-12-03): the tables' first five; its
# analysis is made on these even where a cell holds more.
STUDY_SEEDS = 5
# The tables' searches, whose cells hold the study's pairs in the tables' regime.
TABLES_SEARCHES = {"ccr": RESULTS / "search" / "ccr",
                   "pessimistic": RESULTS / "search" / "pessimistic"}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What a study cell is trained with (a cell made otherwise is redone). ``values`` holds
    the searched parameter of the variants it trains; each program's cells record only
    their own (:meth:`for_program`)."""

    values: dict[str, float]
    seeds: tuple[int, ...] = protocol.TABLE_SEEDS
    scenarios: tuple[str, ...] = protocol.STUDY_SCENARIOS
    algos: tuple[str, ...] = protocol.STUDY_ALGOS
    behaviour_episodes: int = 64  # recorded episodes per seed: the study's measures

    @property
    def penalty(self) -> float:
        """The pessimistic penalty (the plain-and-pessimistic program reads it)."""
        return self.values["pessimistic"]

    def config(self, scenario: str, algo: str, variant: str) -> TrainConfig:
        return protocol.run_config(self, scenario, algo, variant)

    def run_params(self, variant: str) -> dict[str, float]:
        """The run parameters every seed of ``variant`` trains with: its searched value."""
        name = SEARCHED_PARAMETER.get(variant)
        return {} if name is None or variant == "pessimistic" else {name: self.values[variant]}

    def for_program(self, variants: tuple[str, ...]) -> Settings:
        """These settings with only ``variants``' values: what their cells record."""
        return dataclasses.replace(self, values={v: self.values[v] for v in variants
                                                 if v in self.values})


def chosen_value(variant: str, regime: str, algos: tuple[str, ...], folder: Path
                 ) -> float:
    """The value of :func:`chosen` (the protocol's choice of ``variant``'s parameter)."""
    return float(chosen(variant, regime, algos, folder)["value"])


def chosen(variant: str, regime: str, algos: tuple[str, ...], folder: Path
           ) -> dict[str, Any]:
    """The protocol's choice of ``variant``'s parameter for the study in ``regime``: the
    selection rule applied over the study's pairs to the search cells in ``folder``, made
    on the selection seeds at the regime's budget and evaluations
    (:func:`experiments.search.not_the_protocols`), as the rule gives it (``value``,
    ``fallback``: no value met the rule). Raises :class:`ccrjax.cli.UsageError` naming the
    search to run when a cell is missing or the choice is provisional."""
    pairs = protocol.study_pairs(algos)
    settings = search.Settings(
        variant=variant, values=protocol.SEARCHED[variant][1], regime=regime,
        eval_every=protocol.REGIMES[regime].eval_every,
        scenarios=tuple(dict.fromkeys(s for s, _ in pairs)),
        algos=tuple(dict.fromkeys(a for _, a in pairs)))
    record = settings_record(settings)
    cells = {pair: read_json(cell_path(folder, *pair)) for pair in pairs}
    missing = [f"{s}-{a}" for (s, a), cell in cells.items() if not cell_is_current(cell, record)]
    command = (f"python experiments/search.py --variant {variant} --regime {regime} --algos "
               f"{' '.join(settings.algos)} --out {folder}")
    if missing:
        raise cli.UsageError(f"--variants {variant} needs its search's cells {', '.join(missing)}"
                             f" in {folder} (run {command}), or give --value {variant} VALUE")
    chosen = search.selection(settings, cells)
    if not chosen["protocol"]:
        raise cli.UsageError(f"the {variant} search in {folder} is provisional "
                             f"({chosen['provisional_because']}): finish {command}, or give "
                             f"--value {variant} VALUE")
    return chosen


def search_folder(variant: str, regime: str, searches: Path) -> Path:
    """Where the study's search of ``variant`` in ``regime`` is: the tables' for lambda and
    the penalty in the tables' regime, ``searches/<variant>`` otherwise."""
    if regime == protocol.DEFAULT_REGIME and variant in TABLES_SEARCHES:
        return TABLES_SEARCHES[variant]
    return searches / variant


def jobs_of(settings: Settings, variants: tuple[str, ...]) -> list[Job]:
    """The programs of ``variants`` (plain and pessimistic together) for every pair."""
    programs = [p for p in PROGRAMS if set(p) & set(variants)]
    return [Job(scenario, algo, program) for scenario in settings.scenarios
            for algo in settings.algos for program in programs]


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--regime", choices=tuple(protocol.REGIMES), required=True,
                        help="the regime whose cells are trained")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                        help="train only these variants' programs (plain and pessimistic "
                        "train together; default: all)")
    parser.add_argument("--value", nargs=2, action="append", default=[],
                        metavar=("VARIANT", "VALUE"),
                        help="set a searched variant's value by hand (exploratory), one of "
                        + ", ".join(SEARCHED))
    parser.add_argument("--searches", type=Path, default=None,
                        help="the folder of the regime's searches, one per variant (default: "
                        "experiments/results/study/<regime>/search)")
    parser.add_argument("--seeds", type=cli.int_in(5, 10), default=STUDY_SEEDS,
                        help="the tables' seeds from 0, 5 to 10 (default: %(default)s, the "
                        "addition of 2026-12-03)")
    parser.add_argument("--scenarios", nargs="+", choices=PAPER_SCENARIOS,
                        default=list(protocol.STUDY_SCENARIOS),
                        help="scenarios (default: the study's; strong_wind: the negative "
                        "control)")
    parser.add_argument("--algos", nargs="+", choices=protocol.EXPERIMENT_ALGOS,
                        default=list(protocol.STUDY_ALGOS),
                        help="learners, of one family (default: %(default)s; ippo mappo: the "
                        "on-policy learners)")
    parser.add_argument("--quick", action="store_true", help=protocol.quick_help())
    add_out_options(parser, "study/<regime>", default_text="runs/study/<regime>")
    add_checkpoint_option(parser)
    add_no_train_option(parser)
    distributed.add_options(parser)
    return parser


def given_values(pairs: list[list[str]]) -> dict[str, float]:
    """``--value VARIANT VALUE`` pairs, checked: a searched variant and a positive number."""
    values = {}
    for variant, text in pairs:
        if variant not in SEARCHED:
            raise cli.UsageError(f"--value {variant}: not a searched variant; one of "
                                 + ", ".join(SEARCHED))
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not value > 0 or value == float("inf"):
            raise cli.UsageError(f"--value {variant} {text}: give a finite number > 0")
        values[variant] = value
    return values


def settings_from(args: argparse.Namespace) -> tuple[Settings, dict[str, str]]:
    """The settings of an invocation and where each value came from."""
    try:
        protocol.family(args.algos)
    except ValueError as error:
        raise cli.UsageError(str(error)) from None
    regime = protocol.REGIMES[args.regime]
    searches = args.searches or RESULTS / "study" / args.regime / "search"
    variants = tuple(v for v in VARIANTS if v in args.variants
                     or (v == "plain" and "pessimistic" in args.variants)
                     or (v == "pessimistic" and "plain" in args.variants))
    given = given_values(args.value)
    values, sources = {}, {}
    for variant in (v for v in variants if v in SEARCHED):
        if variant in given:
            values[variant], sources[variant] = given[variant], "given by hand (exploratory)"
        elif args.quick:
            values[variant], sources[variant] = QUICK_VALUES[variant], "the quick mode's"
        else:
            folder = search_folder(variant, args.regime, searches)
            choice = chosen(variant, args.regime, tuple(args.algos), folder)
            values[variant] = float(choice["value"])
            sources[variant] = f"the search in {repo_relative(folder)}" + (
                " (its fallback: no value met the rule)" if choice["fallback"] else "")
    fields: dict[str, Any] = {
        "values": values, "regime": args.regime, "seeds": tuple(range(args.seeds)),
        "scenarios": tuple(dict.fromkeys(args.scenarios)),
        "algos": tuple(dict.fromkeys(args.algos)), "eval_every": regime.eval_every}
    if args.quick:
        fields.update(quick=True, seeds=(0, 1), steps=protocol.QUICK_STEPS * regime.quick_scale,
                      eval_every=protocol.QUICK_EVAL_EVERY * regime.quick_scale,
                      eval_episodes=protocol.QUICK_EVAL_EPISODES, behaviour_episodes=4)
    settings = Settings(**fields)
    for job in jobs_of(settings, variants):  # every configuration validated before compiling
        for variant in job.variants:
            settings.config(job.scenario, job.algo, variant)
    return settings, {"variants": " ".join(variants), **sources}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    out = args.out or Path("runs/study") / args.regime
    chosen: dict[str, Any] = {}

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        settings, sources = settings_from(args)
        chosen.update(sources=sources, variants=sources["variants"].split())
        if args.no_train:
            for program in PROGRAMS:
                refuse_untrained(
                    {f"{job.scenario}-{job.algo}-{v}": variant_cell_path(
                        out, job.scenario, job.algo, v)
                     for job in jobs_of(settings, chosen["variants"])
                     if job.variants == program for v in program},
                    settings_record(settings.for_program(program)), out)
        return settings

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    partial = Partial(out, args.checkpoint_minutes)
    trained = 0
    for program in PROGRAMS:
        jobs = [job for job in jobs_of(settings, chosen["variants"]) if job.variants == program]
        if jobs:
            trained += run_grid(settings.for_program(program), out, ledger, partial, jobs,
                                cell_measures, trained_before=trained)
    ledger.record(trained, finished=True)
    if not distributed.is_primary():
        return 0
    made = {job.name: job_cells(out, job, settings.for_program(job.variants))
            for job in jobs_of(settings, chosen["variants"])}
    summary = {"settings": settings_record(settings), "sources": chosen["sources"],
               "programs": {name: cells is not None for name, cells in made.items()},
               "invocations": ledger.invocations}
    write_atomic(out / "study_cells.json", json.dumps(summary, indent=1) + "\n")
    done = sum(cells is not None for cells in made.values())
    print(f"{done} of {len(made)} programs of the {args.regime} regime made in {out}; "
          f"values: " + ", ".join(f"{v} {x:g} ({chosen['sources'][v]})"
                                  for v, x in settings.values.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
