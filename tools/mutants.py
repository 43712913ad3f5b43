"""Mutation check: do the tests catch small, plausible bugs in the core code?  ``make mutants``

    python tools/mutants.py                     # every mutant of tools/mutants.toml
    python tools/mutants.py --only ddpg-actor-sign replay-ring-no-wrap
    python tools/mutants.py --list other.toml --no-baseline
    python tools/mutants.py --check             # only check that every patch applies

For every entry of the list (format: the comment at the top of ``tools/mutants.toml``),
the script replaces the entry's ``original`` text (which must occur exactly once in its
file) by its ``replacement``, runs only the entry's tests (``pytest -x -q -p
no:cacheprovider``), and puts the file back, always (a ``finally``, and on Ctrl-C or
SIGTERM every file is restored before exiting). A mutant is *caught* when its tests fail.

First (unless ``--no-baseline``) the named tests run once on the unmodified code: a test
that fails anyway would "catch" every mutant. Then a table: id, result, seconds, what the
mutant does. The exit status is 0 only if every patch applied and every mutant was caught.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_LIST = ROOT / "tools" / "mutants.toml"
FIELDS = ("id", "file", "description", "original", "replacement", "tests")


@dataclass(frozen=True)
class Mutant:
    id: str
    file: str
    description: str
    original: str
    replacement: str
    tests: tuple[str, ...]


class ListError(Exception):
    """The mutant list is malformed."""


def read_list(path: Path) -> list[Mutant]:
    """The mutants of a TOML list, checked field by field (ids unique, tests named)."""
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise ListError(f"{path}: {error}") from None
    entries = data.get("mutant")
    if not isinstance(entries, list) or not entries:
        raise ListError(f"{path}: no [[mutant]] entries")
    mutants, seen = [], set()
    for number, entry in enumerate(entries, 1):
        where = f"{path}: mutant #{number} ({entry.get('id', '?')})"
        missing = [name for name in FIELDS if name not in entry]
        unknown = sorted(set(entry) - set(FIELDS))
        if missing or unknown:
            raise ListError(f"{where}: missing {missing}, unknown {unknown}")
        tests = entry["tests"]
        if not isinstance(tests, list) or not tests or not all(
                isinstance(t, str) and "::" in t for t in tests):
            raise ListError(f"{where}: tests must be a non-empty list of pytest node ids")
        if entry["id"] in seen:
            raise ListError(f"{where}: duplicate id")
        if entry["original"] == entry["replacement"]:
            raise ListError(f"{where}: the replacement equals the original")
        seen.add(entry["id"])
        mutants.append(Mutant(**{**entry, "tests": tuple(tests)}))
    return mutants


class Files:
    """The original bytes of every file touched, to put back whatever happens."""

    def __init__(self) -> None:
        self.saved: dict[Path, bytes] = {}

    def patch(self, mutant: Mutant) -> None:
        path = ROOT / mutant.file
        text = path.read_text()
        count = text.count(mutant.original)
        if count != 1:
            raise ListError(f"{mutant.id}: the original text occurs {count} times in "
                            f"{mutant.file} (it must occur exactly once)")
        self.saved.setdefault(path, path.read_bytes())
        path.write_text(text.replace(mutant.original, mutant.replacement))

    def restore(self) -> None:
        for path, data in self.saved.items():
            if path.read_bytes() != data:
                path.write_bytes(data)
        self.saved.clear()


def check_applies(mutant: Mutant) -> str | None:
    """Why the mutant cannot be applied, or None."""
    path = ROOT / mutant.file
    if not path.is_file():
        return f"no file {mutant.file}"
    count = path.read_text().count(mutant.original)
    if count != 1:
        return f"original text found {count} times in {mutant.file}"
    return None


def run_tests(tests: tuple[str, ...], python: str, timeout: float) -> tuple[int, str]:
    """pytest's exit status on ``tests`` and the tail of its output."""
    command = [python, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
               *tests]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    try:
        output, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        output, _ = process.communicate()
        return -1, output[-4000:]
    except BaseException:
        process.kill()
        process.communicate()
        raise
    return process.returncode, output[-4000:]


def result_of(status: int) -> str:
    """pytest's exit status as a verdict: 1 means a test failed (the mutant is caught)."""
    return {0: "SURVIVED", 1: "caught", 2: "caught (error)", -1: "timeout"}.get(
        status, f"pytest error {status}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python tools/mutants.py",
                                     description="Apply each listed mutant, run its tests, "
                                     "restore the file; report caught/survived.")
    parser.add_argument("--list", type=Path, default=DEFAULT_LIST,
                        help="the mutant list (default: tools/mutants.toml)")
    parser.add_argument("--only", nargs="+", metavar="ID", help="run only these mutants")
    parser.add_argument("--check", action="store_true",
                        help="only check that every patch applies (runs no test)")
    parser.add_argument("--no-baseline", action="store_true",
                        help="skip running the named tests on the unmodified code first")
    parser.add_argument("--show", action="store_true",
                        help="print the end of every pytest run's output (why it failed)")
    parser.add_argument("--timeout", type=float, default=600.0,
                        help="seconds allowed per pytest run (default: 600)")
    parser.add_argument("--python", default=sys.executable,
                        help="the interpreter that runs pytest (default: this one)")
    args = parser.parse_args(argv)
    try:
        mutants = read_list(args.list)
    except ListError as error:
        print(f"mutants: error: {error}", file=sys.stderr)
        return 2
    if args.only:
        unknown = sorted(set(args.only) - {m.id for m in mutants})
        if unknown:
            print(f"mutants: error: unknown id(s) {unknown}", file=sys.stderr)
            return 2
        mutants = [m for m in mutants if m.id in args.only]

    files = Files()

    def stop(number, frame):  # SIGTERM: unwind through the finally blocks
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    start = time.perf_counter()
    rows: list[tuple[Mutant, str, float, str]] = []
    try:
        broken = {m.id: why for m in mutants if (why := check_applies(m)) is not None}
        for mutant_id, why in broken.items():
            print(f"mutants: error: {mutant_id} does not apply: {why}", file=sys.stderr)
        runnable = [m for m in mutants if m.id not in broken]
        if args.check:
            print(f"{len(runnable)} of {len(mutants)} mutants apply")
            return 0 if not broken else 1
        if not args.no_baseline and runnable:
            tests = tuple(dict.fromkeys(t for m in runnable for t in m.tests))
            print(f"baseline: {len(tests)} test(s) on the unmodified code ...", flush=True)
            began = time.perf_counter()
            status, output = run_tests(tests, args.python, args.timeout * 2)
            if status != 0:
                print(output, file=sys.stderr)
                print("mutants: error: the named tests fail on the unmodified code; fix that "
                      "first", file=sys.stderr)
                return 2
            print(f"baseline passed in {time.perf_counter() - began:.0f} s", flush=True)
        for number, mutant in enumerate(mutants, 1):
            if mutant.id in broken:
                rows.append((mutant, "NOT APPLIED", 0.0, broken[mutant.id]))
                continue
            began = time.perf_counter()
            try:
                files.patch(mutant)
                status, output = run_tests(mutant.tests, args.python, args.timeout)
            finally:
                files.restore()
            seconds = time.perf_counter() - began
            verdict = result_of(status)
            rows.append((mutant, verdict, seconds, ""))
            print(f"[{number}/{len(mutants)}] {mutant.id}: {verdict} ({seconds:.0f} s)",
                  flush=True)
            if args.show or verdict != "caught":
                print(output, file=sys.stderr)
    except KeyboardInterrupt:
        files.restore()
        print("\nmutants: interrupted; every file is restored", file=sys.stderr)
        return 130
    finally:
        files.restore()

    width = max(len(m.id) for m, *_ in rows)
    print(f"\n{'mutant':<{width}}  {'result':<14} {'seconds':>7}  what it does")
    for mutant, verdict, seconds, why in rows:
        note = f"{mutant.description}" + (f" [{why}]" if why else "")
        print(f"{mutant.id:<{width}}  {verdict:<14} {seconds:7.0f}  {note}")
    caught = sum(v.startswith("caught") for _, v, _, _ in rows)
    print(f"\n{caught} of {len(rows)} mutants caught in {time.perf_counter() - start:.0f} s")
    return 0 if caught == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
