"""Does CCR change behaviour? The paper's behavioural analysis on ``hidden_obstacle``.

    python experiments/behaviour.py                 # train both, print the comparison
    python experiments/behaviour.py --json          # one JSON object
    python experiments/behaviour.py --seeds 5 --steps 400000 --figure out.png  # seeds 300-304

The paper (section "Behavioral Analysis"): with plain MADDPG every robot runs into
the hidden obstacle and moves away again; with MADDPG+CCR the first robots run
into it and the others steer away before touching it, warned by the leaders'
emergency scores, so that "robots trained with CCR-aided MADDPG get much farther
to the obstacle".

This script trains MADDPG and MADDPG+CCR (lambda 30 unless ``--lam``: an exploration; the
tables measure the same with the searched lambda) on ``hidden_obstacle``, the
same seeds, every seed of both in one program, then runs the same fresh
evaluation episodes (same starts, same obstacles) with each trained team and
measures, per episode:

* the robots' order of arrival at the obstacle: the step each robot first comes
  within ``--reach`` of the obstacle's surface (robots that never do come last,
  ordered by their closest approach);
* each robot's closest approach to the obstacle's surface during the episode
  (negative if its centre is inside the obstacle), and its average distance to the obstacle's
  centre (the paper's metric).

``plain_distance`` and ``ccr_distance`` are the mean closest approach of the robots
that reach the obstacle *later*, every robot but the first to arrive, **and end in
the target area** (a robot that keeps away by abandoning the task does not count),
over episodes and seeds; a larger value means the followers kept further from the
obstacle while still doing the task. ``experiments/tables.py`` measures the same in
every hidden-obstacle cell of the tables. The per-rank table gives the closest
approach for each arrival rank (all robots), with the ratio CCR / plain of the
average distance to the centre (the paper reports 1.2x to 4.7x).
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/behaviour.py")

import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

from ccrjax import cli
from ccrjax.run.folder import git_commit
from ccrjax.run.stats import mean_ci
from ccrjax.run.sweep_grid import nonfinite_log
from ccrjax.training import TrainConfig
from ccrjax.training.grid import train_grid
from ccrjax.viz.analysis import arrival_analysis, followers_closest
from ccrjax.viz.plots import draw_obstacle_distances
from experiments import protocol

EXPLORATION_SEEDS = 300  # first seed: apart from every seed set of docs/protocol.md


PROG = "python experiments/behaviour.py"

def train_and_measure(seeds: list[int], steps: int | None, episodes: int, reach: float,
                      lam: float, log) -> dict:
    results = {}
    analyses = {}
    key = jax.random.PRNGKey(2**20 + 7)  # evaluation episodes no training run has seen
    for variant in ("plain", "ccr"):
        config = TrainConfig(algo="maddpg", scenario="hidden_obstacle", variant=variant,
                             total_env_steps=steps)
        config = dataclasses.replace(config, eval_every=config.budget)
        log(f"training MADDPG {variant} on hidden_obstacle: {len(seeds)} seed(s) x "
            f"{config.budget:,} steps ...")
        params = {"lam": [lam] * len(seeds)} if variant == "ccr" else None
        runs = train_grid(config, seeds, params, record_episodes=episodes, record_key=key,
                          log=log)
        log(f"  trained in {runs.run_s:.0f} s")
        note = nonfinite_log(runs, f"MADDPG {variant}")
        if note:
            log(f"  {note}")
        recorded = runs.episodes
        analyses[variant] = arrival_analysis(recorded, reach)
        results[variant] = {
            "final_eval": {k: [float(x) for x in v] for k, v in runs.final.items()},
            "nonfinite_iteration": runs.nonfinite_iteration.tolist(),  # -1: all finite
            "danger_frequency": float(recorded["danger"].mean()),
        }
    per_rank = []
    num_robots = analyses["plain"]["closest"].shape[-1]
    for rank in range(num_robots):
        row = {"rank": rank + 1}
        for variant in ("plain", "ccr"):
            closest = analyses[variant]["closest"][..., rank]  # [G, E]
            centre = analyses[variant]["centre_distance"][..., rank]
            row[f"{variant}_closest"] = mean_ci(closest.mean(axis=1))
            row[f"{variant}_centre_distance"] = mean_ci(centre.mean(axis=1))
        row["centre_distance_ratio"] = (row["ccr_centre_distance"]["mean"]
                                        / row["plain_centre_distance"]["mean"])
        per_rank.append(row)
    followers = {v: followers_closest(analyses[v]) for v in ("plain", "ccr")}
    def measured_mean(values: np.ndarray) -> float:  # NaN where no seed had such a follower
        finite = values[np.isfinite(values)]
        return float(finite.mean()) if finite.size else float("nan")

    return {
        "plain_distance": measured_mean(followers["plain"]),
        "ccr_distance": measured_mean(followers["ccr"]),
        # Seeds with no successful follower have nothing to measure (NaN) and are left out.
        **{f"{v}_distance_ci95": mean_ci(followers[v][np.isfinite(followers[v])]
                                         if np.isfinite(followers[v]).any() else [np.nan])
           for v in ("plain", "ccr")},
        "per_rank": per_rank,
        "centre_distance_per_seed": {  # [seeds, rank]
            v: analyses[v]["centre_distance"].mean(axis=1).tolist() for v in ("plain", "ccr")},
        "seeds": seeds,
        "command": " ".join(["python experiments/behaviour.py", *sys.argv[1:]]),
        "commit": git_commit(),
        "episodes_per_seed": episodes,
        "reach": reach,
        "lam": lam,
        "runs": results,
    }


def draw_figure(result: dict, path: Path) -> None:
    """Per arrival rank: average distance to the obstacle's centre, plain vs CCR, with CIs."""
    distances = result["centre_distance_per_seed"]
    draw_obstacle_distances(distances["plain"], distances["ccr"], path)


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog=PROG,
                        description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=3,
                        help="seeds per variant, at least 2 (default: 3)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=EXPLORATION_SEEDS,
                        help="first seed (default: %(default)s, clear of the tables' 0-9, the "
                        "selection's 100-102 and the budgets' 200-202)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: MADDPG's 400,000)")
    parser.add_argument("--episodes", type=cli.positive_int, default=256,
                        help="evaluation episodes per seed (default: 256)")
    parser.add_argument("--reach", type=cli.float_in(0.0), default=0.3,
                        help="a robot 'reaches' the obstacle within this distance of its "
                        "surface (default: 0.3)")
    parser.add_argument("--lam", type=cli.non_negative_float, default=30.0,
                        help="CCR's lambda (default: 30, an exploration; the tables use the "
                        "searched one)")
    parser.add_argument("--figure", type=Path, default=None,
                        help="also draw the per-rank distances to this .png file")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    problem = protocol.seed_overlap(seeds, args.seed_offset, protocol.SEED_SETS)
    if problem:
        cli.fail(parser.prog, problem)
    try:  # the budget checked before anything compiles
        TrainConfig(algo="maddpg", scenario="hidden_obstacle", total_env_steps=args.steps)
    except ValueError as error:
        cli.fail(parser.prog, str(error))
    if args.figure is not None and (args.figure.suffix.lower() != ".png"
                                    or args.figure.is_dir() or not args.figure.parent.is_dir()):
        cli.fail(parser.prog, f"--figure {args.figure} must name a .png file in an existing "
                 "folder")

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    result = train_and_measure(seeds, args.steps, args.episodes, args.reach, args.lam, log)
    if args.figure is not None:
        draw_figure(result, args.figure)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"followers' closest approach to the obstacle surface (mean over robots 2..N that "
          "succeeded, "
          f"{args.episodes} episodes x {len(seeds)} seeds):")
    for name, value in (("MADDPG", result["plain_distance"]),
                        ("MADDPG+CCR", result["ccr_distance"])):
        print(f"  {name:<11} " + (f"{value:.3f}" if np.isfinite(value) else
                                  "none (no follower succeeded)"))
    print("\nevery robot, successful or not, by arrival rank: closest approach to the surface "
          "and average distance to the centre (ratio CCR / plain):")
    print(f"{'rank':>4} {'closest plain':>14} {'closest CCR':>12} {'centre plain':>13} "
          f"{'centre CCR':>11} {'ratio':>6}")
    for row in result["per_rank"]:
        print(f"{row['rank']:4d} {row['plain_closest']['mean']:14.3f} "
              f"{row['ccr_closest']['mean']:12.3f} {row['plain_centre_distance']['mean']:13.3f} "
              f"{row['ccr_centre_distance']['mean']:11.3f} {row['centre_distance_ratio']:6.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(
        PROG, main,
        "nothing was written (the results are written when the measurement ends)"))
