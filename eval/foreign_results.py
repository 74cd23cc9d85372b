"""Our scores in other tools' result shapes, so they can be pasted beside theirs:
`nerfgauge evaluate ... --ns-eval FILE --nerfbaselines FILE`.

- ns-eval (nerfstudio scripts/eval.py): {"experiment_name", "method_name", "checkpoint",
  "results": {metric: mean, metric_std: std, ...}}. As nerfstudio's
  get_average_eval_image_metrics, std is torch.std_mean's: the sample standard deviation
  (ddof=1; NaN for one frame, written as null). Every metric of eval.metrics.METRIC_NAMES
  that has values is included; "fps" and "num_rays_per_sec" come from the renderer's
  ms_per_frame when its timing.json gave one.
- NerfBaselines (nerfbaselines io.serialize_evaluation_results): {"render_dataset_metadata"
  (id "nerfgauge" or the foreign format, scene, color_space, background_color: what
  nerfbaselines.results needs to file the scene), "nb_info",
  "evaluate_datetime", "evaluate_version", "metrics" (means rounded to 5 digits),
  "metrics_raw" (per image: base64 of little-endian float32 values, in frame order),
  "metrics_sha256" (their get_metrics_hash), "predictions_sha256", "ground_truth_sha256",
  "evaluation_protocol"}. The two sha256 are NerfBaselines' get_predictions_sha: one hash
  over the bytes of every prediction file (and of the dataset's ground-truth PNGs), in the
  frames' order. Metrics with a None for some frame (depth on an empty view) are left out
  of metrics_raw: NerfBaselines' lists have one value per image. Our protocol is named
  "nerfgauge-v1" and described in nb_info, because NerfBaselines' "default" protocol
  scores uint8 images and ours does not. A document scored with `--protocol
  nerfbaselines` (eval.protocols) is theirs: "evaluation_protocol": "nerf", with "lpips"
  (AlexNet) and "lpips_vgg" named as they name them.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import importlib.metadata
import math
import struct
from pathlib import Path

import numpy as np

from nerfgauge.eval.metrics import METRIC_NAMES
from nerfgauge.core import bounded
from nerfgauge.core.dataset import FRAME_SUFFIXES

PROTOCOL = "nerfgauge-v1"
DATASET_ID = "nerfgauge"  # render_dataset_metadata.id: the dataset family their tooling groups results by
PRECISION = 5  # NerfBaselines rounds "metrics" to this many digits


def _version() -> str:
    try:
        return importlib.metadata.version("nerfgauge")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _metric_columns(document: dict) -> dict:
    """{metric: [per-frame float or None]} for every metric with at least one value, in
    METRIC_NAMES order first, then any other numeric per-frame key (metrics added later)."""
    names = list(METRIC_NAMES) + sorted({key for frame in document["frames"] for key, value in frame.items()
                                         if key not in METRIC_NAMES and isinstance(value, (int, float))
                                         and not isinstance(value, bool)})
    columns = {name: [frame.get(name) for frame in document["frames"]] for name in names}
    return {name: column for name, column in columns.items() if any(v is not None for v in column)}


def ns_eval_document(document: dict, *, experiment_name: str, method_name: str, checkpoint: str) -> dict:
    """nerfstudio's ns-eval output for a metrics document of eval.evaluate."""
    results = {}
    for name, column in _metric_columns(document).items():
        values = np.asarray([v for v in column if v is not None], np.float64)
        results[name] = float(values.mean())
        std = float(values.std(ddof=1)) if len(values) > 1 else None
        results[f"{name}_std"] = std
    ms = document.get("timing", {}).get("ms_per_frame")
    if isinstance(ms, (int, float)) and ms > 0 and math.isfinite(ms):
        width, height = _image_size(document)
        results["fps"] = 1000.0 / ms
        if width and height:
            results["num_rays_per_sec"] = results["fps"] * width * height
    return {"experiment_name": experiment_name, "method_name": method_name, "checkpoint": checkpoint,
            "results": results}


def _image_size(document: dict):
    resolution = document.get("timing", {}).get("resolution")
    if isinstance(resolution, list) and len(resolution) == 2:
        return resolution
    return None, None


def encode_values(values) -> str:
    """NerfBaselines' _encode_values: base64 of the values packed as little-endian float32."""
    return base64.b64encode(b"".join(struct.pack("<f", v) for v in values)).decode("ascii")


def metrics_hash(metrics_lists: dict) -> str:
    """NerfBaselines' get_metrics_hash: per metric (sorted by name), its lower-case name and
    its sorted values encoded as above, then a newline."""
    digest = hashlib.sha256()
    for key in sorted(metrics_lists):
        digest.update(key.lower().encode("utf8"))
        digest.update(encode_values(sorted(metrics_lists[key])).encode("ascii"))
        digest.update(b"\n")
    return digest.hexdigest()


def files_hash(paths) -> str:
    """One sha256 over the bytes of `paths`, in order (NerfBaselines' get_predictions_sha)."""
    digest = hashlib.sha256()
    for path in paths:
        with bounded.open_regular(path) as (handle, _):  # a stream of 1 MiB blocks; regular files only
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def nerfbaselines_document(document: dict, *, dataset_root, pred_dir, method_name: str) -> dict:
    """NerfBaselines' results.json for a metrics document of eval.evaluate on `dataset_root`,
    whose frames' "file" entries name the prediction files under `pred_dir`."""
    metrics_lists = {name: [float(v) for v in column] for name, column in _metric_columns(document).items()
                     if all(v is not None for v in column)}
    theirs = document.get("protocol") == "nerfbaselines"
    if theirs:  # scored their way (eval.protocols): their names, "lpips" is AlexNet and "lpips_vgg" VGG
        renamed = {"lpips": "lpips_vgg", "lpips_alex": "lpips"}
        metrics_lists = {renamed.get(name, name): values for name, values in metrics_lists.items()}
    protocol = "nerf" if theirs else PROTOCOL
    predictions = [Path(pred_dir) / frame["file"] for frame in document["frames"]]
    gt_files = (document.get("ground_truth") or {}).get("frames")
    ground_truth = [Path(dataset_root) / (gt_files[frame["name"]] if gt_files else frame["name"] + FRAME_SUFFIXES["png"])
                    for frame in document["frames"]]
    description = ({"background": "white (their Blender background_color)", "depth_kind": document["depth_kind"],
                    "colour": "RGBA composited in float32, then truncated to uint8 (their image_to_srgb)",
                    "ssim": "dm_pix ssim, gaussian 11 taps sigma 1.5, valid region",
                    "lpips": "lpips v0.1 VGG as lpips_vgg, AlexNet as lpips"} if theirs else
                   {"background": document["background"], "depth_kind": document["depth_kind"],
                    "colour": "float sRGB composited onto the background, not quantised to uint8",
                    "ssim": "skimage structural_similarity, gaussian sigma 1.5, data_range 1",
                    "depth": "on pixels whose centre ray hits geometry"})
    # what their results tooling (nerfbaselines.results) needs to place the file: dataset id and scene
    metadata = {"id": DATASET_ID if (document.get("ground_truth") or {}).get("format", "nerfgauge") == "nerfgauge"
                else document["ground_truth"]["format"],
                "scene": document["scene"], "color_space": "srgb", "evaluation_protocol": protocol,
                "background_color": [255, 255, 255] if theirs or document["background"] == "white" else [0, 0, 0],
                "type": "object-centric"}
    return {
        "render_dataset_metadata": metadata,
        "nb_info": {"method": method_name, "tool": "nerfgauge", "evaluation_protocol": protocol,
                    "scene": document["scene"], "split": document["split"], "protocol": description,
                    "dataset_metadata": metadata},
        "evaluate_datetime": datetime.datetime.now(datetime.timezone.utc).replace(tzinfo=None).isoformat(timespec="seconds"),
        "evaluate_version": f"nerfgauge {_version()}",
        "metrics": {name: round(sum(values) / len(values), PRECISION) for name, values in metrics_lists.items()},
        "metrics_raw": {name: encode_values(values) for name, values in metrics_lists.items()},
        "metrics_sha256": metrics_hash(metrics_lists),
        "predictions_sha256": files_hash(predictions),
        "ground_truth_sha256": files_hash(ground_truth),
        "evaluation_protocol": protocol,
    }
