"""A run folder: what a training run leaves behind for people to look at, compare and resume.

::

    DIR/config.json        the resolved configuration, ccrjax version, git commit, jax, devices
    DIR/metrics.csv        one row per evaluation point and seed
    DIR/tensorboard/       TensorBoard event files of the same metrics, one run per seed
    DIR/summary.json       final evaluation: per seed, mean and 95% confidence interval
    DIR/curves.png         training curves (mean over seeds with 95% band, seeds faint)
    DIR/episode.png, .gif  the trained team in one evaluation episode
    DIR/checkpoints/       orbax checkpoints (:mod:`ccrjax.run.checkpoint`)

Files other than the checkpoints are written whole to a temporary name and
renamed into place, so a reader (or a killed run) never sees half a file;
``metrics.csv`` is appended row by row while the run goes and rewritten from
the checkpoint's history when a run resumes, so it always matches the state.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import hashlib
import io
import json
import math
import os
import platform
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import jax

import ccrjax
from ccrjax.run.stats import format_mean_ci, mean_ci

# The paper's four metrics and the final distance to the target
# (ccrjax.training.acting.episode_metrics), and the training-time counts of dangerous robot-steps:
# all of training, and from the start of learning (the warm-up's random steps are the
# same for every variant).
# The command that trains a run folder (named in what a stopped run says to type next).
TRAIN_COMMAND = "python -m ccrjax.train"
EVAL_METRICS = ("return", "success_rate", "target_distance", "danger_frequency",
                "hazard_distance")
TRAINING_COUNTS = ("cumulative_danger_steps", "learning_danger_steps")
POINT_METRICS = (*EVAL_METRICS, *TRAINING_COUNTS)
CSV_COLUMNS = ("seed", "env_steps", "wall_time_s", *POINT_METRICS)
METRIC_TITLES = {
    "return": "return",
    "success_rate": "success rate",
    "target_distance": "final distance to the target",
    "danger_frequency": "dangerous-behaviour frequency",
    "hazard_distance": "average distance to the hazard centre",
    "cumulative_danger_steps": "cumulative dangerous robot-steps in training",
    "learning_danger_steps": "dangerous robot-steps since learning started",
    "lagrange_multiplier": "Lagrange multiplier (danger's price)",
    "lagrange_cost": "training danger (the multiplier's input)",
}

# The range of every metric, to which confidence intervals are clipped (the return is a
# sum of negative distances, never above 0).
METRIC_RANGES: dict[str, tuple[float, float]] = {
    "return": (-math.inf, 0.0),
    "success_rate": (0.0, 1.0),
    "target_distance": (0.0, math.inf),
    "danger_frequency": (0.0, 1.0),
    "hazard_distance": (0.0, math.inf),
    "cumulative_danger_steps": (0.0, math.inf),
    "learning_danger_steps": (0.0, math.inf),
    "lagrange_multiplier": (0.0, math.inf),
    "lagrange_cost": (0.0, 1.0),
}


@contextlib.contextmanager
def replacing(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside ``path`` (a hidden name, the same suffix) to write the new
    file to; when the block ends it is renamed onto ``path`` in one step, so a reader or a
    killed writer never sees half a file. On an error it is removed and ``path`` is left
    as it was."""
    path = Path(path)
    temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def folder_bytes(path: Path) -> int:
    """The bytes of every file under ``path``."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def write_atomic(path: Path, text: str) -> None:
    """Writes ``text`` to ``path`` whole (:func:`replacing`), flushed to disk first."""
    with replacing(path) as temporary, open(temporary, "w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())


RESULT_PATHS = ("experiments/results",)
"""Tracked folders of results, not code: a program writing into them beside another one that
starts must not make the other's commit read ``+dirty``."""


@functools.cache
def git_commit() -> str | None:
    """The commit of the ccrjax source tree (with ``+dirty`` if it has changes), if any.

    Read once per process, at the first call (every command makes it when it starts): the
    code that runs is the code imported then, so a commit made while a long program trains
    must not relabel that program's results.

    ``CCRJAX_COMMIT`` in the environment names it instead, for a copy of the tree whose git
    history is not the one it came from (a remote machine that receives the working tree)."""
    if named := os.environ.get("CCRJAX_COMMIT"):
        return named
    return tree_commit(Path(ccrjax.__file__).resolve().parent.parent)


def tree_commit(root: Path) -> str | None:
    """``HEAD`` of the git tree at ``root``, with ``+dirty`` if a tracked file outside
    ``RESULT_PATHS`` differs from it; ``None`` where ``root`` is not in a git tree.

    Result files are left out because experiments write them while others run: two search
    programs started side by side each rewrite their folder's ``invocations.json``, and the
    second to start would otherwise label its results as made from uncommitted code."""
    excluded = [f":(exclude){path}" for path in RESULT_PATHS]
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *excluded],
            cwd=root, capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+dirty" if dirty else "")


# What is not code that trains: a commit that changes only these (results, documentation,
# the tests, tools and benchmarks, and the experiments' modules that only read finished
# cells: reports, analyses, figures) leaves the code that trains as it was (code_commit).
NOT_CODE_PATHS = (
    *RESULT_PATHS, "docs", "*.md", "tests", "tools", "benchmarks", ".ci",
    "experiments/*_report.py", "experiments/*_analysis.py", "experiments/*_figures.py",
    "experiments/results_*.py",
)


@functools.cache
def code_commit() -> str | None:
    """:func:`tree_code_commit` of the ccrjax source tree, read once per process (as
    :func:`git_commit` is); ``CCRJAX_COMMIT`` in the environment names it instead.

    A grid's checkpoint is resumed only by the code that made it; committing a finished
    program's results or a page of documentation between a stop and the restart changes
    ``HEAD`` but not this, so the program in training resumes instead of starting over."""
    if named := os.environ.get("CCRJAX_COMMIT"):
        return named
    return tree_code_commit(Path(ccrjax.__file__).resolve().parent.parent)


def tree_code_commit(root: Path) -> str | None:
    """The newest commit of the git tree at ``root`` that changed the code (anything but
    :data:`NOT_CODE_PATHS`), with ``+dirty`` where :func:`tree_commit` says so; ``None``
    where ``root`` is not in a git tree."""
    head = tree_commit(root)
    excluded = [f":(exclude){path}" for path in NOT_CODE_PATHS]
    try:
        commit = subprocess.run(
            ["git", "log", "-1", "--format=%H", "--", ".", *excluded], cwd=root,
            capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return head
    if not commit or head is None:
        return head
    return commit + ("+dirty" if head.endswith("+dirty") else "")


def environment_record() -> dict[str, Any]:
    """Versions and devices, for ``config.json``."""
    return {
        "ccrjax_version": ccrjax.__version__,
        "git_commit": git_commit(),
        "jax_version": jax.__version__,
        "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()],
        "python": platform.python_version(),
        "host": platform.node(),
    }


def fingerprint(run_config: dict[str, Any]) -> str:
    """A short hash of a run's configuration (what a checkpoint must have been made with).
    The budget (``train.total_env_steps``) is left out: a run extended with a larger
    ``--steps`` is the same run, and its checkpoints stay its own."""
    run_config = dict(run_config)
    if isinstance(run_config.get("train"), dict):
        run_config["train"] = {k: v for k, v in run_config["train"].items()
                               if k != "total_env_steps"}
    text = json.dumps(run_config, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def format_value(value: Any) -> str:
    """A CSV cell: integers as they are, floats with the digits that round-trip exactly."""
    if isinstance(value, int):
        return str(value)
    return repr(float(value))


def own_columns(row: dict[str, Any]) -> list[str]:
    """The transform's own numbers a ``metrics.csv`` row holds beyond :data:`CSV_COLUMNS`
    (a Lagrange multiplier's path), in the order the transform gives them."""
    return [name for name in row if name not in CSV_COLUMNS]


def csv_columns(rows: Sequence[dict[str, Any]]) -> tuple[str, ...]:
    """:data:`CSV_COLUMNS`, then the rows' :func:`own_columns`."""
    return (*CSV_COLUMNS, *(own_columns(rows[0]) if rows else []))


def csv_text(rows: Sequence[dict[str, Any]], header: bool = True) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    columns = csv_columns(rows)
    if header:
        writer.writerow(columns)
    for row in rows:
        writer.writerow([format_value(row[c]) for c in columns])
    return buffer.getvalue()


def read_metrics(path: Path) -> list[dict[str, float]]:
    """The rows of a ``metrics.csv`` as dicts of numbers (seeds, steps and the counts of
    robot-steps as integers; older folders wrote the counts as ``141.0``)."""
    with open(path, encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    integers = ("seed", "env_steps", *TRAINING_COUNTS)
    return [{k: (int(float(v)) if k in integers else float(v)) for k, v in row.items()}
            for row in rows]


class RunFolder:
    """Reads and writes the files of one run folder (not its checkpoints)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._writers: dict[int, Any] = {}

    # ------------------------------------------------------------ paths
    @property
    def config_path(self) -> Path:
        return self.path / "config.json"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.csv"

    @property
    def checkpoint_dir(self) -> Path:
        return self.path / "checkpoints"

    @property
    def tensorboard_dir(self) -> Path:
        return self.path / "tensorboard"

    def holds_run(self) -> bool:
        return self.config_path.exists()

    def checkpoint_steps(self) -> list[int]:
        """The steps of the checkpoints written here (orbax names a complete one by its
        step; one being written has a temporary name)."""
        if not self.checkpoint_dir.is_dir():
            return []
        return sorted(int(p.name) for p in self.checkpoint_dir.iterdir() if p.name.isdigit())

    def has_checkpoint(self) -> bool:
        return bool(self.checkpoint_steps())

    # ------------------------------------------------------------ config
    def write_config(self, record: dict[str, Any]) -> None:
        write_atomic(self.config_path, json.dumps(record, indent=2, sort_keys=False) + "\n")

    def read_config(self) -> dict[str, Any]:
        with open(self.config_path, encoding="utf-8") as handle:
            return json.load(handle)

    # ------------------------------------------------------------ metrics
    def rewrite_metrics(self, rows: Sequence[dict[str, Any]]) -> None:
        write_atomic(self.metrics_path, csv_text(rows))

    def append_metrics(self, rows: Sequence[dict[str, Any]]) -> None:
        with open(self.metrics_path, "a", encoding="utf-8") as handle:
            handle.write(csv_text(rows, header=False))
            handle.flush()

    # ------------------------------------------------------------ tensorboard
    def open_tensorboard(self, seeds: Sequence[int], purge_step: int | None) -> None:
        """One event-file writer per seed; events at or after ``purge_step`` (left by a run
        that was killed after its last checkpoint) are hidden by TensorBoard on resume.
        Without tensorboardX (an optional dependency) no event files are written."""
        try:
            from tensorboardX import SummaryWriter  # optional: pip install -e '.[tensorboard]'
        except ImportError:
            return

        for seed in seeds:
            self._writers[seed] = SummaryWriter(
                logdir=str(self.tensorboard_dir / f"seed_{seed}"), purge_step=purge_step,
                flush_secs=10,
            )

    def log_scalars(self, seed: int, step: int, scalars: dict[str, float]) -> None:
        writer = self._writers.get(seed)
        if writer is None:
            return
        for tag, value in scalars.items():
            writer.add_scalar(tag, float(value), global_step=step)

    def close_tensorboard(self) -> None:
        for writer in self._writers.values():
            writer.close()
        self._writers.clear()

    # ------------------------------------------------------------ summary
    def write_summary(self, final_rows: Sequence[dict[str, Any]], extra: dict[str, Any]) -> dict:
        """``summary.json``: the final evaluation per seed, mean and 95% interval per metric
        (the transform's own numbers too, such as the final Lagrange multiplier)."""
        metrics = (*POINT_METRICS, *own_columns(final_rows[0]))
        summary = {
            "env_steps_per_seed": final_rows[0]["env_steps"],
            "seeds": [row["seed"] for row in final_rows],
            "per_seed": {str(row["seed"]): {m: row[m] for m in metrics} for row in final_rows},
            "mean_ci95": {m: mean_ci([row[m] for row in final_rows],
                                     bounds=METRIC_RANGES.get(m, (-math.inf, math.inf)))
                          for m in metrics},
            **extra,
        }
        write_atomic(self.path / "summary.json", json.dumps(summary, indent=2) + "\n")
        return summary


def timestamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")


def summary_table(summary: dict[str, Any]) -> str:
    """The evaluation metrics per seed, and their mean with its 95% interval (clipped to
    each metric's range), as a text table."""
    width = 28 if len(summary["per_seed"]) > 1 else 18
    header = f"{'seed':>8} " + " ".join(f"{m:>{width}}" for m in EVAL_METRICS)
    lines = [header, "-" * len(header)]
    for seed, values in summary["per_seed"].items():
        lines.append(f"{seed:>8} " + " ".join(f"{values[m]:{width}.4f}" for m in EVAL_METRICS))
    cells = [format_mean_ci(summary["mean_ci95"][m], digits=4) for m in EVAL_METRICS]
    lines.append(f"{'mean':>8} " + " ".join(f"{c:>{width}}" for c in cells))
    if len(summary["per_seed"]) > 1:
        lines.append("([low, high] is the 95% confidence interval of the mean over seeds, "
                     "Student t, clipped to the metric's range)")
    return "\n".join(lines)
