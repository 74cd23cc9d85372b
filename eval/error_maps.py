"""Per-pixel error images written beside metrics.json (folder `error_maps/`).

Two maps per frame, 8-bit RGB PNG, named after the frame (test/r_007 -> r_007_*.png):

- `r_007_colour.png`: mean over the three channels of |prediction - ground truth| on the
  composited sRGB images, colour-mapped with matplotlib's "magma" on a fixed scale
  [0, COLOUR_ERROR_MAX]: 0 is black, COLOUR_ERROR_MAX (0.2, a fifth of the range) and
  above saturate. Fixed scales keep maps comparable across frames and methods.
- `r_007_depth.png` (only when the prediction has depth): relative error |p - g| / g on the
  pixels whose ground-truth ray hits geometry, "viridis" on [0, DEPTH_ERROR_MAX] (10 %);
  pixels that miss are black.

The folder is a nerfgauge "evaluation" folder (`core.folders.claim_folder`: marker and
lock, held while a frame's maps are written): a folder nerfgauge did not make, or one of
another kind, is refused untouched; maps of a later evaluation replace those of the same
frame name.

matplotlib is imported inside the functions and only its colormap registry is used (no
pyplot, no backend selection): no global side effects.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core.folders import claim_folder
from nerfgauge.core.images import write_png

COLOUR_ERROR_MAX = 0.2
DEPTH_ERROR_MAX = 0.1
COLOUR_CMAP = "magma"
DEPTH_CMAP = "viridis"


def colour_error(pred_rgb: np.ndarray, gt_rgb: np.ndarray) -> np.ndarray:
    """Mean absolute error over channels. pred_rgb, gt_rgb: [H, W, 3] in [0, 1]. Returns [H, W]."""
    return np.mean(np.abs(np.asarray(pred_rgb, np.float64) - np.asarray(gt_rgb, np.float64)), axis=-1)


def depth_relative_error(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """|p - g| / g on masked pixels, NaN elsewhere. pred, gt: [H, W]; mask: [H, W] bool."""
    out = np.full(np.shape(gt), np.nan)  # [H, W]
    g = np.asarray(gt, np.float64)[mask]
    out[mask] = np.abs(np.asarray(pred, np.float64)[mask] - g) / g
    return out


def colourize(values: np.ndarray, vmax: float, cmap: str) -> np.ndarray:
    """Map [H, W] values on [0, vmax] through a matplotlib colormap; NaN -> black.

    Returns [H, W, 3] uint8.
    """
    import matplotlib  # matplotlib: only when error maps are drawn

    values = np.asarray(values, np.float64)
    valid = np.isfinite(values)  # [H, W]
    scaled = np.clip(np.where(valid, values, 0.0) / vmax, 0.0, 1.0)
    rgb = matplotlib.colormaps[cmap](scaled)[..., :3]  # [H, W, 3] float in [0, 1]
    rgb[~valid] = 0.0
    return np.round(rgb * 255.0).astype(np.uint8)


def write_error_maps(folder, frame: str, colour_err: np.ndarray, depth_err: Optional[np.ndarray]) -> list[Path]:
    """Write one frame's maps (names in the module docstring) into the claimed evaluation
    folder. Returns the paths written."""
    folder = Path(folder)
    name = Path(frame).name
    written = [folder / f"{name}_colour.png"]
    with claim_folder(folder, "evaluation", None):
        write_png(written[0], colourize(colour_err, COLOUR_ERROR_MAX, COLOUR_CMAP))
        if depth_err is not None:
            written.append(folder / f"{name}_depth.png")
            write_png(written[1], colourize(depth_err, DEPTH_ERROR_MAX, DEPTH_CMAP))
    return written
