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


def partial_coverage(alpha: np.ndarray, alpha_rounding: float = ALPHA_ROUNDING) -> np.ndarray:
    """The pixels an outline crosses: alpha_rounding < alpha < 1 - alpha_rounding. alpha:
    [H, W] (or any shape) on [0, 1]. Returns a bool array of its shape."""
    return (alpha > alpha_rounding) & (alpha < 1 - alpha_rounding)


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
    edges = partial_coverage(alpha, alpha_rounding)
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



def changes_towards(rgba: np.ndarray, offsets: np.ndarray, step: float) -> np.ndarray:
    """For each point at `offsets` from every pixel's centre, whether the pixel centres
    around it differ: the centres of the pixel and of its neighbours toward the point (the
    2 x 2 block of centres whose square holds a point off both axes, the pair whose segment
    holds a point on an axis) spread by more than `step` in premultiplied colour or alpha
    (any channel, on [0, 1]). Where they agree, nothing steps between them that a ray
    through them saw, and the point's value follows from theirs; where they differ, an edge
    may pass anywhere between them. The centre itself never counts (its own ray is the
    centre's). Beyond the image border the border pixels repeat: nothing is known there.

    Args:
        rgba: [H, W, 4] float on [0, 1], straight alpha (a render through the pixel centres).
        offsets: [S, 2] (x, y) in pixels from the centre, each in [-0.5, 0.5].
    Returns:
        [S, H, W] bool.
    """
    height, width = rgba.shape[:2]
    alpha = rgba[..., 3]
    # premultiplied: no colour step hides behind alpha 0; channels first, so that the spread
    # over channels is an elementwise maximum of planes (a reduction over a last axis of 4
    # took most of the time at 256 px); the border repeated: [4, H + 2, W + 2]
    planes = [rgba[..., channel] * alpha for channel in range(3)] + [alpha]
    values = np.pad(np.stack(planes), ((0, 0), (1, 1), (1, 1)), mode="edge")
    # each pair and block of neighbouring centres once: horizontal pairs [H, W + 1] (between
    # padded columns b and b + 1 of row i + 1), vertical pairs [H + 1, W], blocks [H + 1, W + 1]
    row_high, row_low = np.maximum(values[:, :, 1:], values[:, :, :-1]), np.minimum(values[:, :, 1:], values[:, :, :-1])
    column_high = np.maximum(values[:, 1:], values[:, :-1])
    column_low = np.minimum(values[:, 1:], values[:, :-1])
    pairs_x = np.maximum.reduce(row_high[:, 1:-1] - row_low[:, 1:-1]) > step
    pairs_y = np.maximum.reduce(column_high[:, :, 1:-1] - column_low[:, :, 1:-1]) > step
    block_high = np.maximum(row_high[:, 1:], row_high[:, :-1])
    blocks = np.maximum.reduce(block_high - np.minimum(row_low[:, 1:], row_low[:, :-1])) > step
    out = np.zeros((len(offsets), height, width), dtype=bool)
    for index, (x, y) in enumerate(np.asarray(offsets, dtype=np.float64)):
        # the pair or block toward the point starts at row i + (y > 0), column j + (x > 0)
        down, right = int(y > 0), int(x > 0)
        if x != 0 and y != 0:
            out[index] = blocks[down:down + height, right:right + width]
        elif x != 0:
            out[index] = pairs_x[:, right:right + width]
        elif y != 0:
            out[index] = pairs_y[down:down + height]
    return out
