"""The interpolation/extrapolation gap of a dataset with an extrapolation split (issue 35,
item 6; generate.holdout writes scene.json's "extrapolation").

Each test frame is in group "interpolation" (drawn from the train views' own pool: same
directions, same distance) or "extrapolation" (inside the held-out sector, or at another
distance, "scale"). The gap of a metric is

    gap = mean over interpolation frames - mean over extrapolation frames

in the metric's own units (dB for PSNR): positive when the method does worse where it saw
nothing like the view. It is given for psnr, psnr_foreground, ssim, lpips and the
co-visible scores (the share of an extrapolation view that no train view saw is
`covisible_fraction`, reported beside it), overall, for the sector frames alone (`sector`)
and per scale (`scales`, each scale's mean against the interpolation frames).

Across scales, whole-image PSNR mixes in the background: a view from twice as far is
about three-quarters white background that any method gets right. Measured (our NeRF,
600 steps on primitives at 64 px, 40 train views outside azimuth 0..90): at scale 0.5 the
whole-image PSNR was 2.8 dB *above* the interpolation views' while psnr_foreground (the
object alone) was 3.2 dB below, the zoom-out loss Mip-Splatting describes, hidden by the
background; so read psnr_foreground across scales. A group without frames
(or without values, e.g. co-visible scores with --no-held-out) gives null.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError

GAP_METRICS = ("psnr", "psnr_foreground", "ssim", "lpips", "psnr_covisible", "ssim_covisible", "covisible_fraction")
GROUPS = ("interpolation", "extrapolation")


def _mean(frames: list, metric: str) -> Optional[float]:
    values = [frame.get(metric) for frame in frames]
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def _gap(inside: list, outside: list) -> dict:
    """{metric: {"interpolation", "extrapolation", "gap"}} of two lists of frames."""
    out = {}
    for metric in GAP_METRICS:
        a, b = _mean(inside, metric), _mean(outside, metric)
        out[metric] = {"interpolation": a, "extrapolation": b, "gap": None if a is None or b is None else a - b}
    return out


def extrapolation_gap(scene_json: dict, frames: list, split: str) -> Optional[dict]:
    """metrics.json's "extrapolation": None for a dataset without an extrapolation split or
    when `split` is not test. frames: the evaluator's per-frame dicts ("name", metrics)."""
    record = scene_json.get("extrapolation") if isinstance(scene_json, dict) else None
    if record is None or split != "test":
        return None
    listed = record.get("frames") if isinstance(record, dict) else None
    if not isinstance(listed, list) or not all(isinstance(f, dict) and f.get("group") in GROUPS and
                                               isinstance(f.get("name"), str) for f in listed):
        raise InputError("scene.json: extrapolation.frames must list {name, group: interpolation|extrapolation} "
                         "for each test frame")
    group_of = {f["name"]: f for f in listed}
    scored = [frame for frame in frames if frame["name"] in group_of]
    by_group = {g: [f for f in scored if group_of[f["name"]]["group"] == g] for g in GROUPS}
    sector = [f for f in scored if group_of[f["name"]].get("in_sector")]
    scales = sorted({float(group_of[f["name"]].get("scale", 1.0)) for f in scored} - {1.0})
    return {"holdout": record.get("holdout"), "test_scales": record.get("test_scales"),
            "counts": {g: len(v) for g, v in by_group.items()},
            "overall": _gap(by_group["interpolation"], by_group["extrapolation"]),
            "sector": None if record.get("holdout") is None else
            {"count": len(sector), **_gap(by_group["interpolation"], sector)},
            "scales": {f"{scale:g}": {"count": n, **_gap(by_group["interpolation"], these)}
                       for scale in scales
                       for these in [[f for f in scored if float(group_of[f["name"]].get("scale", 1.0)) == scale]]
                       for n in [len(these)]},
            "definition": "gap = mean over interpolation frames - mean over extrapolation frames (PSNR in dB)"}


def format_gap(document: Optional[dict]) -> list:
    """Lines for the evaluator's table: the PSNR and foreground-PSNR gaps overall, in the
    sector, per scale."""
    if not document:
        return []
    lines = []
    parts = [("overall", document["overall"])]
    if document.get("sector"):
        parts.append(("sector", document["sector"]))
    parts += [(f"scale {s}", gap) for s, gap in document["scales"].items()]
    for name, gap in parts:
        for metric in ("psnr", "psnr_foreground"):
            psnr = gap[metric]
            if psnr["gap"] is not None:
                lines.append(f"extrapolation gap ({name}): {metric} {psnr['interpolation']:.2f} (interpolation) - "
                             f"{psnr['extrapolation']:.2f} (extrapolation) = {psnr['gap']:.2f} dB")
    return lines
