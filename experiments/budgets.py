"""Budgets at which the plain learners' return has levelled off: ``python experiments/budgets.py``.

    python experiments/budgets.py --out runs/budgets
    python experiments/budgets.py --algos iddpg maddpg --scenarios hidden_obstacle \\
        --out experiments/results/budgets --force
    python experiments/budgets.py --quick --scenarios turbulence --algos iddpg --out /tmp/b

Trains the **plain** learners only (the control decides the budget, never CCR or the
pessimistic baseline) for ``--steps`` environment steps per seed (default: the protocol's
budget of each learner, so the run confirms it or says where it falls short), on the
budget seeds 200-202, disjoint from the tables' 0-9 and the selection seeds 100-102. For
each candidate budget (every ``--candidate-every`` steps) it checks whether the evaluated
return had plateaued by then (:func:`ccrjax.run.stats.plateau`: the mean of the last 20% of
evaluations lies within the 95% interval of the 20% before). The proposed budget is the
smallest candidate from which on every larger candidate plateaus too, ``None`` if the
return is still moving at ``--steps``.

``--algos ippo mappo --candidate-every 500000 --steps 4000000`` is the on-policy learners'
budgets run (``docs/protocol.md``, amendment of 2026-12-02, "the on-policy learners"); the
summary's last line gives their family's budget, the largest proposed by their six cells
(``protocol.ON_POLICY_BUDGET`` holds the one it gave).

``--regime column --algos maddpg --scenarios hidden_obstacle turbulence`` is the study's
budgets run in the column regime (amendment of 2026-12-01 and its addition): the
candidates 1.2M, 2.4M and 3M at an evaluation every 120,000 steps, and the summary's last
line gives the regime's budget (the smallest candidate at which both cells level off).

``--tables-seeds`` runs the longer-budget check of ``docs/protocol.md`` (its amendment of
2026-11-26): the plain learners alone on the tables' seeds 0-9, 6M steps by default, checked
at the candidates 3M, 4.5M and 6M; the budget for all is the smallest candidate at which
every plain learner's check passes (the summary's last line, once the 9 cells exist):

    python experiments/budgets.py --tables-seeds --out experiments/results/longer_budget

Each scenario and learner is one vmapped program. Its cell is written to
``<out>/cells/<scenario>-<algo>.json`` when it finishes (curves, checks, proposal, wall
time, device, commit); a re-run skips the cells made with the same settings, whatever
scenarios and learners it names, so the grid can be spread over invocations and machines.
Then ``budgets.json`` (every cell of the folder made with these settings, whichever
invocation made it, and every invocation), ``budgets.md`` and ``curves_<algo>.png``
(return, success and danger along training, one line per scenario). Started as several
processes (``--coordinator``, ``--num-processes``, ``--process-id``:
:mod:`ccrjax.run.distributed`), each trains its share of every program's runs and process 0
writes the results.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/budgets.py")

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.run.stats import plateau_or_undetermined
from ccrjax.training import ALGOS, TrainConfig
from ccrjax.training.grid import GridTraining
from experiments import protocol
from experiments.budgets_report import budgets_markdown, check_budgets, draw_budget_curves
from experiments.cell_identity import cell_is_current, settings_record, training_record
from experiments.ledger import (
    STOPPED_KEPT,
    Partial,
    add_checkpoint_option,
    add_out_options,
    check_quick_out,
    device_name,
    log,
    open_experiment,
    plan_pairs,
    read_json,
    train_pairs,
)
from experiments.paper import PAPER_SCENARIOS

PROG = "python experiments/budgets.py"
ALL_SCENARIOS = (*PAPER_SCENARIOS, "nominal")
CANDIDATE_EVERY = 250_000
QUICK_CANDIDATE_EVERY = 200
# The longer-budget check (docs/protocol.md, amendment of 2026-11-26): the plain learners on
# the tables' seeds for 6M steps, checked at these candidates.
LONGER_STEPS = 6_000_000
LONGER_CANDIDATES = (3_000_000, 4_500_000, 6_000_000)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What every cell is trained and checked with (a cell made otherwise is redone)."""

    seeds: tuple[int, ...] = protocol.BUDGET_SEEDS
    candidate_every: int = CANDIDATE_EVERY  # steps between the candidate budgets checked
    # The candidate budgets named one by one (the longer-budget check's); empty: every
    # multiple of ``candidate_every``. Not part of what a cell holds (cell_identity.NOT_IN_CELLS).
    candidate_budgets: tuple[int, ...] = ()

    def config(self, scenario: str, algo: str) -> TrainConfig:
        return protocol.run_config(self, scenario, algo, "plain")

    def candidates(self, algo: str) -> list[int]:
        """The candidate budgets checked for learner ``algo``: those named, or every
        multiple of ``candidate_every``, up to its budget."""
        if self.candidate_budgets:
            return [c for c in sorted(self.candidate_budgets) if c <= self.budget(algo)]
        return list(range(self.candidate_every, self.budget(algo) + 1, self.candidate_every))


def train_cell(settings: Settings, scenario: str, algo: str, partial: Partial
               ) -> dict[str, Any]:
    """One scenario and learner's plain runs on ``settings.seeds``: the curves (checked by
    :func:`checked`), in one program checkpointed under the pair's name."""
    config = settings.config(scenario, algo)
    training = GridTraining(config, settings.seeds)
    training.compile(not settings.quick)
    runs = partial.train(training, f"{scenario}-{algo}")
    return {
        "scenario": scenario, "algo": algo, "settings": settings_record(settings),
        "budget": settings.budget(algo), "training": training_record(config),
        "seeds": list(settings.seeds),
        "env_steps": np.asarray(runs.history["env_steps"][0]).tolist(),
        "curves": {m: runs.history[m].tolist() for m in
                   ("return", "success_rate", "danger_frequency", "target_distance")},
        "nonfinite_iteration": runs.nonfinite_iteration.tolist(),
        "compile_s": runs.compile_s, "train_s": runs.run_s, "device": device_name(),
        "commit": git_commit(), "date": time.strftime("%Y-%m-%d %H:%M %Z"),
    }


def checked(cell: dict[str, Any], settings: Settings) -> dict[str, Any]:
    """``cell`` with its plateau checks at the candidate budgets of ``settings``, the
    proposed budget, and whether the whole curves end level (computed from the stored
    curves, so other candidates need no training)."""
    returns = np.asarray(cell["curves"]["return"])
    checks, proposed = check_budgets(np.asarray(cell["env_steps"]), returns,
                                     settings.candidates(cell["algo"]))
    return {**cell, "checks": checks, "proposed_budget": proposed,
            "plateaued_at_budget": plateau_or_undetermined(returns)["plateaued"]}


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="The budgets at which the plain learners' "
                        "evaluated return has levelled off, on the budget seeds.")
    parser.add_argument("--algos", nargs="+", choices=protocol.EXPERIMENT_ALGOS,
                        default=list(ALGOS),
                        help="learners (default: the paper's three; the on-policy ones, "
                        "ippo and mappo, are named)")
    parser.add_argument("--scenarios", nargs="+", choices=ALL_SCENARIOS,
                        default=list(PAPER_SCENARIOS),
                        help="scenarios (default: the paper's three)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per seed for every learner (default: the "
                        f"protocol's budgets, {protocol.budgets_text()})")
    parser.add_argument("--eval-every", type=cli.positive_int, default=None,
                        help="environment steps between evaluations (default: "
                        f"{protocol.EVAL_EVERY})")
    parser.add_argument("--candidate-every", type=cli.positive_int, default=None,
                        help=f"candidate budgets are its multiples (default: {CANDIDATE_EVERY})")
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=None,
                        help="seeds per learner, at least 2 (default: 3)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=None,
                        help=f"first seed (default: {protocol.BUDGET_SEED_OFFSET}; the tables "
                        "use 0-9, the searches 100-102)")
    parser.add_argument("--tables-seeds", action="store_true",
                        help="the longer-budget check of docs/protocol.md (amendment of "
                        "2026-11-26): the plain learners on the tables' seeds 0-9 (not with "
                        f"--seeds or --seed-offset), --steps {LONGER_STEPS:,} unless given, "
                        "checked at the candidates "
                        + ", ".join(f"{c:,}" for c in LONGER_CANDIDATES)
                        + " (not with --candidate-every)")
    parser.add_argument("--regime", choices=tuple(protocol.REGIMES),
                        default=protocol.DEFAULT_REGIME,
                        help="the hazards' placement, the team's formation and the episode "
                        "length (docs/protocol.md, amendment of 2026-12-01; default: "
                        f"{protocol.DEFAULT_REGIME}, the tables'); another regime checks its "
                        "own candidate budgets at its own evaluation interval (column: "
                        + ", ".join(f"{c:,}" for c in protocol.REGIMES["column"].budget_candidates)
                        + f" every {protocol.REGIMES['column'].eval_every:,} steps; not with "
                        "--candidate-every or --tables-seeds)")
    parser.add_argument("--eval-episodes", type=cli.positive_int, default=None,
                        help="fresh episodes per evaluation and seed (default: "
                        f"{protocol.EVAL_EPISODES})")
    parser.add_argument("--quick", action="store_true",
                        help=protocol.quick_help("the seeds of --seeds"))
    add_out_options(parser, "budgets", default_text="runs/budgets")
    add_checkpoint_option(parser)
    distributed.add_options(parser)
    return parser


def settings_from(args: argparse.Namespace) -> Settings:
    regime = protocol.REGIMES[args.regime]
    other_regime = args.regime != protocol.DEFAULT_REGIME
    if other_regime and (args.tables_seeds or args.candidate_every is not None):
        given = "--tables-seeds" if args.tables_seeds else "--candidate-every"
        raise cli.UsageError(f"--regime {args.regime} checks its own candidate budgets "
                             f"(docs/protocol.md); leave out {given}")
    if args.tables_seeds:
        given = [name for name, value in (("--seeds", args.seeds),
                                          ("--seed-offset", args.seed_offset),
                                          ("--candidate-every", args.candidate_every))
                 if value is not None]
        if given:
            raise cli.UsageError(f"--tables-seeds fixes the seeds (0-9) and the candidate "
                                 f"budgets; leave out {' and '.join(given)}")
        if args.quick:
            raise cli.UsageError("--tables-seeds is the protocol's longer-budget check at full "
                                 "size; --quick has seeds of its own (leave out one of them)")
        seeds = protocol.TABLE_SEEDS
    else:
        offset = protocol.BUDGET_SEED_OFFSET if args.seed_offset is None else args.seed_offset
        seeds = tuple(range(offset, offset + (3 if args.seeds is None else args.seeds)))
        problem = protocol.seed_overlap(seeds, offset, ("the tables'", "the selection"))
        if problem:
            hint = (" (the longer-budget check on the tables' seeds is --tables-seeds)"
                    if "tables'" in problem else "")
            raise cli.UsageError(problem + hint)
    # --quick changes the defaults (tiny sizes); what is given on the command line stays.
    scale = regime.quick_scale
    defaults = ({"steps": 10 * protocol.QUICK_STEPS * scale,
                 "eval_every": protocol.QUICK_EVAL_EVERY * scale,
                 "eval_episodes": protocol.QUICK_EVAL_EPISODES,
                 "candidate_every": QUICK_CANDIDATE_EVERY * scale} if args.quick else
                {"steps": None, "eval_every": protocol.EVAL_EVERY,
                 "eval_episodes": protocol.EVAL_EPISODES, "candidate_every": CANDIDATE_EVERY})
    fields: dict[str, Any] = {
        name: default if getattr(args, name) is None else getattr(args, name)
        for name, default in defaults.items()}
    if args.tables_seeds:
        fields.update(candidate_budgets=LONGER_CANDIDATES,
                      steps=LONGER_STEPS if args.steps is None else args.steps)
    if other_regime and not args.quick:
        fields.update(candidate_budgets=regime.budget_candidates,
                      steps=max(regime.budget_candidates) if args.steps is None else args.steps,
                      eval_every=regime.eval_every if args.eval_every is None
                      else args.eval_every)
    fields.update(seeds=seeds, quick=args.quick, scenarios=tuple(dict.fromkeys(args.scenarios)),
                  algos=tuple(dict.fromkeys(args.algos)), regime=args.regime)
    settings = Settings(**fields)
    for scenario in settings.scenarios:  # every configuration validated before compiling
        for algo in settings.algos:
            settings.config(scenario, algo)
    for algo in settings.algos:
        if not settings.candidates(algo):
            what = ("the smallest of --tables-seeds' candidates "
                    f"{min(settings.candidate_budgets):,}" if settings.candidate_budgets else
                    f"--candidate-every {settings.candidate_every:,}")
            raise cli.UsageError(f"{what} is above the budget {settings.budget(algo):,} of "
                                 f"{algo}: no candidate budget would be checked")
    return settings


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    out = args.out or Path("runs/budgets")

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        return settings_from(args)

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    cells, todo, progress = plan_pairs(settings, out, len(settings.seeds),
                                       f"{len(settings.seeds)} seeds each")
    partial = Partial(out, args.checkpoint_minutes)
    for (scenario, algo), cell in train_pairs(
            todo, out, partial, ledger, progress,
            lambda s, a: train_cell(settings, s, a, partial)):
        cells[(scenario, algo)] = cell
        found = checked(cell, settings)
        log(f"  {algo} {scenario}: plateaued at the end {found['plateaued_at_budget']}, "
            f"proposed budget {found['proposed_budget']}")
    ledger.record(len(todo), finished=True)
    if not distributed.is_primary():  # process 0 writes the summary
        return 0
    # The summary reports every cell of the folder made with these settings, whichever
    # invocation made it (the budgets select nothing, so nothing depends on which are named).
    record = settings_record(settings)
    for path in sorted((out / "cells").glob("*.json")):
        cell = read_json(path)
        if cell_is_current(cell, record):
            cells.setdefault((cell["scenario"], cell["algo"]), cell)
    ordered = {(s, a): checked(cells[(s, a)], settings)
               for a in protocol.EXPERIMENT_ALGOS for s in ALL_SCENARIOS if (s, a) in cells}
    result = {
        "settings": record,
        "budgets": {a: settings.budget(a)
                    for a in dict.fromkeys(a for _, a in ordered) or settings.algos},
        "invocations": ledger.invocations,
        "cells": list(ordered.values()),
    }
    write_atomic(out / "budgets.json", json.dumps(result) + "\n")
    write_atomic(out / "budgets.md", budgets_markdown(result))
    figures = draw_budget_curves(ordered, out, bool(record.get("quick")),
                                 "the tables' seeds" if settings.seeds == protocol.TABLE_SEEDS
                                 else "budget seeds")
    print(budgets_markdown(result))
    print(f"wrote {out / 'budgets.md'}, budgets.json, "
          + ", ".join(path.name for path in figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
