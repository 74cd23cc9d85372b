"""Edge pixels: where a pixel's box-filtered value depends on where in the pixel a ray goes.

One definition for the two sides that need it: the evaluator scores PSNR on these pixels
apart from the rest (eval.metrics.edge_pixels), and training with the `edges` pixel filter
spends several rays on them and one on every other pixel (nerf.train), so the model is
trained and rendered with the filter the ground truth applies where it matters.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

# A colour step between 4-neighbours larger than this (any sRGB channel, on [0, 1]) marks
# both as edge pixels: a texture edge or a shading crease, not the smooth change of shading
# across a surface (a few 1/255 per pixel at 64-512 px).
EDGE_COLOUR_STEP = 0.1
# Alpha within this of 0 or 1 counts as empty or covered: 8-bit rounding, so a straight
# 8-bit ground truth marks exactly its partial pixels, and a rendered opacity of 0.9995
# (density that never quite saturates) is not an edge.
ALPHA_ROUNDING = 0.5 / 255


def edge_mask(rgba: np.ndarray, ids: Optional[np.ndarray] = None, colour_step: float = EDGE_COLOUR_STEP,
              alpha_rounding: float = 0.0) -> np.ndarray:
    """Partial coverage (alpha_rounding < alpha < 1 - alpha_rounding), a boundary between
    instance ids, or a premultiplied colour step above `colour_step` between 4-neighbours;
    the union dilated by one pixel (3 x 3), since a step between two pixel centres blurs
    both of them and their neighbours in a method that resolves the edge a pixel off.

    Args:
        rgba: [H, W, 4] float on [0, 1], straight alpha (checked by the caller).
        ids: [H, W] integer instance ids (0 = none), or None.
    Returns:
        [H, W] bool.
    """
    alpha = rgba[..., 3]
    edges = (alpha > alpha_rounding) & (alpha < 1 - alpha_rounding)
    colour = rgba[..., :3] * alpha[..., None]  # premultiplied: no colour step hides behind alpha 0

    def steps(values: np.ndarray, differs) -> None:
        horizontal = differs(values[:, 1:], values[:, :-1])  # [H, W-1]
        vertical = differs(values[1:], values[:-1])  # [H-1, W]
        edges[:, 1:] |= horizontal
        edges[:, :-1] |= horizontal
        edges[1:] |= vertical
        edges[:-1] |= vertical

    steps(colour, lambda a, b: np.abs(a - b).max(axis=-1) > colour_step)
    if ids is not None:
        steps(ids, lambda a, b: a != b)
    dilated = edges.copy()
    dilated[1:] |= edges[:-1]
    dilated[:-1] |= edges[1:]
    rows = dilated.copy()
    dilated[:, 1:] |= rows[:, :-1]
    dilated[:, :-1] |= rows[:, 1:]
    return dilated
