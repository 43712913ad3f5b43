"""``python -m ccrjax.evaluate DIR``: fresh episodes of a trained run, and its pictures again.

::

    python -m ccrjax.evaluate runs/my-run --episodes 256

Reloads the latest readable checkpoint of the run folder ``DIR`` (falling back to
the previous one if the latest cannot be read, and saying so), runs ``--episodes``
fresh evaluation episodes per seed with the deterministic policy (new episodes:
their key comes from ``--seed``, not from training's evaluation keys), prints the
paper's four metrics per seed with their mean and 95% confidence interval,
writes them to ``DIR/evaluation.json``, and redraws ``DIR/episode.png`` and
``DIR/episode.gif``. Works on a finished run and on one still in progress or
stopped (it evaluates the latest checkpoint).
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python -m ccrjax.evaluate")

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax import cli
from ccrjax.cli import UsageError
from ccrjax.run.checkpoint import CheckpointError, Checkpoints, report_skipped
from ccrjax.run.folder import (
    EVAL_METRICS,
    METRIC_RANGES,
    RunFolder,
    fingerprint,
    summary_table,
    write_atomic,
)
from ccrjax.run.spec import RunSpec
from ccrjax.run.stats import mean_ci
from ccrjax.training import make_train
from ccrjax.viz.episode_pictures import (
    PICTURE_KEY,
    record_trained_episode,
    seed_slice,
    unbroken,
    write_episode_pictures,
)

PROG = "python -m ccrjax.evaluate"
EVALUATION_STREAM = 0xE7A1  # folded into --seed: episodes no training evaluation has seen


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Evaluate the latest checkpoint of a run folder "
                        "on fresh episodes and redraw its episode pictures.")
    parser.add_argument("run", type=Path, help="the run folder (python -m ccrjax.train --out)")
    parser.add_argument("--episodes", type=cli.int_in(1, 65536), default=256,
                        help="fresh episodes per seed (default: 256)")
    parser.add_argument("--seed", type=cli.seed_int, default=0,
                        help="seed of the fresh episodes (default: 0)")
    parser.add_argument("--no-pictures", action="store_true",
                        help="do not redraw episode.png and episode.gif")
    return parser


def evaluate_run(folder_path: Path, episodes: int, seed: int, pictures: bool) -> int:


    folder = RunFolder(folder_path)
    if not folder.holds_run():
        raise UsageError(f"{folder.path} holds no run (no config.json)")
    try:
        spec = RunSpec.from_dict(folder.read_config()["run"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise UsageError(f"cannot read {folder.config_path}: {error}") from None
    if not folder.has_checkpoint():
        raise UsageError(f"{folder.path} has no checkpoint yet")
    checkpoints = Checkpoints(folder.checkpoint_dir, keep=spec.keep_checkpoints)
    program = make_train(dataclasses.replace(spec.train, eval_episodes=episodes))
    seeds = spec.seed_list
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    abstract_state = jax.eval_shape(jax.vmap(program.init), keys)
    try:
        # Evaluation needs the policies, not the replay buffers: those are left on disk.
        restored = checkpoints.restore_latest(abstract_state.replace(buffer=None), None,
                                              fingerprint(spec.to_dict()))
    except CheckpointError as error:
        raise UsageError(str(error)) from None
    finally:
        checkpoints.close()
    report_skipped(restored)
    state = restored.state
    print(f"evaluating checkpoint {restored.step:,} of {folder.path} on {episodes} fresh "
          f"episodes per seed ...", file=sys.stderr, flush=True)
    eval_keys = jax.vmap(lambda k: jax.random.fold_in(k, EVALUATION_STREAM))(
        jax.random.split(jax.random.PRNGKey(seed), len(seeds))
    )
    metrics = jax.device_get(jax.jit(jax.vmap(program.evaluate))(state, eval_keys))
    per_seed = {
        str(s): {m: float(np.asarray(metrics[m])[k]) for m in EVAL_METRICS}
        for k, s in enumerate(seeds)
    }
    summary = {
        "checkpoint_env_steps": restored.step,
        "episodes_per_seed": episodes,
        "episode_seed": seed,
        "seeds": seeds,
        "per_seed": per_seed,
        "mean_ci95": {m: mean_ci([v[m] for v in per_seed.values()], bounds=METRIC_RANGES[m])
                      for m in EVAL_METRICS},
    }
    write_atomic(folder.path / "evaluation.json", json.dumps(summary, indent=2) + "\n")
    print(f"{folder.path}: checkpoint {restored.step:,} steps per seed, "
          f"{episodes} fresh episodes per seed")
    print(summary_table(summary))
    if pictures:
        # The episode comes from --seed, as the scored ones do (a different episode for
        # each --seed), but from a stream of its own.
        key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), EVALUATION_STREAM),
                                 PICTURE_KEY)
        record = record_trained_episode(
            program, seed_slice(state, 0), key,
            caption=f"seed {seeds[0]}'s policy (deterministic), the picture episode of "
            f"{unbroken(f'evaluate --seed {seed}')}")
        png, gif = write_episode_pictures(record, folder.path)
        print(f"\npictures: {png}  {gif}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    with terminal.stopping(PROG) as stop:
        # The files it writes are written whole (evaluation.json, the pictures).
        stop.kept = ("the run's checkpoints are unchanged (evaluation.json and the pictures "
                     "are replaced only once each is complete)")
        args = build_parser().parse_args(argv)
        cli.enable_compilation_cache(cli.default_cache_dir())
        try:
            return evaluate_run(args.run, args.episodes, args.seed, not args.no_pictures)
        except (UsageError, ValueError) as error:
            cli.fail(PROG, str(error))


if __name__ == "__main__":
    sys.exit(main())
