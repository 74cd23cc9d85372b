"""A trained field's normals against the exact ground-truth normals of a split's views.

For each pixel the model renders its expected ray distance D; the predicted normal is the
field's at the expected surface point x = o + D d:

    n(x) = -grad sigma(x) / |grad sigma(x)|        (autograd through model.density)

pointing out of the dense region. It is compared with the dataset's world-space normal
EXR on the pixels whose centre ray hits geometry (the mask). The ground-truth normal is
turned to face the camera (a shading normal of a one-sided surface seen from behind may
point away); the predicted one is not, so a field whose gradient points the wrong way is
scored as wrong. A hit pixel where the model predicts nothing (opacity below one half,
or a zero gradient) scores 90 degrees: no information. Angles in degrees.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from nerfgauge.core.dataset import open_dataset
from nerfgauge.core.errors import InputError
from nerfgauge.nerf.rendering import render_rays_chunked  # the field renders its depth: eval -> nerf by design

WITHIN_DEGREES = (11.25, 22.5, 30.0)
UNDEFINED_DEGREES = 90.0
MIN_OPACITY = 0.5


def field_normals(model, points: torch.Tensor, chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
    """-grad sigma / |grad sigma| at world points [n, 3]. Returns normals [n, 3] and
    defined [n] bool (a non-zero, finite gradient)."""
    normals, defined = [], []
    for start in range(0, points.shape[0], chunk):
        p = points[start:start + chunk].detach().clone().requires_grad_(True)
        with torch.enable_grad():
            sigma = model.density(p)
            (gradient,) = torch.autograd.grad(sigma.sum(), p)
        length = gradient.norm(dim=-1)
        ok = torch.isfinite(length) & (length > 0)
        normals.append(torch.where(ok[:, None], -gradient / length.clamp_min(1e-30)[:, None], torch.zeros_like(p)))
        defined.append(ok)
    return torch.cat(normals), torch.cat(defined)


def angular_errors(predicted: np.ndarray, defined: np.ndarray, truth: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Angles in degrees between predicted [n, 3] and ground-truth [n, 3] unit normals,
    the ground truth turned to face the rays `directions` [n, 3]; UNDEFINED_DEGREES where
    defined [n] is False."""
    truth = truth / np.maximum(np.linalg.norm(truth, axis=1, keepdims=True), 1e-30)
    facing = np.where((np.einsum("ij,ij->i", truth, directions) > 0)[:, None], -truth, truth)
    cos = np.clip(np.einsum("ij,ij->i", predicted, facing), -1.0, 1.0)
    return np.where(defined, np.degrees(np.arccos(cos)), UNDEFINED_DEGREES)


def normal_scores(errors: np.ndarray) -> dict:
    """Mean, median and the shares within WITHIN_DEGREES of angular errors [n] (degrees)."""
    if not len(errors):
        raise InputError("no ground-truth hit pixels to score normals on")
    return {"mean_degrees": float(errors.mean()), "median_degrees": float(np.median(errors)),
            "within": {f"{t:g}": float((errors <= t).mean()) for t in WITHIN_DEGREES}, "pixels": int(len(errors))}


def score_normals(model, root, split: str = "test", views: int | None = None, device="cpu") -> dict:
    """The field's normals at its expected depth on every GT-hit pixel of `split` (the
    first `views` views if given), scored against the dataset's normal EXRs."""
    if not model.has_density:
        raise InputError(f"a {type(model).__name__} has no density query (model.density); normals need one")
    ds = open_dataset(root)  # a path or an open (e.g. checked, nerf.runs) Dataset
    cameras = ds.cameras(split)
    count = len(cameras.stems) if views is None else min(views, len(cameras.stems))
    if not count:
        raise InputError(f"dataset {ds.root} has no {split} views")
    model = model.to(device).eval()
    errors, undefined = [], 0
    for index in range(count):
        mask = ds.mask(split, index).reshape(-1)  # [H*W]
        if not mask.any():
            continue
        truth = ds.normals(split, index).reshape(-1, 3)[mask].astype(np.float64)
        origins, directions = (a.reshape(-1, 3)[mask] for a in cameras.rays(index))
        o = torch.from_numpy(origins.astype(np.float32)).to(device)
        d = torch.from_numpy(directions.astype(np.float32)).to(device)
        with torch.no_grad():
            _, opacity, depth = render_rays_chunked(model, o, d)
        normals, defined = field_normals(model, o + depth[:, None] * d)
        defined = defined & (opacity >= MIN_OPACITY)
        undefined += int((~defined).sum())
        errors.append(angular_errors(normals.double().cpu().numpy(), defined.cpu().numpy(), truth, directions))
    scores = normal_scores(np.concatenate(errors) if errors else np.zeros(0))
    scores.update({"split": split, "views": count, "undefined_pixels": undefined})
    if not all(math.isfinite(v) for v in (scores["mean_degrees"], scores["median_degrees"])):
        raise InputError("normal errors are not finite")
    return scores
