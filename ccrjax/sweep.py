"""``python -m ccrjax.sweep``: a search of one scenario and learner, in one program.

``experiments/search.py`` (``make sweep``, ``make penalty-sweep``) searches every scenario
and learner under the protocol and its selection rule; this command searches one::

    python -m ccrjax.sweep --variant ccr --scenario hidden_obstacle --algo maddpg \\
        --values 0 1 3 10 30 100 --seeds 3 --out runs/sweep
    python -m ccrjax.sweep --variant pessimistic --values 0 0.1 1 10 --out runs/penalty

which trains ``len(values) x seeds`` runs at once (0 is the reference: the pessimistic
penalty 0 is exactly the plain learner; CCR's lambda 0 leaves the reward unchanged while
its robots still observe the shared scores) and writes ``sweep.md`` (a table of the metrics per
value, mean and 95% interval over seeds), ``sweep.json`` (per-seed values) and
``tradeoff.png`` (dangerous-behaviour frequency against success rate, one point per
value with its intervals). Started as several processes (``--coordinator``,
``--num-processes``, ``--process-id``: :mod:`ccrjax.run.distributed`), each trains its share
of the runs and process 0 writes the results.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python -m ccrjax.sweep")

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax

from ccrjax import cli
from ccrjax.cli import UsageError
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.run import distributed
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.run.stats import format_mean_ci
from ccrjax.run.sweep_grid import (
    DEFAULT_VALUES,
    REFERENCE_TEXT,
    SEARCHED_PARAMETER,
    grid_params,
    nonfinite_runs,
    nonfinite_text,
    search_grid,
    search_rows,
)
from ccrjax.training import ALGOS, LEARNING_STARTS, TrainConfig, default_budgets
from ccrjax.training.grid import train_grid
from ccrjax.viz.plots import draw_search_tradeoff

PROG = "python -m ccrjax.sweep"


# ---------------------------------------------------------------------------- the command
def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Search the pessimistic penalty or CCR's lambda "
                        "for one scenario and learner: every value x seed trained at once, then "
                        "a table and the safety-efficiency trade-off.")
    parser.add_argument("--variant", choices=sorted(SEARCHED_PARAMETER), default="ccr",
                        help="what to search: ccr and its parts with an intrinsic reward, "
                        "ccr_reward and ccr_perfect (lambda), pessimistic (penalty) or "
                        "lagrangian (cost limit) (default: %(default)s)")
    parser.add_argument("--scenario", choices=tuple(SCENARIOS), default="hidden_obstacle",
                        help="scenario (default: %(default)s)")
    parser.add_argument("--algo", choices=ALGOS, default="maddpg",
                        help="learner (default: %(default)s)")
    parser.add_argument("--values", type=cli.non_negative_float, nargs="+", default=None,
                        help="values of lambda or of the penalty, each once; 0 is the reference "
                        "(default: 0 and the protocol's six values, docs/protocol.md)")
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=3,
                        help="seeds per value, at least 2 for an interval (default: %(default)s)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=100,
                        help="first seed (default: %(default)s, the selection seeds: disjoint "
                        "from the tables' 0-9)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: python -m ccrjax.train's budget "
                        "of the learner, " + ", ".join(f"{steps:,} for {algo}"
                                              for algo, steps in default_budgets().items())
                        + "; the protocol's searches, experiments/search.py, use more)")
    parser.add_argument("--learning-starts", type=cli.int_in(0), default=LEARNING_STARTS,
                        help="transitions per seed before the first update "
                        "(default: %(default)s)")
    parser.add_argument("--eval-episodes", type=cli.int_in(1, 65536), default=128,
                        help="episodes per evaluation (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"),
                        help="output folder (default: %(default)s)")
    parser.add_argument("--force", action="store_true",
                        help="replace the sweep that --out already holds")
    distributed.add_options(parser)
    return parser


def check_sweep_out(out: Path, force: bool) -> None:
    """Refuses, before anything compiles, an ``--out`` that is a file, that holds other
    files than a sweep's, or that already holds a sweep (unless ``force``), then creates
    the folder, so that no training ends in a folder its results cannot be written to."""
    if out.is_dir() and (out / "sweep.json").exists():
        if not force:
            raise UsageError(f"--out {out} already holds a sweep (sweep.json): name another "
                             "folder, or give --force to replace it")
    elif out.is_dir() and any(out.iterdir()):
        raise UsageError(f"--out {out} holds other files than a sweep's: name a new or "
                         "empty folder")
    if distributed.is_primary():  # several processes: process 0 writes the results
        cli.make_folder(out)


def run_sweep(args: argparse.Namespace) -> dict[str, Any]:
    config = TrainConfig(algo=args.algo, scenario=args.scenario, variant=args.variant,
                         total_env_steps=args.steps, eval_episodes=args.eval_episodes,
                         learning_starts=args.learning_starts)
    config = dataclasses.replace(config, eval_every=config.budget // 10 or 1)
    values = [0.0, *DEFAULT_VALUES[args.variant]] if args.values is None else args.values
    repeated = sorted({float(v) for v in values if values.count(v) > 1})
    if repeated:
        raise UsageError("--values repeats " + ", ".join(f"{v:g}" for v in repeated)
                         + ": give each value once")
    values = sorted(float(v) for v in values)
    check_sweep_out(args.out, args.force)
    seeds = [args.seed_offset + k for k in range(args.seeds)]
    commit = git_commit()  # the code that trains is the code loaded now
    name, grid_seeds, grid_values = search_grid(config, values, seeds)
    schedule = config.schedule()
    for note in schedule["notes"]:  # rounded to whole iterations: said, and recorded
        print(f"{PROG}: note: {note}", file=sys.stderr, flush=True)
    print(f"{PROG}: {args.algo} + {args.variant} on {args.scenario}: {len(values)} {name} x "
          f"{len(seeds)} seeds = {len(grid_seeds)} runs of {config.total_env_steps_run:,} "
          "steps, one program", file=sys.stderr, flush=True)
    runs = train_grid(config, grid_seeds, grid_params(config, name, grid_values),
                      log=lambda text: print(text, file=sys.stderr, flush=True))
    result = {
        "variant": args.variant, "parameter": name,
        "scenario": args.scenario, "algo": args.algo,
        "env_steps": config.total_env_steps_run, "schedule": schedule,
        "eval_episodes": args.eval_episodes, "compile_s": runs.compile_s, "run_s": runs.run_s,
        "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()],
        "command": " ".join([PROG, *sys.argv[1:]]), "commit": commit,
        "rows": search_rows(runs, values, grid_values, seeds),
        "grid_seeds": grid_seeds, "grid_values": grid_values,
        "nonfinite_iteration": runs.nonfinite_iteration.tolist(),
    }
    if not distributed.is_primary():
        return result
    write_atomic(args.out / "sweep.json", json.dumps(result, indent=2) + "\n")
    write_atomic(args.out / "sweep.md", sweep_table(result))
    draw_tradeoff(result, args.out / "tradeoff.png")
    return result


def reference_text(result: dict[str, Any]) -> str:
    """What the value 0 is, where the sweep has it (:data:`REFERENCE_TEXT`)."""
    if not any(row["value"] == 0 for row in result["rows"]):
        return "; no value 0, so no reference"
    return "; " + REFERENCE_TEXT[result["parameter"]]


def sweep_table(result: dict[str, Any]) -> str:
    name = result["parameter"]
    lines = [
        f"# Search of {name}: {result['algo']} + {result['variant']} on {result['scenario']}",
        "",
        f"{result['env_steps']:,} environment steps per run, {len(result['rows'][0]['seeds'])} "
        f"seeds per value, {result['eval_episodes']} evaluation episodes; mean [95% CI] over "
        "seeds (Student t, clipped to the metric's range)"
        + reference_text(result) + ". Command: `" + result["command"] + "`.",
        "",
        f"| {name} | danger frequency | success rate | return | distance to hazard |",
        "|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        cells = [format_mean_ci(row[metric], percent) for metric, percent in (
            ("danger_frequency", True), ("success_rate", True), ("return", False),
            ("hazard_distance", False))]
        lines.append(f"| {row['value']:g} | " + " | ".join(cells) + " |")
    skipped = nonfinite_runs(result, f"{result['algo']} + {result['variant']}")
    runs = f"the {len(result['grid_seeds'])} runs"
    return "\n".join([*lines, "", nonfinite_text(skipped, runs)]) + "\n"


def draw_tradeoff(result: dict[str, Any], path: Path) -> None:
    """Danger frequency against success rate, one point per value with 95% intervals."""
    title = f"{result['algo']} + {result['variant']}, {result['scenario']}: safety vs efficiency"
    draw_search_tradeoff({title: result["rows"]}, result["parameter"], path)


def main(argv: Sequence[str] | None = None) -> int:
    return terminal.run_command(PROG, lambda: _main(argv),
                                "nothing was written (the search writes its files when it ends)")


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    cli.enable_compilation_cache(cli.default_cache_dir())
    try:
        result = run_sweep(args)
    except (UsageError, ValueError) as error:
        cli.fail(PROG, str(error))
    if not distributed.is_primary():
        return 0
    print(sweep_table(result))
    print(f"wrote {args.out / 'sweep.md'}, {args.out / 'sweep.json'}, "
          f"{args.out / 'tradeoff.png'} (training {result['run_s']:.0f} s, compiling "
          f"{result['compile_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
