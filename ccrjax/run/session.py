"""A run in training: its folder's checkpoints, the compiled chunk, the state of every seed
and the evaluation history (:class:`Session`), from preparing (memory check, configuration
record, restore, compilation, the untrained policy's evaluation) through the chunk loop to
closing. ``python -m ccrjax.train`` drives it (:mod:`ccrjax.train`)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax import terminal
from ccrjax.agents.replay import grow
from ccrjax.cli import UsageError
from ccrjax.run.checkpoint import CheckpointError, Checkpoints, report_skipped
from ccrjax.run.folder import (
    EVAL_METRICS,
    POINT_METRICS,
    TRAIN_COMMAND,
    TRAINING_COUNTS,
    RunFolder,
    environment_record,
    fingerprint,
    own_columns,
)
from ccrjax.run.spec import RunSpec
from ccrjax.training import make_train
from ccrjax.training.program import NonFinite, first_nonfinite


def point_rows(point: dict, seeds: Sequence[int], wall: float) -> list[dict[str, Any]]:
    """One ``metrics.csv`` row per seed from an evaluation point (leaves ``[seeds]``): the
    point's metrics, then the transform's own numbers (a Lagrange multiplier's path)."""

    own = [name for name in point if name not in POINT_METRICS and name != "env_steps"]
    rows = []
    for index, seed in enumerate(seeds):
        row = {"seed": seed, "env_steps": int(point["env_steps"][index]), "wall_time_s": wall}
        for name in POINT_METRICS:  # the counts of robot-steps as the integers they are
            value = point[name][index]
            row[name] = int(value) if name in TRAINING_COUNTS else float(value)
        row.update({name: float(point[name][index]) for name in own})
        rows.append(row)
    return rows


def state_bytes(abstract_state: Any) -> int:

    return sum(math.prod(x.shape) * np.dtype(x.dtype).itemsize
               for x in jax.tree_util.tree_leaves(abstract_state))


def physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def training_memory() -> tuple[int, str] | None:
    """The memory the training state must fit in, and what holds it: an accelerator's
    (JAX reports its limit; on a GPU the state lives there), else this machine's."""
    try:
        stats = jax.devices()[0].memory_stats()  # None on the CPU
    except (NotImplementedError, RuntimeError):  # a backend that cannot tell: the host
        stats = None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"the {jax.devices()[0].device_kind}"
    memory = physical_memory()
    return None if memory is None else (memory, "this machine")


@dataclasses.dataclass
class Session:
    """A run ready to train (:func:`prepare`): its folder and checkpoints, the program and
    its compiled chunk, the state of every seed, and the evaluation history so far."""

    folder: RunFolder
    spec: RunSpec
    program: Any
    checkpoints: Checkpoints
    chunk: Any  # jitted (state, train: bool) -> (state, evaluation point, training metrics)
    state: Any
    history: list[dict[str, Any]]
    fingerprint: str
    wall_before: float
    started: float  # time.perf_counter() when this invocation began compiling

    @property
    def seeds(self) -> list[int]:
        return self.spec.seed_list

    @property
    def chunk_steps(self) -> int:
        config = self.spec.train
        return config.iterations_per_eval * config.steps_per_iteration

    @property
    def total_steps(self) -> int:
        return self.program.num_evaluations * self.chunk_steps

    @property
    def steps(self) -> int:
        return int(self.history[-1]["env_steps"])

    @property
    def finished(self) -> bool:
        return self.steps >= self.total_steps

    def wall(self) -> float:
        return self.wall_before + time.perf_counter() - self.started

    def save(self) -> None:
        """Starts writing a checkpoint of the current state and history."""
        meta = {"fingerprint": self.fingerprint, "history": self.history,
                "wall_time_s": self.wall()}
        self.checkpoints.save(self.steps, self.state.replace(buffer=None), self.state.buffer,
                              meta)


def prepare(folder: RunFolder, spec: RunSpec, record: dict | None,
            progress_bar: bool) -> Session:
    """Everything before training: the memory check, the folder's configuration record,
    the restored checkpoint (resuming), the compiled chunk, and a new run's first
    evaluation (the untrained policy)."""
    config = spec.train
    program = make_train(config)
    seeds = spec.seed_list
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])
    abstract_state = jax.eval_shape(jax.vmap(program.init), keys)
    size = state_bytes(abstract_state)
    available = training_memory()
    if available is not None and 2.2 * size > available[0]:
        memory, holder = available
        raise UsageError(
            f"the training state of {len(seeds)} seed(s) needs {size / 2**30:.1f} GiB (twice "
            f"that while training) but {holder} has {memory / 2**30:.1f} GiB; use fewer "
            "--seeds, or a smaller replay buffer (--ddpg-buffer-size / --maac-buffer-size)"
        )
    run_record = spec.to_dict()
    run_fingerprint = fingerprint(run_record)
    resuming = record is not None
    if resuming and record.get("run") != json.loads(json.dumps(run_record)):  # extended
        record["run"] = run_record
        folder.write_config(record)
    if record is None:  # a new run
        record = {**environment_record(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "command": " ".join([TRAIN_COMMAND, *sys.argv[1:]]),
                  "fingerprint": run_fingerprint, "run": run_record,
                  "schedule": config.schedule()}
        folder.write_config(record)
    for note in config.schedule()["notes"]:  # nothing is rounded silently
        print(f"note: {note}", file=sys.stderr, flush=True)
    if record.get("fingerprint") != run_fingerprint:
        raise UsageError(f"{folder.config_path} does not match the run it describes")
    checkpoints = Checkpoints(folder.checkpoint_dir, keep=spec.keep_checkpoints)
    try:
        return _prepared(folder, spec, program, checkpoints, keys, abstract_state, size,
                         run_fingerprint, resuming, progress_bar)
    except BaseException:  # no writer thread outlives a refused or interrupted start
        checkpoints.close()
        folder.close_tensorboard()
        raise


def _prepared(folder: RunFolder, spec: RunSpec, program: Any, checkpoints: Checkpoints,
              keys: jax.Array, abstract_state: Any, size: int, run_fingerprint: str,
              resuming: bool, progress_bar: bool) -> Session:
    """:func:`prepare` once the checkpoints are open: restore, compile, first evaluation."""
    config, seeds = spec.train, spec.seed_list
    chunk_steps = config.iterations_per_eval * config.steps_per_iteration
    total_steps = program.num_evaluations * chunk_steps
    state, history, wall_before = None, [], 0.0
    if checkpoints.steps():
        state, history, wall_before = restore(folder, checkpoints, program, keys,
                                              abstract_state, run_fingerprint, total_steps)
    elif resuming:
        print(f"{folder.path} has no checkpoint (the run stopped before its first one): "
              "it starts again from the beginning, with its configuration",
              file=sys.stderr, flush=True)
    started = time.perf_counter()  # the run's wall time counts its compilation
    chunk = terminal.compile_phase(
        f"the training program for {len(seeds)} seed(s) ({size / 2**20:,.0f} MiB of "
        "training state)",
        jax.jit(jax.vmap(program.chunk, in_axes=(0, None))), abstract_state, True,
        ticker=progress_bar,
    )
    session = Session(folder=folder, spec=spec, program=program, checkpoints=checkpoints,
                      chunk=chunk, state=state, history=history, fingerprint=run_fingerprint,
                      wall_before=wall_before, started=started)
    if state is None:
        state = jax.jit(jax.vmap(program.init))(keys)
        session.state, point, _ = chunk(state, False)  # the untrained policy's evaluation
        session.history = point_rows(jax.device_get(point), seeds, session.wall())
        folder.rewrite_metrics(session.history)
        # A start that stopped before its first checkpoint may have left events behind.
        shutil.rmtree(folder.tensorboard_dir, ignore_errors=True)
        folder.open_tensorboard(seeds, purge_step=None)
        for row in session.history:
            folder.log_scalars(row["seed"], row["env_steps"], eval_scalars(row))
    else:
        # Events written after the checkpoint by the run that stopped are hidden.
        folder.open_tensorboard(seeds, purge_step=session.steps + 1)
    return session


def restore(folder: RunFolder, checkpoints: Checkpoints, program: Any, keys: jax.Array,
            abstract_state: Any, run_fingerprint: str, total_steps: int
            ) -> tuple[Any, list[dict[str, Any]], float]:
    """The latest readable checkpoint's state (its replay buffer grown for an extended run,
    or an empty one where it kept none, said), history and wall time."""
    try:
        restored = checkpoints.restore_latest(abstract_state.replace(buffer=None),
                                              abstract_state.buffer, run_fingerprint)
    except CheckpointError as error:  # IncompatibleCheckpoint included
        raise UsageError(f"--resume: {error}") from None
    report_skipped(restored)
    buffer = restored.buffer
    capacity = abstract_state.buffer.reward.shape[1]
    if buffer is not None and buffer.reward.shape[1] < capacity:
        # Extended: the buffer was sized to the shorter run's transitions and never
        # wrapped; in the longer run's larger ring it holds the same, as it would have.
        buffer = jax.jit(jax.vmap(lambda b: grow(b, capacity)))(buffer)
        print(f"extending the run to {total_steps:,} steps per seed: its replay buffer grows "
              "as it would have in a run started with this budget", file=sys.stderr, flush=True)
    if buffer is not None and jax.tree_util.tree_map(
            lambda x: x.shape, buffer) != jax.tree_util.tree_map(
            lambda x: x.shape, abstract_state.buffer):
        raise UsageError(f"--resume: checkpoint {restored.step:,} holds a replay buffer "
                         "of another shape than this run's")
    if buffer is None:  # an older checkpoint, or a finished run's last one
        buffer = jax.jit(jax.vmap(program.init))(keys).buffer
        if restored.step < total_steps:
            print(f"checkpoint {restored.step:,} kept no replay buffer (only the latest "
                  "checkpoint of a run in progress does): training goes on from an empty "
                  "buffer, so the result will differ from an uninterrupted run's",
                  file=sys.stderr, flush=True)
    history = restored.meta["history"]
    folder.rewrite_metrics(history)
    print(f"resuming {folder.path} from checkpoint {restored.step:,} "
          f"(of {total_steps:,} steps per seed)", file=sys.stderr, flush=True)
    return (restored.state.replace(buffer=buffer), history,
            float(restored.meta["wall_time_s"]))


def run_chunks(session: Session, on_point: Callable[[list[dict[str, Any]]], None],
               should_stop: Callable[[], bool]) -> NonFinite | None:
    """Trains chunk after chunk (``--eval-every`` steps, then an evaluation) until the
    budget is spent or ``should_stop()``; each evaluation goes to ``metrics.csv`` and
    TensorBoard and then to ``on_point(rows)``; checkpoints are started every
    ``--checkpoint-every`` steps, at the end, and when stopping. Returns where training
    turned non-finite (the bad chunk is not recorded), or ``None``."""
    folder, seeds = session.folder, session.seeds
    total_chunks = session.program.num_evaluations
    for index in range(session.steps // session.chunk_steps, total_chunks):
        if should_stop():
            break
        state, point, training = session.chunk(session.state, True)
        point, training, bad = jax.device_get((point, training, state.nonfinite_iteration))
        found = first_nonfinite(bad, seeds)
        if found is not None:
            return found
        session.state = state
        rows = point_rows(point, seeds, session.wall())
        session.history.extend(rows)
        folder.append_metrics(rows)
        for k, row in enumerate(rows):
            scalars = eval_scalars(row)
            scalars.update({f"train/{name}": float(np.asarray(value)[k])
                            for name, value in training.items()})
            folder.log_scalars(row["seed"], row["env_steps"], scalars)
        on_point(rows)
        last = index + 1 == total_chunks
        if last or (index + 1) % session.spec.chunks_per_checkpoint == 0 or should_stop():
            session.save()
    return None


def drop_finished_buffer(checkpoints: Checkpoints, step: int) -> None:
    """A finished run needs no replay buffer, unless it is to be extended exactly: deletes
    the one its last checkpoint ``step`` holds, saying so."""
    freed = checkpoints.drop_buffer(step)
    if freed:
        print(f"the finished run's replay buffer ({freed / 2**20:,.0f} MiB) is not "
              "kept (--keep-buffer keeps it, to extend the run exactly with --resume "
              "--steps)", file=sys.stderr, flush=True)


def close(session: Session, keep_buffer: bool) -> list[int]:
    """Waits for the checkpoints, drops a finished run's replay buffer unless
    ``keep_buffer``, closes the event files; returns the checkpoints kept."""
    checkpoints = session.checkpoints
    checkpoints.wait()
    saved = checkpoints.steps()
    replays = not session.spec.train.on_policy  # an on-policy learner's buffer is empty
    if saved and saved[-1] >= session.total_steps and not keep_buffer and replays:
        drop_finished_buffer(checkpoints, saved[-1])
    checkpoints.close()
    session.folder.close_tensorboard()
    return saved


def eval_scalars(row: dict[str, Any]) -> dict[str, float]:
    """A ``metrics.csv`` row as TensorBoard scalars: the evaluation and the training counts."""
    scalars = {f"eval/{name}": row[name] for name in EVAL_METRICS}
    for name in TRAINING_COUNTS:
        scalars[f"train/{name}"] = row[name]
    for name in own_columns(row):  # the transform's own numbers
        scalars[f"transform/{name}"] = row[name]
    return scalars
