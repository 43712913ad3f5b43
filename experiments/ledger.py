"""What every long experiment shares: where committed results live and when they may be
replaced, the record of each invocation, and progress with an estimate of the time left.

An experiment trains programs (one scenario and learner each) and writes each finished
program's cells atomically, so the next invocation skips what is done. The program in
training is checkpointed every ``--checkpoint-minutes`` into ``<out>/partial/<cell>/``
(:class:`Partial`, :mod:`ccrjax.run.grid_checkpoint`) and resumed from there, exactly, so a
killed invocation loses at most those minutes. Every invocation is recorded in
``<out>/invocations.json`` (command, commit, device, date, wall time, programs trained,
whether it finished), rewritten after each program, so a killed one keeps its record.
Whether a stored cell is current is :mod:`experiments.cell_identity`'s question.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.run.grid_checkpoint import discard, train_resumably
from ccrjax.run.sweep_grid import nonfinite_log
from ccrjax.training.grid import GridRuns, GridTraining
from experiments import protocol
from experiments.cell_identity import (
    NOT_IN_CELLS,
    cell_is_current,
    comparable_identities,
    folder_settings,
    joined_settings,
    same_cells,
    settings_record,
    why_not_current,
)

# The repository's committed results: written only when a command is given --force.
RESULTS = Path(__file__).resolve().parent / "results"


def repo_relative(folder: Path | str) -> str:
    """``folder`` as a record names it: relative to the repository where it is inside (a
    committed result must not name the machine's paths)."""
    root = RESULTS.parent.parent
    resolved = Path(folder).resolve()
    return str(resolved.relative_to(root)) if resolved.is_relative_to(root) else str(folder)


INVOCATIONS = "invocations.json"
PARTIAL = "partial"  # <out>/partial/<cell>/: the program in training's checkpoint
CHECKPOINT_MINUTES = 15.0


def committed_results_problem(out: str | os.PathLike[str], force: bool,
                              results: Path | None = None) -> str | None:
    """Why ``--out out`` may not be written without ``--force`` (``None`` if it may): it
    lies inside the committed ``results`` folder (:data:`RESULTS` by default),
    so a mistyped folder never overwrites (or adds to) the results a repository's tables
    were made from."""
    if force:
        return None
    results = RESULTS if results is None else results
    try:
        inside = Path(out).resolve().is_relative_to(results.resolve())
        if not inside:
            return None
        with os.scandir(out) as entries:
            holds = any(entries)
    except FileNotFoundError:
        holds = False
    except (OSError, RuntimeError):  # unreadable, or a symbolic link loop: not our results
        return None
    if holds:
        return f"--out {out} holds committed results; give --force to add to or replace them"
    return f"--out {out} is inside the committed results ({results}); give --force to write there"


def add_checkpoint_option(parser: Any) -> None:
    """``--checkpoint-minutes``, the same in every experiment."""
    parser.add_argument("--checkpoint-minutes", type=cli.float_in(0.0),
                        default=CHECKPOINT_MINUTES,
                        help=f"save the program in training at most every this many minutes "
                        f"(into <out>/{PARTIAL}/), so that a killed invocation resumes it "
                        "where it was; 0: never (default: %(default)s)")


def add_out_options(parser: Any, committed: str, default: Path | None = None,
                    default_text: str | None = None) -> None:
    """``--out`` and ``--force``, the same in every experiment: results go under ``runs/``
    by default, and the committed ones (``experiments/results/<committed>``) are replaced
    only with ``--force`` (:func:`check_out`)."""
    shown = default_text or str(default)
    parser.add_argument("--out", type=Path, default=default,
                        help=f"results folder (default: {shown}; the committed results are "
                        f"experiments/results/{committed}, replaced only with --force)")
    parser.add_argument("--force", action="store_true",
                        help="allow --out to be a folder of committed results")


@dataclasses.dataclass(frozen=True)
class Partial:
    """Where and how often an experiment checkpoints the program it is training."""

    out: Path
    minutes: float = CHECKPOINT_MINUTES

    def folder(self, name: str) -> Path:
        return self.out / PARTIAL / name

    def train(self, training: GridTraining, name: str) -> GridRuns:
        """``training``'s results, resumed from cell ``name``'s checkpoint if there is one;
        runs whose updates went non-finite are kept (the program skipped those updates) and
        named in the log."""
        runs = train_resumably(training, self.folder(name), self.minutes * 60.0, log)
        note = nonfinite_log(runs, name)
        if note:
            log(f"  {note}")
        return runs

    def discard(self, name: str) -> None:
        """Deletes cell ``name``'s checkpoint once its results are written."""
        discard(self.folder(name))
        if (distributed.is_primary() and (self.out / PARTIAL).is_dir()
                and not any((self.out / PARTIAL).iterdir())):
            (self.out / PARTIAL).rmdir()


def add_no_train_option(parser: Any) -> None:
    """``--no-train``, the same in every experiment that summarises cells."""
    parser.add_argument("--no-train", action="store_true",
                        help="train nothing: write the summary from the cells in --out, or "
                        "say in one line which are missing or were made otherwise (so that a "
                        "changed setting or default never starts a long retraining unasked)")


def refuse_untrained(cells: dict[str, Path], record: dict[str, Any], out: Path) -> None:
    """Under ``--no-train``, raises :class:`ccrjax.cli.UsageError` when any of the named
    ``cells`` (name to path) the summary needs is not what ``record`` would make
    (:func:`experiments.cell_identity.why_not_current`), naming each and why."""
    problems = [f"{name}: {why}" for name, path in cells.items()
                if (why := why_not_current(read_json(path), record))]
    if problems:
        shown = "; ".join(problems[:4]) + (f"; and {len(problems) - 4} more"
                                           if len(problems) > 4 else "")
        raise cli.UsageError(f"--no-train: {len(problems)} of the {len(cells)} cells in {out} "
                             f"that the summary needs are not current ({shown}): run without "
                             "--no-train to train them")


def check_out(out: Path, force: bool) -> str | None:
    """Why ``out`` may not be written (``None`` if it may): a file, or a folder of the
    committed results under ``experiments/results/`` without ``--force``."""
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file, not a folder"
    problem = committed_results_problem(out, force)
    if problem and out.is_dir():  # it holds results: say what --force keeps
        return f"{problem} (cells made with the same settings are kept)"
    return problem


def prepare_out(prog: str, out: Path, force: bool) -> None:
    """For a measurement script: ``out`` checked (:func:`check_out`) and created before
    anything is measured, or one line and status 2."""
    try:
        problem = check_out(out, force)
        if problem:
            raise cli.UsageError(problem)
        cli.make_folder(out)
    except cli.UsageError as error:
        cli.fail(prog, str(error))


# What a cell-based experiment keeps when Ctrl-C or SIGTERM stops it (terminal.run_command).
STOPPED_KEPT = ("the finished programs' cells are kept in the --out folder, and the "
                "program in training from its last save under partial/ if "
                "--checkpoint-minutes allowed one; the same command goes on from them")


def open_experiment(prog: str, argv: list[str] | None, out: Path, force: bool,
                    settings_of: Callable[[], Any]) -> tuple[Any, Ledger]:
    """The start every experiment shares: ``out`` is checked (:func:`check_out`),
    ``settings_of()`` builds and validates the settings (raising
    :class:`ccrjax.cli.UsageError` or ``ValueError``), ``out`` must not hold another
    experiment's results, and any problem ends the command with one line and status 2
    before anything compiles; then the compilation cache, the folder and this invocation's
    record."""
    try:
        problem = check_out(out, force)
        if problem:
            raise cli.UsageError(problem)
        settings = settings_of()
        problem = check_experiment(out, prog, settings_record(settings), force)
        if problem:
            raise cli.UsageError(problem)
        if distributed.is_primary():
            cli.make_folder(out)
    except (cli.UsageError, ValueError) as error:
        cli.fail(prog, str(error))
    distributed.barrier("out folder made")
    cli.enable_compilation_cache(cli.default_cache_dir())
    command = " ".join([prog, *(argv if argv is not None else sys.argv[1:])])
    ledger = Ledger(out, settings, command, prog)
    ledger.record(0)
    return settings, ledger


def check_quick_out(quick: bool, out: Path | None) -> None:
    """``--quick`` needs an explicit ``--out``: quick numbers must not land in the folder a
    real run of the same experiment uses by default (raises :class:`ccrjax.cli.UsageError`)."""
    if quick and out is None:
        raise cli.UsageError("--quick needs --out: quick numbers must not mix with a real "
                             "run's in its default folder")


def cell_path(out: Path, scenario: str, algo: str) -> Path:
    """Where the cell of one scenario and learner is kept (the searches, the budgets)."""
    return out / "cells" / f"{scenario}-{algo}.json"


def plan_pairs(settings: Any, out: Path, runs: int, runs_text: str
               ) -> tuple[dict[tuple[str, str], dict], list[tuple[str, str]], ProgramProgress]:
    """The cells already made with ``settings`` (a dataclass with ``scenarios``, ``algos``,
    ``steps`` and ``budget(algo)``) by (scenario, algo), the pairs still to train (``runs``
    runs of ``budget(algo)`` steps each, described by ``runs_text``), and their progress."""
    pairs = [(s, a) for s in settings.scenarios for a in settings.algos]
    cells, todo = {}, []
    record = settings_record(settings)
    for scenario, algo in pairs:
        cell = read_json(cell_path(out, scenario, algo))
        # Several processes train the same programs in the same order: process 0's list.
        if distributed.agree(cell_is_current(cell, record)):
            cells[(scenario, algo)] = cell
        else:
            todo.append((scenario, algo))
    log(f"{len(pairs) - len(todo)} of {len(pairs)} programs already done; {len(todo)} to train "
        f"({runs_text}, on {device_name()})")
    progress = ProgramProgress([(f"{s}-{a}", a, runs * settings.budget(a)) for s, a in todo])
    if distributed.is_primary():
        (out / "cells").mkdir(parents=True, exist_ok=True)
    return cells, todo, progress


def train_pairs(todo: list[tuple[str, str]], out: Path, partial: Partial, ledger: Ledger,
                progress: ProgramProgress, train_cell: Callable[[str, str], dict[str, Any]]
                ) -> Iterator[tuple[tuple[str, str], dict[str, Any]]]:
    """Trains the program of each (scenario, algo) in ``todo`` with ``train_cell``, writes
    its cell, drops its checkpoint, records the invocation's progress and logs it; yields
    each pair with its cell as it is written (the searches' and the budgets' loop)."""
    for index, (scenario, algo) in enumerate(todo):
        cell = train_cell(scenario, algo)
        if distributed.is_primary():
            write_atomic(cell_path(out, scenario, algo), json.dumps(cell) + "\n")
        partial.discard(f"{scenario}-{algo}")
        ledger.record(index + 1)
        log(progress.finished(index, cell["train_s"] + cell["compile_s"]))
        yield (scenario, algo), cell


def device_name() -> str:
    device = jax.devices()[0]
    return f"{device.platform}:{device.device_kind} x{jax.device_count()}"


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def read_ledger(folder: Path) -> dict[str, Any] | None:
    """``folder``'s invocation records (``None`` if it has none); raises
    :class:`ccrjax.cli.UsageError` if the file is there but is not such a record."""
    path = folder / INVOCATIONS
    if not path.exists():
        return None
    ledger = read_json(path)
    if (not isinstance(ledger, dict) or not isinstance(ledger.get("settings"), dict)
            or not isinstance(ledger.get("invocations"), list)
            or not all(isinstance(record, dict) for record in ledger["invocations"])):
        raise cli.UsageError(f"{path} is not a record of invocations (unreadable, or without "
                             "settings and a list of invocations): move it away first")
    return ledger


def check_experiment(folder: Path, experiment: str, settings: dict[str, Any],
                     force: bool) -> str | None:
    """Why ``folder`` cannot take ``experiment``'s results made with ``settings`` (a
    settings record; ``None`` if it can): it holds another experiment's (the searches and
    the budgets name their cells alike), or the other search's (``variant``), or, unless
    ``force``, cells made with other settings, which would be trained again over them."""
    ledger = read_ledger(folder)
    if not ledger:
        return None
    found = ledger.get("experiment")
    if found is not None and found != experiment:
        return f"{folder} holds the results of {found}, not {experiment}"
    old = ledger["settings"]
    if old.get("variant", settings.get("variant")) != settings.get("variant"):
        return (f"{folder} holds the {old['variant']} search's results, not the "
                f"{settings['variant']} search's: name another --out")
    if not force and not same_cells(old, settings):
        differing = sorted({key for algo in protocol.EXPERIMENT_ALGOS
                            for mine, theirs in [comparable_identities(settings, old, algo)]
                            for key, value in mine.items() if theirs.get(key) != value})
        return (f"{folder} holds cells made with other settings ({', '.join(differing)}): "
                "give --force to train over them, or name another --out")
    return None


@contextlib.contextmanager
def locked(folder: Path) -> Iterator[None]:
    """Holds an exclusive lock on ``folder`` (``flock`` on the directory itself: no lock
    file among the results) while the block runs, so that invocations working in the same
    folder at once take turns."""
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX)
        yield
    finally:
        os.close(descriptor)  # releases the lock


class Ledger:
    """The invocation records of ``out`` made with ``settings`` (a dataclass): the earlier
    ones (dropped when the settings changed) and this one, kept up to date. Invocations
    running in the same folder at once (parts of a grid side by side) each keep the
    others' records: every update re-reads the file under a lock and replaces only its own.
    The file's settings are those the folder's cells share
    (:func:`experiments.cell_identity.folder_settings`, with the value of every variant its
    invocations trained, :func:`experiments.cell_identity.joined_settings`); what
    each invocation made (its scenarios, learners, parts) is in its own record's ``scope``.
    """

    def __init__(self, out: Path, settings: Any, command: str, experiment: str) -> None:
        self.out = out
        self.experiment = experiment
        self.settings = settings_record(settings)
        old = read_ledger(out)
        self.previous = (list(old["invocations"])
                         if old and same_cells(old["settings"], self.settings) else [])
        self.start = time.perf_counter()
        self.current = {"id": uuid.uuid4().hex,  # one invocation, however often copied
                        "command": command,
                        "scope": {k: v for k, v in self.settings.items() if k in NOT_IN_CELLS},
                        "commit": git_commit(), "device": device_name(),
                        "jax": jax.__version__, "date": time.strftime("%Y-%m-%d %H:%M %Z"),
                        "finished": False, "programs_trained": 0, "wall_time_s": 0.0}
        self.position: int | None = None  # where this record stands among the others

    @property
    def invocations(self) -> list[dict[str, Any]]:
        at = len(self.previous) if self.position is None else self.position
        return [*self.previous[:at], self.current, *self.previous[at:]]

    def record(self, trained: int, finished: bool = False) -> None:
        if not distributed.is_primary():  # several processes: process 0 keeps the records
            return
        self.current.update(wall_time_s=time.perf_counter() - self.start,
                            programs_trained=trained, finished=finished)
        folder = folder_settings(self.settings)
        with locked(self.out):
            on_disk = read_json(self.out / INVOCATIONS)
            if isinstance(on_disk, dict) and isinstance(on_disk.get("settings"), dict):
                # The variants this invocation does not train keep their cells, and so
                # their values, even where it trains the others' over other cells (--force).
                folder = joined_settings(folder, on_disk["settings"])
            if (isinstance(on_disk, dict) and isinstance(on_disk.get("settings"), dict)
                    and isinstance(on_disk.get("invocations"), list)
                    and same_cells(on_disk["settings"], self.settings)):
                # The file as it is now, less this invocation (kept in its place): earlier
                # records, and those of invocations in the same folder since this one began.
                ids = [record.get("id") for record in on_disk["invocations"]]
                self.position = (ids.index(self.current["id"]) if self.current["id"] in ids
                                 else None)
                self.previous = [record for record in on_disk["invocations"]
                                 if record.get("id") != self.current["id"]]
            write_atomic(self.out / INVOCATIONS,
                         json.dumps({"experiment": self.experiment,
                                     "settings": folder,
                                     "invocations": self.invocations}, indent=1) + "\n")


def duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{seconds:02d}s"


def invocation_line(run: dict[str, Any], programs: int | None = None) -> str:
    """One Markdown bullet for an invocation record: its command, commit, device, jax, date,
    the programs it trained (``of programs`` where the whole count is fixed) and its time.

    A record's time is rewritten as each program finishes, so an invocation stopped before
    its end (killed, or the machine lent back) is shown with the programs it finished and
    the time up to the last of them; one stopped before its first has no time to show."""
    of = "" if programs is None else f" of {programs}"
    head = (f"* `{run['command']}` at `{run['commit']}` on {run.get('device', '?')} "
            f"(jax {run.get('jax', '?')}), {run['date']}: ")
    trained = run["programs_trained"]
    if run.get("finished", True):
        return head + f"trained {trained}{of} program(s) in {duration(run['wall_time_s'])}"
    if trained:
        return head + (f"stopped before the end, after it trained {trained}{of} program(s) "
                       f"in {duration(run['wall_time_s'])}")
    return head + "stopped before the end, before its first program finished"


class ProgramProgress:
    """ProgramProgress across programs of unequal cost, with an estimate of the time left.

    Each program has a cost in work units (runs x environment steps) and a kind (its
    learner); the seconds per unit of a kind are measured on its programs so far (else
    on every program so far), and the time left is the remaining units at those rates.
    """

    def __init__(self, programs: list[tuple[str, str, float]]) -> None:
        self.programs = programs  # (name, kind, units)
        self.done: list[tuple[str, float, float]] = []  # (kind, units, seconds)
        self.start = time.perf_counter()

    def rate(self, kind: str) -> float | None:
        same = [(u, s) for k, u, s in self.done if k == kind] or [(u, s) for _, u, s in self.done]
        units = sum(u for u, _ in same)
        return sum(s for _, s in same) / units if units else None

    def finished(self, index: int, seconds: float) -> str:
        """Records program ``index`` as done in ``seconds``; returns the progress line."""
        name, kind, units = self.programs[index]
        self.done.append((kind, units, seconds))
        left = self.programs[index + 1:]
        estimate = 0.0
        for _, other_kind, other_units in left:
            estimate += (self.rate(other_kind) or 0.0) * other_units
        elapsed = time.perf_counter() - self.start
        return (f"[{index + 1}/{len(self.programs)}] {name}: {duration(seconds)}; elapsed "
                f"{duration(elapsed)}, about {duration(estimate)} left")
