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

Each scenario and learner is one vmapped program. Its cell is written to
``<out>/cells/<scenario>-<algo>.json`` when it finishes (curves, checks, proposal, wall
time, device, commit); a re-run skips the cells made with the same settings, whatever
scenarios and learners it names, so the grid can be spread over invocations and machines.
Then ``budgets.json`` (every cell of the folder made with these settings, whichever
invocation made it, and every invocation), ``budgets.md`` and ``curves_<algo>.png``
(return, success and danger along training, one line per scenario).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import protocol
from ledger import (
    STOPPED_KEPT,
    Partial,
    add_checkpoint_option,
    add_out_options,
    cell_is_current,
    check_quick_out,
    device_name,
    duration,
    log,
    open_experiment,
    plan_pairs,
    read_json,
    settings_record,
    train_pairs,
    training_record,
)

from ccrjax import cli
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.run.paper import SCENARIOS
from ccrjax.run.search import nonfinite_runs, nonfinite_text, summarise
from ccrjax.run.stats import format_mean_ci, plateau, plateau_or_undetermined
from ccrjax.training import ALGOS, TrainConfig
from ccrjax.training.grid import GridTraining
from ccrjax.viz.plots import Curves, draw_curves

PROG = "python experiments/budgets.py"
ALL_SCENARIOS = (*SCENARIOS, "nominal")
CANDIDATE_EVERY = 250_000
QUICK_CANDIDATE_EVERY = 200
FINAL_METRICS = ("return", "success_rate", "danger_frequency")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What every cell is trained and checked with (a cell made otherwise is redone)."""

    seeds: tuple[int, ...] = protocol.BUDGET_SEEDS
    candidate_every: int = CANDIDATE_EVERY  # steps between the candidate budgets checked

    def config(self, scenario: str, algo: str) -> TrainConfig:
        return protocol.run_config(self, scenario, algo, "plain")

    def candidates(self, algo: str) -> list[int]:
        return list(range(self.candidate_every, self.budget(algo) + 1, self.candidate_every))


def check_budgets(steps: np.ndarray, returns: np.ndarray, candidates: list[int]
                  ) -> tuple[list[dict[str, Any]], int | None]:
    """The plateau check of the curves ``returns`` ``[seeds, points]`` (evaluated at
    ``steps`` ``[points]``) cut at each candidate budget, and the proposed budget: the
    smallest candidate from which on every checked candidate plateaus (``None`` if the
    last one does not). Candidates with too few evaluations to check are left out."""
    checks = []
    for budget in candidates:
        points = int(np.searchsorted(steps, budget, side="right"))
        try:
            result = plateau(returns[:, :points])
        except ValueError:
            continue
        checks.append({"budget": int(budget), **result})
    proposed = None
    for index in range(len(checks)):
        if all(c["plateaued"] for c in checks[index:]):
            proposed = checks[index]["budget"]
            break
    return checks, proposed


def train_cell(settings: Settings, scenario: str, algo: str, partial: Partial
               ) -> dict[str, Any]:
    """One scenario and learner's plain runs: the curves (checked by :func:`checked`)."""
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


def final_stats(cell: dict[str, Any], metric: str) -> dict[str, Any]:
    """Mean and 95% interval (within the metric's range) over seeds of ``metric`` at the
    last evaluation."""
    return summarise(np.array([curve[-1] for curve in cell["curves"][metric]]), metric)


def budgets_markdown(result: dict[str, Any]) -> str:
    settings = result["settings"]
    lines = [
        "# Budgets of the plain learners",
        "",
        *([protocol.quick_note(variants=False), ""] if settings.get("quick") else []),
        f"Budget seeds {settings['seeds']}; environment steps per seed: "
        + ", ".join(f"{steps:,} ({algo})" for algo, steps in result["budgets"].items()) + "; "
        f"evaluation every {settings['eval_every']:,} steps, {settings['eval_episodes']} "
        f"episodes per seed; candidate budgets every {settings['candidate_every']:,} steps. "
        "Plateaued: the mean over seeds of the last 20% of evaluations lies within the 95% "
        "Student-t interval of the 20% before. Proposed: the smallest candidate from which "
        "on every candidate plateaus (none: still moving at the end). Final values: mean "
        "and 95% interval over seeds at the last evaluation. Made by:",
        "",
        *(f"* `{run['command']}` at `{run['commit']}` on {run['device']}, {run['date']}: "
          f"{run['programs_trained']} program(s), {duration(run['wall_time_s'])}"
          + ("" if run["finished"] else " (stopped before the end)")
          for run in result["invocations"]),
        "",
        "| learner | scenario | plateaued at the end | proposed budget | return | success | "
        "danger | program |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for cell in result["cells"]:
        proposed = cell["proposed_budget"]
        lines.append(
            f"| {cell['algo']} | {cell['scenario']} | "
            f"{protocol.PLATEAU_WORDS[cell['plateaued_at_budget']]} | "
            f"{'none' if proposed is None else f'{proposed:,}'} | "
            f"{format_mean_ci(final_stats(cell, 'return'), False, digits=1)} | "
            f"{format_mean_ci(final_stats(cell, 'success_rate'), True, digits=1)} | "
            f"{format_mean_ci(final_stats(cell, 'danger_frequency'), True, digits=1)} | "
            f"{duration(cell['train_s'] + cell['compile_s'])} on {cell['device']} at "
            f"`{cell['commit']}` |")
    skipped = [line for cell in result["cells"]
               for line in nonfinite_runs(cell, f"{cell['scenario']}, {cell['algo']}")]
    runs = sum(len(cell["seeds"]) for cell in result["cells"])
    lines += ["", nonfinite_text(skipped, f"the {runs} runs")]
    return "\n".join(lines) + "\n"


def draw_budget_curves(cells: dict[tuple[str, str], dict], out: Path, quick: bool = False
                       ) -> list[Path]:
    """``curves_<algo>.png``: return, success and danger along training per scenario
    (``quick``: the titles say the quick mode)."""
    paths = []
    for algo in dict.fromkeys(a for _, a in cells):
        curves = Curves()
        for (scenario, cell_algo), cell in cells.items():
            if cell_algo == algo:
                curves.add(scenario, cell["env_steps"],
                           {m: np.asarray(cell["curves"][m]) for m in FINAL_METRICS})
        path = out / f"curves_{algo}.png"
        draw_curves(curves, path, metrics=FINAL_METRICS,
                    title=f"{protocol.QUICK_FIGURE if quick else ''}plain {algo}, budget "
                    "seeds: is the return still moving?")
        paths.append(path)
    return paths


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="The budgets at which the plain learners' "
                        "evaluated return has levelled off, on the budget seeds.")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS),
                        help="learners (default: all three)")
    parser.add_argument("--scenarios", nargs="+", choices=ALL_SCENARIOS,
                        default=list(SCENARIOS), help="scenarios (default: the paper's three)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per seed for every learner (default: the "
                        f"protocol's budgets, {protocol.budgets_text()})")
    parser.add_argument("--eval-every", type=cli.positive_int, default=None,
                        help="environment steps between evaluations (default: "
                        f"{protocol.EVAL_EVERY})")
    parser.add_argument("--candidate-every", type=cli.positive_int, default=None,
                        help=f"candidate budgets are its multiples (default: {CANDIDATE_EVERY})")
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=3,
                        help="seeds per learner, at least 2 (default: %(default)s)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=protocol.BUDGET_SEED_OFFSET,
                        help="first seed (default: %(default)s; the tables use 0-9, the "
                        "searches 100-102)")
    parser.add_argument("--eval-episodes", type=cli.positive_int, default=None,
                        help="fresh episodes per evaluation and seed (default: "
                        f"{protocol.EVAL_EPISODES})")
    parser.add_argument("--quick", action="store_true",
                        help=protocol.quick_help("the seeds of --seeds"))
    add_out_options(parser, "budgets", default_text="runs/budgets")
    add_checkpoint_option(parser)
    return parser


def settings_from(args: argparse.Namespace) -> Settings:
    seeds = tuple(range(args.seed_offset, args.seed_offset + args.seeds))
    problem = protocol.seed_overlap(seeds, args.seed_offset, ("the tables'", "the selection"))
    if problem:
        raise cli.UsageError(problem)
    # --quick changes the defaults (tiny sizes); what is given on the command line stays.
    defaults = ({"steps": 10 * protocol.QUICK_STEPS, "eval_every": protocol.QUICK_EVAL_EVERY,
                 "eval_episodes": protocol.QUICK_EVAL_EPISODES,
                 "candidate_every": QUICK_CANDIDATE_EVERY} if args.quick else
                {"steps": None, "eval_every": protocol.EVAL_EVERY,
                 "eval_episodes": protocol.EVAL_EPISODES, "candidate_every": CANDIDATE_EVERY})
    fields: dict[str, Any] = {
        name: default if getattr(args, name) is None else getattr(args, name)
        for name, default in defaults.items()}
    fields.update(seeds=seeds, quick=args.quick, scenarios=tuple(dict.fromkeys(args.scenarios)),
                  algos=tuple(dict.fromkeys(args.algos)))
    settings = Settings(**fields)
    for scenario in settings.scenarios:  # every configuration validated before compiling
        for algo in settings.algos:
            settings.config(scenario, algo)
    for algo in settings.algos:
        if not settings.candidates(algo):
            raise cli.UsageError(
                f"--candidate-every {settings.candidate_every:,} is above the budget "
                f"{settings.budget(algo):,} of {algo}: no candidate budget would be checked")
    return settings


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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
    # The summary reports every cell of the folder made with these settings, whichever
    # invocation made it (the budgets select nothing, so nothing depends on which are named).
    record = settings_record(settings)
    for path in sorted((out / "cells").glob("*.json")):
        cell = read_json(path)
        if cell_is_current(cell, record):
            cells.setdefault((cell["scenario"], cell["algo"]), cell)
    ordered = {(s, a): checked(cells[(s, a)], settings)
               for a in ALGOS for s in ALL_SCENARIOS if (s, a) in cells}
    result = {
        "settings": record,
        "budgets": {a: settings.budget(a) for a in dict.fromkeys(a for _, a in ordered)},
        "invocations": ledger.invocations,
        "cells": list(ordered.values()),
    }
    write_atomic(out / "budgets.json", json.dumps(result) + "\n")
    write_atomic(out / "budgets.md", budgets_markdown(result))
    figures = draw_budget_curves(ordered, out, bool(record.get("quick")))
    print(budgets_markdown(result))
    print(f"wrote {out / 'budgets.md'}, budgets.json, "
          + ", ".join(path.name for path in figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(cli.run_stoppable(PROG, main, STOPPED_KEPT))
