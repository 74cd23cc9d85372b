"""Which pixels of a held-out view the training views saw: the co-visibility mask.

A held-out pixel whose surface point no training camera saw cannot be predicted from the
capture; a method can only guess it. Whole-image PSNR mixes that guess with how well the
method reproduces what it was shown. Masked metrics (DyCheck's mPSNR / mSSIM, Gao et al.
2022, "Monocular Dynamic View Synthesis: A Reality Check") score only the pixels the
training views saw. DyCheck estimates the mask with optical flow; here it is exact:

- a pixel whose centre ray hits geometry (the ground-truth mask) is co-visible when the
  surface point at its exact ray distance is visible in at least one view of the
  reference split, by core.visibility's depth test (the point projects into the view and
  the view's exact depth there agrees within half a pixel's footprint on the tilted
  surface);
- a pixel whose centre ray misses everything is co-visible: what it shows is the
  background, which every method is given (an empty ray composited on it).

The reference split is `train`: the views a method is trained on. Scoring the train split
itself has no held-out pixels, so it has no mask.

Depth has a second condition: two train views must see the point from far enough apart
for its depth to show. If two views that see point P subtend the angle theta at P, moving
P along one view's ray by a fraction r of its distance moves its image in the other by
about f r sin(theta) pixels (f the focal length in pixels; views at similar distances).
A hit pixel's depth is **resolved** when some pair of train views that see its point has

    f sin(min(theta, 90 deg)) >= RESOLVED_SHIFT_PX / RESOLVED_RELATIVE_DEPTH = 10 px,

so a 5% depth error shifts the point by at least half a pixel between them (half a pixel:
the rounding of a position to the pixel grid, and the depth test's own tolerance). A
forward-facing capture's far content fails this: depth-range's boulder 50 away moves
0.07 px across the whole camera cluster, and no method can measure its depth from the
images; its pebble 0.2 away moves 0.8 px for a 5% depth change, and is resolved.
`depth_absrel_resolved` scores depth on the resolved pixels only. The largest angle is
found by two sweeps (the seeing view farthest from the first seeing view, then the
farthest from that one): never more than the true largest angle, at least half of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nerfgauge.core.dataset import Dataset
from nerfgauge.core.visibility import seen_in_view

REFERENCE_SPLIT = "train"
RESOLVED_RELATIVE_DEPTH = 0.05  # this relative depth change of a resolved pixel's point ...
RESOLVED_SHIFT_PX = 0.5  # ... moves it at least this far between two train views that see it
# (reference view, held-out pixel) pairs judged at once: a frame's pixels are taken in blocks
# of VIEW_PIXEL_PAIRS / views, so memory (1 B a pair, 24 B a seen pair) does not grow with
# views x pixels (200 views of an 800 x 800 frame: 128M pairs, 3 GB of directions at once)
VIEW_PIXEL_PAIRS = 1 << 21


@dataclass(frozen=True)
class HeldOutPixels:
    """What the reference views saw of one held-out frame: both [H, W] bool."""

    covisible: np.ndarray  # a miss, or the surface point seen by some reference view
    resolved: np.ndarray  # a hit whose depth shows between two reference views (module docstring)


def reference_depths(ds: Dataset, reference: str = REFERENCE_SPLIT) -> list:
    """The reference split's ray-distance depth maps [H, W] (float32), read once."""
    return [ds.depth(reference, index, kind="distance") for index in range(len(ds.cameras(reference).c2w))]


def views_seeing(points: np.ndarray, normals: np.ndarray, ds: Dataset, depths: list,
                 reference: str = REFERENCE_SPLIT) -> np.ndarray:
    """[views, n] bool: which reference views see each point [n, 3] (unit normals [n, 3]),
    by core.visibility's depth test. depths: reference_depths(ds, reference). The reference
    views' exact poses (their depth was rendered from them, whatever pose noise the
    transforms hold)."""
    cameras = ds.exact_cameras(reference)
    xyz, nrm = np.ascontiguousarray(points.T), np.ascontiguousarray(normals.T)  # [3, n]
    seen = np.zeros((len(cameras.c2w), len(points)), bool)
    for index, pose in enumerate(cameras.c2w):
        seen[index, seen_in_view(xyz, nrm, pose, cameras.intrinsics, depths[index], cameras.distortion)] = True
    return seen


def parallax_pixels(points: np.ndarray, seen: np.ndarray, centres: np.ndarray, focal: float) -> np.ndarray:
    """focal * sin(min(theta, 90 deg)) for each point [n, 3], theta the largest angle at the
    point between two cameras (centres [views, 3]) that see it (seen [views, n] bool),
    found by two sweeps (module docstring); 0 where fewer than two see it. Returns [n]."""
    columns = [np.flatnonzero(row) for row in seen]  # per camera: the points it sees
    # per camera: unit directions [k, 3] from the points it sees to it, computed once for
    # the three passes below (24 B per seen point and view)
    offsets = (centres[index] - points[these] for index, these in enumerate(columns))
    towards = [offset / np.sqrt(np.einsum("ij,ij->i", offset, offset))[:, None] for offset in offsets]

    def farthest_from(anchor):  # (cos of the widest angle to `anchor` [n, 3], that view's direction)
        best_cos, best = np.full(len(points), 2.0), anchor.copy()
        for these, direction in zip(columns, towards):
            cos = np.einsum("ij,ij->i", direction, anchor[these])
            wider = cos < best_cos[these]
            best_cos[these[wider]], best[these[wider]] = cos[wider], direction[wider]
        return best_cos, best

    first = np.zeros((len(points), 3))
    for these, direction in zip(reversed(columns), reversed(towards)):  # the first seeing view is written last
        first[these] = direction
    _, widest_from_first = farthest_from(first)
    cos, _ = farthest_from(widest_from_first)
    sine = np.sin(np.minimum(np.arccos(np.clip(cos, -1.0, 1.0)), np.pi / 2))
    return np.where(seen.sum(axis=0) >= 2, focal * sine, 0.0)


def held_out_pixels(ds: Dataset, split: str, index: int, depths: list, mask: np.ndarray, distance: np.ndarray,
                    reference: str = REFERENCE_SPLIT) -> HeldOutPixels:
    """The co-visible and depth-resolved pixels of frame `index` of `split` (module
    docstring), from the frame's ground-truth mask [H, W] bool and ray distance [H, W],
    which the caller has read. depths: reference_depths(ds, reference)."""
    cameras = ds.exact_cameras(split)
    distance = distance.astype(np.float64)
    hit = mask & (distance > 0)  # [H, W]
    origins, directions = cameras.rays(index)  # [H, W, 3] each, through the split's distortion if any
    points = origins[hit] + directions[hit] * distance[hit][:, None]  # [n, 3]
    normals = ds.normals(split, index)[hit].astype(np.float64)  # [n, 3]
    reference_cameras = ds.exact_cameras(reference)
    centres = reference_cameras.c2w[:, :3, 3]
    focal = max(reference_cameras.intrinsics.fx, reference_cameras.intrinsics.fy)
    seen_any, parallax = np.zeros(len(points), bool), np.zeros(len(points))
    # the pixels in blocks: seen is [views, pixels], and parallax_pixels keeps 24 B per seen pair
    block = max(1, VIEW_PIXEL_PAIRS // max(1, len(centres)))
    for start in range(0, len(points), block):
        part = slice(start, start + block)
        seen = views_seeing(points[part], normals[part], ds, depths, reference)
        seen_any[part] = seen.any(axis=0)
        parallax[part] = parallax_pixels(points[part], seen, centres, focal)
    covisible, resolved = np.ones(hit.shape, bool), np.zeros(hit.shape, bool)
    covisible[hit] = seen_any
    resolved[hit] = parallax >= RESOLVED_SHIFT_PX / RESOLVED_RELATIVE_DEPTH
    return HeldOutPixels(covisible, resolved)


def holds_out(ds: Dataset, split: str, reference: str = REFERENCE_SPLIT) -> bool:
    """Whether `split` has pixels to hold against `reference`: not when it is the
    reference itself, or the dataset has no reference split."""
    return split != reference and reference in ds.splits
