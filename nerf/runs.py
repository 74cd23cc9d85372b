"""A trained run read back together with the dataset it was trained on.

A run records its dataset by content: RUN/config.json's "recipe" holds `dataset_sha256`,
the sha256 of the dataset's manifest.json (`nerfgauge.core.dataset.manifest_sha256`, the
value `train --resume` compares), and RUN/.nerfgauge.json holds the hash of that recipe
(`core.folders.recipe_hash`), so the record cannot be edited without the marker saying so.
The manifest lists the sha256 of every file of the dataset, so its hash changes when any
frame, pose, mesh or scene.json does: a dataset folder regenerated as another scene, or
edited, is a different dataset.

Every command that reads a run with a dataset (render, render --dataset, mesh, geometry
--run, the pipeline's and the suite's geometry) opens the dataset through `open_run_dataset`,
which refuses a dataset whose manifest differs from the record with one line naming both
hashes and both paths. The run itself is only read, never changed. `render` writes what
its frames show into timing.json (the sha256 of transforms_<split>.json and scene.json),
and `evaluate` refuses to score them against a dataset whose cameras or scene differ
(`core.provenance.check_renders_dataset`).

- `render RUN --dataset OTHER` renders a run on other cameras of the SAME scene (e.g. the
  same training views and test cameras through a thin lens, `bench lens`). OTHER must hold
  the manifest the run recorded (a moved or copied dataset), or the user passes
  `--other-dataset`: then the run's own dataset must still match its record, and OTHER must
  show the scene it shows (scene.json's recipe, seed and bounds).
- Runs made before the record existed (no marker, no recipe in config.json) cannot be
  checked: they are accepted with one warning line on stderr saying so (train again to get
  a checked run). A run whose marker names a recipe that config.json does not hold (edited
  or damaged) is refused.

Nothing here imports torch: eval/ and the pipeline call it before loading a model.
"""

from __future__ import annotations

import sys
from pathlib import Path

from nerfgauge.core.dataset import Dataset, open_dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.core.folders import MARKER, read_marker, recipe_hash
from nerfgauge.core.provenance import short_hash

CONFIG = "config.json"  # nerf.train.CONFIG (train imports torch; this module does not)


def recorded_manifest(run_dir) -> str | None:
    """The sha256 of manifest.json of the dataset the run in `run_dir` was trained on, or
    None for a run made before nerfgauge recorded it (no marker and no recipe). InputError
    when the record is damaged: the marker names a recipe config.json does not hold."""
    run_dir = Path(run_dir)
    marker = read_marker(run_dir) if run_dir.is_dir() and not run_dir.is_symlink() else None
    if marker is not None and marker["kind"] != "run":
        raise InputError(f"{run_dir} holds a nerfgauge {marker['kind']}, not a training run")
    try:
        recipe = read_json(run_dir / CONFIG).get("recipe") if (run_dir / CONFIG).is_file() else None
    except InputError:
        recipe = None
    recipe = recipe if isinstance(recipe, dict) and isinstance(recipe.get("dataset_sha256"), str) else None
    if marker is not None and marker.get("recipe") is not None:
        if recipe is None or recipe_hash(recipe) != marker["recipe"]:
            raise InputError(f"{run_dir / CONFIG} does not hold the recipe {run_dir / MARKER} names (edited or "
                             "damaged): the dataset the run was trained on is unknown; train it again")
    return None if recipe is None else recipe["dataset_sha256"]


def check_same_scene(trained_on: Dataset, other: Dataset) -> None:
    """InputError unless dataset `other` shows the scene (recipe, seed and bounds of
    scene.json) `trained_on` does."""
    key = lambda scene: (scene.get("recipe"), scene.get("seed"), scene.get("bounds"))  # noqa: E731
    a, b = key(trained_on.scene), key(other.scene)
    if a != b:
        raise InputError(f"--dataset {other.root} shows scene {b[:2]}, but the run was trained on "
                         f"{trained_on.root} showing {a[:2]}")


def open_run_dataset(run_dir, config, dataset=None, *, other_dataset: bool = False, warn=None) -> Dataset:
    """The dataset to read with the run in `run_dir` (config: its TrainConfig, from
    model.pt), checked against the run's record of what it was trained on.

    dataset: another path (or Dataset) than config.dataset, e.g. the dataset moved, or
    `render --dataset`; it must hold the recorded manifest unless other_dataset=True, which
    accepts another dataset of the same scene (the run's own dataset must then still match
    its record). warn: where the one-line warning for a run without a record goes
    (default: stderr). InputError, one line, naming both manifest hashes and both paths."""
    run_dir = Path(run_dir)
    recorded = recorded_manifest(run_dir)
    trained_path = Path(config.dataset)
    wanted = open_dataset(trained_path if dataset is None else dataset)
    if recorded is None:
        note = (f"warning: {run_dir} was made before nerfgauge recorded the dataset a run is trained on, so "
                f"{wanted.root} cannot be checked against {trained_path}; train again to get a checked run")
        print(note, file=sys.stderr if warn is None else warn)
        if dataset is not None and other_dataset and Path(wanted.root) != trained_path:
            check_same_scene(open_dataset(trained_path), wanted)
        return wanted
    if wanted.manifest_sha256 == recorded:
        return wanted
    if not other_dataset:
        moved = "" if dataset is None else " (pass --other-dataset to render another dataset of the same scene)"
        raise InputError(f"{run_dir} was trained on a dataset with manifest sha256 {short_hash(recorded)} "
                         f"({trained_path}), but {wanted.root / 'manifest.json'} has {short_hash(wanted.manifest_sha256)}: "
                         f"the dataset changed since training{moved}; train again on it, or give the dataset the run "
                         "was trained on")
    trained = open_dataset(trained_path)
    if trained.manifest_sha256 != recorded:
        raise InputError(f"--other-dataset: {run_dir} was trained on a dataset with manifest sha256 "
                         f"{short_hash(recorded)} ({trained_path}), but {trained.root / 'manifest.json'} now has "
                         f"{short_hash(trained.manifest_sha256)}, so the scene of {wanted.root} cannot be checked")
    check_same_scene(trained, wanted)
    return wanted
