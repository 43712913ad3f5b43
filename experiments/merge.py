"""Gather the cells of one experiment made in several folders (machines, processes) into one.

    python experiments/merge.py runs/search-a runs/search-b --into runs/search/ccr
    python experiments/merge.py /tmp/gpu/budgets --into experiments/results/budgets --force

The searches, the tables and the budgets keep each finished program's cells in
``<out>/cells/`` and every invocation in ``<out>/invocations.json``, so one grid can be
spread over several invocations, each writing its own folder, at once. This copies into
``--into`` the cells it lacks and appends the invocation records it does not hold.
Nothing is written unless every source is compatible: the same experiment settings (the
scenarios and learners named aside), and no cell held in two versions that differ. Then
run the experiment's own command on ``--into`` again to rebuild its summary and figures;
every cell exists, so it trains nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ccrjax import cli
from ccrjax.run.folder import write_atomic
from ccrjax.training import ALGOS
from experiments.ledger import (
    INVOCATIONS,
    NOT_IN_CELLS,
    cell_identity,
    cell_is_current,
    check_out,
    folder_settings,
    read_json,
    read_ledger,
    same_cells,
)

PROG = "python experiments/merge.py"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Gather the cells and invocation records of one "
                        "experiment made in several folders into one.")
    parser.add_argument("sources", type=Path, nargs="+",
                        help="results folders of the same experiment and settings")
    parser.add_argument("--into", type=Path, required=True,
                        help="the folder to complete (created if missing)")
    parser.add_argument("--force", action="store_true",
                        help="allow --into to be a folder of committed results")
    return parser


def ledger_of(folder: Path) -> dict[str, Any]:
    ledger = read_ledger(folder)
    if ledger is None:
        raise cli.UsageError(f"{folder} holds no {INVOCATIONS}: not an experiment's results "
                             "folder")
    return ledger


def record_key(record: dict[str, Any]) -> tuple:
    """One invocation, however often its record was copied: a record copied while the
    invocation ran and again after it ended has the same key. Records carry a unique
    ``id`` since 2026-11-24; older ones are told apart by command, commit, device and
    minute (two started in the same minute merge into one)."""
    if "id" in record:
        return ("id", record["id"])
    return tuple(record.get(k) for k in ("command", "commit", "device", "date"))


# How and where a cell was made, not what it holds: two cells that differ only here (the
# same runs made twice, or read back by a narrower invocation) are the same cell.
PROVENANCE = ("compile_s", "train_s", "compile_seconds_of_program", "train_seconds_of_program",
              "date", "device", "commit")


def cell_results(path: Path) -> dict[str, Any]:
    """A cell file's content less :data:`PROVENANCE` and the settings that only say which
    programs an invocation trained (``ledger.NOT_IN_CELLS``)."""
    cell = {k: v for k, v in read_json(path).items() if k not in PROVENANCE}
    if isinstance(cell.get("settings"), dict):
        cell["settings"] = {k: v for k, v in cell["settings"].items() if k not in NOT_IN_CELLS}
    return cell


def is_current(path: Path, settings: dict[str, Any]) -> bool:
    """Whether the cell file at ``path`` is what ``settings`` make now
    (``ledger.cell_is_current``); settings the current code refuses to run (an interval it
    would round, say) raise :class:`ccrjax.cli.UsageError` naming the folder."""
    try:
        return cell_is_current(read_json(path), settings)
    except ValueError as error:  # protocol.run_config's refusal
        raise cli.UsageError(f"{path.parent.parent} holds settings the current code refuses: "
                             f"{error}") from None


def differing(settings: dict[str, Any], other: dict[str, Any]) -> str:
    """The settings that tell two folders' cells apart, as ``name value / other value``."""
    found: dict[str, tuple[Any, Any]] = {}
    for algo in ALGOS:
        mine, theirs = cell_identity(settings, algo), cell_identity(other, algo)
        for key in sorted(mine.keys() | theirs.keys()):
            if mine.get(key) != theirs.get(key):
                found.setdefault(key, (mine.get(key), theirs.get(key)))
    return "; ".join(f"{key} {a!r} / {b!r}" for key, (a, b) in found.items())


def plan(sources: list[Path], into: Path
         ) -> tuple[dict[str, Path], list[str], int, dict[str, Any]]:
    """The cells to copy (name -> source file), the stale cells left out (made with other
    settings), the number of new invocation records and the merged ledger; raises
    :class:`ccrjax.cli.UsageError` on anything incompatible."""
    target = read_ledger(into)
    ledgers = [ledger_of(folder) for folder in sources]
    reference = target or ledgers[0]
    name = into if target else sources[0]
    # Records written before the experiment was named in them fit any experiment.
    experiment = next((x["experiment"] for x in [reference, *ledgers] if x.get("experiment")),
                      None)
    for folder, ledger in zip(sources, ledgers, strict=True):
        if ledger.get("experiment", experiment) != experiment:
            raise cli.UsageError(f"{folder} holds the results of {ledger['experiment']}, "
                                 f"not of {experiment}")
        if not same_cells(ledger["settings"], reference["settings"]):
            raise cli.UsageError(f"{folder} was made with other settings than {name} "
                                 f"({differing(ledger['settings'], reference['settings'])}): "
                                 "its cells would not match")
    # A cell of the target made with other settings is replaced, not defended.
    held = {path.name: path for path in sorted((into / "cells").glob("*.json"))
            if is_current(path, reference["settings"])}
    copies: dict[str, Path] = {}
    stale: list[str] = []
    for folder in sources:
        for path in sorted((folder / "cells").glob("*.json")):
            if not is_current(path, reference["settings"]):
                stale.append(str(path))
                continue
            known = copies.get(path.name) or held.get(path.name)
            if known is None:
                copies[path.name] = path
            elif cell_results(known) != cell_results(path):
                raise cli.UsageError(f"cell {path.name} differs between {known.parent.parent} "
                                     f"and {folder}: keep one of them")
    records = {record_key(r): r for r in (target["invocations"] if target else [])}
    new = 0
    for ledger in ledgers:
        for record in ledger["invocations"]:
            key = record_key(record)
            old = records.get(key)
            new += old is None
            if old is None or record.get("wall_time_s", 0) > old.get("wall_time_s", 0):
                records[key] = record  # the later copy of a record
    merged = {**reference, "settings": folder_settings(reference["settings"]),
              "invocations": list(records.values())}
    if experiment:
        merged["experiment"] = experiment
    return copies, stale, new, merged


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    into = args.into
    try:
        if any(source.resolve() == into.resolve() for source in args.sources):
            raise cli.UsageError("--into must not be one of the sources")
        problem = check_out(into, args.force)
        if problem:
            raise cli.UsageError(problem.replace("--out", "--into"))
        copies, stale, new, merged = plan(args.sources, into)
    except cli.UsageError as error:
        cli.fail(PROG, str(error))
    (into / "cells").mkdir(parents=True, exist_ok=True)
    for name, path in copies.items():
        write_atomic(into / "cells" / name, path.read_text())
    write_atomic(into / INVOCATIONS, json.dumps(merged, indent=1) + "\n")
    if stale:
        print(f"left out {len(stale)} cell(s) made with other settings: {', '.join(stale)}")
    print(f"{len(copies)} cell(s) copied into {into / 'cells'}: "
          f"{', '.join(copies) or 'none'}; {new} invocation record(s) added. Run the "
          "experiment's command on it again, naming the scenarios and learners to summarise, "
          "to rebuild its summary (it trains nothing for the cells it holds; a search's "
          "selection is the protocol's only over all 9 pairs).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
