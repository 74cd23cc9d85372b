"""Tile binning: which Gaussians can touch which 16 x 16 tile, front to back.

A Gaussian with opacity o and 2D covariance Sigma' changes a pixel only where its alpha
o exp(-q/2) reaches 1/255 (the compositing skips smaller alphas, `raster.ALPHA_MIN`), i.e.
where q(d) = d^T Sigma'^{-1} d <= r(o)^2 with

    r(o)^2 = 2 ln(255 o)                                   (0 when o <= 1/255: never drawn)

That ellipse's bounding box has half extents r(o) sqrt(Sigma'_xx), r(o) sqrt(Sigma'_yy)
(the exact extent of {d : q(d) <= r^2} along each axis), so binning a Gaussian into every
tile holding a pixel centre inside that box drops no pixel where it is drawn: the tiled
rasteriser composites exactly what the brute-force reference does. (3DGS bins a square of
3 sigma of the larger eigenvalue; the box here is never larger and depends on opacity, so
faint Gaussians touch fewer tiles.) BOX_MARGIN widens the box by 1% so float rounding of
the conic never puts a drawn pixel just outside it.

`bin_gaussians` is a counting sort by tile of the Gaussians taken in depth order, so
each tile's list is sorted front to back: offsets [n_tiles + 1] and ids [M] (M = the number
of (tile, Gaussian) pairs: memory grows with the tiles each Gaussian covers, never with
Gaussians x pixels). The rasteriser visits only the pixels of each Gaussian's box inside a
tile (`pixel_span`), the same rule, so it evaluates a pair at about its box's area of pixels
instead of the tile's 256.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch

TILE = 16
ALPHA_MIN = 1.0 / 255.0
BOX_MARGIN = 1.01


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """(tiles across, tiles down) of TILE x TILE tiles covering the image."""
    return -(-width // TILE), -(-height // TILE)


@torch.no_grad()
def footprint_box(cov2d_diagonal: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """Half extents in pixels of the box outside which alpha < 1/255 (the module docstring).
    Not differentiable. cov2d_diagonal: [N, 2] Sigma'_xx, Sigma'_yy; opacities: [N] in [0, 1].
    Returns [N, 2], 0 for a Gaussian never drawn (o <= 1/255)."""
    radius_squared = 2.0 * torch.log(torch.clamp_min(opacities / ALPHA_MIN, 1.0))  # [N]
    return BOX_MARGIN * torch.sqrt(radius_squared[:, None] * cov2d_diagonal)  # [N, 2]


@numba.njit(cache=True)
def pixel_span(centre: float, half: float, size: int) -> tuple[int, int]:
    """First and last pixel index (inclusive) whose centre i + 0.5 lies in [centre - half,
    centre + half], clipped to [0, size - 1]; (1, 0) when none does."""
    low = centre - half - 0.5
    high = centre + half - 0.5
    if not (high >= 0.0 and low <= size - 1.0):  # also refuses NaN
        return 1, 0
    first = 0 if low <= 0.0 else int(math.ceil(low))
    last = size - 1 if high >= size - 1.0 else int(math.floor(high))
    return first, last


@numba.njit(cache=True)
def _bin(means2d, half_extents, order, width, height, tile):
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n = order.shape[0]
    spans = np.empty((n, 4), np.int64)  # tile x0, x1, y0, y1 (inclusive) of order[r]; x0 > x1: none
    counts = np.zeros(tiles_x * tiles_y + 1, np.int64)
    for r in range(n):
        g = order[r]
        px0, px1 = pixel_span(means2d[g, 0], half_extents[g, 0], width)
        py0, py1 = pixel_span(means2d[g, 1], half_extents[g, 1], height)
        if px0 > px1 or py0 > py1 or half_extents[g, 0] <= 0.0:
            spans[r, 0], spans[r, 1] = 1, 0
            continue
        spans[r, 0], spans[r, 1], spans[r, 2], spans[r, 3] = px0 // tile, px1 // tile, py0 // tile, py1 // tile
        for ty in range(spans[r, 2], spans[r, 3] + 1):
            for tx in range(spans[r, 0], spans[r, 1] + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    ids = np.empty(offsets[-1], np.int32)
    cursor = offsets[:-1].copy()
    for r in range(n):  # in depth order: each tile's list comes out sorted front to back
        if spans[r, 0] > spans[r, 1]:
            continue
        for ty in range(spans[r, 2], spans[r, 3] + 1):
            for tx in range(spans[r, 0], spans[r, 1] + 1):
                t = ty * tiles_x + tx
                ids[cursor[t]] = order[r]
                cursor[t] += 1
    return offsets, ids


def depth_order(depths: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """`candidates` [V] (int64 indices into depths [N] float32) sorted by depth, ties in index
    order: what a stable argsort gives, from one sort of unique 64-bit keys (the depth's float32
    bits mapped to an unsigned integer of the same order, above the index), 2.5x faster than
    a stable argsort at 25,000 Gaussians (1.1 against 2.9 ms)."""
    values = depths[candidates].astype(np.float32) + np.float32(0.0)  # [V]; -0.0 + 0.0 is +0.0: equal zeros tie
    bits = values.view(np.uint32).astype(np.uint64)
    negative = bits >= 0x80000000
    ordered = np.where(negative, 0xFFFFFFFF - bits, bits | 0x80000000)  # float order as unsigned order
    keys = np.sort((ordered << np.uint64(32)) | candidates.astype(np.uint64))
    return (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)


class Binning(NamedTuple):
    """Tile t (row-major, `tile_grid`) holds Gaussians ids[offsets[t]:offsets[t + 1]], front
    to back: offsets [n_tiles + 1] int64, ids [M] int32; half_extents [V, 2] float64, the
    footprint boxes the rasteriser limits each Gaussian's pixels to."""

    offsets: np.ndarray
    ids: np.ndarray
    half_extents: np.ndarray


@torch.no_grad()
def bin_gaussians(means2d: torch.Tensor, half_extents: torch.Tensor, depths: torch.Tensor, width: int,
                  height: int, drawn: torch.Tensor | None = None) -> Binning:
    """Each tile's Gaussians front to back. Not differentiable.

    means2d: [N, 2] pixel coordinates; half_extents: [N, 2] (`footprint_box`); depths: [N]
    camera depths (the sort key; ties keep index order); drawn: [V] indices of the Gaussians
    to bin (None: all N). ids index the N Gaussians."""
    candidates = np.arange(depths.shape[0], dtype=np.int64) if drawn is None else drawn.numpy().astype(np.int64)
    order = depth_order(depths.detach().float().numpy(), candidates)
    half = np.ascontiguousarray(half_extents.double().numpy())  # [N, 2]
    offsets, ids = _bin(means2d.detach().double().numpy(), half, order, int(width), int(height), TILE)
    return Binning(offsets, ids, half)
