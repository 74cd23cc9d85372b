"""Rays and targets from a nerfgauge dataset (or any folder in the same format).

Colours stay in the PNGs' sRGB space, as NeRF-synthetic training does; alpha is kept so
the background can be composited per ray.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from nerfgauge.core.camera import SplitCameras, pixel_rays
from nerfgauge.core.dataset import open_dataset
from nerfgauge.core.errors import InputError


@dataclass(frozen=True)
class RayBatch:
    """origins, directions (unit): [n, 3]; rgba: [n, 4] straight alpha or None;
    n_views whole views, row-major, one after another."""

    origins: torch.Tensor
    directions: torch.Tensor
    rgba: Optional[torch.Tensor]
    n_views: int = 1


def split_rays(cameras: SplitCameras, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of one view, row-major. Returns origins, directions [H*W, 3] float32."""
    origins, directions = pixel_rays(cameras.c2w[index], cameras.intrinsics)
    return (torch.from_numpy(origins.reshape(-1, 3).astype(np.float32)),
            torch.from_numpy(directions.reshape(-1, 3).astype(np.float32)))


def load_split_rays(root, split: str, limit: Optional[int] = None,
                    views: Optional[list] = None) -> tuple[SplitCameras, RayBatch]:
    """All rays and RGBA targets of a split (the first `limit` views if given; only the
    frame indices `views`, in that order, if given). root: a dataset folder or an open
    nerfgauge.core.dataset.Dataset."""
    ds = open_dataset(root)
    cameras = ds.cameras(split)
    count = len(cameras.stems) if limit is None else min(limit, len(cameras.stems))
    indices = list(range(count)) if views is None else list(views)
    count = len(indices)
    origins, directions, colours = [], [], []
    for index in indices:
        o, d = split_rays(cameras, index)
        origins.append(o), directions.append(d)
        colours.append(torch.from_numpy(ds.rgba_of(cameras.stems[index], cameras.intrinsics).reshape(-1, 4)))
    if not origins:
        empty = torch.zeros((0, 3))
        return cameras, RayBatch(empty, empty, torch.zeros((0, 4)), 0)
    return cameras, RayBatch(torch.cat(origins), torch.cat(directions), torch.cat(colours), count)


SPARSE_FILE = "sparse_views.json"  # generate.holdout writes it (docs/conventions.md, "Extrapolation splits")


def sparse_train_views(root, count: int) -> list:
    """The train frame indices of the dataset's sparse list of `count` views (nested lists
    by farthest-point sampling on the camera centres), checked; one line when absent."""
    ds = open_dataset(root)
    where = ds.root / SPARSE_FILE
    if SPARSE_FILE not in ds.manifest_files:
        raise InputError(f"{ds.root} has no {SPARSE_FILE} (datasets generated before the sparse view lists "
                         f"have none); regenerate it to train on --sparse {count}")
    try:
        document = json.loads(ds.read_bytes(SPARSE_FILE))
    except ValueError as error:
        raise InputError(f"{where}: not JSON ({error})") from None
    lists = document.get("counts") if isinstance(document, dict) else None
    n_train = len(ds.cameras("train").stems)
    if not isinstance(lists, dict) or str(count) not in lists:
        have = ", ".join(sorted(lists, key=lambda k: (len(k), k))) if isinstance(lists, dict) else "none"
        raise InputError(f"{where} has no list of {count} views (it has: {have})")
    indices = lists[str(count)]
    if (not isinstance(indices, list) or len(indices) != count or len(set(indices)) != count
            or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n_train for i in indices)):
        raise InputError(f"{where}: list {count} must be {count} distinct train frame indices below {n_train}")
    return indices


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
