"""What the commands (``train``, ``evaluate``, ``sweep``, ``demo``) share on the command line.

* :class:`Parser`: argparse whose mistakes are one line on stderr and exit status 2;
* :class:`UsageError` and :func:`fail`: the same one line for mistakes found later
  (a configuration value out of range, a folder that cannot be used);
* typed converters that name what is allowed (``positive_int``, ``unit_float`` ...);
* :func:`add_dataclass_options` / :func:`dataclass_overrides`: one option per field of a
  frozen configuration dataclass (``--ddpg-actor-lr``), so ``--help`` lists every
  hyperparameter with its default and nothing has to be kept in sync by hand.
"""

from __future__ import annotations

import _thread
import argparse
import contextlib
import dataclasses
import inspect
import math
import os
import re
import signal
import sys
import threading
import typing
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import jax

from ccrjax.checks import in_interval, interval_text

USAGE_ERROR = 2
# The repository's committed results (a checkout's experiments/results/): written only when
# a command is given --force.
COMMITTED_RESULTS = Path(__file__).resolve().parents[1] / "experiments" / "results"
INTERRUPTED = 130  # the shell's status for a command stopped by Ctrl-C


class UsageError(Exception):
    """A mistake of the user's: reported as one line, exit status 2, no traceback."""


# A Sphinx role in a docstring (:mod:`x`, :func:`~a.b`): the name alone in --help.
_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")


def plain_text(text: str | None) -> str | None:
    """``text`` (a docstring) without its reStructuredText markup: roles become the names
    they point to and double backticks go, so that ``--help`` reads as plain text."""
    if text is None:
        return None
    return _ROLE.sub(lambda match: match.group(1), text).replace("``", "")


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr, exit status 2, and whose
    description and epilog (often taken from a module's docstring) show as plain text."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        for name in ("description", "epilog"):
            kwargs[name] = plain_text(kwargs.get(name))
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR, f"{self.prog}: error: {message}\n")


def run_stoppable(prog: str, main: Callable[[], int], kept: str) -> int:
    """``main()``, with Ctrl-C and SIGTERM ending it through one line saying what was
    ``kept`` and status 130 (:data:`INTERRUPTED`), not a traceback: the experiments'
    entry point; a stop ends the process there (see below). Ctrl-C is honoured even where
    the process was started with SIGINT ignored (a test runner's worker, a script's
    background job), as ``ccrjax.train`` does."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with stop_noticed(prog), sigterm_as_interrupt(), interrupts_kept():
            return main()
    except KeyboardInterrupt:
        print(f"{prog}: stopped; {kept}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        # What is kept is written by now (the commands' cleanup runs in their finally
        # blocks), but XLA finishes a computation in flight before the interpreter may exit:
        # a chunk of training, minutes on a CPU, at full load. The process ends here instead.
        os._exit(INTERRUPTED)
    finally:
        signal.signal(signal.SIGINT, previous)


STOP_NOTICE = ("stopping (at once, or once the running compilation or chunk of training "
               "returns: XLA cannot be interrupted)")


@contextlib.contextmanager
def stop_noticed(prog: str) -> Iterator[None]:
    """Within the block the first Ctrl-C or SIGTERM is answered at once with
    ``prog: stopping ...`` (:data:`STOP_NOTICE`). Python runs signal handlers only between
    bytecodes, so a request that arrives while XLA compiles or runs a chunk of training
    would otherwise go unanswered until that returns (minutes, for a long program); the
    interpreter's C-level handler writes the signal's number to ``signal.set_wakeup_fd``
    the moment it arrives, and a watcher thread reading it prints the notice. Outside the
    main thread (where no wakeup descriptor can be set) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    read, write = os.pipe()
    os.set_blocking(write, False)
    previous = signal.set_wakeup_fd(write, warn_on_full_buffer=False)

    def watch() -> None:
        while True:
            try:
                numbers = os.read(read, 64)
            except OSError:
                return
            if not numbers:  # the block ended
                return
            if signal.SIGINT in numbers or signal.SIGTERM in numbers:
                print(f"{prog}: {STOP_NOTICE}", file=sys.stderr, flush=True)
                return

    watcher = threading.Thread(target=watch, name="stop-notice", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous)
        os.close(write)  # the watcher reads the end of the pipe, after any number in it
        watcher.join(timeout=5)
        os.close(read)


@contextlib.contextmanager
def interrupts_kept() -> Iterator[None]:
    """Within the block a ``KeyboardInterrupt`` that Python would discard is raised again.

    A signal's Python handler runs at the next bytecode, whatever code that is; when it is
    a garbage-collection callback (JAX registers one) or a ``__del__``, the interpreter
    prints "Exception ignored in ..." and drops the exception, so a Ctrl-C or SIGTERM
    would be announced and then lost while the command ran on to its end. Such exceptions
    reach ``sys.unraisablehook``; this one wakes a helper thread that marks SIGINT as
    arrived again (answered as Ctrl-C by the commands that use it), and prints nothing.
    The mark is made from the helper, once the hook has returned: made in the hook
    (``signal.raise_signal``, ``_thread.interrupt_main``) it would be handled at once,
    inside the hook, and dropped for good. A mark that lands in such a callback again is
    dropped and made again."""
    previous = sys.unraisablehook
    wake = _thread.allocate_lock()
    wake.acquire()
    closing: list[bool] = []

    def interrupt_again() -> None:
        while True:
            wake.acquire()  # blocks (without the GIL) until the hook or the exit wakes it
            if closing:
                return
            _thread.interrupt_main(signal.SIGINT)

    def hook(unraisable: Any) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type,
                                                           KeyboardInterrupt):
            if wake.locked():
                wake.release()  # the hook's last call: the helper needs the GIL to act
            return
        previous(unraisable)

    helper = threading.Thread(target=interrupt_again, name="interrupt-again", daemon=True)
    helper.start()
    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous
        closing.append(True)
        if wake.locked():
            wake.release()
        helper.join(timeout=5)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does, so a command
    stopped either way ends through the same clean path (status 130, one message)."""

    def interrupt(number: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def fail(prog: str, message: str, status: int = USAGE_ERROR) -> NoReturn:
    """Prints ``prog: error: message`` (one line) to stderr and exits with ``status``."""
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
    raise SystemExit(status)


def _number(text: str, kind: type) -> Any:
    try:
        value = kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """A converter to an integer in ``[low, high]`` (``high=None``: no upper bound)."""

    def convert(text: str) -> int:
        value = _number(text, int)
        if value < low or (high is not None and value > high):
            allowed = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"must be an integer {allowed}, got {value}")
        return value

    return convert


def float_in(low: float, high: float | None = None, *, low_open: bool = False,
             high_open: bool = False) -> Callable[[str], float]:
    """A converter to a finite float in the given interval."""

    def convert(text: str) -> float:
        value = _number(text, float)
        if not in_interval(value, low, high, low_open, high_open):
            allowed = interval_text(low, high, low_open, high_open)
            raise argparse.ArgumentTypeError(f"must be in {allowed}, got {text}")
        return value

    return convert


positive_int = int_in(1)
non_negative_int = int_in(0)
positive_float = float_in(0.0, low_open=True)
non_negative_float = float_in(0.0)
seed_int = int_in(0, 2**31 - 1)


def _split(text: str, kind: type, example: str) -> tuple[Any, ...]:
    """``text`` split at commas, each part converted by ``kind`` (``int`` or ``float``)."""
    try:
        return tuple(kind(part) for part in text.split(","))
    except ValueError:
        words = "integers" if kind is int else "numbers"
        message = f"must be comma-separated {words} such as {example}, got {text!r}"
        raise argparse.ArgumentTypeError(message) from None


def int_tuple(text: str) -> tuple[int, ...]:
    """``"64,64"`` to ``(64, 64)``: layer widths, each an integer > 0."""
    values = _split(text, int, "64,64")
    if not values or any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"must be integers > 0, got {text!r}")
    return values


def float_tuple(text: str) -> tuple[float, ...]:
    """``"-1,1"`` to ``(-1.0, 1.0)``, finite numbers (given as ``--option=-1,1``)."""
    values = _split(text, float, "-1,1")
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"must be finite numbers, got {text!r}")
    return values


def boolean(text: str) -> bool:
    lowered = text.lower()
    if lowered in ("1", "true", "yes", "on"):
        return True
    if lowered in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"must be true or false, got {text!r}")


def _converter(annotation: Any, default: Any) -> tuple[Callable[[str], Any], str]:
    """The converter and metavar for a dataclass field of type ``annotation``."""
    kind = typing.get_origin(annotation) or annotation
    if kind not in (bool, int, float, tuple, str):
        kind = type(default)
    if kind is bool:
        return boolean, "BOOL"
    if kind is int:
        return (lambda text: _number(text, int)), "INT"
    if kind is float:
        return (lambda text: _number(text, float)), "X"
    if kind is tuple:
        if default and all(isinstance(v, float) for v in default):
            return float_tuple, "X1,X2"
        return int_tuple, "W1,W2"
    if kind is str:
        return str, "NAME"
    raise TypeError(f"no command-line type for {annotation!r}")


def field_help(cls: type) -> dict[str, str]:
    """Each field's one-line description, from its comment in the class's source: the
    comment on the field's line, else the comment block just above it (first sentence)."""
    helps: dict[str, str] = {}
    block: list[str] = []
    for line in inspect.getsource(cls).splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            block.append(stripped.lstrip("#").strip())
            continue
        match = re.match(r"^\s+(\w+)\s*:[^=]*=[^#]*(?:#\s*(.*))?$", line)
        if match and match.group(1) in {f.name for f in dataclasses.fields(cls)}:
            text = match.group(2) or " ".join(block)
            helps[match.group(1)] = re.split(r"(?<=[.;])\s", text, maxsplit=1)[0].rstrip(".;")
        block = []
    return helps


def add_dataclass_options(
    parser: argparse.ArgumentParser, cls: type, prefix: str, title: str,
    exclude: Iterable[str] = (),
) -> None:
    """Adds ``--<prefix>-<field>`` for every field of the dataclass ``cls`` (defaults shown),
    each by :func:`add_field_option`.

    Values are only converted here; the dataclass validates them when it is built.
    The options default to ``None`` (= keep the dataclass default), so a run's
    configuration records only what was asked for on top of the defaults.
    """
    group = parser.add_argument_group(title)
    hints = typing.get_type_hints(cls)
    defaults = cls()
    for field in dataclasses.fields(cls):
        if field.name in exclude:
            continue
        convert, metavar = _converter(hints.get(field.name, field.type), field.default)
        add_field_option(group, f"--{prefix}-{field.name.replace('_', '-')}", defaults,
                         field.name, convert, dest=f"{prefix}__{field.name}", metavar=metavar)


def add_field_option(
    group: Any, option: str, owner: Any, field: str, convert: Callable[[str], Any] | None = None,
    *, choices: Iterable[str] | None = None, shown: Any = None, dest: str | None = None,
    metavar: str | None = None,
) -> None:
    """Adds ``option`` for the field ``field`` of the dataclass instance ``owner``: its help
    text from the field's comment (:func:`field_help`), its shown default ``owner``'s value
    (or ``shown``). The option defaults to ``None``: left out, the value is not changed."""
    default = getattr(owner, field) if shown is None else shown
    if isinstance(default, tuple):
        default = ",".join(map(str, default))
    elif isinstance(default, int) and not isinstance(default, bool):
        default = f"{default:,}"
    if metavar is None and choices is None:  # named after the option, not the field
        metavar = option.lstrip("-").replace("-", "_").upper()
    group.add_argument(
        option, dest=dest or field, type=convert, default=None, metavar=metavar,
        choices=tuple(choices) if choices is not None else None,
        help=f"{field_help(type(owner)).get(field, field.replace('_', ' '))} "
             f"(default: {default})",
    )


def dataclass_overrides(args: argparse.Namespace, prefix: str) -> dict[str, Any]:
    """The fields given on the command line for options added with ``prefix``."""
    head = f"{prefix}__"
    return {
        name[len(head):]: value
        for name, value in vars(args).items()
        if name.startswith(head) and value is not None
    }


def in_option_terms(message: str, prefixes: dict[str, str], options: Iterable[str]) -> str:
    """``message`` with every ``Owner.field`` of a dataclass whose fields are options
    (:func:`add_dataclass_options`; ``prefixes`` maps the class name to the options'
    prefix) written as the option the user typed: ``DDPGConfig.gamma`` becomes
    ``--ddpg-gamma`` where ``options`` has it."""
    known = set(options)

    def option(match: re.Match[str]) -> str:
        name = f"--{prefixes[match.group(1)]}-{match.group(2).replace('_', '-')}"
        return name if name in known else match.group(0)

    owners = "|".join(re.escape(owner) for owner in prefixes)
    return re.sub(rf"\b({owners})\.([A-Za-z_][A-Za-z0-9_]*)", option, message)


def make_folder(path: str | os.PathLike[str], option: str = "--out") -> None:
    """Creates the output folder ``path`` (and its parents) before any work is done, or
    raises :class:`UsageError` naming ``option``: a file there, or a folder that cannot be
    created, must not surface only when the results are written."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise UsageError(f"{option} {path} is a file, not a folder")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as error:
        raise UsageError(f"{option} {path} cannot be created ({error.strerror})") from None


def committed_results_problem(out: str | os.PathLike[str], force: bool,
                              results: Path | None = None) -> str | None:
    """Why ``--out out`` may not be written without ``--force`` (``None`` if it may): it
    lies inside the committed ``results`` folder (:data:`COMMITTED_RESULTS` by default),
    so a mistyped folder never overwrites (or adds to) the results a repository's tables
    were made from."""
    if force:
        return None
    results = COMMITTED_RESULTS if results is None else results
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


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/ccrjax/xla`` (``~/.cache/ccrjax/xla`` by default)."""

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "ccrjax", "xla")


def enable_compilation_cache(directory: str | None) -> None:
    """Keeps compiled programs on disk, so a run with the same shapes (a resumed run, the
    next seed batch, a re-run) starts in seconds instead of compiling for a minute.

    ``None`` leaves JAX's own setting (e.g. ``JAX_COMPILATION_CACHE_DIR``) alone. A cached
    program is the same executable, so results are identical with or without the cache.
    A folder that cannot be created just means no cache.
    """


    if directory is None or jax.config.jax_compilation_cache_dir:
        return
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError:
        return
    jax.config.update("jax_compilation_cache_dir", directory)
