"""The end of a run: what a finished run leaves (summary, curves, episode pictures, the
exported policy) and how a finished run is recognised and resumed without training."""

from __future__ import annotations

import importlib.util
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from ccrjax.cli import UsageError
from ccrjax.run.checkpoint import CheckpointError, Checkpoints, report_skipped
from ccrjax.run.folder import RunFolder, fingerprint, folder_bytes, own_columns, summary_table
from ccrjax.run.policy import POLICY_DIR, POLICY_RECORD, export_policy
from ccrjax.run.session import drop_finished_buffer
from ccrjax.run.spec import RunSpec
from ccrjax.training import make_train
from ccrjax.viz.episode_pictures import (
    PICTURE_KEY,
    record_trained_episode,
    seed_slice,
    unbroken,
    write_episode_pictures,
)
from ccrjax.viz.plots import CURVE_METRICS, Curves, curves_from_rows, draw_curves


def finish(folder: Any, program: Any, state: Any, seeds: Sequence[int],
           history: list[dict[str, Any]], wall: float) -> None:
    """The summary, the curves and the episode pictures of a finished run."""
    final_steps = history[-1]["env_steps"]
    final_rows = [row for row in history if row["env_steps"] == final_steps]
    summary = folder.write_summary(final_rows, {"wall_time_s": wall})
    curves = Curves()
    own = own_columns(history[-1])  # the transform's numbers
    metrics = (*CURVE_METRICS, *own)
    steps, values = curves_from_rows(history, metrics)
    config = program.config
    label = f"{config.algo} {config.variant}"
    curves.add(label, steps, values)
    plural = "s" if len(seeds) > 1 else ""
    limit = getattr(program.transform, "cost_limit", None)  # a constraint's limit, drawn
    lines = ({} if limit is None else
             {name: (float(limit), "cost limit") for name in ("danger_frequency", *own)
              if name.endswith(("danger_frequency", "cost"))})
    draw_curves(curves, folder.path / "curves.png", metrics=metrics, lines=lines,
                title=f"{config.scenario}: {label}, {len(seeds)} seed{plural}")
    key = jax.random.fold_in(jax.random.PRNGKey(seeds[0]), PICTURE_KEY)
    record = record_trained_episode(
        program, seed_slice(state, 0), key,
        caption=f"seed {seeds[0]}'s policy (deterministic) in the episode its seed fixes for "
        f"the picture ({unbroken('python -m ccrjax.evaluate --seed N')} draws others)")
    png, gif = write_episode_pictures(record, folder.path)
    policy = export_policy(folder.path, program, state.learner, list(seeds), state.transform)
    print_summary(summary, folder)
    print(f"\npictures: {png}  {gif}  {folder.path / 'curves.png'}")
    print(f"policy: {folder.path / policy.name} (ccrjax.load_policy({str(folder.path)!r}, "
          f"seed={seeds[0]}))")
    if program.transform.extra_obs_size(program.env):  # what only whole episodes give
        print(f"team: ccrjax.load_team({str(folder.path)!r}, seed={seeds[0]}) runs whole "
              f"episodes with the {config.variant} transform's shared features")
    stale = earlier_evaluation(folder.path, final_steps)
    if stale is not None:
        print(f"evaluation.json evaluated the checkpoint at {stale:,} steps per seed, before "
              f"this extension: python -m ccrjax.evaluate {folder.path} evaluates the end")
    if importlib.util.find_spec("tensorboard") is not None:
        print(f"TensorBoard: tensorboard --logdir {folder.tensorboard_dir}")
    elif folder.tensorboard_dir.exists():
        print(f"TensorBoard event files: {folder.tensorboard_dir} (to view them: "
              ".venv/bin/pip install -e '.[tensorboard]')")


def earlier_evaluation(path: Path, steps: int) -> int | None:
    """The checkpoint step of ``path``'s ``evaluation.json`` (``python -m ccrjax.evaluate``'s)
    where it is not ``steps``, the run's end (an extension trained past it); else ``None``."""
    try:
        evaluated = json.loads((path / "evaluation.json").read_text())["checkpoint_env_steps"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return int(evaluated) if evaluated != steps else None


def finished(folder: RunFolder, spec: RunSpec) -> bool:
    """Whether the run in ``folder`` has trained all of ``spec``'s budget and finished: its
    last checkpoint (by name; :func:`resume_finished` reads it) at the budget, a summary of
    that step, and the exported policy, which a run writes last. A run stopped while
    finishing, or an extension stopped before its summary, is not finished."""
    steps = folder.checkpoint_steps()
    total = spec.train.total_env_steps_run
    if not steps or steps[-1] < total or not (folder.path / POLICY_DIR / POLICY_RECORD).exists():
        return False
    try:
        summary = json.loads((folder.path / "summary.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and summary.get("env_steps_per_seed") == steps[-1]


def resume_finished(folder: RunFolder, spec: RunSpec, keep_buffer: bool,
                    steps_given: bool = False) -> int | None:
    """``--resume`` of a finished run at its own budget: its last checkpoint's training state
    is read (not its replay buffer) to check that it belongs to this run and can be read;
    then nothing is trained or rewritten, and that checkpoint's replay buffer is dropped
    unless ``keep_buffer``. The schedule's rounding notes are printed only where this
    command named ``--steps`` (``steps_given``): the run's own were said when it ran.
    Returns ``None`` where the last checkpoint was unreadable and moved aside (said): the
    run then resumes from the one before, as any stopped run does."""
    program = make_train(spec.train)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in spec.seed_list])
    abstract_state = jax.eval_shape(jax.vmap(program.init), keys)
    checkpoints = Checkpoints(folder.checkpoint_dir, keep=spec.keep_checkpoints)
    try:
        restored = checkpoints.restore_latest(abstract_state.replace(buffer=None), None,
                                              fingerprint(spec.to_dict()))
        report_skipped(restored)
        if restored.step < spec.train.total_env_steps_run:
            return None
        if not keep_buffer:
            drop_finished_buffer(checkpoints, restored.step)
    except CheckpointError as error:  # IncompatibleCheckpoint included
        raise UsageError(f"--resume: {error}") from None
    finally:
        checkpoints.close()
    for note in spec.train.schedule()["notes"] if steps_given else []:  # a larger --steps
        print(f"note: {note}", file=sys.stderr, flush=True)  # that rounds to the budget run
    print(f"{folder.path} is finished ({spec.train.total_env_steps_run:,} environment steps "
          f"per seed): nothing to train; the folder holds "
          f"{folder_bytes(folder.path) / 2**20:,.1f} MiB. python -m ccrjax.evaluate "
          f"{folder.path} evaluates it again; --resume --steps N, N larger, extends it")
    return 0


def print_summary(summary: dict[str, Any], folder: Any) -> None:
    seeds = summary["seeds"]
    print(f"\n{folder.path}: {summary['env_steps_per_seed']:,} environment steps per seed, "
          f"{len(seeds)} seed(s), {summary['wall_time_s']:.0f} s; the folder holds "
          f"{folder_bytes(folder.path) / 2**20:,.1f} MiB")
    print(summary_table(summary))
