"""What a method is to the harness: it trains on a dataset folder into a run folder, and
renders a split of a dataset from that run into a folder of renders that `eval` scores.

Every method nerfgauge runs goes through this interface: our compact and vanilla NeRFs,
the non-learned baselines, Gaussian splatting, a Python class of the user's
(`module:Class`), and other tools' methods run from their own command lines (a TOML spec,
`nerfgauge.methods.external`). Suites, seeds, the Dask runner and the benches see only
`Method`, so whatever runs one runs all of them.

A method states what it needs from a dataset (`Needs`: the harness checks those before
starting it and skips it with the reason where a dataset lacks them) and what its renders
hold (`Produces`: which metrics can be scored). Training is asked for by a `TrainRequest`
(seed, steps or a time budget, threads, device, the method's own settings) and answered
by a `TrainResult`; rendering by a `RenderResult`. Results hold plain numbers only, so a
job's result crosses a process or a Dask worker as JSON.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Optional

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError

DEVICES = ("auto", "cpu", "cuda")
NAME = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")  # a method's name is a folder name (suites: results/<method>/)


@dataclass(frozen=True)
class Needs:
    """What a method reads from a dataset besides its train images and cameras."""

    transforms: bool = True  # transforms_*.json / transforms.json (cameras and image lists)
    colmap_model: bool = False  # DATASET/sparse/0 (COLMAP text or binary model)
    initial_points: bool = False  # points in that model's points3D (splatting starts from them)
    masks: bool = False  # per-pixel masks
    manifest: bool = False  # a nerfgauge dataset (manifest.json): runs are bound to its hash
    scene_bounds: bool = False  # scene.json's bounding box (a nerfgauge dataset)
    lightfield_layout: bool = False  # cameras on a two-plane grid (`generate --layout lightfield`)

    def names(self) -> list[str]:
        return [item.name.replace("_", " ") for item in dataclasses.fields(self) if getattr(self, item.name)]


@dataclass(frozen=True)
class Produces:
    """What a method's renders hold, so the evaluator knows which scores it can give."""

    colour: bool = True
    depth: bool = False  # ray distance or z-depth EXR beside each frame
    normals: bool = False
    poses: bool = False  # optimised camera poses (scored against the exact ones)

    def names(self) -> list[str]:
        return [item.name for item in dataclasses.fields(self) if getattr(self, item.name)]


@dataclass(frozen=True)
class TrainRequest:
    """One training job: the same fields for every method; `settings` are the method's own
    (for our NeRF, TrainConfig fields). Exactly one of steps and budget_seconds, or neither
    for a method that does not train (a baseline)."""

    dataset: Path
    run: Path
    seed: int = 0
    steps: Optional[int] = None
    budget_seconds: Optional[float] = None
    threads: Optional[int] = None  # None: the method's default
    device: str = "auto"
    settings: Mapping = field(default_factory=dict)
    overwrite: bool = False
    progress: bool = False

    def __post_init__(self):
        object.__setattr__(self, "dataset", Path(self.dataset))
        object.__setattr__(self, "run", Path(self.run))
        object.__setattr__(self, "settings", dict(self.settings))
        self.validate()

    def validate(self) -> None:
        arguments.SEED.check(self.seed, "seed")
        if self.steps is not None:
            arguments.STEPS.check(self.steps, "steps")
        if self.budget_seconds is not None:
            arguments.SECONDS.check(self.budget_seconds, "budget_seconds")
        if self.steps is not None and self.budget_seconds is not None:
            raise InputError("give a method steps or a time budget, not both")
        if self.threads is not None:
            arguments.THREADS.check(self.threads, "threads")
        if self.device not in DEVICES:
            raise InputError(f"unknown device {self.device!r}; choose one of {', '.join(DEVICES)}")


@dataclass(frozen=True)
class TrainResult:
    """What a training job cost. steps: None when the method does not say (an external
    tool's log was not parsed) or does not train. Memory in bytes (peak resident set)."""

    seconds: float
    steps: Optional[int] = None
    cpu_seconds: Optional[float] = None
    peak_memory_bytes: Optional[int] = None
    model_bytes: Optional[int] = None
    extra: Mapping = field(default_factory=dict)

    @property
    def steps_per_second(self) -> Optional[float]:
        if self.steps is None or not self.seconds > 0:
            return None
        return self.steps / self.seconds

    def to_json(self) -> dict:
        row = {"seconds": self.seconds, "steps": self.steps, "steps_per_second": self.steps_per_second,
               "cpu_seconds": self.cpu_seconds, "peak_memory_bytes": self.peak_memory_bytes,
               "model_bytes": self.model_bytes, **dict(self.extra)}
        return {key: (None if isinstance(value, float) and not math.isfinite(value) else value)
                for key, value in row.items()}


@dataclass(frozen=True)
class RenderResult:
    """Where a split's renders landed and in which layout `eval.predictions` reads them
    (`evaluate --pred-format`), with the time it took."""

    out: Path
    frames: int
    seconds: float
    pred_format: str = "nerfgauge"

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * self.seconds / max(self.frames, 1)


def check_name(name, where: str = "method name") -> str:
    """`name` if it can name a method (and its folder): lower-case letters, digits, '.', '_'
    and '-', starting with a letter or digit, at most 64 characters."""
    if not isinstance(name, str) or not NAME.match(name) or name in (".", ".."):
        raise InputError(f"{where} {name!r} must be 1-64 lower-case letters, digits, '.', '_' or '-', "
                         "starting with a letter or digit")
    return name


class Method:
    """A method the harness can run. Subclasses set `name`, `summary`, `needs`, `produces`,
    `learned` and implement `train` and `render`; a class of the user's that does so can be
    named in a suite or on the command line as `module:Class` (its constructor takes the
    method's settings table as keyword arguments, or nothing).

    train(request) -> TrainResult: write everything the method keeps into request.run.
    render(run, dataset, split, out) -> RenderResult: render every frame of `split` of the
    dataset at `dataset` (the one trained on, or a copy with the same manifest) into `out`.
    Errors a user can fix are `InputError`s (one line); anything else is the method's bug."""

    name: str = ""
    summary: str = ""
    needs: Needs = Needs()
    produces: Produces = Produces()
    learned: bool = True  # False: nothing to train (a baseline); train() only records the request
    accepts_budget: bool = True  # False: the method takes steps only (a time budget is refused)

    def train(self, request: TrainRequest) -> TrainResult:
        raise NotImplementedError

    def render(self, run: Path, dataset: Path, split: str, out: Path, *, overwrite: bool = False,
               progress: bool = False) -> RenderResult:
        raise NotImplementedError

    def check(self, request: TrainRequest) -> None:
        """Refuse (InputError, one line) a request this method cannot run, before anything
        runs: a suite checks each of its methods this way when it reads the suite file, so a
        bad setting is the file's error, not a job's failure. The default checks the length:
        a budget only where the method accepts one, and neither steps nor a budget for one
        that does not train. A method with settings or its own rules checks those too."""
        if not self.learned:
            if request.steps is not None or request.budget_seconds is not None:
                raise InputError(f"method {self.name} does not train: it takes no steps or time budget")
            return
        if request.budget_seconds is not None and not self.accepts_budget:
            raise InputError(f"method {self.name} takes a step count, not a time budget")

    def train_length(self, steps: Optional[int], budget_seconds: Optional[float]) -> tuple:
        """(steps, budget_seconds) this method is given when a suite or a bench offers `steps`
        and, where it has one, a time budget: the budget to a method that accepts one, else
        the steps; neither to a method that does not train. A method that trains on its own
        schedule (taking neither) overrides this."""
        if not self.learned:
            return None, None
        if budget_seconds is not None and self.accepts_budget:
            return None, budget_seconds
        return steps, None

    def describe(self) -> dict:
        """The row `nerfgauge methods` prints and a suite records."""
        return {"name": self.name, "summary": self.summary, "learned": self.learned,
                "needs": self.needs.names(), "produces": self.produces.names(),
                "budget": self.accepts_budget}


def missing_needs(method: Method, ds) -> list[str]:
    """What `method` needs that the dataset `ds` (a core.dataset.Dataset) lacks, as reasons a
    leaderboard can show ("needs a COLMAP model (sparse/0)"); empty when it can run."""
    needs, root = method.needs, Path(ds.root)
    reasons = []
    if needs.manifest and ds.foreign is not None:
        reasons.append(f"needs a nerfgauge dataset (manifest.json); this is a {ds.foreign.format} folder")
    if needs.scene_bounds and ds.bounds is None:
        reasons.append("needs the scene's bounds (scene.json), which this dataset lacks")
    if needs.lightfield_layout and (ds.scene.get("camera") or {}).get("layout") != "lightfield":
        reasons.append("needs a light-field camera grid (generate --layout lightfield)")
    if (needs.colmap_model or needs.initial_points) and not (root / "sparse" / "0").is_dir():
        reasons.append("needs a COLMAP model (sparse/0): nerfgauge export colmap DATASET")
    if needs.masks and not ds.has("masks"):
        reasons.append("needs masks: " + ds.unavailable_reason("masks"))
    return reasons
