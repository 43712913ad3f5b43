"""Pictures of random teams in every scenario: ``python -m ccrjax.demo --out runs/demo``.

For each of the four scenarios, a fresh environment (``num_envs=1``) runs one
episode of uniformly random continuous actions in ``[-1, 1]``; the episode is
drawn to ``<out>/<scenario>.png`` and animated to ``<out>/<scenario>.gif``.
This is what ``make train`` runs until there is a learner to train.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python -m ccrjax.demo")

import argparse
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NoReturn

import jax

from ccrjax.envs.env import MAX_ROBOTS, MIN_ROBOTS, EmergencyEnv
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.viz.record import EpisodeRecord, record_episode
from ccrjax.viz.render import animate_episode, draw_episode

# The order in which scenarios are run and printed.
DEMO_SCENARIOS = tuple(SCENARIOS)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr, exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _robots(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not MIN_ROBOTS <= value <= MAX_ROBOTS:
        raise argparse.ArgumentTypeError(
            f"must be in [{MIN_ROBOTS}, {MAX_ROBOTS}], got {value}"
        )
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**32), got {value}")
    return value


def _steps(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 1 <= value <= 1000:
        raise argparse.ArgumentTypeError(f"must be in [1, 1000], got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m ccrjax.demo``."""
    parser = _Parser(
        prog="python -m ccrjax.demo",
        description="Roll out random actions in every scenario and write a PNG and a GIF each.",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/demo"),
                        help="folder for the pictures (default: runs/demo)")
    parser.add_argument("--robots", type=_robots, default=5,
                        help=f"team size, {MIN_ROBOTS} to {MAX_ROBOTS} (default: 5)")
    parser.add_argument("--seed", type=_seed, default=0, help="random seed (default: 0)")
    parser.add_argument("--steps", type=_steps, default=25,
                        help="episode length in steps (default: 25)")
    return parser


def random_policy(obs: jax.Array, key: jax.Array) -> jax.Array:
    """Uniformly random continuous actions ``float[N, 2, B]`` in ``[-1, 1]``."""
    num_robots, _, num_envs = obs.shape
    return jax.random.uniform(key, (num_robots, 2, num_envs), minval=-1.0, maxval=1.0)


def main(argv: Sequence[str] | None = None) -> int:
    """Writes ``<scenario>.png`` and ``<scenario>.gif`` for every scenario; returns 0."""
    return terminal.run_command("python -m ccrjax.demo", lambda: _main(argv),
                                "the pictures listed above are written")


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(f"python -m ccrjax.demo: error: cannot create {args.out}: {error}", file=sys.stderr)
        return 1
    start = time.perf_counter()
    keys = jax.random.split(jax.random.key(args.seed), len(DEMO_SCENARIOS))

    def draw(name: str, record: EpisodeRecord) -> None:
        png, gif = args.out / f"{name}.png", args.out / f"{name}.gif"
        draw_episode(record, png)
        animate_episode(record, gif)
        print(f"{name:16s} {png}  {gif}", flush=True)

    # One drawing thread (the only one touching matplotlib) draws a scenario while
    # the main thread compiles and runs the next: XLA's compiler releases the GIL.
    with ThreadPoolExecutor(max_workers=1) as painter:
        drawings = []
        for name, key in zip(DEMO_SCENARIOS, keys, strict=True):
            env = EmergencyEnv(name, num_robots=args.robots, num_envs=1, episode_length=args.steps)
            record = record_episode(env, random_policy, key,
                                    caption="random actions (an untrained team)")
            drawings.append(painter.submit(draw, name, record))
        for drawing in drawings:
            drawing.result()
    print(f"wrote {2 * len(DEMO_SCENARIOS)} pictures to {args.out}/ "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
