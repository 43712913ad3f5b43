"""The paper's Tables I and II under a valid protocol: ``make tables``.

    python experiments/tables.py --out experiments/results/tables --force   # the grid
    python experiments/tables.py --out runs/tables                          # elsewhere
    python experiments/tables.py --quick --out /tmp/q     # a tiny budget, for the tests
    python experiments/tables.py --algos maac --scenarios turbulence --out runs/lane1
                                  # part of the grid; the tables once all 18 programs exist
    python experiments/tables.py --algos ippo mappo --out experiments/results/tables_on_policy \
        --force                   # the on-policy family's 12 programs and tables, with its
                                  # own searches (experiments/results/search_on_policy)

Trains the grid 3 scenarios x 3 learners x 3 variants (plain, pessimistic, CCR) under the
protocol of ``docs/protocol.md`` (``experiments/protocol.py``): the tables' seeds 0-9, each
learner's budget (chosen on the plain learners), CCR's lambda and the pessimistic penalty
as selected by their searches (``experiments/search.py``, on the disjoint selection seeds;
``--lam`` and ``--penalty`` override). The grid's 18 programs, their cells and the
reference controllers' rows: :mod:`experiments.tables_grid`; the statistics:
:mod:`experiments.tables_statistics`; ``tables.md``: :mod:`experiments.tables_report`; the
figures: :mod:`experiments.tables_figures`. Writing into ``experiments/results/`` also
regenerates the results report, ``experiments/results/README.md``
(:mod:`experiments.results_report`).

Cost: 270 runs of 3,000,000 environment steps (30 per scenario and learner: 3 variants x 10
seeds), about 34 hours of a 2-core CPU and half an hour of one H100
(``docs/experiments.md``). Cells are resumable across invocations; the program in training
is checkpointed every ``--checkpoint-minutes`` into ``<out>/partial/`` and resumed from
there (:mod:`ccrjax.run.grid_checkpoint`).

Then ``tables.md`` and ``tables.json``: Tables I and II in the paper's layout with the
reference controllers' rows (go-to-goal, oracle), the final distance, the hazard distance
and the return; per cell the mean and Student-t 95% interval over seeds, the paper's
number, and Welch tests of CCR against plain and pessimistic; rliable's aggregate view over
the 9 scenario x learner pairs; the paper's headline numbers recomputed; the claim
scorecard; and the figures ``progress_<scenario>.png``, ``curves_<scenario>_<algo>.png``,
``trajectories_hidden_obstacle_maddpg.png``, ``distance_hidden_obstacle_maddpg.png``.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/tables.py")

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import write_atomic
from ccrjax.training import ALGOS
from experiments import protocol
from experiments.cell_identity import settings_record
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
from experiments.tables_figures import draw_figures
from experiments.tables_grid import (
    QUICK,
    VARIANTS,
    Settings,
    cell_stem,
    grid_cells,
    grid_jobs,
    job_cells,
    jobs_of,
    reference_rows,
    run_grid,
    variant_cell_path,
)
from experiments.tables_report import tables_markdown
from experiments.tables_statistics import summary

PROG = "python experiments/tables.py"
SEARCHES = RESULTS / "search"
# The on-policy learners' committed searches (docs/protocol.md, amendment of 2026-12-02).
ON_POLICY_SEARCHES = RESULTS / "search_on_policy"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0],
                        epilog=__doc__.split("\n\n")[3],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=None,
                        help=f"seeds per cell, at least 2 (default: {len(protocol.TABLE_SEEDS)})")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=None,
                        help="first seed (default: 0); must stay clear of the selection "
                        "seeds 100-102 and the budgets' 200-202")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: the protocol's budgets, "
                        f"{protocol.budgets_text()})")
    parser.add_argument("--lam", type=cli.non_negative_float, default=None,
                        help="CCR's lambda (default: the lambda search's choice, "
                        "<searches>/ccr/search.json)")
    parser.add_argument("--penalty", type=cli.non_negative_float, default=None,
                        help="the pessimistic penalty (default: the penalty search's choice, "
                        "<searches>/pessimistic/search.json)")
    parser.add_argument("--searches", type=Path, default=None,
                        help="the folder holding both searches' results, ccr/ and "
                        "pessimistic/, whose choices the tables use (default: the committed "
                        "ones, experiments/results/search; `make sweep` and `make "
                        "penalty-sweep` write runs/search; with --quick the default is "
                        "lambda 30 and penalty 1, and a named folder gives its quick "
                        "searches' provisional choices)")
    parser.add_argument("--scenarios", nargs="+", choices=PAPER_SCENARIOS,
                        default=list(PAPER_SCENARIOS),
                        help="train only these scenarios' programs (default: all three; the "
                        "tables are written once all 18 programs exist)")
    parser.add_argument("--algos", nargs="+", choices=protocol.EXPERIMENT_ALGOS,
                        default=list(ALGOS),
                        help="train only these learners' programs, of one family (default: "
                        "the paper's three; ippo mappo: the on-policy family's tables, with "
                        "its own searches, experiments/results/search_on_policy)")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                        help="train only the programs of these variants (default: all three; "
                        "plain trains beside pessimistic, in one program; pessimistic "
                        "without plain trains alone)")
    parser.add_argument("--quick", action="store_true",
                        help=protocol.quick_help())
    add_out_options(parser, "tables", default_text="runs/tables")
    add_checkpoint_option(parser)
    add_no_train_option(parser)
    distributed.add_options(parser)
    return parser


def selected(variant: str, given: float | None, quick: bool, searches: Path | None = None,
             steps: int | None = None, algos: tuple[str, ...] = ALGOS) -> tuple[float, str]:
    """The value of ``variant``'s parameter and where it came from: given, or the
    search's result in ``searches/<variant>/`` (default :data:`SEARCHES`), the protocol's
    choice only, made at the budgets these tables train (``steps`` per run, else the
    protocol's); with ``quick``, a fixed value unless ``searches`` names (quick) searches,
    whose provisional choice it then takes, to check the way from searches to tables.
    ``algos``: the learner family of the tables, whose searches (default
    :data:`ON_POLICY_SEARCHES` for the on-policy one) and budgets count."""
    if given is not None:
        return given, "given on the command line"
    if quick and searches is None:
        return {"ccr": 30.0, "pessimistic": 1.0}[variant], "the quick mode's fixed value"
    default = SEARCHES if algos == ALGOS else ON_POLICY_SEARCHES
    searches = default if searches is None else searches
    path = searches / variant / "search.json"
    search = read_json(path)
    if not search or "selection" not in search:
        option = "--lam" if variant == "ccr" else "--penalty"
        raise cli.UsageError(f"no {variant} search result at {path}: run experiments/search.py "
                             f"--variant {variant} first, name its folder's parent with "
                             f"--searches, or give {option}")
    chosen = search["selection"]
    if quick:
        return (float(chosen["value"]),
                f"the provisional choice of the search in {repo_relative(path.parent)}")
    if not chosen.get("protocol"):
        option = "--lam" if variant == "ccr" else "--penalty"
        why = chosen.get("provisional_because") or "made before selections said so"
        raise cli.UsageError(f"the {variant} search at {path} is not the protocol's choice "
                             f"({why}): finish it on all its pairs at the protocol's "
                             f"settings, or give {option}")
    budgets = {algo: protocol.budget(algo, steps) for algo in algos}
    if search.get("budgets") != budgets:  # e.g. the protocol's budgets changed after it ran
        raise cli.UsageError(f"the {variant} search at {path} trained the budgets "
                             f"{search.get('budgets')}, not these tables' {budgets}: run it "
                             "again at these budgets, or name searches made at them with "
                             "--searches")
    where = path.parent.name if searches == default else repo_relative(path.parent)
    fallback = " (its fallback: no value met the rule)" if chosen.get("fallback") else ""
    return float(chosen["value"]), f"selected by the search in {where}{fallback}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    out = args.out or Path("runs/tables")
    variants = tuple(dict.fromkeys(args.variants))
    sources: dict[str, str] = {}

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        fields: dict[str, Any] = dict(QUICK, quick=True) if args.quick else {}
        if args.steps is not None:
            fields["steps"] = args.steps
        offset = args.seed_offset if args.seed_offset is not None else fields.get(
            "seeds", protocol.TABLE_SEEDS)[0]
        count = args.seeds or len(fields.get("seeds", protocol.TABLE_SEEDS))
        fields["seeds"] = tuple(range(offset, offset + count))
        problem = protocol.seed_overlap(fields["seeds"], offset,
                                        ("the selection", "the budgets'"))
        if problem:
            raise cli.UsageError(problem)
        fields["scenarios"] = tuple(dict.fromkeys(args.scenarios))
        fields["algos"] = tuple(dict.fromkeys(args.algos))
        try:
            family = protocol.family(fields["algos"])
        except ValueError as error:
            raise cli.UsageError(str(error)) from None

        def validated(settings: Settings) -> Settings:
            # Every configuration validated before compiling.
            for job in jobs_of(settings, variants):
                for variant in job.variants:
                    settings.config(job.scenario, job.algo, variant)
            return settings

        # The searches' choices last: the command line's own problems are named first.
        settings = validated(Settings(lam=0.0, penalty=0.0, **fields))
        chosen, problems = {}, []
        for name, variant, given in (("lam", "ccr", args.lam),
                                     ("penalty", "pessimistic", args.penalty)):
            try:  # both named at once when both are missing
                chosen[name], sources[name] = selected(variant, given, args.quick,
                                                       args.searches, args.steps, family)
            except cli.UsageError as error:
                problems.append(str(error))
        if problems:
            raise cli.UsageError("; and ".join(problems))
        settings = validated(dataclasses.replace(settings, **chosen))
        if args.no_train:
            cells = [(job.scenario, job.algo, variant) for job in jobs_of(settings, variants)
                     for variant in job.variants]
            refuse_untrained({cell_stem(*cell): variant_cell_path(out, *cell) for cell in cells},
                             settings_record(settings), out)
        return settings

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    trained = run_grid(settings, out, ledger, Partial(out, args.checkpoint_minutes),
                       jobs_of(settings, variants))
    ledger.record(trained, finished=True)
    if not distributed.is_primary():  # process 0 writes the tables
        return 0
    cells, missing = grid_cells(out, settings)
    family = protocol.family(settings.algos)
    if missing:
        named = jobs_of(settings, variants)
        made = sum(job_cells(out, job, settings) is not None for job in named)
        total = len(grid_jobs(family))
        print(f"{made} of the {len(named)} programs this command names made in {out}; the "
              f"tables are written once the whole grid's {total} exist (missing: "
              f"{', '.join(missing)}): run again naming the others, or all")
        return 0
    controllers = reference_rows(settings)
    whole = dataclasses.replace(settings, scenarios=PAPER_SCENARIOS, algos=family)  # all exist
    result = summary(cells, whole, ledger.invocations, controllers, sources)
    write_atomic(out / "tables.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "tables.md", tables_markdown(result))
    figures = draw_figures(cells, out, settings.quick)
    print(tables_markdown(result))
    print(f"wrote {out / 'tables.md'}, {out / 'tables.json'} and "
          + ", ".join(str(f) for f in figures))
    if out.resolve().parent == RESULTS.resolve():  # the committed results: their report too
        print(f"wrote {write_report(RESULTS)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
