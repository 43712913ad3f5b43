"""Budgets at which the plain learners have levelled off: ``python experiments/budgets.py``.

    python experiments/budgets.py --steps 2000000 --seeds 3 --out runs/budgets
    python experiments/budgets.py --algos maddpg --scenarios nominal --steps 40000 \\
        --eval-every 10000 --seeds 2 --out /tmp/b            # small, for the tests

Trains the **plain** learners only (never CCR or the pessimistic baseline: the control
decides the budget) in every scenario for ``--steps`` environment steps per seed,
``--seeds`` seeds at once per scenario and learner (one vmapped program each, seeds
200, 201, ... by default: disjoint from the tables' seeds 0-9 and the searches' selection
seeds 100-102), and reports, for each candidate budget (every ``--candidate-every``
steps), whether the evaluated return has plateaued by then (:func:`ccrjax.run.stats.plateau`:
the mean of the last 20% of evaluations lies within the 95% interval of the 20% before).
The proposed budget of a scenario and learner is the smallest candidate from which on
every larger candidate plateaus too. Writes ``budgets.json`` (the curves and the checks)
and ``budgets.md`` to ``--out`` (default ``runs/budgets``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
import protocol

from ccrjax import cli
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.run.stats import plateau
from ccrjax.training import ALGOS, TrainConfig
from ccrjax.training.grid import train_grid

SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
SEED_OFFSET = protocol.BUDGET_SEED_OFFSET


def check_budgets(steps: np.ndarray, returns: np.ndarray, candidates: list[int]
                  ) -> tuple[list[dict[str, Any]], int | None]:
    """The plateau check of the curves ``returns`` ``[seeds, points]`` cut at each candidate
    budget, and the proposed budget (``None`` if the curve never settles)."""
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


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog="python experiments/budgets.py",
                        description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    parser.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--steps", type=int, default=2_000_000,
                        help="environment steps per seed (default 2,000,000)")
    parser.add_argument("--eval-every", type=int, default=50_000,
                        help="environment steps between evaluations (default 50,000)")
    parser.add_argument("--candidate-every", type=int, default=250_000,
                        help="candidate budgets are multiples of this (default 250,000)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per learner (default 3)")
    parser.add_argument("--seed-offset", type=int, default=SEED_OFFSET)
    parser.add_argument("--eval-episodes", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path("runs/budgets"))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.seeds < 2:
        parser.error(f"--seeds must be at least 2 for the plateau's interval, got {args.seeds}")
    for name in ("steps", "eval_every", "candidate_every", "eval_episodes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be an integer >= 1")
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    if set(seeds) & (set(protocol.TABLE_SEEDS) | set(protocol.SELECTION_SEEDS)):
        parser.error("--seed-offset: the budget seeds must stay clear of the tables' seeds "
                     f"{protocol.TABLE_SEEDS[0]}-{protocol.TABLE_SEEDS[-1]} and the selection "
                     f"seeds {protocol.SELECTION_SEEDS}")
    try:  # every configuration validated before anything compiles
        for algo in args.algos:
            for scenario in args.scenarios:
                TrainConfig(algo=algo, scenario=scenario, variant="plain",
                            total_env_steps=args.steps, eval_every=args.eval_every,
                            eval_episodes=args.eval_episodes)
    except ValueError as error:
        parser.error(str(error))
    args.out.mkdir(parents=True, exist_ok=True)
    candidates = list(range(args.candidate_every, args.steps + 1, args.candidate_every))
    rows, start = [], time.time()
    device = str(jax.devices()[0].device_kind)
    for algo in args.algos:
        for scenario in args.scenarios:
            config = TrainConfig(algo=algo, scenario=scenario, variant="plain",
                                 total_env_steps=args.steps, eval_every=args.eval_every,
                                 eval_episodes=args.eval_episodes)
            began = time.time()
            runs = train_grid(config, seeds)
            steps = np.asarray(runs.history["env_steps"][0])
            checks, proposed = check_budgets(steps, runs.history["return"], candidates)
            row = {
                "algo": algo, "scenario": scenario, "seeds": seeds,
                "env_steps": steps.tolist(),
                "curves": {m: runs.history[m].tolist() for m in
                           ("return", "success_rate", "danger_frequency", "target_distance")},
                "checks": checks, "proposed_budget": proposed,
                "compile_s": runs.compile_s, "run_s": runs.run_s,
                "wall_s": time.time() - began,
            }
            rows.append(row)
            final = {m: float(np.mean(runs.history[m][:, -1])) for m in
                     ("return", "success_rate", "danger_frequency")}
            print(f"{algo:7} {scenario:16} proposed {proposed} · final return "
                  f"{final['return']:.1f} success {final['success_rate']:.3f} danger "
                  f"{final['danger_frequency']:.3f} · {row['wall_s']:.0f} s", flush=True)
            result = {"rows": rows, "steps": args.steps, "eval_every": args.eval_every,
                      "device": device, "commit": git_commit(),
                      "command": " ".join(["python experiments/budgets.py",
                                           *(argv if argv is not None else sys.argv[1:])]),
                      "seconds": time.time() - start}
            write_atomic(args.out / "budgets.json", json.dumps(result))
    lines = ["| learner | scenario | proposed budget | final return | final success | "
             "final danger |", "|---|---|---|---|---|---|"]
    for row in rows:
        curves = row["curves"]
        lines.append(
            f"| {row['algo']} | {row['scenario']} | {row['proposed_budget']} | "
            f"{np.mean([c[-1] for c in curves['return']]):.1f} | "
            f"{np.mean([c[-1] for c in curves['success_rate']]):.3f} | "
            f"{np.mean([c[-1] for c in curves['danger_frequency']]):.3f} |")
    lines += ["", f"`{result['command']}`, commit `{result['commit']}`, {device}, "
              f"{result['seconds']:.0f} s"]
    write_atomic(args.out / "budgets.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
