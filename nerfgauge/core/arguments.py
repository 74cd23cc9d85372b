"""Command-line value types shared by every stage's `commands.py`.

argparse's own `float` accepts "nan" and "inf"; these do not. Each raises
argparse.ArgumentTypeError with what it expected, which the `nerfgauge` command prints as
one line and exit 2.
"""

from __future__ import annotations

import argparse
import math
import re
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


def number_pair(what: str, example: str):
    """An argparse type for "MIN,MAX": two finite numbers, MIN <= MAX, negatives as written
    ("-15,25"; the parser must also allow_negative_values)."""

    def parse(text: str) -> tuple[float, float]:
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected {what} as MIN,MAX (e.g. {example}), got {text!r}")
        low, high = (_number(part.strip(), float) for part in parts)
        if low > high:
            raise argparse.ArgumentTypeError(f"expected {what} MIN,MAX with MIN <= MAX, got {text!r}")
        return low, high

    return parse


def spp(text: str):
    """Samples per pixel: a positive integer, or "auto" (grow until a noise target)."""
    return "auto" if text.strip().lower() == "auto" else positive_int(text)


# argparse takes any word starting with "-" for an option unless it looks like a negative
# number; "-15,25" does not, so `--elevation -15,25` failed with "expected one argument".
# Numbers and comma-separated lists of them (with signs, decimals, exponents) are values.
NEGATIVE_VALUE = re.compile(r"^-\.?\d[\d.eE+-]*(,\s*[-+]?\.?\d[\d.eE+-]*)*$")


def allow_negative_values(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Let `parser` take negative numbers and lists like "-15,25" as option values as
    written. Sets argparse's own negative-number pattern (an attribute of the parser;
    safe while no option name itself looks like a negative number, which ours never do)."""
    parser._negative_number_matcher = NEGATIVE_VALUE
    return parser
