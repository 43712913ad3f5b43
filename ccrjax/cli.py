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

import argparse
import dataclasses
import importlib
import importlib.util
import inspect
import math
import os
import re
import sys
import typing
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, NoReturn

import jax

from ccrjax.checks import in_interval, interval_text

USAGE_ERROR = 2


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


PLUGIN_HELP = ("a module that registers transforms, learners or scenarios "
               "(ccrjax.registry): a dotted name or a .py file; repeatable (default: none)")


def plugin_names(argv: Sequence[str]) -> list[str]:
    """The values of every ``--plugin`` in ``argv`` (``--plugin X`` or ``--plugin=X``)."""
    names = []
    for index, word in enumerate(argv):
        if word == "--plugin" and index + 1 < len(argv):
            names.append(argv[index + 1])
        elif word.startswith("--plugin="):
            names.append(word.split("=", 1)[1])
    return names


def load_plugins(argv: Sequence[str]) -> None:
    """Imports each ``--plugin`` of ``argv`` before the parser is built, so that what it
    registers is among the options' choices; a module that cannot be imported raises
    :class:`UsageError` naming it and why."""
    for name in plugin_names(argv):
        try:
            if name.endswith(".py"):
                path = Path(name)
                spec = importlib.util.spec_from_file_location(path.stem, path)
                if spec is None or spec.loader is None or not path.is_file():
                    raise ImportError(f"no such file {name}")
                module = importlib.util.module_from_spec(spec)
                sys.modules[path.stem] = module  # dataclasses look their module up there
                spec.loader.exec_module(module)
            else:
                importlib.import_module(name)
        except (ImportError, ValueError, SyntaxError) as error:
            raise UsageError(f"--plugin {name}: cannot import it ({error})") from None


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
