"""A suite arm's initial points: `points = "sfm"` on a [[methods]] entry (orchestrate.suite.methods).

A dataset holds one kind of initial points in its COLMAP model (sparse/0, scene.json
"points"; generate.export). An arm that states other points trains on a copy of the scene
entry's dataset with those points, made once per scene entry and points spec by the
export's own code (`export_colmap`, as `nerfgauge export colmap DS --points KIND` does):

    OUT/points/<spec>/<id>/       the entry's dataset, every file it lists hard-linked (a byte
                                  copy where the file system has none), then re-exported with
                                  <spec>'s points: only sparse/0, images/ (links to the same
                                  train PNGs), transforms.json, scene.json and manifest.json
                                  differ; every image, camera and test view is the entry's own

The arm trains, renders and is scored on the copy (renders state the scene.json they show,
and the copy's records other points); the copy is checked when made to hold the entry's
ground truth byte for byte (`check_same_views`: every file but the export's has the sha256
the entry's manifest lists; scene.json and transforms.json differ only in the points
records), so its scores are over the entry's own test views. Its results are keyed to the
entry (results/<method>/<id>/), so the leaderboard pairs it with every other arm there. A dataset that already holds the spec's points (scene.json "points".spec: the
default export is surface) is used as it is.

Resumable: the copy's marker (a "dataset" folder) records the hash of {the entry's dataset
manifest sha256, the spec}, written when the copy is complete (a copy cut short holds the
entry's manifest, which verifies, so its marker records no recipe until then); a copy with
that recipe whose manifest verifies is kept, any other is removed (it holds our marker)
and made again; one that could not be made is removed. The job that trains on it records
the copy's manifest sha256 in its recipe (orchestrate.suite.jobs.method_job), so a copy
made again redoes the arm's jobs. Nothing is written outside OUT/points/.

A copy that cannot be made (SfM that registers too few points, a dataset without scene
bounds for random points) fails the arms that need it on that entry only, with the reason
(result.json "failed"); the suite goes on.
"""

from __future__ import annotations

from pathlib import Path

from nerfgauge.core import dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import link_or_copy_atomic, read_json, sha256_file
from nerfgauge.core.folders import claim_folder, read_marker, recipe_hash, remove_owned, write_marker
from nerfgauge.generate import export
from nerfgauge.generate.points import parse_spec
from nerfgauge.orchestrate.suite.jobs import failure_line

POINTS = "points"  # OUT/points/<spec>/<id>/


def points_folder(out, spec: str, entry_id: str) -> Path:
    return Path(out) / POINTS / spec / entry_id


def held_spec(folder) -> str | None:
    """The points spec a dataset's COLMAP export was made with (scene.json "points".spec), None if none."""
    try:
        record = read_json(Path(folder) / "scene.json").get("points")
    except InputError:
        return None
    return record.get("spec") if isinstance(record, dict) and isinstance(record.get("spec"), str) else None


def needs_copy(base, spec: str) -> bool:
    """Whether an arm stating `spec` needs a copy of the dataset at `base` (it holds other points)."""
    return held_spec(base) != parse_spec(spec).to_text()


def check_points_available(entries) -> None:
    """Before anything is written: what the stated points need on this machine (sfm: pycolmap)."""
    for entry in entries:
        if entry.points is not None and parse_spec(entry.points).kind == "sfm":
            export.require_pycolmap(f'method {entry.name}\'s points = "{entry.points}"')


def _recipe(base: Path, spec: str) -> str:
    return recipe_hash({"kind": POINTS, "dataset_manifest_sha256": dataset.manifest_sha256(base), "spec": spec})


def _complete(folder: Path, recipe: str) -> bool:
    """The copy at `folder` was made from this recipe and holds every file it lists, unchanged."""
    marker = read_marker(folder) if folder.is_dir() and not folder.is_symlink() else None
    return (marker is not None and marker.get("kind") == "dataset" and marker.get("recipe") == recipe
            and (folder / dataset.MANIFEST).is_file() and not (folder / export.JOURNAL).exists()
            and not dataset.verify_manifest(folder))


def make_points_dataset(out: str, base: str, spec: str, target: str) -> dict:
    """A job (run here or on a dask worker like the method jobs): the dataset at `base`
    with `spec`'s initial points, at `target` (points_folder). Returns {"dataset": target,
    "manifest_sha256": the copy's, "resumed": bool} or {"failed": why, "resumed": False}."""
    base, target, spec = Path(base), Path(target), parse_spec(spec).to_text()
    if not target.resolve().is_relative_to((Path(out) / POINTS).resolve()):
        raise InputError(f"{target} is not inside {Path(out) / POINTS}")  # the caller's fault, never the user's
    recipe = _recipe(base, spec)
    if _complete(target, recipe):
        return {"dataset": str(target), "manifest_sha256": dataset.manifest_sha256(target), "resumed": True}
    if target.exists() or target.is_symlink():
        remove_owned(target, "dataset")  # another recipe, or cut short: ours (its marker), made again
    owned.make_folder(target.parent)
    try:
        with claim_folder(target, "dataset", None):  # no recipe until complete (module docstring)
            for rel in [*dataset.read_manifest(base), dataset.MANIFEST]:
                owned.make_folder((target / rel).parent)
                link_or_copy_atomic(base / rel, target / rel)
            export.export_colmap(target, spec)
            check_same_views(base, target)
            write_marker(target, "dataset", recipe)
    except Exception as error:  # noqa: BLE001 - the points' failure is the arms', not the suite's
        if read_marker(target) is not None:
            remove_owned(target, "dataset")
        return {"failed": f"its {spec} points could not be made: {failure_line(error)}", "resumed": False}
    return {"dataset": str(target), "manifest_sha256": sha256_file(target / dataset.MANIFEST), "resumed": False}


EXPORTED = (f"{export.MODEL_DIR}/", f"{export.IMAGES_DIR}/")  # what the export rewrites, beside POINTS_RECORDS
POINTS_RECORDS = {"scene.json": ("points",), "transforms.json": ("ply_file_path",)}  # keys it replaces in them


def check_same_views(base: Path, copy: Path) -> None:
    """InputError unless the copy lists the same files as the dataset at `base` with the same
    sha256, but for the export's own (sparse/0, images/) and its records in scene.json and
    transforms.json (POINTS_RECORDS): the images, cameras and every split's ground truth are the entry's."""
    ours, theirs = dataset.read_manifest(base), dataset.read_manifest(copy)
    kept = lambda listing: {rel: item.sha256 for rel, item in listing.items()  # noqa: E731
                            if not rel.startswith(EXPORTED) and rel not in POINTS_RECORDS}
    if kept(ours) != kept(theirs):
        differ = sorted(set(kept(ours).items()) ^ set(kept(theirs).items()))
        raise InputError(f"the copy {copy} differs from {base} in {differ[0][0]}, not only in its points")
    for rel, keys in POINTS_RECORDS.items():
        before, after = (read_json(folder / rel) for folder in (base, copy))
        if {k: v for k, v in before.items() if k not in keys} != {k: v for k, v in after.items() if k not in keys}:
            raise InputError(f"the copy {copy}'s {rel} differs from {base}'s beyond its points records ({', '.join(keys)})")
