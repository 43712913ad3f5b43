"""The constrained baseline's tables: the Lagrangian beside plain, pessimistic and CCR.

    python experiments/constrained.py --out experiments/results/constrained --force
    python experiments/constrained.py --quick --cost-limit 0.05 --scenarios turbulence \\
        --algos iddpg --out /tmp/q                   # the pipeline at a tiny size

Under the amendment of 2026-12-02 (``docs/protocol.md``): trains the ``lagrangian``
variant's cells, the tables' seeds 0-9 on the 9 scenario x learner pairs at
``protocol.LAGRANGIAN_BUDGET`` steps, with the cost limit its search chose at that budget
(``--lagrangian-search``, default ``experiments/results/search_lagrangian``; ``--cost-limit``
overrides). Once all 9 cells exist it reads the other variants at the same budget from the
6M tables' cells (``--tables``) and the three searches' choices there (``--searches`` for
lambda's and the penalty's, read at the budget from the 6M searches; where those choose
other values than the 6M tables', their cells from ``--at-budget-tables``), and writes
``constrained.json``, ``constrained.md`` and ``multiplier_<scenario>.png``
(:mod:`experiments.constrained_analysis`, :mod:`experiments.constrained_report`); into
``experiments/results/constrained`` it also regenerates the results report.

Cost: 90 runs of 2,000,000 steps, about 6 to 9 hours of a 2-core CPU (IDDPG, MADDPG and
MAAC at 5,000 to 10,000 environment steps per second); cells and the program in training
are resumable as the tables' are.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/constrained.py")

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import write_atomic
from ccrjax.training import ALGOS, TrainConfig
from experiments import protocol
from experiments.cell_identity import settings_record
from experiments.constrained_report import report
from experiments.ledger import (
    RESULTS,
    STOPPED_KEPT,
    Partial,
    add_checkpoint_option,
    add_no_train_option,
    add_out_options,
    check_quick_out,
    open_experiment,
    read_json,
    refuse_untrained,
    repo_relative,
)
from experiments.paper import PAPER_SCENARIOS
from experiments.results_report import write_report
from experiments.tables_grid import QUICK, Job, job_cells, run_grid, variant_cell_path

PROG = "python experiments/constrained.py"
VARIANT = "lagrangian"
# Pessimistic and CCR at the budget with the rule's choices there, where they are not the
# 6M tables' (the amendment's "reported beside"): experiments/tables.py --steps 2000000,
# or the 3M tables where their value is the rule's (a run's first 2M steps are the 2M run).
AT_BUDGET_TABLES = RESULTS / "constrained" / "tables_at_budget"
AT_BUDGET_SOURCES = (AT_BUDGET_TABLES, RESULTS / "tables")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What every Lagrangian cell is trained with (a cell made otherwise is redone)."""

    cost_limit: float  # d: the search's choice at the budget
    seeds: tuple[int, ...] = protocol.TABLE_SEEDS
    behaviour_episodes: int = 64  # recorded episodes per seed (the arrival analysis)

    def config(self, scenario: str, algo: str, variant: str = VARIANT) -> TrainConfig:
        return protocol.run_config(self, scenario, algo, variant)

    def run_params(self, variant: str) -> dict[str, float]:
        return {"cost_limit": self.cost_limit}


def jobs_of(settings: Settings) -> list[Job]:
    return [Job(scenario, algo, (VARIANT,)) for scenario in PAPER_SCENARIOS for algo in ALGOS
            if scenario in settings.scenarios and algo in settings.algos]


def chosen_limit(given: float | None, quick: bool, search: Path) -> tuple[float, str]:
    """The cost limit and where it came from: given, the quick mode's 0.05, or the
    Lagrangian search's protocol choice at :data:`protocol.LAGRANGIAN_BUDGET`."""
    if given is not None:
        return given, "given on the command line"
    if quick:
        return 0.05, "the quick mode's fixed value"
    path = search / "search.json"
    result = read_json(path)
    if not result or "selection" not in result:
        raise cli.UsageError(f"no Lagrangian search result at {path}: run experiments/search.py "
                             "--variant lagrangian first, name its folder with "
                             "--lagrangian-search, or give --cost-limit")
    chosen = result["selection"]
    budgets = {algo: protocol.LAGRANGIAN_BUDGET for algo in ALGOS}
    if not chosen.get("protocol") or result.get("budgets") != budgets:
        why = chosen.get("provisional_because") or f"budgets {result.get('budgets')}"
        raise cli.UsageError(f"the Lagrangian search at {path} is not the protocol's choice "
                             f"({why}): finish it on all 9 pairs at {budgets}, or give "
                             "--cost-limit")
    return float(chosen["value"]), f"selected by the search in {repo_relative(path.parent)}"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cost-limit", type=cli.float_in(0.0, 1.0), default=None,
                        help="the cost limit (default: the Lagrangian search's choice)")
    parser.add_argument("--lagrangian-search", type=Path, default=RESULTS / "search_lagrangian",
                        help="the Lagrangian search's folder (default: %(default)s)")
    parser.add_argument("--searches", type=Path, default=RESULTS / "search_6m",
                        help="the folder of the ccr/ and pessimistic/ searches whose "
                        "evaluations at the budget the rule is applied to (default: "
                        "%(default)s)")
    parser.add_argument("--at-budget-tables", type=Path, nargs="+",
                        default=list(AT_BUDGET_SOURCES),
                        help="where the pessimistic and CCR cells of the penalty and lambda "
                        "the rule chose at the budget are read, where those are not the 6M "
                        "tables': each variant's from the first of these folders that holds "
                        "them, tables made at the budget (experiments/tables.py --steps) or "
                        "longer tables of the same seeds, read at the budget (default: "
                        f"{' '.join(str(f) for f in AT_BUDGET_SOURCES)})")
    parser.add_argument("--tables", type=Path, default=RESULTS / "tables_6m",
                        help="the tables whose plain, pessimistic and CCR cells are read at "
                        "the budget (default: %(default)s)")
    parser.add_argument("--scenarios", nargs="+", choices=PAPER_SCENARIOS,
                        default=list(PAPER_SCENARIOS), help="train only these scenarios' cells")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS),
                        help="train only these learners' cells")
    parser.add_argument("--quick", action="store_true", help=protocol.quick_help())
    add_out_options(parser, "constrained", default_text="runs/constrained")
    add_checkpoint_option(parser)
    add_no_train_option(parser)
    distributed.add_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    out = args.out or Path("runs/constrained")
    sources: dict[str, str] = {}

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        fields: dict[str, Any] = ({key: QUICK[key] for key in ("steps", "seeds", "eval_every",
                                                                "eval_episodes")}
                                  if args.quick else {"steps": protocol.LAGRANGIAN_BUDGET})
        if args.quick:
            fields.update(quick=True, behaviour_episodes=QUICK["behaviour_episodes"])
        fields["scenarios"] = tuple(dict.fromkeys(args.scenarios))
        fields["algos"] = tuple(dict.fromkeys(args.algos))
        limit, sources["cost_limit"] = chosen_limit(args.cost_limit, args.quick,
                                                    args.lagrangian_search)
        settings = Settings(cost_limit=limit, **fields)
        for job in jobs_of(settings):  # every configuration validated before compiling
            settings.config(job.scenario, job.algo)
        if args.no_train:
            refuse_untrained({job.name: variant_cell_path(out, job.scenario, job.algo, VARIANT)
                              for job in jobs_of(settings)}, settings_record(settings), out)
        return settings

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    trained = run_grid(settings, out, ledger, Partial(out, args.checkpoint_minutes),
                       jobs_of(settings))
    ledger.record(trained, finished=True)
    if not distributed.is_primary():
        return 0
    whole = dataclasses.replace(settings, scenarios=PAPER_SCENARIOS, algos=ALGOS)
    found = {(job.scenario, job.algo): job_cells(out, job, whole) for job in jobs_of(whole)}
    missing = [f"{s}-{a}" for (s, a), cells in found.items() if cells is None]
    if missing:
        print(f"{len(found) - len(missing)} of {len(found)} Lagrangian cells made in {out}; "
              f"the tables need them all (missing: {', '.join(missing)})")
        return 0
    lagrangian = {pair: cells[VARIANT] for pair, cells in found.items()}
    result, markdown, figures = report(lagrangian, whole, args.tables, args.searches,
                                       args.lagrangian_search, sources, out, ledger.invocations,
                                       resamples=200 if settings.quick else 2000,
                                       at_budget=args.at_budget_tables)
    write_atomic(out / "constrained.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "constrained.md", markdown)
    print(markdown)
    print(f"wrote {out / 'constrained.md'}, {out / 'constrained.json'} and "
          + ", ".join(str(f) for f in figures))
    if out.resolve().parent == RESULTS.resolve():  # the committed results: their report too
        print(f"wrote {write_report(RESULTS)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
