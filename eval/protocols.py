"""Scoring protocols, named: how a render and its ground truth become PSNR, SSIM and LPIPS.

    nerfgauge evaluate DATASET --pred DIR --protocol nerfgauge|nerfbaselines|ns-eval

The same renders score differently under the field's protocols (background colour,
8-bit rounding, the SSIM filter and border, the LPIPS backbone). Each protocol here is
written down from its source (docs/conventions.md, "Protocols", cites the files):

- "nerfgauge" (ours, the default): both images composited onto --background (white) in
  float64, no rounding; PSNR per image on [0, 1]; SSIM as eval.metrics.ssim (scikit-image,
  Gaussian sigma 1.5, mirror-reflected borders, (win - 1) // 2 cropped); LPIPS-Alex.
- "nerfbaselines": NerfBaselines' "nerf" protocol for Blender scenes
  (nerfbaselines/evaluation.py NerfEvaluationProtocol, utils.image_to_srgb,
  metrics.py): RGBA composited in float32 onto the dataset's background_color (white for
  Blender), then converted to uint8 by `(x * 255).clip(0, 255).astype(uint8)` (truncation,
  not rounding) and back to float32 / 255; PSNR = -10 log10(MSE) per image; SSIM is
  dm_pix's (11-tap Gaussian, sigma 1.5, *valid* convolution: no padding, the 5-pixel
  border never scored; variances clipped at eps^2); LPIPS-VGG (their `lpips_vgg`), and
  LPIPS-Alex (their `lpips`) beside it.
- "ns-eval": nerfstudio's `ns-eval` for nerfacto on a nerfstudio-data folder
  (nerfstudio/models/nerfacto.py get_image_metrics_and_images, model_components/
  renderers.py blend_background): the ground truth's RGBA blended onto black (nerfacto's
  background "last_sample" evaluates against black; the nerfstudio dataparser sets no
  alpha_color), float32, no rounding; PSNR torchmetrics PeakSignalNoiseRatio(data_range=1);
  SSIM torchmetrics structural_similarity_index_measure with its defaults (Gaussian 11,
  sigma 1.5, reflect padding, the whole map averaged as torchmetrics 1.9 does,
  data_range=None: taken from the images as max(pred range, gt range)); LPIPS torchmetrics
  LearnedPerceptualImagePatchSimilarity(normalize=True): AlexNet, [0, 1] mapped to [-1, 1].

A prediction's own alpha (RGBA render or opacity plane) is composited onto the protocol's
background like the ground truth; an RGB prediction is taken as rendered.

The protocol-sensitivity table (`sensitivity`, `sensitivity_rows`): the same renders under
every protocol, and the spread (max - min) of each metric across them. The report shows
it; a suite leaderboard calls `suite_sensitivity({method: [(dataset, renders), ...]})`
(each method's datasets combined by `combine`: means per protocol, spread between them)
and `sensitivity_rows(...)` for the table (`format_rows` for text, or
eval.report.sortable_table_html for HTML).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core import dataset
from nerfgauge.core.errors import InputError
from nerfgauge.eval import metrics
from nerfgauge.eval.lpips import LABELS, MIN_SIDES, NOT_AVAILABLE, LpipsBatch, load_lpips
from nerfgauge.eval.lpips_cache import features_source
from nerfgauge.eval.metrics import BACKGROUNDS, MSE_FLOOR, composite, summarize
from nerfgauge.eval.predictions import locate_predictions, read_colour, read_plane

DEFAULT = "nerfgauge"
SENSITIVITY_METRICS = ("psnr", "ssim", "lpips")


@dataclass(frozen=True)
class Protocol:
    """How renders are scored. background: RGB in [0, 1] the protocol composites onto, or
    None where it composites onto the evaluation's (evaluate's --background: ours;
    `composited_on`); float64: composite in float64 as eval.metrics.composite, no clipping
    (ours), else in float32 and clipped to [0, 1] as the other tools do; quantise: round-trip
    through uint8 (truncating) before scoring; ssim: which SSIM; lpips_net: the network of
    the "lpips" metric; extra_lpips: {metric name: net} also reported (NerfBaselines'
    lpips_vgg protocol keeps AlexNet as "lpips_alex")."""

    name: str
    background: Optional[tuple]
    quantise: bool
    ssim: str
    lpips_net: str
    extra_lpips: tuple = ()
    their_name: Optional[str] = None  # the protocol's own name in its tool's results JSON
    source: str = ""
    float64: bool = False

    def composited_on(self, evaluation_background) -> tuple:
        """The RGB this protocol composites colour onto when the evaluation composites onto
        `evaluation_background` (RGB)."""
        return tuple(evaluation_background) if self.background is None else self.background


PROTOCOLS = {
    "nerfgauge": Protocol("nerfgauge", None, False, "skimage", "alex", source="docs/conventions.md (Metrics)",
                          float64=True),
    "nerfbaselines": Protocol("nerfbaselines", (1.0, 1.0, 1.0), True, "dm_pix", "vgg", (("lpips_alex", "alex"),),
                              their_name="nerf",
                              source="nerfbaselines/evaluation.py NerfEvaluationProtocol; nerfbaselines/utils.py "
                                     "image_to_srgb, convert_image_dtype; nerfbaselines/metrics.py ssim, psnr, lpips_vgg; "
                                     "nerfbaselines/datasets/blender.py background_color"),
    "ns-eval": Protocol("ns-eval", (0.0, 0.0, 0.0), False, "torchmetrics", "alex", their_name="ns-eval",
                        source="nerfstudio/models/nerfacto.py get_image_metrics_and_images; "
                               "nerfstudio/model_components/renderers.py blend_background"),
}


def get(name: str) -> Protocol:
    """The protocol called `name`; an InputError (one line) naming the known ones otherwise."""
    protocol = PROTOCOLS.get(name) if isinstance(name, str) else None
    if protocol is None:
        raise InputError(f"unknown protocol {name!r}; choose one of {', '.join(PROTOCOLS)}")
    return protocol


# --- preparing a pair -------------------------------------------------------------------------


def _composite32(rgb, alpha, background) -> np.ndarray:
    """rgb * a + bg * (1 - a) in float32 (NerfBaselines and nerfstudio work in float32)."""
    rgb = np.asarray(rgb, np.float32)
    if alpha is None:
        return rgb
    a = np.asarray(alpha, np.float32)[..., None]
    return rgb * a + np.asarray(background, np.float32) * (np.float32(1.0) - a)


def _uint8_truncate(image) -> np.ndarray:
    """NerfBaselines' convert_image_dtype(float -> uint8 -> float32): (x * 255).clip(0, 255)
    cast to uint8 (truncates), then / 255."""
    return ((np.asarray(image, np.float32) * np.float32(255.0)).clip(0, 255).astype(np.uint8)
            .astype(np.float32) / np.float32(255.0))


def prepare(protocol: Protocol, pred_rgb, pred_alpha, gt_rgba, background=(1.0, 1.0, 1.0)) -> tuple:
    """The pair a protocol scores: (pred, gt), each [H, W, 3] in [0, 1].

    Args:
        pred_rgb: [H, W, 3] the prediction's straight colour in [0, 1].
        pred_alpha: [H, W] its opacity, or None for an RGB prediction (taken as rendered).
        gt_rgba: [H, W, 4] the ground truth, straight alpha (an opaque dataset: alpha 1).
        background: the evaluation's RGB, for protocols that take it ("nerfgauge").
    """
    colour = protocol.composited_on(background)
    if protocol.float64:  # as eval.metrics.composite
        pred = np.asarray(pred_rgb, np.float64) if pred_alpha is None else \
            composite(np.concatenate([pred_rgb, np.asarray(pred_alpha)[..., None]], -1), colour)
        return pred, composite(gt_rgba, colour)
    pred = _composite32(pred_rgb, pred_alpha, colour)
    gt = _composite32(np.asarray(gt_rgba)[..., :3], np.asarray(gt_rgba)[..., 3], colour)
    if protocol.quantise:
        pred, gt = _uint8_truncate(pred), _uint8_truncate(gt)
    return np.clip(pred, 0.0, 1.0), np.clip(gt, 0.0, 1.0)


# --- the metrics of each protocol ---------------------------------------------------------------


def _gaussian_taps(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    taps = np.exp(-0.5 * (x / sigma) ** 2)
    return taps / taps.sum()


def _filter_valid(image: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation of [H, W, C] with a symmetric 1D kernel along H and W."""
    k = taps.size
    h, w = image.shape[0] - k + 1, image.shape[1] - k + 1
    rows = sum(taps[i] * image[i:i + h] for i in range(k))  # [h, W, C]
    return sum(taps[i] * rows[:, i:i + w] for i in range(k))  # [h, w, C]


def ssim_dm_pix(pred, gt) -> float:
    """dm_pix / NerfBaselines SSIM of two [H, W, 3] images in [0, 1] (max_val 1): 11-tap
    Gaussian (sigma 1.5) over the valid region only, variances clipped at float32 eps^2,
    the covariance at sqrt(var0 var1); mean over the map and channels. Float32 inputs,
    float64 arithmetic. Images under 11 px a side: None."""
    a, b = (np.clip(np.asarray(x, np.float32), 0, 1).astype(np.float64) for x in (gt, pred))
    if min(a.shape[:2]) < 11:
        return None
    taps = _gaussian_taps()
    mu0, mu1 = _filter_valid(a, taps), _filter_valid(b, taps)
    s00 = _filter_valid(a * a, taps) - mu0 * mu0
    s11 = _filter_valid(b * b, taps) - mu1 * mu1
    s01 = _filter_valid(a * b, taps) - mu0 * mu1
    eps = float(np.finfo(np.float32).eps) ** 2
    s00, s11 = np.maximum(eps, s00), np.maximum(eps, s11)
    s01 = np.sign(s01) * np.minimum(np.sqrt(s00 * s11), np.abs(s01))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim_map = (2 * mu0 * mu1 + c1) * (2 * s01 + c2) / ((mu0 ** 2 + mu1 ** 2 + c1) * (s00 + s11 + c2))
    return float(ssim_map.mean())


def ssim_torchmetrics(pred, gt) -> Optional[float]:
    """torchmetrics.functional.structural_similarity_index_measure(pred, gt) with its
    defaults, as ns-eval calls it: Gaussian 11 taps, sigma 1.5, reflect padding by 5, the
    SSIM map averaged over the whole image (padded border included, as torchmetrics 1.9
    does; NerfBaselines' numpy copy of an older torchmetrics crops it), data_range=None:
    max(range(pred), range(gt)) of the image pair; the variances clamped at 0. Images under 6 px a side (reflect padding needs more): None."""
    p, g = (np.asarray(x, np.float32).astype(np.float64) for x in (pred, gt))
    if min(p.shape[:2]) < 6:
        return None
    data_range = max(p.max() - p.min(), g.max() - g.min())
    if data_range == 0:  # two constant images (an empty scene): their formula is 0/0, undefined
        return None
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    taps, pad = _gaussian_taps(), 5
    padded = [np.pad(x, ((pad, pad), (pad, pad), (0, 0)), mode="reflect") for x in (p, g, p * p, g * g, p * g)]
    mu_p, mu_g, pp, gg, pg = (_filter_valid(x, taps) for x in padded)
    s_p, s_g, s_pg = np.maximum(pp - mu_p ** 2, 0.0), np.maximum(gg - mu_g ** 2, 0.0), pg - mu_p * mu_g
    ssim_map = ((2 * mu_p * mu_g + c1) * (2 * s_pg + c2)) / ((mu_p ** 2 + mu_g ** 2 + c1) * (s_p + s_g + c2))
    return float(ssim_map.mean())  # torchmetrics 1.9 (tested) averages the whole map; NerfBaselines' copy of an older one crops 5 px


def psnr32(pred, gt) -> float:
    """-10 log10(MSE) with the MSE of float32 images in float32 (NerfBaselines, torchmetrics);
    identical images give eval.metrics.PSNR_CAP_DB instead of inf."""
    mse = float(np.mean((np.asarray(pred, np.float32) - np.asarray(gt, np.float32)) ** 2, dtype=np.float32))
    return -10.0 * math.log10(max(mse, MSE_FLOOR))


def image_scores(protocol: Protocol, pred, gt) -> dict:
    """{"psnr", "ssim"} of a prepared pair under `protocol`."""
    if protocol.ssim == "skimage":
        return {"psnr": metrics.psnr(pred, gt), "ssim": metrics.ssim(pred, gt)}
    ssim = ssim_dm_pix(pred, gt) if protocol.ssim == "dm_pix" else ssim_torchmetrics(pred, gt)
    scores = {"psnr": psnr32(pred, gt), "ssim": ssim}
    # a value a protocol's own formula leaves undefined (NaN) is not a score: None, as for ours
    return {key: value if value is None or math.isfinite(value) else None for key, value in scores.items()}


def background_name(rgb) -> str:
    """The name (eval.metrics.BACKGROUNDS) of a background colour."""
    return {colour: name for name, colour in BACKGROUNDS.items()}[tuple(rgb)]


def lpips_scorers(protocol: Protocol, intrinsics) -> tuple[dict, dict]:
    """({metric: eval.lpips.LpipsBatch}, {metric: why it is n/a}) for the protocol's "lpips"
    and its extra LPIPS metrics."""
    batches, notes = {}, {}
    for metric, net in (("lpips", protocol.lpips_net),) + tuple(protocol.extra_lpips):
        if min(intrinsics.width, intrinsics.height) < MIN_SIDES[net]:
            notes[metric] = f"n/a ({LABELS[net]} needs images of at least {MIN_SIDES[net]} px)"
            continue
        model = load_lpips(net=net)
        if model is None:
            notes[metric] = NOT_AVAILABLE
        else:
            batches[metric] = LpipsBatch(model, features_source(model))  # the ground truth's features, cached
    return batches, notes


# --- the same renders under every protocol ------------------------------------------------------


def sensitivity(root, pred_dir, split: str = "test", *, background: str = "white", pred_format: str = "auto",
                protocols=tuple(PROTOCOLS)) -> dict:
    """Score the renders in `pred_dir` under each protocol (no files written).

    Returns {"split", "frames": n, "protocols": {name: {"psnr", "ssim", "lpips", "lpips_net",
    "notes"}}, "spread": {metric: max - min over the protocols that gave a value, or None}}.
    """
    ds = dataset.open_dataset(root)
    cameras = ds.cameras(split)
    found = locate_predictions(ds, Path(pred_dir), split, pred_format, "distance")
    chosen = [get(name) for name in protocols]
    scorers = {p.name: lpips_scorers(p, cameras.intrinsics) for p in chosen}
    per_frame = {p.name: {"psnr": [], "ssim": []} for p in chosen}
    for stem, files in found.items():
        rgb, alpha = read_colour(files.colour, cameras.intrinsics)
        if files.opacity is not None:
            alpha = read_plane(files.opacity, cameras.intrinsics)
        gt_rgba = ds.rgba_of(stem, cameras.intrinsics)
        for p in chosen:
            pred, gt = prepare(p, rgb, alpha, gt_rgba, BACKGROUNDS[background])
            for key, value in image_scores(p, pred, gt).items():
                per_frame[p.name][key].append(value)
            for batch in scorers[p.name][0].values():
                batch.add(pred, gt)
    results = {}
    for p in chosen:
        batches, notes = scorers[p.name]
        row = {key: summarize(values)[0] for key, values in per_frame[p.name].items()}
        for metric, batch in batches.items():
            row[metric] = summarize(batch.scores())[0]
        for metric in notes:
            row[metric] = None
        results[p.name] = {**row, "lpips_net": p.lpips_net, "notes": notes}
    spread = _spread(results)
    return {"split": split, "frames": len(found), "background": background, "protocols": results, "spread": spread}


def _spread(rows: dict) -> dict:
    spread = {}
    for metric in SENSITIVITY_METRICS:
        values = [r[metric] for r in rows.values() if r.get(metric) is not None]
        spread[metric] = (max(values) - min(values)) if len(values) > 1 else None
    return spread


def combine(documents: list) -> dict:
    """One sensitivity document from several (a method over a suite's datasets): each
    protocol's metrics are the mean over the documents where they are defined, the spread
    is taken between those means; "datasets" says how many were combined."""
    if not documents:
        raise InputError("no protocol-sensitivity documents to combine")
    names = list(documents[0]["protocols"])
    rows = {}
    for name in names:
        row = {metric: summarize([d["protocols"][name].get(metric) for d in documents])[0]
               for metric in SENSITIVITY_METRICS}
        notes = {}
        for d in documents:
            notes.update(d["protocols"][name].get("notes", {}))
        rows[name] = {**row, "lpips_net": documents[0]["protocols"][name]["lpips_net"],
                      "notes": {m: n for m, n in notes.items() if row.get(m) is None}}
    return {"split": documents[0]["split"], "frames": sum(d["frames"] for d in documents),
            "datasets": len(documents), "protocols": rows, "spread": _spread(rows)}


def suite_sensitivity(entries: dict, split: str = "test", pred_format: str = "auto", background: str = "white") -> dict:
    """For a suite leaderboard: entries {method: [(dataset folder, render folder), ...]} ->
    {method: combined sensitivity document} (pass it to `sensitivity_rows`). background:
    the suite protocol's, for the "nerfgauge" rows (the others fix their own)."""
    return {method: combine([sensitivity(root, pred, split, pred_format=pred_format, background=background)
                             for root, pred in pairs])
            for method, pairs in entries.items() if pairs}


def sensitivity_rows(documents: dict) -> list[list[str]]:
    """The protocol-sensitivity table: documents {method: sensitivity(...)}. A header row,
    then per method one row per protocol and a "spread" row (max - min)."""
    table = [["method", "protocol", "PSNR dB", "SSIM", "LPIPS", "LPIPS net"]]
    formats = {"psnr": "{:.2f}", "ssim": "{:.4f}", "lpips": "{:.4f}"}
    for method, document in documents.items():
        for name, row in document["protocols"].items():
            cells = [method, name]
            for metric in SENSITIVITY_METRICS:
                value = row.get(metric)
                cells.append(row.get("notes", {}).get(metric, "–") if value is None else formats[metric].format(value))
            table.append(cells + [row.get("lpips_net", "–")])
        table.append([method, "spread (max - min)"]
                     + ["–" if document["spread"].get(m) is None else formats[m].format(document["spread"][m])
                        for m in SENSITIVITY_METRICS] + [""])
    return table


def format_rows(table: list[list[str]]) -> str:
    """A plain-text rendering of a table of rows (first row the header)."""
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in table)
