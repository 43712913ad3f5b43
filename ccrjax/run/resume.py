"""Opening a run folder for ``python -m ccrjax.train``: a new run's folder checked, or a
stopped run's configuration read and compared with the command (only ``--steps`` may grow,
which extends the run), and what a stopped run keeps."""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ccrjax.cli import UsageError
from ccrjax.run.checkpoint import holds_buffer
from ccrjax.run.folder import TRAIN_COMMAND, RunFolder, timestamp
from ccrjax.run.spec import RunSpec


def differences(saved: dict[str, Any], asked: dict[str, Any], prefix: str = "") -> list[str]:
    """``name: saved -> asked`` for every entry that differs (nested dicts flattened)."""
    lines = []
    for key in sorted(set(saved) | set(asked)):
        a, b = saved.get(key), asked.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            lines += differences(a, b, f"{prefix}{key}.")
        elif a != b:
            lines.append(f"{prefix}{key} is {a!r} in the run, {b!r} here")
    return lines


# ---------------------------------------------------------------------------- the folder
def check_writable(path: Path) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as error:
        reason = error.strerror or str(error)
        raise UsageError(f"cannot write to the run folder {path}: {reason}") from None


def open_folder(out: Path | None, resume: bool,
                resolve: Callable[[RunSpec | None], RunSpec]) -> tuple[RunFolder, RunSpec,
                                                                       dict | None]:
    """Checks the run folder ``out`` against the command and returns it, the run, and
    (resuming) the saved configuration record. ``resolve(saved)`` is the run the command
    asks for on top of a resumed run's ``saved`` one (or of the defaults, for ``None``).
    Without ``out``, a new run goes to ``runs/<scenario>-<algo>-<variant>-<time>``."""
    if resume and out is None:
        raise UsageError("--resume needs --out: the folder of the run to continue")
    if out is None:
        spec = resolve(None)
        out = Path("runs") / (f"{spec.train.scenario}-{spec.train.algo}-"
                              f"{spec.train.variant}-{timestamp()}")
    folder = RunFolder(out)
    if resume:
        if not folder.holds_run():
            raise UsageError(f"--resume: {folder.path} holds no run (no config.json)")
        try:
            record = folder.read_config()
            saved = RunSpec.from_dict(record["run"])
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise UsageError(f"--resume: cannot read {folder.config_path}: {error}") from None
        spec = resolve(saved)
        asked, budget = spec.train.total_env_steps, saved.train.total_env_steps
        if asked < budget:
            raise UsageError(f"--resume --steps {asked:,}: the run's budget is {budget:,} "
                             "environment steps per seed; a run can be extended, not shortened")
        same_budget = dataclasses.replace(spec, train=dataclasses.replace(
            spec.train, total_env_steps=budget))
        changed = differences(saved.to_dict(), same_budget.to_dict())
        if changed:
            raise UsageError(
                f"--resume: options contradict the run in {folder.path} ("
                + "; ".join(changed) + "); a run resumes with its own configuration "
                "(only --steps may grow, to extend it)"
            )
        check_writable(folder.path)
        if asked > budget:  # the extension is recorded where the run is described
            steps = folder.checkpoint_steps()
            exact = bool(steps) and holds_buffer(folder.checkpoint_dir, steps[-1])
            record.setdefault("extensions", []).append(
                {"from_total_env_steps": budget, "to_total_env_steps": asked,
                 "runs_as_total_env_steps": spec.train.total_env_steps_run,
                 "replay_buffer": "in the last checkpoint: the extension is exact" if exact
                 else "none in the last checkpoint: training goes on from an empty buffer",
                 "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
            record["schedule"] = spec.train.schedule()
        return folder, spec, record
    spec = resolve(None)
    if folder.holds_run() and folder.has_checkpoint():
        raise UsageError(
            f"{folder.path} already holds a run; pass --resume to continue it, "
            "or choose another --out (nothing was overwritten)"
        )
    if folder.holds_run():  # nothing of it can be resumed: this run takes its place
        print(f"{folder.path} holds a run stopped before its first checkpoint; this run "
              "starts in its place", file=sys.stderr, flush=True)
        check_writable(folder.path)
        return folder, spec, None
    if folder.path.exists() and (not folder.path.is_dir() or any(folder.path.iterdir())):
        raise UsageError(f"{folder.path} exists and is not an empty folder; choose another --out")
    check_writable(folder.path)
    return folder, spec, None


def what_was_kept(folder: RunFolder, saved: Sequence[int]) -> str:
    """What a stopped run leaves, and the command that continues it (one line)."""
    command = f"{TRAIN_COMMAND} --out {folder.path} --resume"
    if saved:
        return f"checkpoint {saved[-1]:,} is saved; continue with: {command}"
    return ("no checkpoint was written; the folder keeps its configuration; start it again "
            f"with the same command, or with: {command}")
