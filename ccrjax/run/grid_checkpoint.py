"""Checkpoints of a grid of runs (:class:`ccrjax.training.grid.GridTraining`), so that an
experiment's program of many hours resumes after a kill instead of starting over.

:func:`train_resumably` trains a grid, saving every run's whole training state (replay
buffers included) into a folder of its own at most every ``every_s`` seconds, between two
chunks, with :class:`ccrjax.run.checkpoint.Checkpoints` (orbax: written whole or not at
all; one checkpoint kept). Started again with the same folder, it restores the newest one
onto the devices and continues with the same compiled chunk from the same state: the result
is the one an uninterrupted run gives, bit for bit. A kill loses at most the time since the
last checkpoint.

A checkpoint is resumed only by the same grid: the same configuration (budget included),
seeds, run parameters, recorded episodes, device count (the state is padded to it) and
code (:func:`ccrjax.run.folder.code_commit`: committing results or documentation in between
does not count). Another one is set aside and the grid starts over, saying why. The caller
deletes the folder once the grid's results are safely written (:func:`discard`).

With several processes (:mod:`ccrjax.run.distributed`) every process writes its share of
each checkpoint into the same folder and restores its share from it; process 0 decides
when to save, and moves or deletes folders.

The saves are synchronous (the next chunk reuses the state's memory). The state is about
0.6 GB per run at the protocol's replay size, so a 21-run grid writes about 13 GB per
checkpoint: 16-44 s each on this project's 2-core CPU (the lambda search's strong-wind IDDPG
program, 2026-11-23).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ccrjax.run import distributed
from ccrjax.run.checkpoint import CheckpointError, Checkpoints
from ccrjax.run.folder import code_commit, fingerprint
from ccrjax.training import config_to_dict
from ccrjax.training.grid import GridProgress, GridRuns, GridTraining

DEFAULT_EVERY_S = 900.0


def grid_fingerprint(training: GridTraining) -> str:
    """What a grid's checkpoint must have been made by (see the module's docstring)."""
    return fingerprint({
        "grid": {
            "config": config_to_dict(training.config),
            "seeds": training.seeds,
            "params": {k: [float(x) for x in v] for k, v in training.params.items()},
            "record_episodes": training.record_episodes,
            "record_key": np.asarray(training.record_key).tolist(),
            "devices": training.num_devices,
            "commit": code_commit(),
        }
    })


def _history_record(history: list[dict[str, np.ndarray]]) -> dict:
    return {"dtypes": {k: str(np.asarray(v).dtype) for k, v in history[0].items()},
            "points": [{k: np.asarray(v).tolist() for k, v in point.items()}
                       for point in history]}


def _history_from(record: dict) -> list[dict[str, np.ndarray]]:
    dtypes = record["dtypes"]
    return [{k: np.asarray(point[k], dtype=dtypes[k]) for k in dtypes}
            for point in record["points"]]


def restore(training: GridTraining, checkpoints: Checkpoints,
            log: Callable[[str], None]) -> GridProgress | None:
    """The grid's newest checkpoint in ``checkpoints`` as progress to resume, or ``None``
    (there is none, or it is another grid's or unreadable: then it is set aside)."""
    if not checkpoints.steps():
        return None
    abstract = training.abstract_state()
    try:
        restored = checkpoints.restore_latest(
            abstract.replace(buffer=None), abstract.buffer, grid_fingerprint(training),
            buffer_as_abstract=True)
        if restored.buffer is None:
            raise CheckpointError(f"checkpoint {restored.step} kept no replay buffer")
    except CheckpointError as error:  # IncompatibleCheckpoint included
        aside = checkpoints.directory.with_name(
            f"{checkpoints.directory.name}-set-aside-{int(time.time())}")
        checkpoints.close()
        if distributed.is_primary():
            shutil.move(str(checkpoints.directory), str(aside))
        distributed.barrier("grid checkpoint set aside")
        log(f"  not resuming from {checkpoints.directory} ({error}); set it aside as "
            f"{aside.name} and starting over")
        return None
    history = _history_from(restored.meta["history"])
    log(f"  resuming from its checkpoint after {len(history) - 1} of "
        f"{training.program.num_evaluations} evaluations ({restored.step:,} steps per run, "
        f"{restored.meta['run_s'] / 60:.1f} min of training so far)")
    return GridProgress(state=restored.state.replace(buffer=restored.buffer),
                        history=history, run_s=float(restored.meta["run_s"]))


class ProgressNotes:
    """Lines saying how far a grid in training is, with the time its program has left,
    the first after ``first_s`` seconds and then at most every ``every_s``: a program of
    hours (or one on a machine held for minutes) shows early whether it will end in time."""

    def __init__(self, training: GridTraining, resume: GridProgress | None,
                 log: Callable[[str], None], first_s: float, every_s: float) -> None:
        self.total = training.program.num_evaluations
        self.from_evaluations = resume.evaluations if resume is not None else 0
        self.log, self.every_s = log, every_s
        self.began = time.perf_counter()
        self.next_note = self.began + first_s

    def __call__(self, progress: GridProgress) -> None:
        now = time.perf_counter()
        done = progress.evaluations - self.from_evaluations
        if now < self.next_note or done <= 0:
            return
        self.next_note = now + self.every_s
        left_s = (now - self.began) / done * (self.total - progress.evaluations)
        self.log(f"  {progress.evaluations} of {self.total} evaluations trained "
                 f"({progress.run_s / 60:.1f} min); about {left_s / 60:.1f} min left in "
                 "this program")


def train_resumably(training: GridTraining, folder: Path | None,
                    every_s: float = DEFAULT_EVERY_S,
                    log: Callable[[str], None] = print,
                    note_first_s: float = 30.0, note_every_s: float = 300.0) -> GridRuns:
    """Trains ``training`` (compiled or not), resuming from ``folder``'s checkpoint if it
    holds one of this grid and saving one there at most every ``every_s`` seconds.
    ``folder=None`` or ``every_s=0`` trains without checkpoints (``every_s=0`` still resumes).
    Progress is logged after ``note_first_s`` seconds, then every ``note_every_s``
    (:class:`ProgressNotes`)."""
    if folder is None:
        return training.run(None, ProgressNotes(training, None, log, note_first_s, note_every_s))
    checkpoints = Checkpoints(Path(folder), keep=1)
    try:
        resume = restore(training, checkpoints, log)
        if resume is None:
            checkpoints = Checkpoints(Path(folder), keep=1)  # a fresh manager after set-aside
        steps_per_chunk = training.config.iterations_per_eval * training.config.steps_per_iteration
        last_save = time.perf_counter()
        meta_base = {"fingerprint": grid_fingerprint(training)}
        notes = ProgressNotes(training, resume, log, note_first_s, note_every_s)

        def after_chunk(progress: GridProgress) -> None:
            nonlocal last_save
            notes(progress)
            # Every process saves its share, so they decide alike (process 0's clock).
            if not distributed.agree(every_s > 0 and time.perf_counter() - last_save >= every_s):
                return
            began = time.perf_counter()
            state = progress.state
            checkpoints.save(progress.evaluations * steps_per_chunk,
                             state.replace(buffer=None), state.buffer,
                             {**meta_base, "history": _history_record(progress.history),
                              "run_s": progress.run_s})
            checkpoints.wait()  # before the next chunk reuses the state's memory
            last_save = time.perf_counter()
            log(f"  checkpoint after {progress.evaluations} of "
                f"{training.program.num_evaluations} evaluations saved in "
                f"{last_save - began:.0f} s")

        return training.run(resume, after_chunk)
    finally:
        checkpoints.close()


def discard(folder: Path | None) -> None:
    """Deletes a grid's checkpoint folder (once its results are written)."""
    if folder is not None and distributed.is_primary():
        shutil.rmtree(folder, ignore_errors=True)
    distributed.barrier("grid checkpoint discarded")


__all__ = [
    "DEFAULT_EVERY_S", "ProgressNotes", "discard", "grid_fingerprint", "restore",
    "train_resumably",
]
