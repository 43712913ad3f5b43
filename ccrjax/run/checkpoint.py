"""Checkpoints of a training run with orbax-checkpoint: atomic, pruned, and read defensively.

A checkpoint holds three items: ``state``, the training state of every seed but its
replay buffer (parameters, optimiser states, transform state, random keys, counters);
``buffer``, the replay buffers; and ``meta``, a JSON object (the evaluation history so
far, wall time, the run's configuration fingerprint). It is named by its step, the
number of environment steps per seed it holds.

Only the latest checkpoint keeps its ``buffer``, the one thing exact resumption needs
beyond the state and by far the largest (hundreds of MB): once a newer checkpoint is
complete on disk, the older ones' buffers are deleted (:meth:`Checkpoints.save`,
:meth:`Checkpoints.drop_old_buffers`). An older checkpoint still restores everything
else; resuming from it starts from an empty buffer, which the caller reports.

Orbax writes each checkpoint into a temporary folder and renames it into place
once every file is written, so a process killed at any moment (SIGKILL
included) leaves either a whole checkpoint or a temporary folder, which is
ignored and cleaned up on the next start. Saving is asynchronous: the arrays are
copied to host memory, then written in the background while training goes on.

:meth:`Checkpoints.restore_latest` reads the newest checkpoint; one that cannot
be read (a corrupted or truncated file) is moved aside and the previous one is
tried, and the caller is told which ones were skipped and why. A checkpoint of a
different configuration (another fingerprint, or arrays of other shapes) is an
:class:`IncompatibleCheckpoint`, never silently mixed into a run.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from ccrjax import terminal
from ccrjax.run import distributed


class _NotAnInterrupt(logging.Filter):
    """Drops a log record carrying a ``KeyboardInterrupt`` (a Ctrl-C in a program that uses
    the library with Python's default handler; the commands' own stop handling,
    :mod:`ccrjax.terminal`, raises none): orbax logs a wait for a save cut short so as an
    ERROR with its traceback ("Save Finalize thread failed"), while the save itself goes on
    and completes when the checkpoints are closed."""

    def filter(self, record: logging.LogRecord) -> bool:
        kind = record.exc_info[0] if record.exc_info else None
        return not (kind is not None and issubclass(kind, KeyboardInterrupt))


# Orbax reports routine events (waiting for a save, cleaning temporary folders)
# through absl at WARNING; the commands print their own messages.
logging.getLogger("absl").setLevel(logging.ERROR)
logging.getLogger("absl").addFilter(_NotAnInterrupt())


class CheckpointError(Exception):
    """No usable checkpoint."""


class IncompatibleCheckpoint(CheckpointError):
    """A readable checkpoint made with another configuration."""


@dataclasses.dataclass(frozen=True)
class Restored:
    step: int
    state: Any
    buffer: Any  # None: this checkpoint kept no replay buffer
    meta: dict
    skipped: tuple[tuple[int, str], ...]  # (step, why) of newer checkpoints that were unreadable


def _short(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _shapes(tree: Any) -> list[tuple[tuple[int, ...], str]]:
    return [(tuple(x.shape), str(np.dtype(x.dtype))) for x in jax.tree_util.tree_leaves(tree)]


def _as_like(saved: Any, abstract: Any) -> Any:
    """A buffer restored as saved (a dict of arrays) in the dataclass of ``abstract``, after
    checking that its fields, dtypes and ranks are ``abstract``'s (sizes may differ). A field
    that ``abstract`` holds as ``None`` (a channel this run does not keep, such as the cost of
    a transform without reward channels) must be absent or ``None`` in ``saved`` too."""
    if not isinstance(saved, dict):
        raise ValueError("the saved buffer has other fields")
    names = [f.name for f in dataclasses.fields(abstract)]
    kept = {name for name in names if getattr(abstract, name) is not None}
    if {name for name, value in saved.items() if value is not None} != kept:
        raise ValueError("the saved buffer has other fields")
    for name in kept:
        want, have = getattr(abstract, name), saved[name]
        if np.dtype(have.dtype) != np.dtype(want.dtype) or np.ndim(have) != len(want.shape):
            raise ValueError(f"the saved buffer's {name} is {have.dtype}{list(np.shape(have))}")
    return type(abstract)(**{name: jax.numpy.asarray(saved[name]) if name in kept else None
                             for name in names})


def report_skipped(restored: Restored) -> None:
    """Names, on stderr, the unreadable checkpoints a restore moved aside and the one it used."""
    for step, why in restored.skipped:
        print(f"checkpoint {step} is unreadable ({why}); moved it aside and fell back to "
              f"checkpoint {restored.step}", file=sys.stderr, flush=True)


def holds_buffer(directory: Path, step: int) -> bool:
    """Whether checkpoint ``step`` in ``directory`` kept its replay buffer (only the latest
    of a run in progress, or a finished run's kept with ``--keep-buffer``, does)."""
    return (Path(directory) / str(step) / "buffer").is_dir()


class Checkpoints:
    """The checkpoints of one run folder (``<run>/checkpoints/<step>``)."""

    def __init__(self, directory: Path, keep: int = 2) -> None:
        self.directory = Path(directory).absolute()
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep, create=True, cleanup_tmp_directories=True
            ),
            item_names=("state", "buffer", "meta"),
        )
        # orbax removes unfinished writes in a thread of its own; a process that ends before
        # that thread does (a refused or interrupted command) would print its traceback at
        # exit. Waiting here (a directory listing) keeps every exit quiet.
        await_cleanup = getattr(self.manager, "_maybe_await_cleanup_tmp_directory", None)
        if await_cleanup is not None:
            await_cleanup()
        # A stop that ends the process (ccrjax.terminal) first lets a write in flight finish.
        self._exit_token = terminal.on_exit(self.manager.wait_until_finished)

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def save(self, step: int, state: Any, buffer: Any, meta: dict) -> None:
        """Starts writing checkpoint ``step`` (returns once the arrays are copied). The
        previous checkpoint is complete first; every checkpoint before it then loses its
        buffer (the previous one keeps its buffer until this one is on disk)."""
        self.manager.wait_until_finished()
        self.drop_old_buffers(keep=1)
        self.manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), buffer=ocp.args.StandardSave(buffer),
                meta=ocp.args.JsonSave(meta),
            ),
            force=True,
        )

    def has_buffer(self, step: int) -> bool:
        return holds_buffer(self.directory, step)

    def drop_buffer(self, step: int) -> int:
        """Deletes checkpoint ``step``'s replay buffer; returns the bytes freed."""
        folder = self.directory / str(step) / "buffer"
        if not folder.is_dir() or not distributed.is_primary():  # several processes: one deletes
            return 0
        freed = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        shutil.rmtree(folder)
        return freed

    def drop_old_buffers(self, keep: int = 1) -> None:
        """Deletes the buffers of every complete checkpoint but the newest ``keep``."""
        for step in self.steps()[:-keep] if keep else self.steps():
            self.drop_buffer(step)

    def wait(self) -> None:
        """Blocks until every checkpoint started is on disk, then keeps only the newest
        one's buffer."""
        self.manager.wait_until_finished()
        self.drop_old_buffers(keep=1)

    def close(self) -> None:
        terminal.forget(self._exit_token)
        self.manager.close()

    def _move_aside(self, step: int) -> Path:
        target = self.directory.parent / f"checkpoint-unreadable-{step}-{int(time.time())}"
        shutil.move(str(self.directory / str(step)), str(target))
        self.manager.reload()
        return target

    def restore_latest(self, abstract_state: Any, abstract_buffer: Any,
                       fingerprint: str, buffer_as_abstract: bool = False) -> Restored:
        """The newest readable checkpoint, restored into the structure of ``abstract_state``,
        and its buffer in the structure of ``abstract_buffer`` with the sizes it was saved
        with (a run extended with a larger budget has a larger buffer than its older
        checkpoints); the buffer is ``None`` if the checkpoint kept none, or if
        ``abstract_buffer`` is ``None`` (not asked for). ``buffer_as_abstract``: the buffer
        was saved with ``abstract_buffer``'s sizes, and is restored straight into its
        shapes and shardings (onto the devices, never whole in host memory first).

        Raises :class:`IncompatibleCheckpoint` for a checkpoint of another configuration
        and :class:`CheckpointError` when there is none, or none is readable.
        """
        steps = self.steps()
        if not steps:
            raise CheckpointError(f"there is no checkpoint in {self.directory}")
        skipped: list[tuple[int, str]] = []
        for step in reversed(steps):
            try:
                meta = self.manager.restore(
                    step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())
                )["meta"]
            except Exception as error:  # unreadable meta: corrupted
                skipped.append((step, _short(error)))
                self._move_aside(step)
                continue
            if not isinstance(meta, dict) or meta.get("fingerprint") != fingerprint:
                raise IncompatibleCheckpoint(
                    f"checkpoint {step} was made with another configuration than this run's "
                    "config.json"
                )
            try:
                items = {"state": ocp.args.StandardRestore(abstract_state)}
                if abstract_buffer is not None and self.has_buffer(step):
                    items["buffer"] = ocp.args.StandardRestore(
                        abstract_buffer if buffer_as_abstract else None)  # else its own shapes
                restored = self.manager.restore(step, args=ocp.args.Composite(**items))
                state = restored["state"]
                if _shapes(state) != _shapes(abstract_state):
                    raise ValueError("restored arrays have other shapes")
                buffer = restored["buffer"] if "buffer" in items else None
                if buffer is not None and buffer_as_abstract:
                    if _shapes(buffer) != _shapes(abstract_buffer):
                        raise ValueError("the restored buffer has other shapes")
                elif buffer is not None:
                    buffer = _as_like(buffer, abstract_buffer)
            except Exception as error:
                if self._layout_differs(step, abstract_state):
                    raise IncompatibleCheckpoint(
                        f"checkpoint {step} holds a training state of another layout "
                        "(made by another ccrjax version?)"
                    ) from None
                skipped.append((step, _short(error)))
                self._move_aside(step)
                continue
            return Restored(step=step, state=state, buffer=buffer, meta=meta,
                            skipped=tuple(skipped))
        raise CheckpointError(
            "no readable checkpoint: " + "; ".join(f"{s}: {why}" for s, why in skipped)
        )

    def _layout_differs(self, step: int, abstract_state: Any) -> bool:
        # Only the state item is compared: a missing buffer is not another layout.
        """Whether checkpoint ``step``'s recorded array shapes differ from ``abstract_state``'s
        (False when its metadata cannot be read: then it is corrupted, not incompatible)."""
        try:
            metadata = self.manager.item_metadata(step)["state"]
            recorded = [
                (tuple(m.shape), str(np.dtype(m.dtype)))
                for m in jax.tree_util.tree_leaves(metadata)
            ]
        except Exception:
            return False
        return sorted(recorded) != sorted(_shapes(abstract_state))
