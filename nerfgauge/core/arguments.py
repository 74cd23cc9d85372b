"""Command-line value types shared by every stage's `commands.py`.

argparse's own `float` accepts "nan" and "inf"; these do not. Each raises
argparse.ArgumentTypeError with what it expected, which the `nerfgauge` command prints as
one line and exit 2.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def _number(text: str, kind):
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    return _number(text, float)


def _at_least(kind, bound, strict: bool, wanted: str):
    """An argparse type for numbers of `kind` above `bound` (strict) or at least it."""

    def parse(text: str):
        value = _number(text, kind)
        if value < bound or (strict and value == bound):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}")
        return value

    return parse


positive_float = _at_least(float, 0, True, "a positive number")
nonnegative_float = _at_least(float, 0, False, "a number >= 0")
positive_int = _at_least(int, 0, True, "a positive integer")
nonnegative_int = _at_least(int, 0, False, "an integer >= 0")


def path(text: str) -> Path:
    """A non-empty path (an empty one would silently mean the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"expected a path, got {text!r} (NUL byte)")
    return Path(text)
