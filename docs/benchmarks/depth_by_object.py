"""A model's depth against the ground truth's, by object: where colour steps bend the geometry.
docs/results.md, "Where the error sits".

    python docs/benchmarks/depth_by_object.py DATASET PRED_DIR OUT.png [VIEWS, default 0,3,7]

PRED_DIR: the predicted test PNGs and depth EXRs (`nerfgauge render RUN --split test`, under
OUT/test). Prints, per instance, the predicted ray distance minus the true one on the pixels
fully covered by it and away from its outline (its 3 x 3 neighbourhood all the same
instance): mean and RMS. OUT.png: per view, the ground truth and that difference less the
median over all such pixels (red: the model's surface deeper, blue: nearer, full at 0.02).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from error_shares import neighbourhood  # this folder's script, beside this one
from PIL import Image

from nerfgauge.core.dataset import DEPTH_CHANNEL
from nerfgauge.core.images import read_exr_single

FULL_SCALE = 0.02  # scene units of depth difference drawn at full colour


def read_depth(path: Path) -> np.ndarray:
    return read_exr_single(path, name=DEPTH_CHANNEL).astype(np.float64)


def main(dataset: Path, predictions: Path, out: str, views: list) -> None:
    names = json.loads((dataset / "scene.json").read_text())["instances"]["names"]
    frames = sorted((dataset / "test").glob("r_???.png"))
    differences, per_object = [], {name: [] for name in names}
    for truth_path in frames:
        stem = truth_path.stem
        truth = read_depth(dataset / "test" / f"{stem}_distance.exr")
        pred = read_depth(predictions / f"{stem}_depth.exr")
        ids = np.asarray(Image.open(dataset / "test" / f"{stem}_instance.png")).astype(np.int64)
        covered = (np.asarray(Image.open(truth_path))[..., 3] == 255) & (neighbourhood(ids) == ids).all(0) & (ids > 0)
        difference = np.where(covered, pred - truth, np.nan)
        differences.append(difference)
        for index, name in enumerate(names):
            per_object[name].append(difference[covered & (ids == index + 1)])
    for name, values in per_object.items():
        values = np.concatenate(values)
        print(f"{name}: {values.size} pixels, depth error mean {values.mean():+.4f}, RMS {np.sqrt((values ** 2).mean()):.4f}, "
              f"spread about the mean {values.std():.4f}")
    median = float(np.nanmedian(np.concatenate([d.ravel() for d in differences])))
    tiles = []
    for number in views:
        truth = np.asarray(Image.open(frames[number]), dtype=np.float64)[..., :3] / 255
        scaled = np.clip(np.nan_to_num(differences[number] - median) / FULL_SCALE, -1, 1)
        shown = np.stack([np.clip(scaled, 0, 1), np.zeros_like(scaled), np.clip(-scaled, 0, 1)], -1)
        tiles.append(np.concatenate([truth, shown], 1))
    picture = (np.concatenate(tiles, 0) * 255).astype(np.uint8)
    Image.fromarray(picture).resize((picture.shape[1] * 2, picture.shape[0] * 2), Image.NEAREST).save(out)


if __name__ == "__main__":
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3],
         [int(v) for v in (sys.argv[4] if len(sys.argv) == 5 else "0,3,7").split(",")])
