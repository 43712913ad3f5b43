"""Validation of configuration values, shared by every configuration of ccrjax.

Each check raises ``ValueError`` with one line naming the field (``Owner.name``, or the
bare name when ``owner`` is empty) and what is allowed; configurations call them once,
in ``__post_init__``, so a bad value is refused where it is given, before anything
compiles.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _field(owner: str, name: str) -> str:
    return f"{owner}.{name}" if owner else name


def check_int(owner: str, name: str, value: Any, low: int, high: int | None = None) -> None:
    """``ValueError`` unless ``value`` is an integer in ``[low, high]`` (``high=None``: no
    upper bound)."""
    allowed = f"an integer in [{low}, {high}]" if high is not None else f"an integer >= {low}"
    ok = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if not (ok and value >= low and (high is None or value <= high)):
        raise ValueError(f"{_field(owner, name)} must be {allowed}, got {value!r}")


def check_number(owner: str, name: str, value: Any, *, positive: bool) -> None:
    """``ValueError`` unless ``value`` is a finite number, > 0 (``positive``) or >= 0."""
    ok = isinstance(value, int | float | np.floating) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and (value > 0 if positive else value >= 0)):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{_field(owner, name)} must be a finite number {bound}, "
                         f"got {value!r}")


def check_choice(owner: str, name: str, value: Any, choices: Any) -> None:
    """``ValueError`` naming the field unless ``value`` is one of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{_field(owner, name)} must be one of {sorted(choices)}, "
                         f"got {value!r}")


def check_positive_int(owner: str, name: str, value: Any) -> None:
    """``ValueError`` naming the field unless ``value`` is an integer > 0."""
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{_field(owner, name)} must be an integer > 0, got {value!r}")


def in_interval(value: float, low: float, high: float | None, low_open: bool,
                high_open: bool) -> bool:
    """Whether ``value`` lies in the interval (``high=None``: unbounded above)."""
    ok = value > low if low_open else value >= low
    if high is not None:
        ok = ok and (value < high if high_open else value <= high)
    return ok


def interval_text(low: float, high: float | None, low_open: bool, high_open: bool) -> str:
    """The interval written out, e.g. ``(0.0, 1.0]`` or ``[0.0, inf)``."""
    left = "(" if low_open else "["
    right = (")" if high_open else "]") if high is not None else ")"
    return f"{left}{low}, {high if high is not None else 'inf'}{right}"


def check_finite(
    owner: str, name: str, value: Any, *, low: float = 0.0, low_open: bool = True,
    high: float | None = None, high_open: bool = False,
) -> None:
    """``ValueError`` naming the field unless ``value`` is a finite number in range."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and in_interval(value, low, high, low_open, high_open)):
        raise ValueError(
            f"{_field(owner, name)} must be a finite number in "
            f"{interval_text(low, high, low_open, high_open)}, got {value!r}"
        )


def check_hidden(owner: str, name: str, value: Any) -> None:
    """``ValueError`` unless ``value`` is a non-empty tuple of positive layer widths."""
    if not isinstance(value, tuple | list) or not value or any(
        isinstance(v, bool) or not isinstance(v, int) or v <= 0 for v in value
    ):
        raise ValueError(f"{_field(owner, name)} must be a non-empty tuple of integers > 0, "
                         f"got {value!r}")


def check_range(owner: str, name: str, value: tuple[float, float], *, positive: bool) -> None:
    """Validates a ``(low, high)`` pair; raises ``ValueError`` naming the field."""
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{name} must be a pair (low, high), got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise ValueError(f"{owner}.{name} must be finite with low <= high, got {value!r}")
    if positive and low <= 0:
        raise ValueError(f"{owner}.{name} must hold sizes > 0, got {value!r}")


def check_pair(owner: str, name: str, value: Any) -> None:
    """``ValueError`` unless ``value`` is a finite ``(x, y)`` pair."""
    try:
        ok = len(value) == 2 and all(math.isfinite(float(v)) for v in value)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{owner}.{name} must be a finite (x, y) pair, got {value!r}")
