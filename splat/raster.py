"""The CPU rasteriser: front-to-back alpha compositing per tile, forward and backward.

For a pixel centre p and the Gaussians of its tile in depth order (`tiles.bin_gaussians`),
with d = mu' - p, conic (a, b, c), opacity o and feature vector f (colour, depth, ...):

    power_i = -(a d_x^2 + c d_y^2) / 2 - b d_x d_y
    alpha_i = min(0.99, o_i exp(power_i))           skipped when alpha_i < 1/255 (or power_i > 0)
    T_i     = prod_{j < i, not skipped} (1 - alpha_j)
    F       = sum_i alpha_i T_i f_i,   A = sum_i alpha_i T_i = 1 - T_final

and the loop stops before the first Gaussian that would take T below 1e-4 (3DGS's forward
exactly: alpha clamp 0.99, skip under 1/255, early termination). The background is
composited outside (`render`): C = F_rgb + (1 - A) background.

The backward is 3DGS's, walking each pixel's list back to front: T_i is recovered from
T_final by dividing by (1 - alpha), and the features behind i, S_i = sum_{j > i} alpha_j
(T_j / T_{i+1}) f_j, by the recursion S_{i-1} = alpha_i f_i + (1 - alpha_i) S_i, so that

    dF/df_i     = alpha_i T_i
    dF/dalpha_i = T_i (f_i - S_i)         (and dA/dalpha_i likewise with f = 1)
    dalpha/do   = exp(power),  dalpha/dpower = alpha       (both 0 where the 0.99 clamp holds)
    dpower/dmu' = -(a d_x + b d_y, b d_x + c d_y),  dpower/d(a, b, c) = -(d_x^2 / 2, d_x d_y, d_y^2 / 2)

Unlike 3DGS, the gradient through the clamp is zero (the derivative of what the forward
computes; gsplat does the same), so the brute-force reference (`splat.reference`, torch
autograd) is the exact oracle.

Kernels are compiled with numba and run in parallel over tiles (prange). Each thread owns
its tile's pixels, and the backward writes per (tile, Gaussian) pair into rows of buffers
the caller sums per Gaussian (no two threads write one row), so the result does not depend
on the thread count. Arithmetic inside is float64 whatever the input dtype, outputs are
rounded once to it: the tests compare float32 renders with a float64 oracle to a few ulps.
Memory: the per-pair gradient rows, M x (6 + C) float64 (M pairs, `tiles`), summed per
Gaussian afterwards, and the image.

Designs measured (forward + backward of one 128 x 128 view of the primitives dataset's surface
points, `python -m nerfgauge.splat.bench_raster DATASET`; a shared 2-core machine, so CPU
milliseconds, with the load average, say more than wall time):

    (a) batched torch ops per 16 tiles, autograd       20k Gaussians: 9,585 ms CPU, 5.6 GB peak
        (bench_raster.torch_tiles)                     (2 threads, load 16.6); 100k: not run, it
                                                       would not fit the machine's 23 GB
    (b) numba, every pixel walking its tile's list     20k: 764 ms wall (1 torch + 2 numba
        (3DGS's CUDA loop)                             threads, load 11, whole-step script)
    (b) numba, each Gaussian over its box's pixels     20k: 225 ms wall, same script and load;
        in the tile (this module)                      bench_raster: 20k 52 ms CPU, 100k 152 ms
                                                       CPU (1 thread, load 10); 2 threads 112 and
                                                       228 ms CPU (load 10: no core to spare)
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from nerfgauge.splat.tiles import ALPHA_MIN, TILE, pixel_span, tile_grid

ALPHA_MAX = 0.99
T_MIN = 1e-4
PAIR_FEATURES = 6  # a pair's gradient row: mean (2), conic (3), opacity (1), then the features
CUTOFF_MARGIN = 1e-9


@numba.njit(cache=True, inline="always")
def _cutoff(o):
    """The power below which o exp(power) < 1/255 for certain (CUTOFF_MARGIN short of the
    exact bound, so no pair near it is skipped unevaluated): saves the exp there."""
    return math.log(ALPHA_MIN / o) - CUTOFF_MARGIN if o > 0.0 else math.inf


@numba.njit(cache=True, inline="always")
def _alpha(mx, my, a, b, c, o, cutoff, px, py):
    """(alpha, raw = o exp(power), power) of one Gaussian at pixel centre (px, py); alpha 0
    where the pair is skipped (power > 0, or below `cutoff`: alpha < 1/255)."""
    dx = mx - px
    dy = my - py
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    if power > 0.0 or power < cutoff:
        return 0.0, 0.0, power
    raw = o * np.exp(power)
    return min(ALPHA_MAX, raw), raw, power


@numba.njit(cache=True, inline="always")
def _pair(means2d, conics, opacities, half_extents, g, x0, y0, width, height):
    """What a (tile at x0, y0; Gaussian g) pair reads: mean, conic, opacity, its exp cutoff,
    and the pixels of its footprint box inside the tile (first, last in x and y)."""
    mx, my, o = means2d[g, 0], means2d[g, 1], opacities[g]
    px0, px1 = _span_in_tile(mx, half_extents[g, 0], x0, width)
    py0, py1 = _span_in_tile(my, half_extents[g, 1], y0, height)
    return mx, my, conics[g, 0], conics[g, 1], conics[g, 2], o, _cutoff(o), px0, px1, py0, py1


@numba.njit(cache=True, inline="always")
def _span_in_tile(centre, half, origin, size):
    """First and last pixel (inclusive, image coordinates) of the tile starting at `origin`
    whose centre lies in [centre - half, centre + half]: the Gaussian's footprint box
    (`tiles.footprint_box`), outside which its alpha is below 1/255."""
    first, last = pixel_span(centre, half, size)
    return max(first, origin), min(last, origin + TILE - 1)


@numba.njit(parallel=True, cache=True)
def _forward(means2d, conics, opacities, features, half_extents, offsets, ids, width, height, out_features, out_t,
             out_last):
    tiles_x = (width + TILE - 1) // TILE
    n_tiles = offsets.shape[0] - 1
    channels = features.shape[1]
    for t in numba.prange(n_tiles):
        start, end = offsets[t], offsets[t + 1]
        x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        transmittance = np.ones(TILE * TILE)  # per pixel of the tile, row-major
        acc = np.zeros((TILE * TILE, channels))
        last = np.full(TILE * TILE, start)  # one past the last pair composited
        done = np.zeros(TILE * TILE, np.bool_)
        alive = min(TILE, width - x0) * min(TILE, height - y0)
        for k in range(start, end):  # Gaussians front to back, each over the pixels of its box
            g = ids[k]
            mx, my, a, b, c, o, cutoff, px0, px1, py0, py1 = _pair(means2d, conics, opacities, half_extents, g, x0,
                                                                    y0, width, height)
            for py in range(py0, py1 + 1):
                for px in range(px0, px1 + 1):
                    p = (py - y0) * TILE + (px - x0)
                    if done[p]:
                        continue
                    alpha, raw, power = _alpha(mx, my, a, b, c, o, cutoff, px + 0.5, py + 0.5)
                    if alpha < ALPHA_MIN:
                        continue
                    after = transmittance[p] * (1.0 - alpha)
                    if after < T_MIN:  # this pixel is finished: nothing behind it counts
                        done[p] = True
                        alive -= 1
                        continue
                    weight = alpha * transmittance[p]
                    for ch in range(channels):
                        acc[p, ch] += weight * features[g, ch]
                    transmittance[p] = after
                    last[p] = k + 1
            if alive == 0:
                break
        for py in range(y0, min(y0 + TILE, height)):
            for px in range(x0, min(x0 + TILE, width)):
                p = (py - y0) * TILE + (px - x0)
                for ch in range(channels):
                    out_features[py, px, ch] = acc[p, ch]
                out_t[py, px] = transmittance[p]
                out_last[py, px] = last[p]


@numba.njit(parallel=True, cache=True)
def _backward(means2d, conics, opacities, features, half_extents, offsets, ids, width, height, final_t, last,
              grad_features, grad_alpha, g_pairs):
    tiles_x = (width + TILE - 1) // TILE
    n_tiles = offsets.shape[0] - 1
    channels = features.shape[1]
    for t in numba.prange(n_tiles):
        start, end = offsets[t], offsets[t + 1]
        x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        transmittance = np.ones(TILE * TILE)
        behind = np.zeros((TILE * TILE, channels))  # S: the features behind, normalised
        behind_alpha = np.zeros(TILE * TILE)
        for py in range(y0, min(y0 + TILE, height)):
            for px in range(x0, min(x0 + TILE, width)):
                transmittance[(py - y0) * TILE + (px - x0)] = final_t[py, px]
        for k in range(end - 1, start - 1, -1):  # back to front
            g = ids[k]
            mx, my, a, b, c, o, cutoff, px0, px1, py0, py1 = _pair(means2d, conics, opacities, half_extents, g, x0,
                                                                    y0, width, height)
            for py in range(py0, py1 + 1):
                for px in range(px0, px1 + 1):
                    if k >= last[py, px]:
                        continue  # behind where the forward stopped
                    p = (py - y0) * TILE + (px - x0)
                    alpha, raw, power = _alpha(mx, my, a, b, c, o, cutoff, px + 0.5, py + 0.5)
                    if alpha < ALPHA_MIN:
                        continue
                    transmittance[p] /= 1.0 - alpha  # T_i, before this Gaussian
                    weight = alpha * transmittance[p]
                    d_alpha = (1.0 - behind_alpha[p]) * grad_alpha[py, px]
                    for ch in range(channels):
                        f = features[g, ch]
                        g_pairs[k, PAIR_FEATURES + ch] += weight * grad_features[py, px, ch]
                        d_alpha += (f - behind[p, ch]) * grad_features[py, px, ch]
                        behind[p, ch] = alpha * f + (1.0 - alpha) * behind[p, ch]
                    behind_alpha[p] = alpha + (1.0 - alpha) * behind_alpha[p]
                    if raw > ALPHA_MAX:
                        continue  # clamped: alpha does not move with o or power
                    d_alpha *= transmittance[p]
                    g_pairs[k, 5] += np.exp(power) * d_alpha  # opacity
                    d_power = raw * d_alpha
                    dx, dy = mx - (px + 0.5), my - (py + 0.5)
                    g_pairs[k, 0] -= d_power * (a * dx + b * dy)  # mean
                    g_pairs[k, 1] -= d_power * (b * dx + c * dy)
                    g_pairs[k, 2] -= 0.5 * d_power * dx * dx  # conic
                    g_pairs[k, 3] -= d_power * dx * dy
                    g_pairs[k, 4] -= 0.5 * d_power * dy * dy


@numba.njit(cache=True)
def _sum_pairs(ids, rows, out):
    """out[g] += rows[k] for every pair k of Gaussian g = ids[k] (serial: rows of one Gaussian
    come from several tiles)."""
    for k in range(ids.shape[0]):
        g = ids[k]
        for column in range(rows.shape[1]):
            out[g, column] += rows[k, column]


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


class RasteriseTiles(torch.autograd.Function):
    """(means2d [N, 2], conics [N, 3], opacities [N], features [N, C]) -> (F [H, W, C], A [H, W])
    with the binning (offsets, ids, half extents) of `tiles.bin_gaussians`; differentiable in
    the four tensors (zero gradient for Gaussians in no tile)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, half_extents, offsets, ids, width, height):
        channels = features.shape[1]
        out_features = np.zeros((height, width, channels), _numpy(features).dtype)  # [H, W, C]
        out_t = np.ones((height, width), np.float64)  # [H, W]
        out_last = np.zeros((height, width), np.int64)  # [H, W]: one past the last pair composited
        if len(ids):
            _forward(_numpy(means2d), _numpy(conics), _numpy(opacities), _numpy(features), half_extents, offsets, ids,
                     width, height, out_features, out_t, out_last)
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.binning = (half_extents, offsets, ids, width, height, out_t, out_last)
        alpha = torch.from_numpy((1.0 - out_t).astype(out_features.dtype))
        return torch.from_numpy(out_features), alpha

    @staticmethod
    def backward(ctx, grad_features, grad_alpha):
        means2d, conics, opacities, features = ctx.saved_tensors
        half_extents, offsets, ids, width, height, out_t, out_last = ctx.binning
        pairs, channels = len(ids), features.shape[1]
        g_pairs = np.zeros((pairs, PAIR_FEATURES + channels))  # [M, 6 + C] per (tile, Gaussian)
        if grad_features is None:
            grad_features = torch.zeros((height, width, channels), dtype=features.dtype)
        if grad_alpha is None:
            grad_alpha = torch.zeros((height, width), dtype=features.dtype)
        if pairs:
            _backward(_numpy(means2d), _numpy(conics), _numpy(opacities), _numpy(features), half_extents, offsets,
                      ids, width, height, out_t, out_last, _numpy(grad_features).astype(np.float64),
                      _numpy(grad_alpha).astype(np.float64), g_pairs)
        totals = np.zeros((means2d.shape[0], PAIR_FEATURES + channels))  # [N, 6 + C]
        _sum_pairs(ids, g_pairs, totals)
        totals = torch.from_numpy(totals).to(features.dtype)
        return (totals[:, 0:2], totals[:, 2:5], totals[:, 5], totals[:, PAIR_FEATURES:], None, None, None, None, None)


def rasterise(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
              binning: tuple, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite the binned Gaussians front to back in every tile (module docstring), on the CPU.

    means2d: [N, 2] pixel coordinates; conics: [N, 3]; opacities: [N] in [0, 1]; features:
    [N, C]; binning: `tiles.bin_gaussians` of these N Gaussians (those it leaves out, e.g. not
    drawn, are read nowhere).
    Returns F [H, W, C] = sum_i alpha_i T_i f_i and A [H, W] (accumulated alpha), both
    differentiable (the backward is hand-written: `RasteriseTiles`)."""
    tiles_x, tiles_y = tile_grid(width, height)
    if len(binning.offsets) != tiles_x * tiles_y + 1:
        raise ValueError(f"binning has {len(binning.offsets) - 1} tiles; a {width} x {height} image has "
                         f"{tiles_x * tiles_y}")
    if binning.half_extents.shape != (means2d.shape[0], 2):
        raise ValueError(f"binning is of {binning.half_extents.shape[0]} Gaussians, got {means2d.shape[0]}")
    return RasteriseTiles.apply(means2d, conics, opacities, features, binning.half_extents, binning.offsets,
                                binning.ids, int(width), int(height))
