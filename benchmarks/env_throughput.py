"""Environment throughput: env-steps per second of the full ``EmergencyEnv.step``.

Every scenario and batch size runs ``--steps`` steps of uniformly random
continuous actions in ``[-1, 1]`` inside one jitted ``lax.scan`` (actions drawn
inside the scan), through the full step: physics, hazard, observations,
rewards, metrics and the automatic reset. The rollout is compiled and run once
before timing; then it is timed ``--repeats`` times and the median is reported.
One env-step is one environment advanced by one step, so a batch of 16384
environments stepped once counts 16384.

    python benchmarks/env_throughput.py                    # a table
    python benchmarks/env_throughput.py --json             # one JSON object per line
    python benchmarks/env_throughput.py --scenarios nominal --envs 1024 4096
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

import jax

# Runs from a checkout without installing: make the repository importable.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ccrjax.envs.env import MAX_ROBOTS, MIN_ROBOTS, EmergencyEnv, random_actions  # noqa: E402
from ccrjax.envs.scenarios import SCENARIOS  # noqa: E402
from ccrjax.run.folder import git_commit  # noqa: E402

DEFAULT_SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
DEFAULT_ENVS = (1024, 4096, 16384)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr, exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _int_at_least(low: int, high: int | None = None) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
        if value < low or (high is not None and value > high):
            bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {value}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    """The command line of this benchmark."""
    parser = _Parser(prog="env_throughput.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", nargs="+", choices=sorted(SCENARIOS),
                        default=list(DEFAULT_SCENARIOS), metavar="NAME",
                        help=f"scenarios to run (default: all; from {sorted(SCENARIOS)})")
    parser.add_argument("--envs", nargs="+", type=_int_at_least(1), default=list(DEFAULT_ENVS),
                        help="batch sizes (default: 1024 4096 16384)")
    parser.add_argument("--robots", type=_int_at_least(MIN_ROBOTS, MAX_ROBOTS), default=5,
                        help="robots per environment (default: 5)")
    parser.add_argument("--steps", type=_int_at_least(1), default=100,
                        help="steps per timed rollout (default: 100, four episodes of 25)")
    parser.add_argument("--repeats", type=_int_at_least(1), default=5,
                        help="timed rollouts; the median is reported (default: 5)")
    parser.add_argument("--sampler", choices=("ccrjax", "uniform"), default="ccrjax",
                        help="how random actions are drawn (see make_rollout)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per line instead of a table")
    return parser


def make_rollout(
    env: EmergencyEnv, steps: int, sampler: str = "ccrjax"
) -> Callable[[Any, jax.Array], Any]:
    """A jitted ``(state, key) -> state`` running ``steps`` random steps in one scan.

    ``sampler``: ``"ccrjax"`` draws actions with :func:`ccrjax.envs.env.random_actions`
    (16-bit uniform, one 32-bit random word per robot); ``"uniform"`` with
    ``jax.random.uniform`` (one 32-bit word per component, about twice the cost of
    the random numbers, a visible share of a step on CPU).
    """
    shape = (env.num_robots, 2, env.num_envs)

    def body(state: Any, key: jax.Array) -> tuple[Any, None]:
        if sampler == "uniform":
            action = jax.random.uniform(key, shape, minval=-1.0, maxval=1.0)
        else:
            action = random_actions(key, env)
        return env.step(state, action), None

    @jax.jit
    def rollout(state: Any, key: jax.Array) -> Any:
        state, _ = jax.lax.scan(body, state, jax.random.split(key, steps))
        return state

    return rollout


def measure(
    scenario: str, robots: int, envs: int, steps: int, repeats: int, sampler: str = "ccrjax"
) -> dict[str, Any]:
    """Times ``repeats`` rollouts after a compile-and-warm-up run; returns the result row."""
    env = EmergencyEnv(scenario, num_robots=robots, num_envs=envs)
    rollout = make_rollout(env, steps, sampler)
    key = jax.random.key(0)
    key, reset_key = jax.random.split(key)
    state = env.reset(reset_key)
    start = time.perf_counter()
    state = jax.block_until_ready(rollout(state, key))  # compile + warm-up
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        key, run_key = jax.random.split(key)
        start = time.perf_counter()
        state = jax.block_until_ready(rollout(state, run_key))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {
        "scenario": scenario,
        "robots": robots,
        "envs": envs,
        "env_steps_per_s": envs * steps / median,
        "ms_per_step": 1000.0 * median / steps,
        "median_s": median,
        "min_s": min(times),
        "steps": steps,
        "repeats": repeats,
        "sampler": sampler,
        "warmup_s": warmup_s,
        "device": f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}",
        "jax": jax.__version__,
    }


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """A plain-text table: scenario, robots, envs, env-steps/s, ms per step."""
    header = f"{'scenario':<22} {'robots':>6} {'envs':>7} {'env-steps/s':>14} {'ms/step':>9}"
    lines = [header, "-" * len(header)]
    for row in rows:
        lines.append(
            f"{row['scenario']:<22} {row['robots']:>6d} {row['envs']:>7d} "
            f"{row['env_steps_per_s']:>14,.0f} {row['ms_per_step']:>9.3f}"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Runs every scenario and batch size; prints a table or JSON lines."""
    args = build_parser().parse_args(argv)
    rows = []
    for scenario in args.scenarios:
        for envs in args.envs:
            row = measure(scenario, args.robots, envs, args.steps, args.repeats, args.sampler)
            rows.append(row)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                print(
                    f"  {scenario} envs={envs}: {row['env_steps_per_s']:,.0f} env-steps/s "
                    f"(compile + first run {row['warmup_s']:.1f} s)",
                    file=sys.stderr, flush=True,
                )
    if not args.json:
        device = rows[0]["device"] if rows else ""
        print(f"Full env.step, random continuous actions ({args.sampler} sampler), "
              f"{args.steps} steps per rollout, "
              f"median of {args.repeats}; {device}, jax {jax.__version__}, commit "
              f"{git_commit()[:12]}")
        print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
