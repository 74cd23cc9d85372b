"""Command-line value types shared by every stage's `commands.py`.

argparse's own `float` accepts "nan" and "inf"; these do not. Each raises
argparse.ArgumentTypeError with what it expected, which the `nerfgauge` command prints as
one line and exit 2.

Every numeric flag has a `Range` (`bounded(kind, low, high)`): its type on the command
line, its `check` for the same value given through the Python API or a config's
validate(), and its text in --help (`document_ranges`, run by `nerfgauge.cli`). The shared
ranges are named below with the reason for each bound. `path` refuses empty paths, NUL
bytes and paths that are not UTF-8 (`encodable_path`).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import types
import typing
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core.errors import InputError


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


def _show(number) -> str:
    if isinstance(number, int) or float(number).is_integer() and abs(number) < 1e7:
        return str(int(number))
    return f"{number:g}"


def is_int(value) -> bool:
    """An integer (Python or numpy), not a bool: the one test for "a whole number" values."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_number(value) -> bool:
    """A finite int or float (Python or numpy), not a bool."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
            and math.isfinite(value))


@dataclass(frozen=True)
class Range:
    """A numeric flag's range, one definition for the command line and the Python API.

    As an argparse `type` it parses the flag's text (argparse.ArgumentTypeError naming the
    range otherwise); `check(value, name)` checks a value given through the API or a
    config (InputError naming the range). `text` is what --help shows: `bounded` values
    are listed there by `document_ranges`. above/below: the bound itself is excluded."""

    kind: type
    low: float
    high: float
    above: bool = False
    below: bool = False

    @property
    def text(self) -> str:
        """ "1 to 1024"; with an excluded bound "above 0, up to 2" or "above 0, below 180"."""
        if not (self.above or self.below):
            return f"{_show(self.low)} to {_show(self.high)}"
        low = f"above {_show(self.low)}" if self.above else f"at least {_show(self.low)}"
        high = f"below {_show(self.high)}" if self.below else f"up to {_show(self.high)}"
        return f"{low}, {high}"

    @property
    def wanted(self) -> str:
        what = "an integer" if self.kind is int else "a number"
        return f"{what} {self.text}" if self.above or self.below else f"{what} from {self.text}"

    def contains(self, value) -> bool:
        return ((self.low < value if self.above else self.low <= value)
                and (value < self.high if self.below else value <= self.high))

    def __call__(self, text: str):
        value = _number(text, self.kind)
        if not self.contains(value):
            raise argparse.ArgumentTypeError(f"expected {self.wanted}, got {text!r}")
        return value

    @property
    def __name__(self) -> str:  # argparse names the type in some messages
        return self.wanted

    def check(self, value, name: str):
        """`value` if it is a number of this range's kind inside it; InputError otherwise."""
        ok = is_int(value) if self.kind is int else is_number(value)
        if not ok or not self.contains(value):
            raise InputError(f"{name} must be {self.wanted}, got {value!r}")
        return int(value) if self.kind is int else float(value)


def bounded(kind, low, high, *, above: bool = False, below: bool = False) -> Range:
    """A Range of `kind` (int or float) from `low` to `high` (above/below: excluding it)."""
    return Range(kind, low, high, above, below)


def check_fields(config, ranges: dict, flags: dict | None = None) -> None:
    """Check a config dataclass's numeric fields against their command-line ranges, for
    values that come through the Python API or a saved config rather than argparse.
    ranges: {field: Range}; a field holding None is skipped where its annotation admits None
    (Optional[...], ... | None: "auto" or "not given") and refused where it does not (a saved
    model.pt whose `threads` reads None would otherwise reach `threads > 1`). flags: {field:
    flag} where the flag is not --field-with-dashes. InputError naming the flag otherwise."""
    annotations = field_types(type(config))
    for name, limits in ranges.items():
        value = getattr(config, name)
        flag = (flags or {}).get(name, f"--{name.replace('_', '-')}")
        if value is None:
            if not admits_none(annotations.get(name)):
                raise InputError(f"{flag} needs a value, got None")
            continue
        limits.check(value, flag)


def field_types(cls) -> dict:
    """{field: type} of a class's annotations, strings (`from __future__ import annotations`)
    resolved in its module with typing's names behind it (a class made in a function may
    name Optional without its module importing it); {} where one names what neither holds."""
    module = sys.modules.get(cls.__module__)
    names = {**vars(typing), **(vars(module) if module is not None else {})}
    try:
        return typing.get_type_hints(cls, localns=names)
    except (NameError, TypeError):
        return {}


def admits_none(annotation) -> bool:
    """Whether a field's annotation, resolved to a type, allows None: None itself, Any, or a
    union with None (Optional[X], X | None). An unknown one (None) is taken to allow it."""
    if annotation is None or annotation is typing.Any or annotation is type(None):
        return True
    is_union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    return is_union and type(None) in typing.get_args(annotation)


def document_ranges(parser: argparse.ArgumentParser) -> None:
    """Add each Range-typed option's range to its help ("(1 to 1024)"), in `parser` and
    every subcommand below it, unless the help already states it."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                document_ranges(sub)
            continue
        found = getattr(action.type, "range", action.type)
        if isinstance(found, Range) and (action.help is None or found.text not in action.help):
            each = "each " if found is not action.type else ""
            action.help = f"{action.help or ''} ({each}{found.text})".strip()


# Ranges shared by several commands and their configs. Each bound is where the value stops
# meaning anything or starts overflowing something downstream.
THREADS = bounded(int, 1, 1024)  # torch/Dr.Jit thread pools; more than any machine's cores
# Seeds reach Mitsuba's 32-bit sampler seed, numpy and torch generators: a signed 32-bit value fits all.
SEED = bounded(int, 0, 2**31 - 1)
# View counts: 100,000 views of the smallest image already need days of rendering.
VIEWS = bounded(int, 1, 100_000)
SPLIT_VIEWS = bounded(int, 0, 100_000)
# Samples per pixel: Mitsuba's sample count is 32-bit per pass, and 65536 spp is beyond any
# noise level a dataset needs (noise PSNR grows by 3 dB per doubling).
SPP = bounded(int, 1, 1 << 16)
MAX_PATH_DEPTH = bounded(int, 1, 1024)  # path tracer bounces; light is gone long before
IMAGE_SIDE = bounded(int, 1, 8192)  # nerfgauge.core.validate.MAX_IMAGE_SIDE
STEPS = bounded(int, 1, 10**9)  # training steps; a step takes >= 1 ms, 10^9 is ten days
SECONDS = bounded(float, 0, 1e7, above=True)  # time budgets: 1e7 s is about 116 days
REPEATS = bounded(int, 1, 10_000)
WORKERS = bounded(int, 1, 256)  # processes
# Scene-unit lengths: scenes are normalised into [-1, 1]^3; 1e6 keeps float32 positions
# (7 digits) meaningful at the scale of the scene.
DISTANCE = bounded(float, 0, 1e6, above=True)
APERTURE = bounded(float, 0, 1e6)
FOV_DEGREES = bounded(float, 0, 180, above=True, below=True)
ELEVATION_DEGREES = bounded(float, -90, 90)
ROTATION_DEGREES = bounded(float, -360, 360)
WEIGHT = bounded(float, 0, 1e6)  # loss weights
LENS_SAMPLES = bounded(int, 1, 4096)  # lens samples per pixel (4096 resolves any blur to 1/64 of its disc)
PIXEL_SAMPLES = bounded(int, 1, 16)  # rays per pixel along each axis when rendering a box-filtered frame (16: 256 rays)
# Colour or alpha on [0, 1]: 0 gives a ray to every point between centres that differ at all,
# 1 to none (the centres alone)
CHANGE_STEP = bounded(float, 0, 1)
SAMPLES = bounded(int, 1, 10**8)  # point samples on a surface (10^8 float64 points: 2.4 GB)
# A ray-marching step below 1/20 of a voxel adds nothing to a trilinear grid, and 1e-9
# overflowed the sample count (an OverflowError traceback); above 2 whole cells are skipped.
STEP_RATIO = bounded(float, 0.05, 2)
GRID_RESOLUTION = bounded(int, 4, 1024)  # voxels a side of the compact model's grid (1024^3 fills memory)
# PSNR of float images stops near 150 dB (float32 rounding); 200 is beyond any target.
TARGET_PSNR = bounded(float, 0, 200, above=True)
BATCH_RAYS = bounded(int, 1, 1 << 20)  # a batch's samples must fit in memory: ~126 per contracted ray


MAX_SEEDS = 1000  # training runs of one configuration (`--seeds`): 1000 runs are weeks of CPU time


def check_seeds(seeds) -> list:
    """A list of distinct training seeds (SEED each, 1 to MAX_SEEDS of them); InputError otherwise."""
    seeds = list(seeds)
    if not 1 <= len(seeds) <= MAX_SEEDS:
        raise InputError(f"--seeds needs 1 to {MAX_SEEDS} seeds, got {len(seeds)}")
    for seed in seeds:
        SEED.check(seed, "--seeds")
    if len(set(seeds)) != len(seeds):
        raise InputError(f"--seeds lists a seed twice: {','.join(map(str, seeds))}")
    return seeds


def parse_seeds(text: str) -> list:
    """`--seeds K` (K seeds: 0, 1, ..., K-1) or `--seeds A,B,C` (those seeds; `7,` is the
    one seed 7). InputError otherwise."""
    text = str(text).strip()
    parts = [part for part in text.split(",") if part.strip()] if "," in text else [text]
    try:
        numbers = [int(part) for part in parts]
    except ValueError:
        numbers = []
    if not numbers:
        raise InputError(f"--seeds {text!r}: give a count K (seeds 0..K-1) or a list A,B,C of seeds, "
                         f"each {SEED.text}")
    if "," not in text:
        if not 1 <= numbers[0] <= MAX_SEEDS:
            raise InputError(f"--seeds {text}: the number of seeds must be 1 to {MAX_SEEDS} "
                             f"(or give a list of seeds, each {SEED.text}: --seeds 0,5,9)")
        numbers = list(range(numbers[0]))
    return check_seeds(numbers)


def seeds(text: str) -> list:
    """argparse type of `--seeds` (parse_seeds): a bad value is an argument error (one line, exit 2)."""
    try:
        return parse_seeds(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix(f"--seeds {text}: ")) from None


seeds.range = SEED  # each listed seed's range, shown in --help (document_ranges)


def comma_separated(item_type, *, distinct: bool = False):
    """An argparse type: "a,b,c" -> a tuple of item_type(each), at least one item; with
    distinct=True a repeated value is refused. Item errors name the item and the list."""
    def parse(text: str) -> tuple:
        parts = [part.strip() for part in text.split(",")]
        if not all(parts):
            raise argparse.ArgumentTypeError(f"expected comma-separated values, got {text!r}")
        values = []
        for part in parts:
            try:
                values.append(item_type(part))
            except argparse.ArgumentTypeError as error:
                raise argparse.ArgumentTypeError(f"{error} (in {text!r})" if len(parts) > 1 else str(error)) from None
        if distinct and len(set(values)) < len(values):
            repeated = next(v for v in values if values.count(v) > 1)
            raise argparse.ArgumentTypeError(f"{repeated} appears more than once in {text!r}")
        return tuple(values)

    parse.__name__ = f"comma-separated {item_type.__name__.replace('_', ' ')}s"  # argparse's fallback message
    parse.range = item_type if isinstance(item_type, Range) else None  # shown in --help
    return parse


def names(text: str) -> tuple:
    """ "a, b" -> ("a", "b"): comma-separated names, at least one, none empty."""
    parts = tuple(part.strip() for part in text.split(","))
    if not all(parts):
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    return parts


def path(text: str) -> Path:
    """A non-empty path (an empty one would silently mean the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"expected a path, got {text!r} (NUL byte)")
    try:
        encodable_path(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return Path(text)


def encodable_path(value, what: str = "path"):
    """`value` (a str or Path) if it is valid Unicode, InputError otherwise. A path whose
    bytes are not UTF-8 arrives from the OS with surrogate escapes; Mitsuba's path
    conversion (and JSON, which records paths) cannot encode it and crashed."""
    try:
        str(value).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{what} {str(value)!r} is not valid UTF-8; rename it (Mitsuba and nerfgauge's "
                         "JSON files need UTF-8 paths)") from None
    return value


def number_pair(what: str, example: str, within: "Range | None" = None):
    """An argparse type for "MIN,MAX": two finite numbers, MIN <= MAX, negatives as written
    ("-15,25"; the parser must also allow_negative_values); each inside `within` if given."""

    def parse(text: str) -> tuple[float, float]:
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected {what} as MIN,MAX (e.g. {example}), got {text!r}")
        low, high = (_number(part.strip(), float) for part in parts)
        if low > high:
            raise argparse.ArgumentTypeError(f"expected {what} MIN,MAX with MIN <= MAX, got {text!r}")
        if within is not None and not (within.contains(low) and within.contains(high)):
            raise argparse.ArgumentTypeError(f"expected {what} MIN,MAX each from {within.text}, got {text!r}")
        return low, high

    parse.range = within
    return parse


def spp(text: str):
    """Samples per pixel: a positive integer, or "auto" (grow until a noise target)."""
    return "auto" if text.strip().lower() == "auto" else SPP(text)


spp.range = SPP  # for --help and the range tests


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
