"""Checkpoints of a training run with orbax-checkpoint: atomic, pruned, and read defensively.

A checkpoint holds two items: ``state``, the whole training state of every seed
(parameters, optimiser states, replay buffers, transform state, random keys,
counters), and ``meta``, a JSON object (the evaluation history so far, wall time,
the run's configuration fingerprint). It is named by its step, the number of
environment steps per seed it holds.

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
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

# Orbax reports routine events (waiting for a save, cleaning temporary folders)
# through absl at WARNING; the commands print their own messages.
logging.getLogger("absl").setLevel(logging.ERROR)


class CheckpointError(Exception):
    """No usable checkpoint."""


class IncompatibleCheckpoint(CheckpointError):
    """A readable checkpoint made with another configuration."""


@dataclasses.dataclass(frozen=True)
class Restored:
    step: int
    state: Any
    meta: dict
    skipped: tuple[tuple[int, str], ...]  # (step, why) of newer checkpoints that were unreadable


def _short(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _shapes(tree: Any) -> list[tuple[tuple[int, ...], str]]:
    return [(tuple(x.shape), str(np.dtype(x.dtype))) for x in jax.tree_util.tree_leaves(tree)]


class Checkpoints:
    """The checkpoints of one run folder (``<run>/checkpoints/<step>``)."""

    def __init__(self, directory: Path, keep: int = 2) -> None:
        self.directory = Path(directory).absolute()
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep, create=True, cleanup_tmp_directories=True
            ),
            item_names=("state", "meta"),
        )

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def save(self, step: int, state: Any, meta: dict) -> None:
        """Starts writing checkpoint ``step`` (returns once the arrays are copied)."""
        self.manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)
            ),
            force=True,
        )

    def wait(self) -> None:
        """Blocks until every checkpoint started is on disk."""
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.close()

    def _move_aside(self, step: int) -> Path:
        target = self.directory.parent / f"checkpoint-unreadable-{step}-{int(time.time())}"
        shutil.move(str(self.directory / str(step)), str(target))
        self.manager.reload()
        return target

    def restore_latest(self, abstract_state: Any, fingerprint: str) -> Restored:
        """The newest readable checkpoint, restored into the structure of ``abstract_state``.

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
                state = self.manager.restore(
                    step,
                    args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract_state)),
                )["state"]
                if _shapes(state) != _shapes(abstract_state):
                    raise ValueError("restored arrays have other shapes")
            except Exception as error:
                if self._layout_differs(step, abstract_state):
                    raise IncompatibleCheckpoint(
                        f"checkpoint {step} holds a training state of another layout "
                        "(made by another ccrjax version?)"
                    ) from None
                skipped.append((step, _short(error)))
                self._move_aside(step)
                continue
            return Restored(step=step, state=state, meta=meta, skipped=tuple(skipped))
        raise CheckpointError(
            "no readable checkpoint: " + "; ".join(f"{s}: {why}" for s, why in skipped)
        )

    def _layout_differs(self, step: int, abstract_state: Any) -> bool:
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
