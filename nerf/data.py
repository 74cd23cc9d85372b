"""Rays and targets from a nerfgauge dataset (or any folder in the same format).

Colours stay in the PNGs' sRGB space, as NeRF-synthetic training does; alpha is kept so
the background can be composited per ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from nerfgauge.core.camera import SplitCameras
from nerfgauge.core.dataset import open_dataset
from nerfgauge.core.pixel_edges import edge_mask


@dataclass(frozen=True)
class RayBatch:
    """origins, directions (unit): [n, 3]; rgba: [n, 4] straight alpha or None;
    n_views whole views, row-major, one after another. footprint: [n, 2, 3], how a ray's
    direction moves per pixel in x and in y (`pixel_footprints`), or None. edges: [n] bool,
    the target's edge pixels (nerfgauge.core.pixel_edges.edge_mask of its RGBA), or None."""

    origins: torch.Tensor
    directions: torch.Tensor
    rgba: Optional[torch.Tensor]
    n_views: int = 1
    footprint: Optional[torch.Tensor] = None
    edges: Optional[torch.Tensor] = None


def split_rays(cameras: SplitCameras, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of one view, row-major, through the split's lens distortion if it has one (the
    camera the dataset's pixels were rendered with). Returns origins, directions [H*W, 3]
    float32."""
    origins, directions = cameras.rays(index)
    return (torch.from_numpy(origins.reshape(-1, 3).astype(np.float32)),
            torch.from_numpy(directions.reshape(-1, 3).astype(np.float32)))


def pixel_footprints(directions: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Each pixel-centre ray's change per pixel, so a ray through any point of the pixel is
    `jittered_direction`. With the forward axis f (c2w's -z), the direction scaled to unit
    depth, u = d / (d . f), is linear in the pixel position for a pinhole; its central
    differences across the grid (one-sided at the border) are then exact, and for any other
    camera model they are the model's local linearisation. Returned scaled by (d . f), so
    that d + a dx + b dy is parallel to the unit-depth ray at offset (a, b) pixels.

    Args:
        directions: [H, W, 3] unit pixel-centre directions of one view.
        c2w: [4, 4] (or [3, 4]) camera-to-world.
    Returns:
        [H * W, 2, 3] float32: the x (column) and y (row) steps.
    """
    forward = -np.asarray(c2w, dtype=np.float64)[:3, 2]
    cosine = directions @ forward  # [H, W]
    unit_depth = directions / cosine[..., None]  # [H, W, 3]
    steps = [np.gradient(unit_depth, axis=axis) if unit_depth.shape[axis] > 1 else np.zeros_like(unit_depth)
             for axis in (1, 0)]  # x along columns, y along rows
    footprint = np.stack(steps, axis=-2) * cosine[..., None, None]  # [H, W, 2, 3]
    return footprint.reshape(-1, 2, 3).astype(np.float32)


def jittered_direction(directions: torch.Tensor, footprint: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Unit directions through a point of each ray's pixel instead of its centre.

    Args:
        directions: [n, 3] unit pixel-centre directions.
        footprint: [n, 2, 3] from `pixel_footprints`.
        offsets: [n, 2] in pixels from the centre, x then y, in [-0.5, 0.5) for the pixel.
    Returns:
        [n, 3] unit directions.
    """
    moved = directions + offsets[:, :1] * footprint[:, 0] + offsets[:, 1:] * footprint[:, 1]
    return moved / torch.linalg.vector_norm(moved, dim=-1, keepdim=True)


def load_split_rays(root, split: str, limit: Optional[int] = None, views: Optional[list] = None,
                    footprint: bool = False, edges: bool = False) -> tuple[SplitCameras, RayBatch]:
    """All rays and RGBA targets of a split (the first `limit` views if given; only the
    frame indices `views`, in that order, if given), with each ray's pixel footprint when
    `footprint` (24 more bytes a ray) and whether its target is an edge pixel when `edges`
    (from the colours alone: a real capture has no instance ids). root: a dataset folder or
    an open nerfgauge.core.dataset.Dataset."""
    ds = open_dataset(root)
    cameras = ds.cameras(split)
    count = len(cameras.stems) if limit is None else min(limit, len(cameras.stems))
    indices = list(range(count)) if views is None else list(views)
    count = len(indices)
    origins, directions, colours, footprints, edge_flags = [], [], [], [], []
    for index in indices:
        o, d = cameras.rays(index)  # [H, W, 3] float64, through the split's distortion if any
        origins.append(torch.from_numpy(o.reshape(-1, 3).astype(np.float32)))
        directions.append(torch.from_numpy(d.reshape(-1, 3).astype(np.float32)))
        if footprint:
            footprints.append(torch.from_numpy(pixel_footprints(d, cameras.c2w[index])))
        rgba = ds.rgba_of(cameras.stems[index], cameras.intrinsics)  # [H, W, 4]
        colours.append(torch.from_numpy(rgba.reshape(-1, 4)))
        if edges:
            edge_flags.append(torch.from_numpy(edge_mask(rgba.astype(np.float64)).reshape(-1)))
    if not origins:
        empty = torch.zeros((0, 3))
        return cameras, RayBatch(empty, empty, torch.zeros((0, 4)), 0, torch.zeros((0, 2, 3)) if footprint else None,
                                 torch.zeros(0, dtype=torch.bool) if edges else None)
    return cameras, RayBatch(torch.cat(origins), torch.cat(directions), torch.cat(colours), count,
                             torch.cat(footprints) if footprint else None, torch.cat(edge_flags) if edges else None)


def sparse_train_views(root, count: int) -> list:
    """The train frame indices of the dataset's sparse list of `count` views
    (nerfgauge.core.dataset.Dataset.sparse_train_views)."""
    return open_dataset(root).sparse_train_views(count)


def scene_info(root) -> tuple[Optional[dict], Optional[np.ndarray]]:
    """(needs, aabb [2, 3]) from scene.json (either None when absent). The bounds are
    checked on open: finite, min < max on every axis (nerfgauge.core.validate.bounds)."""
    ds = open_dataset(root)
    return ds.scene.get("needs"), ds.bounds


def aabb_from_cameras(c2w: np.ndarray) -> np.ndarray:
    """Fallback bounds without scene.json: a cube around the point the cameras look at,
    half as wide as their mean distance to it."""
    forward = -c2w[:, :3, 2]
    origins = c2w[:, :3, 3]
    # least-squares point closest to every optical axis
    eye = np.eye(3)
    a = sum(eye - np.outer(f, f) for f in forward)
    b = sum((eye - np.outer(f, f)) @ o for f, o in zip(forward, origins))
    centre = np.linalg.lstsq(a, b, rcond=None)[0]
    half = 0.5 * float(np.linalg.norm(origins - centre, axis=1).mean())
    return np.stack([centre - half, centre + half])
