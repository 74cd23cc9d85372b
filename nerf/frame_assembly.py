"""Compiled assembly of an edges frame on the CPU: the host work around the two kernel
passes of `nerf.frames.changing_points_frame` (the centre rays, then the rays through the
points where the centre render changes), as three numba loops.

Each loop computes what the torch and numpy path computes, and tests/test_render_sub_rays.py
checks both against a per-pixel oracle:

- `changing_points`: the (point, pixel) pairs whose neighbouring centres differ, as
  `nerfgauge.core.pixel_edges.changes_towards` finds them on the 8-bit RGBA (the same
  float64 operations, so the same pairs), in its order (by point, then pixel);
- `sub_directions`: the unit direction through each such point, `nerf.data.jittered_direction`
  of `nerf.data.pixel_footprints` (the central differences of the unit-depth directions),
  computed at the pixels that need it rather than over the whole frame;
- `touched_box_means`: every touched pixel's points, rendered where they change and
  interpolated between the centres elsewhere (`nerf.frames.interpolate_centres`), and
  their box mean in linear light (`nerf.rendering.pixel_mean`).

Why compiled: at 128 px the torch and numpy ops around the kernel took about 16 ms of a
1200-s model's 55-65 ms frame (docs/results.md, "Render time"), mostly in a few dozen small
ops over arrays of a frame's size; each loop here touches only the pixels it needs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from nerfgauge.nerf.rendering import STRAIGHT_EPS


@numba.njit(cache=True)
def changing_points(rgba8: np.ndarray, offsets: np.ndarray, step: float) -> tuple:
    """The points whose pixel centres around them spread by more than `step` in
    premultiplied colour or alpha: rgba8 [H, W, 4] uint8 (straight alpha, the PNG's),
    offsets [S, 2] (x, y) pixels, none the centre. Returns point [N], pixel [N] (row-major
    index), int64, ordered by point, then pixel: `changes_towards(...).nonzero()`."""
    height, width = rgba8.shape[0], rgba8.shape[1]
    planes = np.empty((height, width, 4))  # premultiplied, as changes_towards builds them
    for i in range(height):
        for j in range(width):
            alpha = rgba8[i, j, 3] / 255.0
            for channel in range(3):
                planes[i, j, channel] = (rgba8[i, j, channel] / 255.0) * alpha
            planes[i, j, 3] = alpha
    # the centres around a point depend only on the signs of its offset: one test per sign
    # pair (3 x 3 of them, [1, 1] the centre's) and pixel, which the offsets then share
    side = np.empty(offsets.shape[0], np.int64)
    for s in range(offsets.shape[0]):
        side[s] = 3 * (1 + int(np.sign(offsets[s, 1]))) + 1 + int(np.sign(offsets[s, 0]))
    differs = np.zeros((9, height * width), np.bool_)
    for sign in range(9):
        if sign == 4 or not np.any(side == sign):
            continue
        down, across = sign // 3 - 1, sign % 3 - 1
        for i in range(height):
            i2 = min(max(i + down, 0), height - 1)
            for j in range(width):
                j2 = min(max(j + across, 0), width - 1)
                for channel in range(4):
                    a, b = planes[i, j, channel], planes[i, j2, channel]
                    c, d = planes[i2, j, channel], planes[i2, j2, channel]
                    if max(max(a, b), max(c, d)) - min(min(a, b), min(c, d)) > step:
                        differs[sign, i * width + j] = True
                        break
    total = 0
    for s in range(offsets.shape[0]):
        total += np.count_nonzero(differs[side[s]])
    point, pixel = np.empty(total, np.int64), np.empty(total, np.int64)
    k = 0
    for s in range(offsets.shape[0]):
        row = differs[side[s]]
        for p in range(height * width):
            if row[p]:
                point[k], pixel[k] = s, p
                k += 1
    return point, pixel


@numba.njit(cache=True)
def _footprint(directions, forward, i, j, out):
    """`pixel_footprints` at pixel (i, j) into out [2, 3]: the central differences (one-sided
    at the border, none across an axis of one pixel) of the unit-depth directions d / (d . f),
    times the pixel's own d . f."""
    height, width = directions.shape[0], directions.shape[1]
    cosine = directions[i, j, 0] * forward[0] + directions[i, j, 1] * forward[1] + directions[i, j, 2] * forward[2]
    for along in range(2):  # 0: x, along a row (columns); 1: y, down a column (rows)
        size, at = (width, j) if along == 0 else (height, i)
        low, high, half = at - 1, at + 1, True
        if size == 1:
            low, high = at, at
        elif at == 0:
            low, high, half = 0, 1, False
        elif at == size - 1:
            low, high, half = size - 2, size - 1, False
        (i_low, j_low), (i_high, j_high) = ((i, low), (i, high)) if along == 0 else ((low, j), (high, j))
        cos_low = (directions[i_low, j_low, 0] * forward[0] + directions[i_low, j_low, 1] * forward[1]
                   + directions[i_low, j_low, 2] * forward[2])
        cos_high = (directions[i_high, j_high, 0] * forward[0] + directions[i_high, j_high, 1] * forward[1]
                    + directions[i_high, j_high, 2] * forward[2])
        for axis in range(3):
            change = directions[i_high, j_high, axis] / cos_high - directions[i_low, j_low, axis] / cos_low
            out[along, axis] = (change / 2.0 if half else change) * cosine


@numba.njit(cache=True)
def sub_directions(directions: np.ndarray, forward: np.ndarray, offsets: np.ndarray, point: np.ndarray,
                   pixel: np.ndarray) -> np.ndarray:
    """Unit directions [N, 3] float32 through offsets[point] of each pixel: directions [H, W, 3]
    float64 the unit pixel-centre directions, forward [3] the camera's forward axis (c2w's
    -z). The footprint is `pixel_footprints`' (`_footprint`, once a pixel), the direction
    `jittered_direction`'s, in float32 as it is."""
    height, width = directions.shape[0], directions.shape[1]
    footprints = np.empty((height * width, 2, 3), np.float32)
    known = np.zeros(height * width, np.bool_)
    steps = np.empty((2, 3))
    out = np.empty((point.shape[0], 3), np.float32)
    moved = np.empty(3, np.float32)
    for k in range(point.shape[0]):
        p = pixel[k]
        i, j = p // width, p % width
        if not known[p]:
            _footprint(directions, forward, i, j, steps)
            for along in range(2):
                for axis in range(3):
                    footprints[p, along, axis] = steps[along, axis]
            known[p] = True
        x, y = np.float32(offsets[point[k], 0]), np.float32(offsets[point[k], 1])
        for axis in range(3):
            moved[axis] = np.float32(directions[i, j, axis]) + x * footprints[p, 0, axis] + y * footprints[p, 1, axis]
        norm = np.float32(math.sqrt(moved[0] * moved[0] + moved[1] * moved[1] + moved[2] * moved[2]))
        for axis in range(3):
            out[k, axis] = moved[axis] / norm
    return out


# sRGB's transfer in float32 (the torch path's precision): a power of float32 costs half
# of float64's, and a touched pixel of a 4 x 4 grid takes 48 of them
_LOW, _HIGH = np.float32(0.0), np.float32(1.0)


@numba.njit(cache=True, inline="always")
def _srgb_to_linear(x):
    x = min(max(x, _LOW), _HIGH)
    return x / np.float32(12.92) if x <= np.float32(0.04045) else ((x + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4)


@numba.njit(cache=True, inline="always")
def _linear_to_srgb(x):
    x = min(max(x, _LOW), _HIGH)
    return (np.float32(12.92) * x if x <= np.float32(0.0031308)
            else np.float32(1.055) * x ** np.float32(1 / 2.4) - np.float32(0.055))


@numba.njit(cache=True, parallel=True)
def touched_box_means(rgb: np.ndarray, opacity: np.ndarray, height: int, width: int, offsets: np.ndarray,
                      with_centre: bool, point: np.ndarray, pixel: np.ndarray, sub_rgb: np.ndarray,
                      sub_opacity: np.ndarray) -> tuple:
    """The frame with each touched pixel (one that holds a changing point) replaced by the
    box mean, in linear light, of its points: sub_rgb [N, 3] / sub_opacity [N] where
    (point, pixel) changes, else the bilinear interpolation of the centres around the point
    (the border repeated), and the centre itself where with_centre (an odd grid's middle
    point). rgb [P, 3] premultiplied, opacity [P]: the centre render (float32, unchanged).
    Returns new rgb [P, 3], opacity [P] float32. The touched pixels are spread over numba's
    threads, each written by one."""
    samples = offsets.shape[0]
    count = samples + (1 if with_centre else 0)
    slot = np.full(height * width, -1, np.int64)
    touched = 0
    for k in range(point.shape[0]):
        if slot[pixel[k]] < 0:
            slot[pixel[k]] = touched
            touched += 1
    pixels = np.empty(touched, np.int64)
    rendered = np.full((touched, samples), -1, np.int64)  # which sub-ray a point's is (-1: none)
    for k in range(point.shape[0]):
        pixels[slot[pixel[k]]] = pixel[k]
        rendered[slot[pixel[k]], point[k]] = k
    out_rgb, out_opacity = rgb.copy(), opacity.copy()
    for t in numba.prange(touched):
        p = pixels[t]
        i, j = p // width, p % width
        value = np.empty(4, np.float32)
        linear = np.zeros(3, np.float32)
        coverage = np.float32(0.0)
        for s in range(count):
            if s == samples:  # the centre
                for channel in range(3):
                    value[channel] = rgb[p, channel]
                value[3] = opacity[p]
            elif rendered[t, s] >= 0:
                k = rendered[t, s]
                for channel in range(3):
                    value[channel] = sub_rgb[k, channel]
                value[3] = sub_opacity[k]
            else:
                x, y = np.float32(offsets[s, 0]), np.float32(offsets[s, 1])
                j2 = min(max(j + (1 if x > 0 else (-1 if x < 0 else 0)), 0), width - 1)
                i2 = min(max(i + (1 if y > 0 else (-1 if y < 0 else 0)), 0), height - 1)
                ax, ay = abs(x), abs(y)
                w0, w1 = (1 - ax) * (1 - ay), ax * (1 - ay)
                w2, w3 = (1 - ax) * ay, ax * ay
                c1, c2, c3 = i * width + j2, i2 * width + j, i2 * width + j2
                for channel in range(3):
                    value[channel] = (w0 * rgb[p, channel] + w1 * rgb[c1, channel] + w2 * rgb[c2, channel]
                                      + w3 * rgb[c3, channel])
                value[3] = w0 * opacity[p] + w1 * opacity[c1] + w2 * opacity[c2] + w3 * opacity[c3]
            alpha = value[3]
            for channel in range(3):
                linear[channel] += _srgb_to_linear(value[channel] / max(alpha, np.float32(STRAIGHT_EPS))) * alpha
            coverage += alpha
        mean_opacity = coverage / np.float32(count)
        for channel in range(3):
            out_rgb[p, channel] = _linear_to_srgb(linear[channel] / np.float32(count)
                                                  / max(mean_opacity, np.float32(STRAIGHT_EPS))) * mean_opacity
        out_opacity[p] = mean_opacity
    return out_rgb, out_opacity
