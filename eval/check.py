"""The CI gate: compare a metrics.json against per-scene bounds from a thresholds.toml.

    nerfgauge check METRICS.json --thresholds thresholds.toml [--junit FILE] [--scene NAME]

Exit codes: 0 every check passes (or is skipped), 1 at least one fails, 2 malformed input
(`InputError`: unreadable or malformed files, unknown scene / metric / key, wrong schema,
nothing to check), 4 at least one fails and the run is **under-trained**: the thresholds
record a calibrated training (`training = { steps, steps_per_second }`, written by
`check --calibrate`) and metrics.json's `training.steps` is below half of its steps (a
time-budgeted run on a slower or busier machine). The line
`under-trained: got N steps, calibration had M (...)` says so, so the failure is not read
as a quality drop; CI may treat 4 as "rerun on a calibrated machine" rather than "regressed".
An under-trained run whose bounds all pass exits 0 (the line is still printed).
`nerfgauge run` writes metrics.json's `training` (steps, seconds, steps_per_second,
budget_seconds, seed); check prints it beside the table (the machine's measured speed).
`nerfgauge check --calibrate RESULTS...` proposes thresholds from measured runs
(eval/calibrate.py).

thresholds.toml
---------------
One table per scene, one entry per metric, each an inline table with `min` and/or `max`::

    ["*"]                            # applies to every scene
    ssim = { min = 0.90 }

    [primitives]
    psnr = { min = 30.0 }
    depth_absrel = { max = 0.02 }
    ssim = { min = 0.95 }            # replaces the "*" entry for ssim
    depth_delta1 = { min = 0.97, max = 1.0 }

    ["mesh:assets/bunny.obj"]        # user meshes by their full scene name
    psnr = { min = 25.0 }

- `training = { steps = N, steps_per_second = X }` in a scene table (or "*") is not a
  metric: the calibration runs' median steps and speed, read for the under-trained test.
- Table names: a scene from `scenes.registry.RECIPES`, a `mesh:PATH` scene, or `"*"`.
  Anything else is an error naming it.
- Metric names: `eval.metrics.METRIC_NAMES` (psnr, ssim, psnr_foreground, psnr_covisible,
  ssim_covisible, covisible_fraction, psnr_capture_bound, depth_absrel, depth_rmse,
  depth_mae, depth_delta1, depth_bias, depth_absrel_resolved, resolved_fraction, opacity_iou, psnr_edges,
  psnr_interior, edge_fraction, psnr_outline, outline_alpha_bias, outline_alpha_rmse, lpips),
  compared with metrics.json's `mean` table,
  and the geometry figures `eval.geometry.SUMMARY_NAMES` (geometry_chamfer_l1,
  geometry_fscore_1pct, normal_angle_mean, ...), compared with metrics.json's `geometry`
  table (written by `nerfgauge run` for the compact model).
- Entry keys: `min` and `max`, finite numbers, at least one, min <= max, and optionally
  `on`, what the bounds are compared with: "mean" (the default: metrics.json's `mean`) or
  "ci95" (metrics.json's `ci95`, the 95% bootstrap interval over the views,
  eval.uncertainty): `min` is then checked against the interval's lower end and `max`
  against its upper end, so the gate passes only when the whole interval clears the
  bound: `psnr = { min = 29.0, on = "ci95" }`. Only image metrics have intervals: `on =
  "ci95"` on a geometry figure is an error, and so is a ci95 bound against a metrics file
  without a `ci95` table (written before it existed: re-run `nerfgauge evaluate`).
  Bounds are inclusive: a value equal to its bound passes.
- The bounds for a scene are the `"*"` table overlaid by the scene's own table (per
  metric, the scene's entry replaces the `"*"` one). The metrics' scene (or `--scene`)
  must end up with at least one bound, otherwise nothing would be checked: an error.

Each bound is one check. Its margin is `value - min` or `max - value`: positive or zero
passes. A metric that is null or missing in metrics.json while it has a bound fails, with
the reason (for lpips without its weights: "lpips is n/a (install: nerfgauge lpips install)").
A value that is not a finite number (NaN, Infinity, an integer beyond float range) is no
score at all: the metrics file is malformed, exit 2 with one line, not a failed bound (exit
1). `--scene NAME` checks the metrics against NAME's bounds instead of
those of the scene the metrics file names (e.g. a `random` run with another seed).

Protocols: scores are compared only with bounds measured under the same scoring protocol
(`ScoringProtocol`: eval.protocols' name, nerfgauge, nerfbaselines or ns-eval; the
background colour is composited onto; the depth kind). A thresholds file states its own in a
`[protocol]` table (`check --calibrate` writes it from its runs)::

    [protocol]
    name = "nerfgauge"          # eval.protocols.PROTOCOLS
    background = "white"        # default: the protocol's own (ns-eval: black), else white
    depth_kind = "distance"     # default distance

A file without one (written before protocols were recorded) is read as ours, nerfgauge on
white with ray distance, and the first line of the output says so. metrics.json states its
protocol in "protocol", "protocol_background" (else "background") and "depth_kind" (one
without them, from before protocols existed, is ours on white with ray distance). A
metrics file scored under another protocol than its bounds is refused (exit 2, one line
naming both), and so is `check --calibrate` over runs of mixed protocols.

Geometry bounds are checked only against a metrics.json that has a `geometry` table.
One thresholds file serves both kinds of metrics file: `nerfgauge run` writes the table
(for the compact model; every figure null when the field had no surface, which fails its
bounds), plain `nerfgauge evaluate` scores images only and writes none. Against a file
without the table, each geometry bound is reported as skipped ("SKIP" in the table,
`<skipped>` in JUnit, `skipped=True, passed=True` from the API) with the reason "skipped:
no geometry in metrics", and does not fail the gate. A table that is present but lacks a
bounded figure, or holds it as null, fails as any metric does. If every bound of the scene
would be skipped, nothing would be checked: an error, as for a scene without bounds.

metrics.json (written by `nerfgauge evaluate`; `nerfgauge run` adds `geometry`), schema 1::

    {"schema": 1, "scene": "primitives", "split": "test",
     "mean": {"psnr": 31.2, "ssim": 0.95, "depth_absrel": 0.01, ...},
     "geometry": {"geometry_fscore_1pct": 0.30, "normal_angle_mean": 28.2, ...},
     "std": {...}, "ci95": {"psnr": [30.6, 31.8], ...}, "frames": [...], "timing": {...}}

Only `schema`, `scene`, `mean`, `geometry`, `ci95` ({metric: [low, high] or null},
`nerfgauge evaluate`), `training` and the protocol fields are read here; every number read
must be finite.
"""

from __future__ import annotations

import json
import math
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import tomllib
from nerfgauge.eval.geometry import SUMMARY_NAMES
from nerfgauge.eval.metrics import BACKGROUNDS, METRIC_NAMES as IMAGE_METRIC_NAMES
from nerfgauge.eval.predictions import DEPTH_SUFFIXES
from nerfgauge.eval.protocols import DEFAULT as DEFAULT_PROTOCOL_NAME, PROTOCOLS

from nerfgauge.core import bounded
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic
from nerfgauge.core.outputs import check_output_file, xml_mark

METRICS_SCHEMA = 1
# image metrics (metrics.json `mean`) and geometry figures (metrics.json `geometry`, written
# by `nerfgauge run`: eval.geometry.summary)
METRIC_NAMES = IMAGE_METRIC_NAMES + SUMMARY_NAMES
DEFAULT_TABLE = "*"
BOUND_KEYS = ("min", "max")
ENTRY_KEYS = BOUND_KEYS + ("on",)
ON_VALUES = ("mean", "ci95")  # what a bound is compared with (module docstring)
MESH_PREFIX = "mesh:"
TRAINING_KEY = "training"  # a table's calibrated training, not a metric (check --calibrate)
UNDER_TRAINED_FRACTION = 0.5  # fewer steps than this share of the calibration's: under-trained
EXIT_UNDER_TRAINED = 4  # a bound failed on a run that got under half the calibrated steps
JUNIT_KIND = "junit"  # the JUnit file's mark, `<!-- nerfgauge-kind: junit -->` (core.outputs)
PROTOCOL_TABLE = "protocol"  # thresholds' [protocol]: what the bounds were measured under
PROTOCOL_KEYS = ("name", "background", "depth_kind")
TRAINING_NUMBERS = ("steps", "seconds", "steps_per_second", "budget_seconds", "seed")  # metrics.json training, read here


@dataclass(frozen=True)
class ScoringProtocol:
    """What a score was measured under: eval.protocols' protocol, the background colour
    the images were composited onto, and the depth kind. Two scores are comparable only
    under equal protocols. recorded: False for a thresholds file without [protocol] (read
    as ours)."""

    name: str = DEFAULT_PROTOCOL_NAME
    background: str = "white"
    depth_kind: str = "distance"
    recorded: bool = field(default=True, compare=False)

    def __str__(self) -> str:
        return f"{self.name} (colour on {self.background}, depth {self.depth_kind})"

    def to_toml(self) -> str:
        """The [protocol] table of a thresholds file."""
        return (f"[{PROTOCOL_TABLE}]\nname = \"{self.name}\"\nbackground = \"{self.background}\"\n"
                f"depth_kind = \"{self.depth_kind}\"\n")


OURS = ScoringProtocol()


@dataclass(frozen=True)
class Bound:
    """Inclusive bounds on one metric; at least one of min / max is set."""

    metric: str
    min: Optional[float] = None
    max: Optional[float] = None
    on: str = "mean"  # "ci95": min against the interval's lower end, max against its upper end
    protocol: ScoringProtocol = OURS  # what the bound was measured under (the file's [protocol])


@dataclass(frozen=True)
class Training:
    """A scene table's `training = { steps, steps_per_second }`: what the calibration runs got."""

    steps: int
    steps_per_second: float


@dataclass(frozen=True)
class CheckResult:
    """One bound tested against one value.

    kind is "min" (value >= bound) or "max" (value <= bound). margin is value - bound for
    "min" and bound - value for "max" (>= 0 passes); None when the value is null or
    missing. reason explains a failure or a skip and is "" for a pass. A skipped check (a
    geometry bound against metrics without geometry) has skipped=True and passed=True: it
    does not fail the gate.
    """

    scene: str
    metric: str
    kind: str
    bound: float
    value: Optional[float]
    margin: Optional[float]
    passed: bool
    reason: str
    skipped: bool = False
    on: str = "mean"  # "ci95": value is the interval's lower (min) or upper (max) end

    @property
    def status(self) -> str:
        return "SKIP" if self.skipped else "PASS" if self.passed else "FAIL"

    @property
    def relation(self) -> str:
        return ">=" if self.kind == "min" else "<="

    @property
    def label(self) -> str:
        """The metric, and which end of its interval when the bound is on ci95."""
        return self.metric if self.on == "mean" else f"{self.metric}.ci95_{'low' if self.kind == 'min' else 'high'}"

    @property
    def name(self) -> str:
        return f"{self.label} {self.relation} {self.bound:.6g}"


# --- reading the inputs -------------------------------------------------------------


def known_scene(name: str) -> bool:
    """A recipe from `scenes.registry.RECIPES` or a `mesh:PATH` scene."""
    from nerfgauge.scenes.registry import RECIPES  # loads trimesh: only when a scene name is checked

    return name in RECIPES or (name.startswith(MESH_PREFIX) and len(name) > len(MESH_PREFIX))


def _known_scenes_text() -> str:
    from nerfgauge.scenes.registry import RECIPES  # trimesh, as above

    return ", ".join(list(RECIPES) + [MESH_PREFIX + "PATH", repr(DEFAULT_TABLE)])


def _read_text(path: Path, what: str) -> str:
    try:
        bounded.check_size(Path(path).stat().st_size, bounded.MAX_JSON_BYTES, path, what)
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read {what} {path}: {error}") from None


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def finite_number(value) -> bool:
    """An int or float (not a bool) that is a finite float: not NaN or +-inf, and not an
    integer beyond float range (JSON integers are unbounded; float(10**400) overflows)."""
    if not _is_number(value):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def shown(value, limit: int = 40) -> str:
    """repr(value), cut to `limit` characters, for one-line messages (a 400-digit integer
    or a forged 1 MB string stays one short line)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _choice(value, known, what: str, source: str) -> str:
    if not isinstance(value, str) or value not in known:
        raise InputError(f"{source}: {what} must be one of {', '.join(known)}, got {shown(value)}")
    return value


def protocol_of_metrics(document: dict, source: str = "metrics") -> ScoringProtocol:
    """The protocol a metrics.json was scored under (module docstring): "protocol",
    "protocol_background" (else "background") and "depth_kind"; absent fields are ours
    (files from before protocols were recorded). InputError when they are unknown or
    contradict the protocol (ns-eval scores on black)."""
    name = _choice(document.get("protocol", DEFAULT_PROTOCOL_NAME), PROTOCOLS, "protocol", source)
    background = _choice(document.get("protocol_background", document.get("background", "white")), BACKGROUNDS,
                         "protocol_background", source)
    fixed = PROTOCOLS[name].background
    if fixed is not None and BACKGROUNDS[background] != tuple(fixed):
        raise InputError(f"{source}: protocol {name} composites onto {_background_name(fixed)}, but the file says "
                         f"{background}")
    depth_kind = _choice(document.get("depth_kind", "distance"), DEPTH_SUFFIXES, "depth_kind", source)
    return ScoringProtocol(name, background, depth_kind)


def _background_name(colour) -> str:
    return next(name for name, value in BACKGROUNDS.items() if value == tuple(colour))


def _protocol_table(table, source: str) -> ScoringProtocol:
    """A thresholds file's [protocol] table: name (required), background (default: the
    protocol's own, else white), depth_kind (default distance)."""
    where = f"{source}: [{PROTOCOL_TABLE}]"
    if not isinstance(table, dict):
        raise InputError(f"{where} must be a table (name, background, depth_kind), got {shown(table)}")
    unknown = sorted(set(table) - set(PROTOCOL_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(PROTOCOL_KEYS)}")
    if "name" not in table:
        raise InputError(f"{where} has no name; give one of {', '.join(PROTOCOLS)}")
    fixed = PROTOCOLS.get(table["name"]).background if table["name"] in PROTOCOLS else None
    document = {"protocol": table["name"], "depth_kind": table.get("depth_kind", "distance"),
                "protocol_background": table.get("background", "white" if fixed is None else _background_name(fixed))}
    return protocol_of_metrics(document, where)


def check_protocol(metrics: dict, bounds: list, metrics_source: str = "metrics",
                   thresholds_source: str = "thresholds") -> ScoringProtocol:
    """The metrics' protocol when it is the one every bound was measured under; InputError
    (one line naming both) otherwise: scores of different protocols are not comparable."""
    scored = protocol_of_metrics(metrics, metrics_source)
    for bound in bounds:
        if bound.protocol != scored:
            raise InputError(f"{metrics_source} was scored under protocol {scored}, but the bounds of "
                             f"{thresholds_source} were measured under {bound.protocol}: scores of different "
                             f"protocols are not comparable (score with nerfgauge evaluate --protocol "
                             f"{bound.protocol.name}, or calibrate thresholds under {scored.name})")
    return scored


def parse_thresholds(data: dict, source: str = "thresholds") -> dict[str, dict[str, Bound]]:
    """Validate parsed TOML: {table name: {metric: Bound}}, in file order.

    Raises InputError naming the offending table, metric or key.
    """
    tables: dict[str, dict[str, Bound]] = {}
    protocol = (_protocol_table(data[PROTOCOL_TABLE], source) if PROTOCOL_TABLE in data
                else ScoringProtocol(recorded=False))
    for scene, table in data.items():
        if scene == PROTOCOL_TABLE:
            continue
        if scene in METRIC_NAMES:
            raise InputError(f"{source}: metric {scene!r} is outside a scene table; "
                             f"put it under [scene] or [\"{DEFAULT_TABLE}\"]")
        if scene != DEFAULT_TABLE and not known_scene(scene):
            raise InputError(f"{source}: unknown scene {scene!r}; known: {_known_scenes_text()}")
        if not isinstance(table, dict):
            raise InputError(f"{source}: [{scene}] must be a table of metrics, got {table!r}")
        bounds: dict[str, Bound] = {}
        for metric, entry in table.items():
            where = f"{source}: [{scene}] {metric}"
            if metric == TRAINING_KEY:
                bounds[metric] = _training_entry(entry, where)
                continue
            if metric not in METRIC_NAMES:
                raise InputError(f"{source}: [{scene}] unknown metric {metric!r}; known: {', '.join(METRIC_NAMES)}")
            if not isinstance(entry, dict):
                raise InputError(f"{where} must be a table like {{ min = ... }} or {{ max = ... }}, got {entry!r}")
            unknown = [key for key in entry if key not in ENTRY_KEYS]
            if unknown:
                raise InputError(f"{where}: unknown key {unknown[0]!r}; only 'min', 'max' and 'on' are allowed")
            on = entry.get("on", "mean")
            if on not in ON_VALUES:
                raise InputError(f"{where}.on must be one of {', '.join(map(repr, ON_VALUES))}, got {on!r}")
            if on == "ci95" and metric in SUMMARY_NAMES:
                raise InputError(f"{where}: on = \"ci95\" needs per-view values; the geometry figure {metric!r} "
                                 "has no interval: bound its value (on = \"mean\")")
            if not any(key in entry for key in BOUND_KEYS):
                raise InputError(f"{where} has no bound; give min and/or max")
            for key, value in entry.items():
                if key == "on":
                    continue
                if not finite_number(value):
                    raise InputError(f"{where}.{key} must be a finite number, got {shown(value)}")
            low, high = entry.get("min"), entry.get("max")
            if low is not None and high is not None and low > high:
                raise InputError(f"{where}: min {low} is greater than max {high}")
            bounds[metric] = Bound(metric,
                                   None if low is None else float(low),
                                   None if high is None else float(high), on, protocol)
        tables[scene] = bounds
    return tables


def _training_entry(entry, where: str) -> "Training":
    """A table's `training = { steps = N, steps_per_second = X }` (check --calibrate writes it)."""
    if not isinstance(entry, dict) or set(entry) != {"steps", "steps_per_second"}:
        raise InputError(f"{where} must be {{ steps = N, steps_per_second = X }}, got {entry!r}")
    steps, speed = entry["steps"], entry["steps_per_second"]
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise InputError(f"{where}.steps must be a positive integer, got {steps!r}")
    if not finite_number(speed) or speed <= 0:
        raise InputError(f"{where}.steps_per_second must be a positive number, got {speed!r}")
    return Training(steps, float(speed))


def load_thresholds(path) -> dict[str, dict[str, Bound]]:
    """Read and validate a thresholds.toml (format in the module docstring)."""
    text = _read_text(Path(path), "thresholds file")
    try:
        data = bounded.loads_toml(text, path)
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"malformed TOML in {path}: {error}") from None
    return parse_thresholds(data, str(path))


def validate_metrics(data, source: str = "metrics") -> dict:
    """Check the parts of a metrics.json that the gate reads; returns it unchanged."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: expected a JSON object, got {type(data).__name__}")
    if "schema" not in data:
        raise InputError(f"{source}: no 'schema' field; expected schema {METRICS_SCHEMA}")
    if data["schema"] != METRICS_SCHEMA or isinstance(data["schema"], bool):
        raise InputError(f"{source}: schema {data['schema']!r} is not supported; expected schema {METRICS_SCHEMA}")
    if not isinstance(data.get("scene"), str) or not data["scene"]:
        raise InputError(f"{source}: 'scene' must be a non-empty string, got {data.get('scene')!r}")
    mean = data.get("mean")
    if not isinstance(mean, dict):
        raise InputError(f"{source}: 'mean' must be an object of metric values, got {mean!r}")
    _finite_values(mean, "mean", source)
    geometry = data.get("geometry", {})
    if not isinstance(geometry, dict):
        raise InputError(f"{source}: 'geometry' must be an object of values, got {shown(geometry)}")
    _finite_values(geometry, "geometry", source)
    training = data.get("training", {})
    if training is not None and not isinstance(training, dict):
        raise InputError(f"{source}: 'training' must be an object (steps, seconds, steps_per_second), "
                         f"got {shown(training)}")
    _finite_values({key: value for key, value in (training or {}).items() if key in TRAINING_NUMBERS}, "training",
                   source)
    intervals = data.get("ci95", {})
    if not isinstance(intervals, dict):
        raise InputError(f"{source}: 'ci95' must be an object of [low, high] intervals, got {shown(intervals)}")
    for metric, value in intervals.items():
        if value is not None and not (isinstance(value, list) and len(value) == 2 and all(map(finite_number, value))
                                      and value[0] <= value[1]):
            raise InputError(f"{source}: ci95.{metric} must be [low, high] finite numbers with low <= high or null, "
                             f"got {shown(value)}")
    protocol_of_metrics(data, source)
    return data


def validate_scores(data, source: str = "metrics") -> dict:
    """validate_metrics, and the parts a report reads beside them: `std` (finite or null per
    metric), `frames` (objects with a string `name`, every metric finite or null), `notes`
    (strings), `noise.psnr_ceiling` and `timing.ms_per_frame` (finite or null). Returns
    `data` unchanged; InputError (one line naming the field) otherwise."""
    validate_metrics(data, source)
    for name in ("std", "notes", "noise", "timing"):
        if data.get(name) is not None and not isinstance(data[name], dict):
            raise InputError(f"{source}: '{name}' must be an object, got {shown(data[name])}")
    _finite_values(data.get("std") or {}, "std", source)
    if not all(isinstance(note, str) for note in (data.get("notes") or {}).values()):
        raise InputError(f"{source}: notes must be strings")
    _finite_values({"psnr_ceiling": (data.get("noise") or {}).get("psnr_ceiling")}, "noise", source)
    _finite_values({"ms_per_frame": (data.get("timing") or {}).get("ms_per_frame")}, "timing", source)
    frames = data.get("frames")
    if not isinstance(frames, list) or not all(isinstance(frame, dict) and isinstance(frame.get("name"), str)
                                               for frame in frames):
        raise InputError(f"{source}: frames must be a list of objects with a name, got {shown(frames)}")
    for frame in frames:
        _finite_values({key: value for key, value in frame.items() if key in METRIC_NAMES}, f"frames[{frame['name']}]",
                       source)
    return data


def _finite_values(table: dict, name: str, source: str) -> None:
    """Every value of `table` null or a finite number: a NaN or infinite score is not a
    score (exit 2, not a failed bound)."""
    for metric, value in table.items():
        if value is not None and not finite_number(value):
            reason = " (not finite: a score that is no number cannot be checked)" if _is_number(value) else ""
            raise InputError(f"{source}: {name}.{metric} must be a number or null, got {shown(value)}{reason}")


def load_metrics(path) -> dict:
    """Read and validate a metrics.json."""
    text = _read_text(Path(path), "metrics file")
    try:
        data = bounded.loads_json(text, path)
    except json.JSONDecodeError as error:
        raise InputError(f"malformed JSON in {path}: {error}") from None
    return validate_metrics(data, str(path))


def bounds_for_scene(tables: dict[str, dict[str, Bound]], scene: str, source: str = "thresholds") -> list[Bound]:
    """The "*" bounds overlaid by the scene's own, per metric. Raises if there are none."""
    merged = {metric: bound for metric, bound in tables.get(DEFAULT_TABLE, {}).items() if isinstance(bound, Bound)}
    merged.update({metric: bound for metric, bound in tables.get(scene, {}).items() if isinstance(bound, Bound)})
    if not merged:
        raise InputError(f"{source} has no bounds for scene {scene!r} (and no [\"{DEFAULT_TABLE}\"] table): "
                         "nothing would be checked")
    return list(merged.values())


def training_for_scene(tables: dict, scene: str) -> Optional["Training"]:
    """The calibrated training of the scene's table (else the "*" table's), or None."""
    for name in (scene, DEFAULT_TABLE):
        found = tables.get(name, {}).get(TRAINING_KEY)
        if found is not None:
            return found
    return None


def training_line(training) -> Optional[str]:
    """"training: N steps in S s, X steps/s (time budget B s)" from metrics.json's `training`, or None."""
    if not isinstance(training, dict) or not _is_number(training.get("steps")):
        return None
    speed = training.get("steps_per_second")
    budget = training.get("budget_seconds")
    return (f"training: {training['steps']} steps"
            + (f" in {training['seconds']:.1f} s" if _is_number(training.get("seconds")) else "")
            + (f", {speed:.3g} steps/s on this machine" if _is_number(speed) else "")
            + (f" (time budget {budget:g} s)" if _is_number(budget) else " (step-counted)"))


def under_trained(training, calibrated: Optional["Training"]) -> Optional[str]:
    """The under-trained line when the run got fewer than UNDER_TRAINED_FRACTION of the
    calibrated steps, else None (also when either side is unknown)."""
    if calibrated is None or not isinstance(training, dict) or not _is_number(training.get("steps")):
        return None
    if training["steps"] >= UNDER_TRAINED_FRACTION * calibrated.steps:
        return None
    speed = training.get("steps_per_second")
    return (f"under-trained: got {training['steps']} steps, calibration had {calibrated.steps} "
            + (f"({speed:.3g} steps/s here, {calibrated.steps_per_second:.3g} in calibration)"
               if _is_number(speed) else f"({calibrated.steps_per_second:.3g} steps/s in calibration)")
            + ": this machine trained less than the thresholds assume; a failed bound below is not a verdict "
              f"on quality (exit {EXIT_UNDER_TRAINED})")


# --- checking -----------------------------------------------------------------------


SKIPPED_NO_GEOMETRY = "skipped: no geometry in metrics"


def evaluate_bounds(scene: str, mean: dict, bounds: list[Bound], geometry: Optional[dict] = None,
                    notes: Optional[dict] = None, intervals: Optional[dict] = None) -> list[CheckResult]:
    """One CheckResult per (metric, min/max) bound, in the order of `bounds`.

    mean: the image metrics (metrics.json `mean`); geometry: metrics.json's `geometry`
    table, None when it has none (geometry bounds are then skipped, see the module
    docstring); notes: metrics.json's "notes" (e.g. {"lpips": "n/a (install: ...)"}),
    which explain null values; intervals: metrics.json's `ci95`, needed by the bounds with
    on = "ci95" (InputError when it is None and such a bound exists)."""
    values = {**(geometry or {}), **mean}
    results = []
    for bound in bounds:
        for kind in BOUND_KEYS:
            limit = getattr(bound, kind)
            if limit is None:
                continue
            if geometry is None and bound.metric in SUMMARY_NAMES:
                results.append(CheckResult(scene, bound.metric, kind, limit, None, None, True, SKIPPED_NO_GEOMETRY,
                                           skipped=True))
            elif bound.on == "ci95":
                if intervals is None:
                    raise InputError(f"the bound {bound.metric} on ci95 needs the metrics file's 'ci95' table, which "
                                     "it does not have (written before intervals existed: re-run nerfgauge evaluate)")
                ends = {metric: None if interval is None else interval[0 if kind == "min" else 1]
                        for metric, interval in intervals.items()}  # the lower end for min, the upper for max
                results.append(_check_one(scene, bound.metric, kind, limit, ends, notes or {}, on="ci95"))
            else:
                results.append(_check_one(scene, bound.metric, kind, limit, values, notes or {}))
    return results


def check_metrics(metrics: dict, bounds: list[Bound], source: str = "thresholds",
                  metrics_source: str = "metrics") -> list[CheckResult]:
    """The checks of a validated metrics document against `bounds`; InputError when every
    one would be skipped (nothing would be checked) or when the metrics were scored under
    another protocol than the bounds (`check_protocol`)."""
    check_protocol(metrics, bounds, metrics_source, source)
    notes = metrics.get("notes") if isinstance(metrics.get("notes"), dict) else {}
    results = evaluate_bounds(metrics["scene"], metrics["mean"], bounds, metrics.get("geometry"), notes,
                              metrics.get("ci95"))
    if results and all(r.skipped for r in results):
        raise InputError(f"{source}: every bound for scene {metrics['scene']!r} is a geometry figure and the metrics "
                         "have no geometry table (from `nerfgauge evaluate`, not `nerfgauge run`): nothing would be "
                         "checked")
    return results


def _check_one(scene: str, metric: str, kind: str, limit: float, mean: dict, notes: dict,
               on: str = "mean") -> CheckResult:
    """mean: {metric: value}; for on="ci95", {metric: the interval's end for this kind}."""
    label = CheckResult(scene, metric, kind, limit, None, None, False, "", on=on).label

    def fail(value, reason):
        return CheckResult(scene, metric, kind, limit, value, None, False, reason, on=on)

    if metric not in mean:
        return fail(None, f"{label} is missing from the metrics file")
    value = mean[metric]
    if value is None and isinstance(notes.get(metric), str):
        return fail(None, f"{label} is {notes[metric]} but has a bound")
    if value is None:
        return fail(None, f"{label} is null in the metrics file (not measured) but has a bound")
    if not finite_number(value):  # validate_metrics refuses these in a file; the same for the API's tables
        raise InputError(f"{label} is {shown(value)}, not a finite number: it cannot be checked against a bound")
    value = float(value)
    margin = value - limit if kind == "min" else limit - value
    passed = margin >= 0
    reason = "" if passed else (
        f"{label} = {value:.6g} is {'below the minimum' if kind == 'min' else 'above the maximum'} "
        f"{limit:.6g} by {-margin:.6g}")
    return CheckResult(scene, metric, kind, limit, value, margin, passed, reason, on=on)


# --- reporting ----------------------------------------------------------------------


def format_table(results: list[CheckResult]) -> str:
    """A plain-text table: scene, metric, value, bound, margin, result, reason."""
    header = ("scene", "metric", "value", "bound", "margin", "result", "reason")
    rows = [header]
    for r in results:
        rows.append((
            r.scene,
            r.label,
            "null" if r.value is None else f"{r.value:.6g}",
            f"{r.relation} {r.bound:.6g}",
            "-" if r.margin is None else f"{r.margin:+.6g}",
            r.status,
            r.reason,
        ))
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    return "\n".join(lines)


def junit_xml(results: list[CheckResult], properties: Optional[dict[str, str]] = None) -> bytes:
    """JUnit XML: one <testsuite>, one <testcase> per check, <failure> for failing ones."""
    failures = sum(not r.passed for r in results)
    suite = ET.Element("testsuite", {
        "name": "nerfgauge check",
        "tests": str(len(results)),
        "failures": str(failures),
        "errors": "0",
        "skipped": str(sum(r.skipped for r in results)),
    })
    if properties:
        props = ET.SubElement(suite, "properties")
        for key, value in properties.items():
            ET.SubElement(props, "property", {"name": key, "value": str(value)})
    for r in results:
        case = ET.SubElement(suite, "testcase", {"classname": f"nerfgauge.check.{r.scene}", "name": r.name})
        if r.skipped:
            ET.SubElement(case, "skipped", {"message": r.reason})
        elif not r.passed:
            failure = ET.SubElement(case, "failure", {"message": r.reason, "type": "ThresholdFailure"})
            failure.text = (f"scene {r.scene}: {r.label} = {'null' if r.value is None else f'{r.value:.6g}'}, "
                            f"required {r.relation} {r.bound:.6g}")
    ET.indent(suite)
    return xml_mark(ET.tostring(suite, encoding="utf-8", xml_declaration=True), JUNIT_KIND)


def write_junit(results: list[CheckResult], path, properties: Optional[dict[str, str]] = None) -> None:
    """Write JUnit XML through the atomic writer (a temporary file beside `path`, renamed into
    place; devices, FIFOs, folders and symlinks are refused)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"cannot write JUnit file {path}: directory {path.parent} does not exist")
    write_bytes_atomic(path, junit_xml(results, properties))


def run_check(metrics_path, thresholds_path, junit_path=None, scene: Optional[str] = None, out=None,
              overwrite: bool = False) -> int:
    """Load, check, print the table (and write JUnit). Returns 0 all pass, 1 any fails, 4
    (EXIT_UNDER_TRAINED) any fails on a run that got fewer than half the calibrated steps.
    metrics.json's `training` (nerfgauge run), when present, is printed beside the table:
    steps, seconds, steps per second and the time budget.
    junit_path: a new path or a JUnit file nerfgauge wrote (core.outputs.check_output_file);
    overwrite=True also replaces another nerfgauge file."""
    out = sys.stdout if out is None else out
    if junit_path is not None:  # refused before the table is printed, not after
        check_output_file(junit_path, JUNIT_KIND, overwrite=overwrite)
        if not Path(junit_path).parent.is_dir():
            raise InputError(f"cannot write JUnit file {junit_path}: directory {Path(junit_path).parent} does not exist")
    metrics = load_metrics(metrics_path)
    tables = load_thresholds(thresholds_path)
    table_scene = metrics["scene"] if scene is None else scene
    if scene is not None and not known_scene(scene):
        raise InputError(f"unknown scene {scene!r} for --scene; known: {_known_scenes_text()}")
    bounds = bounds_for_scene(tables, table_scene, str(thresholds_path))
    results = check_metrics(metrics, bounds, str(thresholds_path), str(metrics_path))
    protocol = bounds[0].protocol  # one per file, and the metrics' own (check_metrics refused others)

    via = "" if table_scene == metrics["scene"] else f" (bounds of scene {table_scene})"
    note = "" if protocol.recorded else (f"; note: {thresholds_path} records no [{PROTOCOL_TABLE}] (written before "
                                         "protocols were recorded): read as ours")
    print(f"checking {metrics_path} (scene {metrics['scene']}, split {metrics.get('split', '?')}) "
          f"against {thresholds_path}{via}, protocol {protocol}{note}", file=out)
    print(format_table(results), file=out)
    failed, skipped = sum(not r.passed for r in results), sum(r.skipped for r in results)
    print(f"{len(results)} checks: {len(results) - failed - skipped} passed, {failed} failed"
          + (f", {skipped} skipped (no geometry in metrics)" if skipped else ""), file=out)
    training = metrics.get("training")
    line, short = training_line(training), under_trained(training, training_for_scene(tables, table_scene))
    if line is not None:
        print(line, file=out)
    if short is not None:
        print(short, file=out)
    properties = {"metrics": str(metrics_path), "thresholds": str(thresholds_path), "scene": metrics["scene"],
                  "bounds_scene": table_scene, "protocol": str(protocol)}
    if line is not None:
        properties["training"] = line
    if short is not None:
        properties["under_trained"] = short
    if junit_path is not None:
        write_junit(results, junit_path, properties)
    if failed and short is not None:
        return EXIT_UNDER_TRAINED
    return 1 if failed else 0
