"""What a folder of renders says it shows, checked against the dataset it is scored on.

`nerfgauge render` writes into its timing.json the sha256 of the dataset's
transforms_<split>.json (the cameras) and scene.json (the scene), as the manifest lists
them (`renders_record`); `nerfgauge evaluate` refuses to score those renders against a
dataset whose cameras or scene differ (`check_renders_dataset`). Only the cameras and the
scene count, so ground truth rendered again at more spp still scores the same renders.
A run's own record of its dataset (the manifest hash) is checked in nerf/runs.py.
"""

from __future__ import annotations

from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError

SHORT = 12  # hex digits of a hash shown in messages


def short_hash(digest) -> str:
    """The first SHORT hex digits of a sha256, for one-line messages ("none" for None)."""
    return f"{str(digest)[:SHORT]}..." if digest else "none"


def renders_record(source: Dataset, split: str) -> dict:
    """What renders of `split` show: {rel: sha256} of the dataset's transforms_<split>.json
    (the cameras) and scene.json (the scene), as its manifest lists them."""
    names = (f"transforms_{split}.json", "scene.json")
    return {rel: source.file_sha256(rel) for rel in names if source.file_sha256(rel) is not None}


def check_renders_dataset(pred_dir, timing: dict, ds: Dataset) -> None:
    """Renders of `nerfgauge render` state in timing.json the cameras and the scene they
    show (`renders_record`): refuse to score them against a dataset whose transforms or
    scene.json differ (one line, both hashes and both paths). Only the cameras and the
    scene count: ground truth rendered again at more spp still scores the same renders.
    Folders without that record (other methods, older renders) are not checked."""
    recorded = timing.get("dataset_files")
    if not isinstance(recorded, dict):
        return
    for rel, digest in sorted(recorded.items()):
        now = ds.file_sha256(rel)
        if now != digest:
            raise InputError(f"{pred_dir} shows the {rel} with sha256 {short_hash(digest)} of "
                             f"{timing.get('dataset', 'a dataset')}, but {ds.root / rel} has {short_hash(now)}: the "
                             "renders show other cameras or another scene; render the run again on this dataset")
