"""Which ground-truth surface samples a dataset's views see: the exact depth test.

Only ground truth that some camera saw can be asked of a method, so the evaluator scores
completeness on the samples some view of a reference split sees (eval.geometry), and the
COLMAP export's surface points keep those a train view sees (generate.points applies the
same rule). A sample is visible in a view if it projects into the image and its distance
from the camera matches the view's exact ray-distance depth at that pixel within

    tol = r * sqrt(2) / (2 f) * min(tan(theta), tan(80 deg)) + 1e-5 r

(r the sample's distance, f the focal length in pixels, theta the angle between the
sample's normal and the ray): the sample is at most half a pixel diagonal,
r sqrt(2) / (2 f), off the pixel-centre ray, and on a plane tilted by theta that moves the
depth by that offset times tan(theta); grazing angles are capped at GRAZING_CAP_DEGREES;
1e-5 r covers float32 storage.
"""

from __future__ import annotations

import math

import numpy as np

from nerfgauge.core.camera import pixel_coordinates
from nerfgauge.core.dataset import Dataset

GRAZING_CAP_DEGREES = 80.0


def visible_in_views(points: np.ndarray, normals: np.ndarray, ds: Dataset, split: str) -> np.ndarray:
    """Ground-truth samples [n, 3] (unit normals [n, 3]) visible in some view of `split`,
    by the exact depth test of the module docstring. Returns [n] bool.

    Samples no view sees are tested against every view, so the cost is about
    n_hidden x n_views: samples a view confirms leave the working set. The views' exact
    poses, which their depth was rendered from (Dataset.exact_cameras)."""
    cameras = ds.exact_cameras(split)
    visible = np.zeros(len(points), bool)
    left = np.arange(len(points))  # samples no view has confirmed yet (a superset: compacted lazily)
    xyz, nrm = np.ascontiguousarray(points.T), np.ascontiguousarray(normals.T)  # [3, m]
    for index, pose in enumerate(cameras.c2w):
        if not len(left):
            break
        seen = seen_in_view(xyz, nrm, pose, cameras.intrinsics, ds.depth(split, index, kind="distance"),
                            cameras.distortion)
        visible[left[seen]] = True
        if len(seen) * 16 >= len(left):  # compact when it pays; confirmed samples re-tested meanwhile are harmless
            keep = ~visible[left]
            left, xyz, nrm = left[keep], xyz[:, keep], nrm[:, keep]
    return visible


def seen_in_view(xyz: np.ndarray, nrm: np.ndarray, pose: np.ndarray, intrinsics, depth: np.ndarray,
                 distortion=None) -> np.ndarray:
    """The columns of xyz [3, m] (samples as rows of x, y, z, each contiguous; unit normals
    nrm [3, m]) that one view (c2w `pose` [4, 4], its exact ray-distance `depth` [H, W])
    sees, by the depth test of the module docstring (its pixels through `distortion`, a
    core.distortion.Distortion, when the view has one). Returns their indices [k] int64.
    The normal-dependent tolerance is only computed for samples within the widest
    tolerance (the grazing cap) of the recorded depth."""
    cap = math.tan(math.radians(GRAZING_CAP_DEGREES))
    half_pixel = math.sqrt(2) / (2 * max(intrinsics.fx, intrinsics.fy))
    widest = half_pixel * cap + 1e-5  # tolerance / distance at the grazing cap
    offset = xyz - pose[:3, 3, None]  # [3, m] camera centre to sample
    local = pose[:3, :3].T @ offset  # [3, m] camera axes
    if distortion is not None:
        u, v = distortion.project(local[0], local[1], local[2], intrinsics)
    else:
        u, v = pixel_coordinates(local[0], local[1], local[2], intrinsics)
    with np.errstate(invalid="ignore"):  # u, v are NaN behind the camera
        inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        pixel = np.where(inside, v.astype(np.int64) * intrinsics.width + u.astype(np.int64), 0)  # [m] flat
    if not inside.any():
        return np.zeros(0, np.int64)
    recorded = depth.astype(np.float64).ravel()[pixel]
    distance = np.sqrt(local[0] ** 2 + local[1] ** 2 + local[2] ** 2)
    gap = np.abs(recorded - distance)
    inside = np.flatnonzero(inside & (recorded > 0) & (gap <= distance * widest))
    distance, gap = distance[inside], gap[inside]
    cos = np.abs(nrm[0, inside] * offset[0, inside] + nrm[1, inside] * offset[1, inside]
                 + nrm[2, inside] * offset[2, inside]) / np.maximum(distance, 1e-300)
    cos = np.clip(cos, 1e-12, 1.0)
    tan = np.minimum(np.sqrt(1 - cos ** 2) / cos, cap)
    return inside[gap <= distance * (half_pixel * tan + 1e-5)]
