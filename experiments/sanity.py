"""Do the learners learn? Each one, at its default budget, on the hazard-free `nominal` task.

    python experiments/sanity.py                 # all three learners, one table
    python experiments/sanity.py --algos maddpg  # one learner
    python experiments/sanity.py --json          # one JSON object per line

Trains one seed per learner with the default configuration (``TrainConfig``),
evaluates the deterministic policy on fresh episodes, and prints: learner, success
rate, dangerous-behaviour frequency, return, wall time (compilation included) and
environment steps.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/sanity.py")

import dataclasses
import json
import sys
import time

import jax

from ccrjax import cli
from ccrjax.training import ALGOS, TrainConfig, make_train

PROG = "python experiments/sanity.py"

def sanity_config(algo: str, steps: int | None, eval_episodes: int) -> TrainConfig:
    """The default configuration of ``algo`` on ``nominal``, ``steps`` if given, evaluated
    once at the end (raises ``ValueError`` on a budget that ends before learning)."""
    config = TrainConfig(algo=algo, scenario="nominal", eval_episodes=eval_episodes)
    if steps is not None:
        config = dataclasses.replace(config, total_env_steps=steps)
    # One evaluation at the end is all this check needs.
    return dataclasses.replace(config, eval_every=config.budget)


def run(algo: str, seed: int, steps: int | None, eval_episodes: int) -> dict:
    config = sanity_config(algo, steps, eval_episodes)
    program = make_train(config)
    start = time.perf_counter()
    state, history = jax.jit(program.train)(jax.random.PRNGKey(seed))
    history = jax.device_get(history)
    wall = time.perf_counter() - start
    program.raise_if_nonfinite(state)
    return {
        "algo": algo,
        "success_rate": float(history["success_rate"][-1]),
        "danger_frequency": float(history["danger_frequency"][-1]),
        "return": float(history["return"][-1]),
        "initial_return": float(history["return"][0]),
        "env_steps": int(state.env_steps),
        "updates": int(state.updates),
        "wall_s": round(wall, 1),
        "seed": seed,
    }


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog=PROG,
                        description=__doc__.split("\n")[0])
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS),
                        help="learners to train, one seed each (default: all three)")
    parser.add_argument("--seed", type=cli.seed_int, default=0,
                        help="random seed (default: %(default)s)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: each learner's default "
                        "budget)")
    parser.add_argument("--eval-episodes", type=cli.int_in(1, 65536), default=128,
                        help="episodes of the final evaluation (default: %(default)s)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    for algo in args.algos:  # every configuration checked before anything compiles
        try:
            sanity_config(algo, args.steps, args.eval_episodes)
        except ValueError as error:
            cli.fail(parser.prog, str(error))

    rows = [run(algo, args.seed, args.steps, args.eval_episodes) for algo in args.algos]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    header = (
        f"{'learner':8} {'success':>8} {'danger':>7} {'return':>9} {'wall s':>7} "
        f"{'env steps':>10}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        print(
            f"{row['algo']:8} {row['success_rate']:8.1%} {row['danger_frequency']:7.1%} "
            f"{row['return']:9.1f} {row['wall_s']:7.1f} {row['env_steps']:10d}"
        )
    print(f"\n{jax.devices()[0].device_kind}, seed {args.seed}, nominal scenario", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(
        PROG, main,
        "nothing to keep (it prints its results as they come)"))
