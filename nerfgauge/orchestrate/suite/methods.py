"""The methods a suite runs: its `[[methods]]` tables, or those `suite run --methods` names.

    [train]                        # the length every learned method's job is given
    steps = 2000                   #   required: step-counted runs repeat (methods taking steps)
    budget_seconds = 120           #   optional: a time budget, given to the methods that accept
                                   #   one (Method.train_length); the others get the steps
    threads = 2                    #   optional: threads per job (default: the method's)
    [[methods]]
    name = "compact-nerf"          # optional: its name on the leaderboard and its folders
    method = "compact"             #   (default: the method's own name); method: a built-in
    settings = { final_resolution = 48 }   # name, a shipped spec's name, module:Class, or a
    [[methods]]                    #   method spec .toml (relative to the suite file); settings:
    method = "nearest"             #   the method's own (methods.registry); steps and
    [[methods]]                    #   budget_seconds, where given, replace [train]'s for it
    method = "specs/nerfacto.toml"
    steps = 300
    [[methods]]                    # points (optional, a method that starts from the dataset's
    name = "splat-sfm"             #   COLMAP points): KIND[:COUNT] as `export colmap --points`
    method = "splat"               #   takes (surface, sfm, random, none); the arm trains on a
    points = "sfm"                 #   copy of each dataset with those points (same images,
                                   #   scored on the entry's own test views: orchestrate.suite.points)

Every method goes through the method interface (nerfgauge.methods.interface) and the
registry (nerfgauge.methods.registry); each is resolved and its request checked
(`Method.check`: a bad setting, a budget a method does not take) when the suite is read,
so a bad entry is the file's one-line error, not a job's failure. A job resolves it again
where it runs (here or on a dask worker).

A suite file without `[[methods]]` (every suite before methods had tables) runs our
compact NeRF, named `compact-nerf` (OURS), with the [train] table's other keys as its
settings (TrainConfig fields), and the baselines its [protocol] table lists.

The methods are what runs on a suite, not what the suite is: they are not part of the
suite's sha256 (`suite run --methods` runs others on the same datasets and scoring), and
each job's recipe holds its method, settings and length instead (orchestrate.suite.jobs).
"""

from __future__ import annotations

import hashlib
import importlib.util
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.eval.check import shown
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.interface import Method, TrainRequest, check_name
from nerfgauge.methods.registry import resolve

OURS = "compact-nerf"  # our NeRF's name on the leaderboard of a suite file without [[methods]]
TRAIN_KEYS = ("steps", "budget_seconds", "threads")  # [train] beside [[methods]]: the jobs' length
ENTRY_KEYS = ("name", "method", "settings", "steps", "budget_seconds", "points")
# the setting with which a method that reads initial points picks their kind (splat's --init):
# with `points`, it must be "auto" or that kind, or the arm would not train from the points it states
POINTS_SETTING = "init"


@dataclass(frozen=True)
class MethodEntry:
    """One method of a suite run: its leaderboard name, the method as written (a name,
    module:Class or a spec file), its settings, and the length it is given where it
    replaces the suite's. path: a spec file as found (relative to the suite file)."""

    name: str
    method: str
    settings: dict = field(default_factory=dict)
    steps: Optional[int] = None
    budget_seconds: Optional[float] = None
    path: Optional[str] = field(default=None, compare=False)
    points: Optional[str] = None  # the initial points its datasets hold (generate.points spec text), None: as generated

    @property
    def spec(self) -> str:
        """What the registry resolves: a spec file where it was found, else as written."""
        return self.path or self.method

    def resolve(self) -> Method:
        return resolve(self.spec, dict(self.settings) or None)

    def length(self, train: dict) -> tuple:
        """(steps, budget_seconds) offered to this method: its own where it names either,
        else the suite's [train]."""
        if self.steps is not None or self.budget_seconds is not None:
            return self.steps, self.budget_seconds
        return train.get("steps"), train.get("budget_seconds")

    def request(self, method: Method, train: dict, *, dataset, run, seed: int, threads=None,
                overwrite: bool = False) -> TrainRequest:
        """The TrainRequest of one job: the length the method takes of what is offered
        (Method.train_length), the entry's settings."""
        steps, budget = method.train_length(*self.length(train))
        return TrainRequest(dataset=dataset, run=run, seed=seed, steps=steps, budget_seconds=budget,
                            threads=threads, settings=self.settings, overwrite=overwrite)

    def identity(self) -> dict:
        """What a job's recipe holds of its method: the entry, and the sha256 of the file
        that defines the method where there is one (a spec; a user's module), so a job is
        redone when that file changes (our own code is in the job's version)."""
        return {"name": self.name, "method": self.method, "settings": self.settings, "steps": self.steps,
                "budget_seconds": self.budget_seconds, "source_sha256": _source_sha256(self.spec),
                **({"points": self.points} if self.points is not None else {})}  # without: as before (records resume)

    def definition(self) -> dict:
        return {key: value for key, value in (("name", self.name), ("method", self.method),
                                              ("settings", self.settings), ("steps", self.steps),
                                              ("budget_seconds", self.budget_seconds), ("points", self.points))
                if value not in (None, {})}


def _source_sha256(spec: str) -> Optional[str]:
    path = None
    if spec.endswith(".toml"):
        path = Path(spec)
    elif ":" in spec:
        found = importlib.util.find_spec(spec.split(":")[0])
        path = Path(found.origin) if found is not None and found.origin not in (None, "built-in") else None
    if path is None or not path.is_file():
        return None
    return hashlib.sha256(path.read_bytes()).hexdigest()


def check_train(train: dict, where: str) -> dict:
    """[train] beside [[methods]]: steps (required), budget_seconds, threads."""
    unknown = sorted(set(train) - set(TRAIN_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown field {unknown[0]!r} in [train] (beside [[methods]] it holds the jobs' "
                         f"length: {', '.join(TRAIN_KEYS)}; a method's own settings go in its settings table)")
    if "steps" not in train:
        raise InputError(f"{where}: missing field train.steps (the step count every learned method is offered)")
    _length(train, f"{where}: train")
    if "threads" in train:
        arguments.THREADS.check(train["threads"], f"{where}: train.threads")
    return train


def _length(table: dict, where: str) -> None:
    if table.get("steps") is not None:
        arguments.STEPS.check(table["steps"], f"{where}.steps")
    if table.get("budget_seconds") is not None:
        arguments.SECONDS.check(table["budget_seconds"], f"{where}.budget_seconds")


def parse_methods(raw, train: dict, where: str, base=None) -> tuple:
    """The [[methods]] tables, each resolved and its request checked; names unique.
    base: the folder a relative spec path is found in (the suite file's)."""
    if not isinstance(raw, list) or not raw or not all(isinstance(item, dict) for item in raw):
        raise InputError(f"{where}: [[methods]] must be a non-empty list of tables")
    entries = []
    for k, table in enumerate(raw):
        at = f"{where} methods[{k}]"
        unknown = sorted(set(table) - set(ENTRY_KEYS))
        if unknown:
            raise InputError(f"{at}: unknown field {unknown[0]!r}; known: {', '.join(ENTRY_KEYS)}")
        if not isinstance(table.get("method"), str) or not table["method"].strip():
            raise InputError(f"{at}: method must be a method's name, module:Class or a spec .toml, "
                             f"got {shown(table.get('method'))}")
        settings = table.get("settings", {})
        if not isinstance(settings, dict):
            raise InputError(f"{at}: settings must be a table, got {shown(settings)}")
        _length(table, at)
        entries.append(checked_entry(table["method"], at, base, train, name=table.get("name"), settings=settings,
                                     steps=table.get("steps"), budget_seconds=table.get("budget_seconds"),
                                     points=table.get("points")))
    return unique(entries, where)


def checked_entry(method: str, where: str, base, train: dict, *, name=None, settings=None, steps=None,
                  budget_seconds=None, points=None) -> MethodEntry:
    """A MethodEntry whose method resolves and accepts its settings, length and points
    (`check_points`; one line naming `where` otherwise)."""
    path = None
    if method.endswith(".toml"):
        found = Path(method).expanduser()
        path = str((Path(base if base is not None else ".") / found).resolve() if not found.is_absolute() else found)
    entry = MethodEntry(name or "", method, dict(settings or {}), steps, budget_seconds, path)
    try:
        resolved = entry.resolve()
        entry = MethodEntry(name or resolved.name, method, entry.settings, steps, budget_seconds, path,
                            None if points is None else check_points(points, resolved, entry.settings))
        check_name(entry.name, "name")
        if steps is not None or budget_seconds is not None:  # a length the entry names is meant for this method
            resolved.check(TrainRequest(dataset=".", run=".", steps=steps, budget_seconds=budget_seconds,
                                        settings=entry.settings))
        resolved.check(entry.request(resolved, train, dataset=".", run=".", seed=0, threads=train.get("threads")))
    except InputError as error:
        raise InputError(f"{where}: {error}") from None
    return entry


def check_points(points, method: Method, settings: dict) -> str:
    """A [[methods]] entry's `points`, as its canonical spec text ("sfm", "random:5000"):
    KIND[:COUNT] as generate.points.parse_spec reads it, for a method that reads initial
    points (Needs.initial_points), whose POINTS_SETTING, where given, is "auto" or that kind.
    InputError (one line) otherwise."""
    from nerfgauge.generate.points import KINDS, parse_spec  # the one reader of a points spec

    if not isinstance(points, str):
        raise InputError(f"points must be KIND[:COUNT] with KIND one of {', '.join(KINDS)}, got {shown(points)}")
    try:
        spec = parse_spec(points)
    except InputError as error:
        raise InputError(f"points: {str(error).removeprefix('--points ')}") from None
    if not method.needs.initial_points:
        raise InputError(f"points {spec.to_text()!r}: method {method.name} reads no initial points (its needs: "
                         f"{', '.join(method.needs.names())}); only a method that starts from the dataset's COLMAP "
                         "points takes them")
    chosen = settings.get(POINTS_SETTING)
    if chosen is not None and chosen not in ("auto", spec.kind):
        raise InputError(f"points {spec.to_text()!r}: settings.{POINTS_SETTING} is {shown(chosen)}, so the arm would "
                         f"not start from those points; set {POINTS_SETTING} = \"auto\" or \"{spec.kind}\"")
    return spec.to_text()


def unique(entries: list, where: str) -> tuple:
    seen = set()
    for entry in entries:
        if entry.name in seen:
            raise InputError(f"{where}: method name {entry.name!r} is used twice; give one a name")
        seen.add(entry.name)
    return tuple(entries)


def shorthand_methods(train: dict, baselines: list, where: str) -> tuple[dict, tuple]:
    """A suite file without [[methods]]: ([train]'s length keys, the methods): our NeRF
    (OURS: [train]'s model, default compact, its other keys as settings) and `baselines`."""
    length = {key: train[key] for key in TRAIN_KEYS if key in train and key != "budget_seconds"}
    if "budget_seconds" in train:
        raise InputError(f"{where}: [train] takes steps, not budget_seconds, without [[methods]] (suites are "
                         "step-counted; list methods in [[methods]] to give a time budget)")
    if "steps" not in train:
        raise InputError(f"{where}: missing field train.steps")
    settings = {key: value for key, value in train.items() if key not in TRAIN_KEYS and key != "model"}
    model = train.get("model", "compact")
    if not isinstance(model, str):
        raise InputError(f"{where}: train.model must be a string, got {shown(model)}")
    entries = [checked_entry(model, f"{where} [train]", None, length, name=OURS, settings=settings)]
    if not isinstance(baselines, list):
        raise InputError(f"{where}: protocol.baselines must be a list, got {shown(baselines)}")
    for baseline in baselines:
        if not isinstance(baseline, str) or not resolve_is_baseline(baseline):
            raise InputError(f"{where}: protocol.baselines: unknown baseline {shown(baseline)}")
        entries.append(checked_entry(baseline, f"{where} protocol.baselines", None, length))
    return length, unique(entries, where)


def resolve_is_baseline(name: str) -> bool:
    """`name` is a built-in method that does not train (a non-learned baseline)."""
    method = builtin_methods().get(name)
    return method is not None and not method.learned


def select(entries: tuple, names, train: dict) -> tuple:
    """`suite run --methods A,B,...`: each a name or method of the suite's entries (with
    their settings), else anything the registry resolves (with no settings)."""
    if isinstance(names, str):
        names = [name.strip() for name in names.split(",")]
    if not names or any(not name for name in names):
        raise InputError(f"--methods must be a comma-separated list of methods, got {shown(','.join(names))}")
    chosen = []
    for name in names:
        entry = next((e for e in entries if e.name == name), None) or next((e for e in entries if e.method == name), None)
        chosen.append(entry or checked_entry(name, "--methods", None, train))
    return unique(chosen, "--methods")
