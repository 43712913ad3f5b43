"""Peer throughput: JaxMARL's MPE ``simple_spread`` measured like our environment.

Same method as ``benchmarks/env_throughput.py``: 5 agents (and 5 landmarks, as
in the MPE's ``simple_spread``), continuous actions drawn uniformly inside one
jitted ``lax.scan``, the environment ``vmap``-ed over a batch of 1024, 4096 and
16384, through JaxMARL's full ``step`` (with its automatic reset), a compile and
warm-up run, then the median of ``--repeats`` timed rollouts. Episodes are 50
steps, like ours (JaxMARL's default is 25). JaxMARL's continuous action is 5
numbers in ``[0, 1]`` (none, -x, +x, -y, +y) that it turns into the force
``5 (a[2] - a[1], a[4] - a[3])``, so uniform draws give the same force
distribution as our uniform ``[-1, 1]^2`` actions would after differencing.

JaxMARL is never a dependency of ccrjax: this script runs in its own virtual
environment, ``benchmarks/.peer-venv``, which ``make bench-peers`` creates.

    benchmarks/.peer-venv/bin/python benchmarks/jaxmarl_peer.py [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn

import jax
import jax.numpy as jnp

SCENARIO = "jaxmarl_simple_spread"
DEFAULT_ENVS = (1024, 4096, 16384)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr, exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _int_at_least(low: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    """The command line of this benchmark."""
    parser = _Parser(prog="jaxmarl_peer.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", type=_int_at_least(1), default=list(DEFAULT_ENVS),
                        help="batch sizes (default: 1024 4096 16384)")
    parser.add_argument("--robots", type=_int_at_least(1), default=5,
                        help="agents (and landmarks) per environment (default: 5)")
    parser.add_argument("--steps", type=_int_at_least(1), default=100,
                        help="steps per timed rollout (default: 100, four episodes of 25)")
    parser.add_argument("--episode-length", type=_int_at_least(1), default=25,
                        help="JaxMARL's max_steps (default: 25, as ours)")
    parser.add_argument("--repeats", type=_int_at_least(1), default=5,
                        help="timed rollouts; the median is reported (default: 5)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per line instead of a table")
    return parser


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silences file descriptor 1 (and ``sys.stdout``) for the duration.

    jaxmarl prints a notice about optional environments on import, and something
    it imports puts back the real ``sys.stdout`` under ``contextlib.redirect_stdout``,
    so the notice is silenced at the file-descriptor level; stdout stays JSON.
    """
    stdout = sys.stdout
    stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
        sys.stdout = stdout


def make_env(agents: int, episode_length: int) -> Any:
    """JaxMARL's ``MPE_simple_spread_v3`` with continuous actions."""
    with _quiet_stdout():
        from jaxmarl import make
        from jaxmarl.environments.mpe.default_params import CONTINUOUS_ACT
    return make("MPE_simple_spread_v3", num_agents=agents, num_landmarks=agents,
                action_type=CONTINUOUS_ACT, max_steps=episode_length)


def make_rollout(env: Any, envs: int, steps: int) -> Callable[[Any, jax.Array], Any]:
    """A jitted ``(state, key) -> state`` running ``steps`` random steps of ``envs`` envs."""
    step = jax.vmap(env.step)
    sizes = {agent: env.action_space(agent).shape for agent in env.agents}

    def body(carry: Any, key: jax.Array) -> tuple[Any, None]:
        state, total = carry
        step_key, *action_keys = jax.random.split(key, 1 + len(env.agents))
        actions = {
            agent: jax.random.uniform(k, (envs, *sizes[agent]))
            for agent, k in zip(env.agents, action_keys, strict=True)
        }
        obs, state, reward, done, info = step(jax.random.split(step_key, envs), state, actions)
        # Keep observations and rewards live, as our env.step returns them in its state.
        checksum = sum(jnp.sum(o) for o in obs.values()) + sum(
            jnp.sum(r) for r in reward.values()
        )
        return (state, total + checksum), None

    @jax.jit
    def rollout(carry: Any, key: jax.Array) -> Any:
        carry, _ = jax.lax.scan(body, carry, jax.random.split(key, steps))
        return carry

    return rollout


def measure(agents: int, envs: int, steps: int, episode_length: int,
            repeats: int) -> dict[str, Any]:
    """Times ``repeats`` rollouts after a compile-and-warm-up run; returns the result row."""
    env = make_env(agents, episode_length)
    rollout = make_rollout(env, envs, steps)
    key, reset_key = jax.random.split(jax.random.key(0))
    _, state = jax.vmap(env.reset)(jax.random.split(reset_key, envs))
    carry = (state, jnp.zeros(()))
    start = time.perf_counter()
    carry = jax.block_until_ready(rollout(carry, key))
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        key, run_key = jax.random.split(key)
        start = time.perf_counter()
        carry = jax.block_until_ready(rollout(carry, run_key))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {
        "scenario": SCENARIO,
        "robots": agents,
        "envs": envs,
        "env_steps_per_s": envs * steps / median,
        "ms_per_step": 1000.0 * median / steps,
        "median_s": median,
        "min_s": min(times),
        "steps": steps,
        "repeats": repeats,
        "warmup_s": warmup_s,
        "device": f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}",
        "jax": jax.__version__,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Runs every batch size; prints a table or JSON lines."""
    args = build_parser().parse_args(argv)
    rows = []
    for envs in args.envs:
        row = measure(args.robots, envs, args.steps, args.episode_length, args.repeats)
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
    if not args.json:
        print(f"JaxMARL simple_spread, random continuous actions, {args.steps} steps per "
              f"rollout, median of {args.repeats}; {rows[0]['device']}, jax {jax.__version__}")
        header = f"{'scenario':<22} {'robots':>6} {'envs':>7} {'env-steps/s':>14} {'ms/step':>9}"
        print(header)
        print("-" * len(header))
        for row in rows:
            print(f"{row['scenario']:<22} {row['robots']:>6d} {row['envs']:>7d} "
                  f"{row['env_steps_per_s']:>14,.0f} {row['ms_per_step']:>9.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
