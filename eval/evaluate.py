"""Score a folder of renders against a dataset split: `nerfgauge evaluate`.

    nerfgauge evaluate DATASET --pred DIR [--split test] [--out FILE]
                       [--background white|black] [--depth-kind distance|z]
                       [--pred-format auto|nerfgauge|nerfstudio|nerfbaselines|folder]
                       [--protocol nerfgauge|nerfbaselines|ns-eval]

--protocol (eval/protocols.py) chooses how psnr, ssim and lpips are scored; the document
names it ("protocol", "evaluation_protocol", "protocol_background", "lpips_net"). DATASET
may also be a NeRF-synthetic, nerfstudio or COLMAP text-model folder nerfgauge did not
write (nerfgauge/core/foreign_dataset.py): "ground_truth" then records the sha256 of every
file read, and what the folder cannot give is null with "unavailable: <reason>" in notes.

Other tools' folders (ns-render dataset output, NerfBaselines predictions, plain folders of
PNG/JPEG/EXR matched by stem or order) are read as they are: eval/predictions.py, which
finds and reads every prediction file. What follows is our own naming ("nerfgauge" format).

Accepted prediction files, for the dataset frame "test/r_007" (r_007 below):

- colour: DIR/test/r_007.png or DIR/r_007.png (flat); or the same names with .exr. In one
  folder PNG wins over EXR. A frame found both in DIR/test/ and flat in DIR is an error.
  PNG: 8-bit or 16-bit sRGB; gray, gray+alpha, RGB or RGBA with straight alpha.
  EXR: linear RGB, or RGBA with premultiplied alpha (un-premultiplied, then converted with
  `linear_to_srgb`); channels "RGB(A)" or "R", "G", "B"(, "A").
- depth (optional), in the folder where the colour was found, first match wins:
  `r_007_depth.exr|.npy` (holds the --depth-kind), then `r_007_distance.exr|.npy` for ray
  distance or `r_007_zdepth.exr|.npy` for z-depth. EXR: one channel; .npy: [H, W].
  An EXR whose `nerfgauge_depth` header names the other kind is an error.
- opacity (optional): `r_007_opacity.png|.npy` ([H, W] in [0, 1]), else the colour's alpha.

Everything in DIR/test/ and in DIR whose name looks like a frame (`r_<digits>` with an
optional `_suffix` and .png/.exr/.npy) must belong to a frame of the split: anything else
is reported as an extra frame. DIR/timing.json (a JSON object, e.g. ms per frame from the
renderer), if present, is copied into metrics.json's `timing`; when it records the sha256
of the transforms and scene.json the frames were rendered from (`nerfgauge render` does),
DATASET must list the same (core.provenance.check_renders_dataset), else one line naming both.

Metrics (eval.metrics): PSNR and SSIM on colour composited onto the background (prediction
and the straight-alpha ground-truth PNG alike; RGB predictions are taken as composited);
PSNR on the foreground (pixels with ground-truth coverage or visible predicted opacity;
null when a view has none); depth on ground-truth hit pixels (Dataset.mask_of), null when a view
hits nothing; opacity IoU when the prediction has alpha (1 when both silhouettes are empty);
LPIPS-Alex (eval.lpips) on the composited pair, null with a reason in metrics.json's `notes`
when its weights are not installed or the images are under 31 px. `psnr_covisible` and
`ssim_covisible` (DyCheck's mPSNR, mSSIM) on the pixels some train view saw,
`covisible_fraction`, the share of such pixels, and `psnr_capture_bound`, the PSNR of a
method exact (to the noise) on them and right on average elsewhere; `depth_absrel_resolved`
on the hit pixels whose depth two train views resolve (5% at half a pixel), and
`resolved_fraction`, their share of the hit pixels (eval.covisibility; all null with a
note when the scored split is train itself, or with --no-held-out).
NaN or inf in colour or opacity (anywhere) or in depth (on hit pixels) fails the whole
evaluation naming the frame: no mean is computed over the other frames, nothing is written.
The dataset is opened as a nerfgauge.core.dataset.Dataset: validated, each ground-truth
file confined to it and checked against its manifest as it is read (one read per file).
Outputs: FILE (default DIR/metrics.json, schema 1, `"tool": "nerfgauge"`, `"kind": "metrics"`,
written atomically; at the CLI and in nerfgauge.evaluate, FILE must be a new path or a
metrics file nerfgauge wrote, core.outputs)
and error maps in `error_maps/` beside it (eval.error_maps).

`ci95` beside `mean` and `std`: per metric, [low, high], the 95% percentile bootstrap
interval of the mean over the views (eval.uncertainty.bootstrap_ci, 10000 resamples of
the defined frames, a fresh np.random.default_rng(EVALUATE_SEED = 0) per metric, so the
same scores give the same interval); [mean, mean] with one defined frame (degenerate: no
spread is known); null when no frame is defined. The means are unchanged by it.

Beside the metrics (docs/conventions.md, "Noise"): each frame's `psnr_ceiling`, the PSNR the
noise-free image would score against the ground truth (from the dataset's noise estimate,
for the chosen background; null for datasets without one or rendered at spp 1), and
`noise` with their mean and `at_noise_floor` (mean PSNR within NOISE_FLOOR_DB of it: the
methods cannot be told apart there; render with more spp). `psnr_objects`: PSNR on each
instance's pixels (datasets with instance ids), per frame and averaged per object.
`empty_views`: test views whose ground truth holds no geometry (they score background
against background) with a warning when more than a quarter of the split is empty.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from nerfgauge.core.progress import progress
from nerfgauge.eval.error_maps import (
    colour_error,
    depth_relative_error,
    write_error_maps,
)
from nerfgauge.eval.extrapolation import extrapolation_gap, format_gap
from nerfgauge.eval.covisibility import REFERENCE_SPLIT, HeldOutPixels, held_out_pixels, holds_out, reference_depths
from nerfgauge.eval import protocols as protocols_module
from nerfgauge.eval.protocols import Protocol, background_name, image_scores, prepare
from nerfgauge.eval.predictions import (
    DEPTH_SUFFIXES,
    PredictionFiles,
    locate_predictions,
    read_plane,
    read_prediction,
)
from nerfgauge.eval.metrics import (
    BACKGROUNDS,
    METRIC_NAMES,
    composite,
    depth_metrics,
    edge_pixels,
    opacity_iou,
    outline_alpha_error,
    outline_pixels,
    psnr_capture_bound,
    psnr_masked,
    ssim_masked,
    summarize,
)
from nerfgauge.eval.uncertainty import EVALUATE_SEED, bootstrap_ci

from nerfgauge.core import dataset, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import check_writable_target, json_from_bytes, read_json, write_json
from nerfgauge.core.outputs import TOOL
from nerfgauge.core.provenance import check_renders_dataset

SCHEMA = 1
METRICS_KIND = "metrics"  # metrics.json's "kind" (core.outputs: what a rerun may replace)
NOISE_FLOOR_DB = 1.0  # a mean PSNR this close to the mean ceiling is at the noise floor
EMPTY_WARNING_FRACTION = 0.25
COVISIBLE_NONE = f"split {{split}} is not held out from {REFERENCE_SPLIT}: no co-visibility mask"
COVISIBLE_SKIPPED = "not computed (--no-held-out)"


# --- scoring ----------------------------------------------------------------------------


def composited_pair(ds: dataset.Dataset, stem: str, intrinsics, files: PredictionFiles, background) -> tuple:
    """One frame's prediction and ground truth composited onto `background` [3]:
    pred, gt [H, W, 3], the ground truth's RGBA [H, W, 4] and the prediction's alpha
    [H, W] (its opacity plane when it has one; None for an opaque RGB prediction)."""
    rgb, alpha = read_prediction(files, intrinsics)
    pred = composite(np.concatenate([rgb, alpha[..., None]], -1), background) if alpha is not None else rgb
    gt_rgba = ds.rgba_of(stem, intrinsics)  # [H, W, 4]
    return pred, composite(gt_rgba, background), gt_rgba, alpha


def score_frame(ds: dataset.Dataset, stem: str, intrinsics, files: PredictionFiles, background, depth_kind: str,
                protocol: Protocol, lpips_batches: dict,
                held_out_of: Optional[Callable[[np.ndarray, np.ndarray], HeldOutPixels]] = None,
                ceiling_of: Optional[Callable[[], Optional[float]]] = None):
    """Metrics of one frame ({metric: float or None}) and its error images. psnr, ssim and
    the pairs given to `lpips_batches` ({metric: eval.lpips.LpipsBatch}, whose scores the
    caller reads) are the `protocol`'s (eval.protocols.Protocol; ours composites onto
    `background` [3]); everything else is ours, on `background`. LPIPS is left None here.
    held_out_of(mask, ray distance): the frame's co-visible and depth-resolved pixels
    (eval.covisibility), or None; called after the frame's images are read, so a bad frame
    is named by them. ceiling_of(): the frame's psnr_ceiling (frame_ceiling), read after
    them too, or None. Each ground-truth file is read once."""
    rgb, alpha = read_prediction(files, intrinsics)
    pred = composite(np.concatenate([rgb, alpha[..., None]], -1), background) if alpha is not None else rgb
    gt_rgba = ds.rgba_of(stem, intrinsics)  # [H, W, 4]
    gt = composite(gt_rgba, background)
    # [H, W] bool; None for a foreign folder (no hit mask: foreground, depth, opacity IoU need one)
    mask = ds.mask_of(stem, intrinsics) if ds.has("masks") else None
    distance = None if held_out_of is None else ds.depth_of(stem, intrinsics, "distance")  # [H, W]
    held_out = None if held_out_of is None else held_out_of(mask, distance)
    values = dict.fromkeys(METRIC_NAMES)
    values["psnr_ceiling"] = None if ceiling_of is None else ceiling_of()
    scored = prepare(protocol, rgb, alpha, gt_rgba, background)
    values.update(image_scores(protocol, *scored))
    if held_out is not None:
        covisible = held_out.covisible
        values["psnr_covisible"], values["ssim_covisible"] = psnr_masked(pred, gt, covisible), \
            ssim_masked(pred, gt, covisible)
        values["covisible_fraction"] = float(covisible.mean())
        values["psnr_capture_bound"] = psnr_capture_bound(gt, covisible, values["psnr_ceiling"])
        values["resolved_fraction"] = float(held_out.resolved.sum() / mask.sum()) if mask.any() else None
    values["psnr_foreground"] = psnr_masked(pred, gt, foreground_pixels(gt_rgba[..., 3], alpha))
    for batch in lpips_batches.values():
        batch.add(*scored)
    values["psnr_objects"] = object_psnrs(ds, stem, intrinsics, pred, gt)
    values.update(edge_scores(ds, stem, intrinsics, pred, gt, gt_rgba, alpha))
    values["empty"] = None if mask is None else not mask.any()
    depth_err = None
    if files.depth is not None and mask is not None and ds.has("depth"):
        depth = read_plane(files.depth, intrinsics, depth_kind)
        gt_depth = distance if depth_kind == "distance" and distance is not None else \
            ds.depth_of(stem, intrinsics, depth_kind)
        try:
            scores = depth_metrics(depth, gt_depth, mask)
        except InputError as error:  # the prediction's fault or (a corrupt dataset) the ground truth's
            gt_file = ds.root / (stem + dataset.FRAME_SUFFIXES["distance" if depth_kind == "distance" else "z_depth"])
            raise InputError(f"{files.depth} against {gt_file}: {error}") from None
        values.update({f"depth_{key}": value for key, value in scores.items()})
        if held_out is not None:
            values["depth_absrel_resolved"] = depth_metrics(depth, gt_depth, mask & held_out.resolved)["absrel"]
        depth_err = depth_relative_error(depth, gt_depth, mask)
    if alpha is not None and mask is not None:
        values["opacity_iou"] = opacity_iou(alpha, mask)
    return values, colour_error(pred, gt).astype(np.float32), depth_err


def object_psnrs(ds: dataset.Dataset, stem: str, intrinsics, pred, gt) -> Optional[dict]:
    """{shape name: PSNR on the pixels whose centre ray hits it} for the shapes in view;
    None for a dataset without instance ids."""
    if stem + dataset.FRAME_SUFFIXES["instance"] not in ds.manifest_files:
        return None
    ids, names = ds.instance_of(stem, intrinsics), ds.instance_names()
    return {names.get(int(number), f"instance {int(number)}"): psnr_masked(pred, gt, ids == number)
            for number in np.unique(ids) if number != 0}


def edge_scores(ds: dataset.Dataset, stem: str, intrinsics, pred, gt, gt_rgba, alpha=None) -> dict:
    """PSNR on the frame's edge pixels (eval.metrics.edge_pixels: where a pixel's box filter
    mixes what its rays see) and on the other pixels the ground truth covers, with the
    edges' share of the image: the error of a method that samples one ray per pixel, or
    resolves an edge a pixel off, sits on the first. Instance ids where the dataset has them.
    Of the edges, the outline (eval.metrics.outline_pixels: partial coverage) apart: its
    PSNR, and with the prediction's `alpha` [H, W] (None: no alpha) how far its alpha
    sits from the truth's (outline_alpha_error)."""
    has_ids = stem + dataset.FRAME_SUFFIXES["instance"] in ds.manifest_files
    edges = edge_pixels(gt_rgba, ds.instance_of(stem, intrinsics) if has_ids else None)
    interior = ~edges & (gt_rgba[..., 3] > 0)
    outline = outline_pixels(gt_rgba)
    alpha_error = outline_alpha_error(alpha, gt_rgba[..., 3], outline) if alpha is not None else {}
    return {"psnr_edges": psnr_masked(pred, gt, edges), "psnr_interior": psnr_masked(pred, gt, interior),
            "edge_fraction": float(edges.mean()), "psnr_outline": psnr_masked(pred, gt, outline),
            "outline_alpha_bias": alpha_error.get("bias"), "outline_alpha_rmse": alpha_error.get("rmse")}


def frame_ceiling(ds: dataset.Dataset, stem: str, background: str) -> Optional[float]:
    """The frame's psnr_ceiling on `background` from its noise estimate (None without one)."""
    if stem + dataset.FRAME_SUFFIXES["noise"] not in ds.manifest_files:
        return None
    noise = ds.frame_file(stem, "noise", lambda path, data: json_from_bytes(data, path, finite=True))
    ceiling = noise.get("psnr_ceiling") if isinstance(noise, dict) else None
    value = ceiling.get(background) if isinstance(ceiling, dict) else None
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def noise_summary(frames: list) -> dict:
    """Mean psnr_ceiling of the frames that have one, and whether the mean PSNR is at it."""
    ceilings = [frame["psnr_ceiling"] for frame in frames if frame["psnr_ceiling"] is not None]
    if len(ceilings) < len(frames):
        return {"psnr_ceiling": None, "at_noise_floor": None,
                "note": f"{len(frames) - len(ceilings)} of {len(frames)} frames have no noise estimate "
                        "(an older dataset, or spp 1)"}
    mean_ceiling, _ = summarize(ceilings)
    mean_psnr, _ = summarize([frame["psnr"] for frame in frames])
    at_floor = mean_psnr is not None and mean_ceiling is not None and mean_psnr >= mean_ceiling - NOISE_FLOOR_DB
    return {"psnr_ceiling": mean_ceiling, "at_noise_floor": bool(at_floor),
            "note": "at the noise floor: add spp" if at_floor else None}


def object_means(frames: list) -> Optional[dict]:
    """{shape name: mean PSNR over the frames that show it}; None without instance ids."""
    if any(frame["psnr_objects"] is None for frame in frames):
        return None
    names = sorted({name for frame in frames for name in frame["psnr_objects"]})
    return {name: summarize([frame["psnr_objects"][name] for frame in frames if name in frame["psnr_objects"]])[0]
            for name in names}


def empty_views(frames: list) -> dict:
    """Which frames' ground truth holds no geometry, and a warning past a quarter."""
    empty = [frame["name"] for frame in frames if frame["empty"]]
    warning = None
    if frames and len(empty) > EMPTY_WARNING_FRACTION * len(frames):
        warning = (f"{len(empty)} of {len(frames)} views hold no geometry (background scored against background); "
                   "choose cameras that see the scene (e.g. --elevation)")
    return {"count": len(empty), "of": len(frames), "frames": empty, "warning": warning}


def foreground_pixels(gt_alpha: np.ndarray, pred_alpha) -> np.ndarray:
    """Where either image is not pure background: ground-truth coverage (PNG alpha [H, W])
    above zero, or predicted opacity that shows in 8 bits (> 0.5 / 255). Coverage rather
    than the centre-ray mask, so wires thinner than a pixel count. Returns [H, W] bool."""
    foreground = gt_alpha > 0
    if pred_alpha is not None:
        foreground |= pred_alpha > 0.5 / 255
    return foreground


def read_timing(pred_dir: Path) -> dict:
    path = pred_dir / "timing.json"
    return read_json(path, finite=True) if path.is_file() else {}


@dataclass(frozen=True)
class EvaluateConfig:
    """How `evaluate` scores a folder of renders: the settings of `nerfgauge evaluate`
    (its flags: eval.options), and of `nerfgauge run`'s scoring (eval.options.SCORING).
    evaluate's keyword arguments are these fields. split: the dataset split scored;
    background: what colour is composited onto before PSNR and SSIM (eval.metrics.BACKGROUNDS);
    depth_kind: what predicted depth holds (ray distance or z-depth); protocol: how psnr,
    ssim and lpips are scored (eval.protocols.PROTOCOLS); held_out: the co-visible and
    depth-resolved scores (eval.covisibility); pred_format: how the prediction folder names
    its files (eval.predictions.FORMATS; "auto" detects it)."""

    split: str = "test"
    background: str = "white"
    depth_kind: str = "distance"
    protocol: str = protocols_module.DEFAULT
    held_out: bool = True
    pred_format: str = "auto"

    def validate(self) -> Protocol:
        """One-line InputError for a setting evaluate cannot use. Returns the protocol."""
        if self.background not in BACKGROUNDS:
            raise InputError(f"unknown background {self.background!r}; choose white or black")
        if not isinstance(self.held_out, bool):
            raise InputError(f"held_out must be True or False, got {self.held_out!r}")
        if self.depth_kind not in DEPTH_SUFFIXES:
            raise InputError(f"unknown depth kind {self.depth_kind!r}; choose distance or z")
        return protocols_module.get(self.protocol)


def evaluate(root, pred_dir, split: str = EvaluateConfig.split, out=None,
             background: str = EvaluateConfig.background, depth_kind: str = EvaluateConfig.depth_kind,
             pred_format: str = EvaluateConfig.pred_format, held_out: bool = EvaluateConfig.held_out,
             protocol: str = EvaluateConfig.protocol) -> dict:
    """Score every frame of `split`; write metrics.json and error maps. Returns the document.
    The settings are EvaluateConfig's fields (a config passes as `**dataclasses.asdict(config)`).
    pred_format: how `pred_dir` names its files (eval.predictions.FORMATS; "auto" detects it).
    held_out=False skips the co-visible and depth-resolved scores (eval.covisibility).
    protocol: how psnr, ssim and lpips are scored (eval.protocols.PROTOCOLS; the document
    names it in "protocol", and its own name in "evaluation_protocol").
    A user's `out` is checked by the caller (core.outputs.check_output_file: the CLI and
    nerfgauge.evaluate); `run` and `suite` write here into folders they claimed."""
    start = time.perf_counter()
    chosen = EvaluateConfig(split, background, depth_kind, protocol, held_out, pred_format).validate()
    ds, pred_dir = dataset.Dataset(root), Path(pred_dir)
    if not pred_dir.is_dir():
        raise InputError(f"prediction folder not found: {pred_dir}")
    out = check_writable_target(pred_dir / "metrics.json" if out is None else Path(out))  # before the work
    check_renders_dataset(pred_dir, read_timing(pred_dir), ds)  # renders of our runs say what they show
    cameras = ds.cameras(split)
    ds.check_sizes(f"{split}/")  # a file grown past its manifest size: refused before LPIPS loads
    scene = ds.scene.get("recipe") if ds.foreign is None else ds.root.resolve().name
    if not isinstance(scene, str) or not scene:
        raise InputError(f"{ds.root / 'scene.json'}: 'recipe' must name the scene, got {scene!r}")
    found = locate_predictions(ds, pred_dir, split, pred_format, depth_kind)
    timing = read_timing(pred_dir)
    # frames whose ground truth was rendered through a thin lens say so (they are scored
    # against that defocused truth like any other frame)
    lens_of = {stem: {"lens": cameras.lens(i).to_json()} for i, stem in enumerate(cameras.stems) if cameras.lens(i)}
    lpips_batches, lpips_notes = protocols_module.lpips_scorers(chosen, cameras.intrinsics)
    depths = reference_depths(ds) if held_out and holds_out(ds, split) and ds.has("depth") else None  # the train views', read once
    index_of = {stem: index for index, stem in enumerate(cameras.stems)}
    frames, maps = [], []
    for stem, files in progress(found.items(), desc=f"evaluate {split}", unit="frame", enabled=None, leave=False):
        try:
            values, colour_err, depth_err = score_frame(ds, stem, cameras.intrinsics, files,
                                                        BACKGROUNDS[background], depth_kind, chosen, lpips_batches,
                                                        None if depths is None else
                                                        partial(held_out_pixels, ds, split, index_of[stem], depths),
                                                        partial(frame_ceiling, ds, stem, background))
        except InputError as error:  # name the frame once (the dataset reader may have already)
            message = str(error)
            raise InputError(message if message.startswith(f"frame {stem}:") else f"frame {stem}: {message}") from None
        frames.append({"name": stem, "file": files.colour.relative_to(pred_dir).as_posix(), **values,
                       **lens_of.get(stem, {})})
        maps.append((stem, colour_err, depth_err))
    extra_metrics = [metric for metric, _ in chosen.extra_lpips]
    for frame in frames:
        frame.update(dict.fromkeys(extra_metrics))
    for metric, batch in lpips_batches.items():
        for frame, value in zip(frames, batch.scores()):
            frame[metric] = value
    means, stds, counts, intervals = {}, {}, {}, {}
    for metric in list(METRIC_NAMES) + extra_metrics:
        column = [frame[metric] for frame in frames]
        means[metric], stds[metric] = summarize(column)
        counts[metric] = sum(value is not None for value in column)
        # eval.uncertainty: percentile bootstrap over the views, a fresh Generator seeded
        # EVALUATE_SEED per metric (the same file gives the same interval)
        intervals[metric] = bootstrap_ci(column, np.random.default_rng(EVALUATE_SEED)).to_json()
    owned.make_folder(out.parent)
    for stem, colour_err, depth_err in maps:
        write_error_maps(out.parent / "error_maps", stem, colour_err, depth_err)
    document = {"tool": TOOL, "kind": METRICS_KIND, "schema": SCHEMA, "scene": scene, "split": split, "background": background,
                "depth_kind": depth_kind, "mean": means, "std": stds, "ci95": intervals, "count": counts,
                "protocol": chosen.name, "evaluation_protocol": chosen.their_name or chosen.name,
                "protocol_background": background_name(chosen.composited_on(BACKGROUNDS[background])),
                "lpips_net": chosen.lpips_net,
                "notes": {**lpips_notes,
                          **({} if depths is not None else
                             {"covisible": COVISIBLE_NONE.format(split=split) if held_out else COVISIBLE_SKIPPED}),
                          **unavailable_notes(ds, held_out)},
                "ground_truth": ds.ground_truth_record(),
                "noise": noise_summary(frames) if ds.has("noise_ceiling") else
                {"psnr_ceiling": None, "at_noise_floor": None, "note": ds.unavailable_reason("noise_ceiling")}, "psnr_objects": object_means(frames), "empty_views": empty_views(frames),
                **({"extrapolation": gap} if (gap := extrapolation_gap(ds.scene, frames, split)) else {}),
                "frames": frames,
                "timing": {**timing, "evaluate_seconds": time.perf_counter() - start}}
    write_json(out, document)
    return document


def unavailable_notes(ds: dataset.Dataset, held_out: bool) -> dict:
    """{metric: "unavailable: why"} for what a foreign ground-truth folder cannot give
    (depth, hit masks, noise ceiling, co-visibility); {} for our datasets."""
    if ds.foreign is None:
        return {}
    notes = {}
    for metric in ("depth_absrel", "depth_rmse", "depth_mae", "depth_delta1", "depth_bias", "depth_absrel_resolved",
                   "resolved_fraction"):
        notes[metric] = "unavailable: " + ds.unavailable_reason("depth")
    notes["opacity_iou"] = "unavailable: " + ds.unavailable_reason("masks")
    notes["psnr_ceiling"] = "unavailable: " + ds.unavailable_reason("noise_ceiling")
    for metric in ("psnr_covisible", "ssim_covisible", "covisible_fraction", "psnr_capture_bound"):
        notes[metric] = "unavailable: " + ds.unavailable_reason("covisibility")
    if held_out:
        notes["covisible"] = "unavailable: " + ds.unavailable_reason("covisibility")
    notes["psnr_objects"] = "unavailable: " + ds.unavailable_reason("instances")
    return notes


def format_means(document: dict) -> str:
    """A plain-text table of mean, std and frame count per metric."""
    total = len(document["frames"])
    rows = [("metric", "mean", "std", "frames")]
    for metric in list(METRIC_NAMES) + [m for m in document["mean"] if m not in METRIC_NAMES]:
        mean, std = document["mean"][metric], document["std"][metric]
        note = document.get("notes", {}).get(metric)
        rows.append((metric, (note or "-") if mean is None else f"{mean:.4f}", "-" if std is None else f"{std:.4f}",
                     f"{document['count'][metric]}/{total}"))
    noise = document.get("noise") or {}
    if noise.get("psnr_ceiling") is not None:
        rows.insert(2, ("psnr_ceiling", f"{noise['psnr_ceiling']:.4f}", "-", f"{total}/{total}"))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    if noise.get("at_noise_floor"):
        lines.append(f"psnr within {NOISE_FLOOR_DB:g} dB of the ceiling: at the noise floor: add spp")
    lines += format_gap(document.get("extrapolation"))
    if (document.get("empty_views") or {}).get("warning"):
        lines.append("warning: " + document["empty_views"]["warning"])
    return "\n".join(lines)
