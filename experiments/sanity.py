"""Do the learners learn? Each one, at its default budget, on the hazard-free `nominal` task.

    python experiments/sanity.py                 # every learner, one table
    python experiments/sanity.py --algos maddpg  # one learner
    python experiments/sanity.py --json          # one JSON object per line
    python experiments/sanity.py --algos ippo mappo --seeds 3 --eval-every 51200 \
        --steps 400000                           # the curve IPPO's and MAPPO's defaults came from

Trains one seed per learner (``--seeds N``: seeds ``--seed`` to ``--seed + N - 1`` in one
vmapped program) with the default configuration (``TrainConfig``), evaluates the
deterministic policy on fresh episodes, and prints: learner, success rate,
dangerous-behaviour frequency, return, wall time (compilation included) and environment
steps, over the seeds their minimum and maximum; with ``--eval-every``, also the success of
every seed at every evaluation.
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
from ccrjax.registry import learner_names
from ccrjax.run.folder import git_commit
from ccrjax.training import TrainConfig, make_train

PROG = "python experiments/sanity.py"

def sanity_config(algo: str, steps: int | None, eval_episodes: int,
                  eval_every: int | None = None) -> TrainConfig:
    """The default configuration of ``algo`` on ``nominal``, ``steps`` if given, evaluated
    every ``eval_every`` steps or once at the end (raises ``ValueError`` on a budget that
    ends before learning)."""
    config = TrainConfig(algo=algo, scenario="nominal", eval_episodes=eval_episodes)
    if steps is not None:
        config = dataclasses.replace(config, total_env_steps=steps)
    return dataclasses.replace(config, eval_every=eval_every or config.budget)


def run(algo: str, seed: int, steps: int | None, eval_episodes: int, seeds: int = 1,
        eval_every: int | None = None) -> dict:
    """Trains seeds ``seed .. seed + seeds - 1`` of ``algo`` in one program; the final
    metrics per seed (lists), and the success curve."""
    config = sanity_config(algo, steps, eval_episodes, eval_every)
    program = make_train(config)
    keys = jax.numpy.stack([jax.random.PRNGKey(seed + k) for k in range(seeds)])
    start = time.perf_counter()
    state, history = jax.jit(jax.vmap(program.train))(keys)
    history = jax.device_get(history)
    wall = time.perf_counter() - start
    program.raise_if_nonfinite(state, [seed + k for k in range(seeds)])
    final = {name: [float(x) for x in history[name][:, -1]]
             for name in ("success_rate", "danger_frequency", "return")}
    return {
        "algo": algo,
        **final,
        "initial_return": [float(x) for x in history["return"][:, 0]],
        "env_steps": int(state.env_steps[0]),
        "updates": int(state.updates[0]),
        "num_envs": config.num_envs,
        "wall_s": round(wall, 1),
        "seeds": [seed + k for k in range(seeds)],
        "eval_steps": [int(x) for x in history["env_steps"][0]],
        "success_curve": [[round(float(x), 4) for x in row] for row in history["success_rate"]],
        "device": jax.devices()[0].device_kind,
        "commit": git_commit(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog=PROG,
                        description=__doc__.split("\n")[0])
    parser.add_argument("--algos", nargs="+", choices=learner_names(),
                        default=list(learner_names()),
                        help="learners to train, one seed each (default: all of them)")
    parser.add_argument("--seed", type=cli.seed_int, default=0,
                        help="random seed (default: %(default)s)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: each learner's default "
                        "budget)")
    parser.add_argument("--eval-episodes", type=cli.int_in(1, 65536), default=128,
                        help="episodes of the final evaluation (default: %(default)s)")
    parser.add_argument("--seeds", type=cli.int_in(1, 64), default=1,
                        help="seeds per learner, from --seed, in one program (default: 1)")
    parser.add_argument("--eval-every", type=cli.positive_int, default=None,
                        help="environment steps between evaluations, to print the success "
                        "curve (default: one evaluation, at the end)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    for algo in args.algos:  # every configuration checked before anything compiles
        try:
            sanity_config(algo, args.steps, args.eval_episodes, args.eval_every)
        except ValueError as error:
            cli.fail(parser.prog, str(error))

    rows = [run(algo, args.seed, args.steps, args.eval_episodes, args.seeds, args.eval_every)
            for algo in args.algos]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    wide = args.seeds > 1  # minimum to maximum over the seeds
    success_w, danger_w, return_w = (17, 15, 17) if wide else (8, 7, 9)
    header = (
        f"{'learner':8} {'success':>{success_w}} {'danger':>{danger_w}} "
        f"{'return':>{return_w}} {'wall s':>7} {'env steps':>10}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        print(
            f"{row['algo']:8} {spread(row['success_rate'], '.1%', success_w)} "
            f"{spread(row['danger_frequency'], '.1%', danger_w)} "
            f"{spread(row['return'], '.1f', return_w)} "
            f"{row['wall_s']:7.1f} {row['env_steps']:10d}"
        )
    if args.eval_every:
        print("\nsuccess per seed at each evaluation (environment steps)")
        for row in rows:
            for index, steps in enumerate(row["eval_steps"]):
                values = " ".join(f"{curve[index]:6.1%}" for curve in row["success_curve"])
                print(f"{row['algo']:8} {steps:10,d}  {values}")
    seeds = (f"seed {args.seed}" if args.seeds == 1 else
             f"seeds {args.seed}-{args.seed + args.seeds - 1} (min-max)")
    print(f"\n{jax.devices()[0].device_kind}, {seeds}, nominal scenario, commit "
          f"{git_commit()[:12]}", file=sys.stderr)
    return 0


def spread(values: list[float], form: str, width: int) -> str:
    """One value, or the minimum and maximum of several, in ``width`` characters."""
    if len(values) == 1:
        return f"{values[0]:{width}{form}}"
    return f"{min(values):{form}} to {max(values):{form}}".rjust(width)


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(
        PROG, main,
        "nothing to keep (it prints its results as they come)"))
