"""Which pixels of a held-out view the training views saw: the co-visibility mask.

A held-out pixel whose surface point no training camera saw cannot be predicted from the
capture; a method can only guess it. Whole-image PSNR mixes that guess with how well the
method reproduces what it was shown. Masked metrics (DyCheck's mPSNR / mSSIM, Gao et al.
2022, "Monocular Dynamic View Synthesis: A Reality Check") score only the pixels the
training views saw. DyCheck estimates the mask with optical flow; here it is exact:

- a pixel whose centre ray hits geometry (the ground-truth mask) is co-visible when the
  surface point at its exact ray distance is visible in at least one view of the
  reference split, by eval.geometry's depth test (the point projects into the view and
  the view's exact depth there agrees within half a pixel's footprint on the tilted
  surface);
- a pixel whose centre ray misses everything is co-visible: what it shows is the
  background, which every method is given (an empty ray composited on it).

The reference split is `train`: the views a method is trained on. Scoring the train split
itself has no held-out pixels, so it has no mask.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from nerfgauge.core.camera import pixel_rays
from nerfgauge.core.dataset import Dataset
from nerfgauge.eval.geometry import visible_in_views

REFERENCE_SPLIT = "train"


def reference_depths(ds: Dataset, reference: str = REFERENCE_SPLIT) -> list:
    """The reference split's ray-distance depth maps [H, W] (float32), read once."""
    return [ds.depth(reference, index, kind="distance") for index in range(len(ds.cameras(reference).c2w))]


def covisible_mask(ds: Dataset, split: str, index: int, depths: list,
                   reference: str = REFERENCE_SPLIT) -> np.ndarray:
    """[H, W] bool: the pixels of frame `index` of `split` that the reference views saw
    (misses count as seen, see the module docstring). depths: reference_depths(ds)."""
    cameras = ds.cameras(split)
    distance = ds.depth(split, index, kind="distance").astype(np.float64)  # [H, W]
    hit = ds.mask(split, index) & (distance > 0)  # [H, W]
    origins, directions = pixel_rays(cameras.c2w[index], cameras.intrinsics)  # [H, W, 3] each
    points = origins[hit] + directions[hit] * distance[hit][:, None]  # [n, 3]
    normals = ds.normals(split, index)[hit].astype(np.float64)  # [n, 3]
    seen = np.ones(hit.shape, bool)
    seen[hit] = visible_in_views(points, normals, ds, reference, depth_maps=depths)
    return seen


def covisible_masks(ds: Dataset, split: str, reference: str = REFERENCE_SPLIT) -> Optional[dict]:
    """{frame stem: [H, W] bool} for every frame of `split`; None when `split` is the
    reference itself (nothing is held out) or the dataset has no reference split."""
    if split == reference or reference not in ds.splits:
        return None
    depths = reference_depths(ds, reference)
    stems = ds.cameras(split).stems
    return {stem: covisible_mask(ds, split, index, depths, reference) for index, stem in enumerate(stems)}
