"""A trained field's normals against the exact ground-truth normals of a split's views.

For each pixel the model renders its expected ray distance D. The predicted normal is the
density's gradient by central differences of one voxel h (the grid's voxel in world units
there, `model.world_voxel`), taken FRONT_VOXELS voxels in front of the expected surface
point along the ray, x = o + (D - FRONT_VOXELS h) d:

    g_i(x) = (sigma(x + h e_i) - sigma(x - h e_i)) / (2 h),   n(x) = -g / |g|

pointing out of the dense region. Why not the analytic gradient at o + D d (as before):
the expected depth lands inside the surface's density peak, where a trilinear grid's
gradient is piecewise constant and small, so its direction is mostly noise; on the rising
side of the peak the density's change across a voxel follows the surface. Measured on three
runs (primitives 64 px centre-trained and box-trained, 600 steps; 128 px, 3000 steps;
docs/conventions.md "Normals from the field"): mean error 26.7 / 33.1 / 27.9 deg at the
surface point with autograd, 15.1 / 14.7 / 16.4 deg with this rule; offsets of 1 to 2
voxels and steps of 0.75 to 1.5 voxels are within 1.5 deg of it. A model without a voxel
grid (the vanilla MLP) keeps the analytic gradient at o + D d. It is compared with the dataset's world-space normal
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


FRONT_VOXELS = 1.5  # where the gradient is taken: this many voxels in front of the expected depth


def field_normals(model, points: torch.Tensor, step: torch.Tensor | None = None,
                  chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
    """-grad sigma / |grad sigma| at world points [n, 3]: by central differences of `step`
    [n] (world units) when given, else by autograd. Returns normals [n, 3] and defined [n]
    bool (a non-zero, finite gradient)."""
    normals, defined = [], []
    for start in range(0, points.shape[0], chunk):
        p = points[start:start + chunk].detach()
        if step is None:
            p = p.clone().requires_grad_(True)
            with torch.enable_grad():
                sigma = model.density(p)
                (gradient,) = torch.autograd.grad(sigma.sum(), p)
        else:
            h = step[start:start + chunk, None]  # [m, 1]
            with torch.no_grad():
                gradient = torch.stack([model.density(p + h * axis) - model.density(p - h * axis)
                                        for axis in torch.eye(3, dtype=p.dtype, device=p.device)], dim=-1) / (2 * h)
        length = gradient.norm(dim=-1)
        ok = torch.isfinite(length) & (length > 0)
        normals.append(torch.where(ok[:, None], -gradient / length.clamp_min(1e-30)[:, None], torch.zeros_like(p)))
        defined.append(ok)
    return torch.cat(normals), torch.cat(defined)


def surface_normals(model, origins: torch.Tensor, directions: torch.Tensor,
                    depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The field's normals where rays (origins, unit directions [n, 3]) meet its surface at
    expected distance depth [n] (module docstring: one-voxel central differences
    FRONT_VOXELS voxels in front of it on a voxel grid; autograd at the point otherwise).
    Returns normals [n, 3] and defined [n] bool."""
    surface = origins + depth[:, None] * directions
    if not model.has_grid:
        return field_normals(model, surface)
    step = model.world_voxel(surface)  # [n]
    return field_normals(model, surface - (FRONT_VOXELS * step)[:, None] * directions, step)


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
        normals, defined = surface_normals(model, o, d, depth)
        defined = defined & (opacity >= MIN_OPACITY)
        undefined += int((~defined).sum())
        errors.append(angular_errors(normals.double().cpu().numpy(), defined.cpu().numpy(), truth, directions))
    scores = normal_scores(np.concatenate(errors) if errors else np.zeros(0))
    scores.update({"split": split, "views": count, "undefined_pixels": undefined})
    if not all(math.isfinite(v) for v in (scores["mean_degrees"], scores["median_degrees"])):
        raise InputError("normal errors are not finite")
    return scores
