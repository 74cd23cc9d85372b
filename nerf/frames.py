"""One frame of a trained model: its rays through a model, as `nerfgauge render` writes
them and training's end checks them (nerf.train picks an edges run's render filter on the
val views with these).

A frame is rendered through pixel centres, box-filtered over each pixel (the ground
truth's filter, `box_frame`), box-filtered on the centre render's edge pixels only (an
`edges` run), or through a thin lens (`lens_frame`). Colours are premultiplied, depth is
always the pixel-centre rays' (as the dataset's ground truth is).
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from nerfgauge.nerf.config import CHANGE_STEP, SUB_RAYS
from nerfgauge.nerf.data import jittered_direction, pixel_footprints, split_rays
from nerfgauge.nerf.frame_assembly import changing_points, sub_directions, touched_box_means
from nerfgauge.nerf.march_cpu import kernel_threads
from nerfgauge.nerf.rendering import pixel_mean, render_rays_chunked

from nerfgauge.core.camera import lens_samples, thin_lens_rays
from nerfgauge.core.pixel_edges import ALPHA_ROUNDING, changes_towards, edge_mask

# A frame's rays are split into this many parts per thread: rays that hit the scene cost
# far more than rays that miss it, so two halves of an image rarely cost the same, and the
# thread with the cheap half waits. Measured at 256 px on 2 threads: 2 parts 106-122 ms,
# 8 parts 85-88 ms a frame.
PARTS_PER_THREAD = 4
# Rays per pixel along each axis by the run's pixel filter (nerf.config.PIXEL_FILTERS): a
# box-trained model renders the mean of 2 x 2 rays through each pixel, the box filter the
# ground truth applies (docs/conventions.md, "Pixel footprint"); a centre-trained one its
# centre ray. An `edges` run renders by the filter chosen on its val views instead
# (nerf.config.RENDER_FILTERS), when it has one.
PIXEL_SAMPLES = {"box": 2, "jitter": 2, "centre": 1, "edges": 2}
# Pixel filters whose renders spend those rays on edge pixels only: the centre render's
# edges (nerfgauge.core.pixel_edges.edge_mask of the rendered RGBA), as training found them
# on the targets; every other pixel keeps its centre ray.
EDGES_ONLY = ("edges",)


def rgba_png(rgb_premultiplied: np.ndarray, opacity: np.ndarray, height: int, width: int) -> np.ndarray:
    """Premultiplied sRGB [n, 3] and opacity [n] -> straight-alpha uint8 [H, W, 4]."""
    alpha = np.clip(opacity, 0, 1)[:, None]
    straight = np.divide(rgb_premultiplied, alpha, out=np.zeros_like(rgb_premultiplied), where=alpha > 1e-6)
    rgba = np.concatenate([np.clip(straight, 0, 1), alpha], axis=1).reshape(height, width, 4)
    return np.round(rgba * 255).astype(np.uint8)


def renders_compiled(model, device) -> bool:
    """Whether `model` renders a batch of rays on `device` through a compiled kernel on
    threads of its own (RadianceModel.renders_compiled; a stand-in model with only a
    `render` does not)."""
    return getattr(model, "renders_compiled", None) is not None and model.renders_compiled(device)


def compiled_render_threads(model, device, threads: int):
    """A context within which `model` renders on `threads` threads: the compiled kernel's
    (march_cpu.kernel_threads, torch on one meanwhile) when it renders compiled, else
    nothing changes (the caller sets torch's own)."""
    return kernel_threads(threads) if renders_compiled(model, device) else contextlib.nullcontext()


def render_frame(model, origins, directions, pool, parts: int = 1) -> tuple:
    """One frame's rays split into `parts` over the worker threads of `pool` (None: this thread).
    On a CPU, a few threads each running single-threaded ops on part of the rays use the
    cores better than one thread of many small multi-threaded ops (measured: ~1.3x). A
    model that renders compiled (RadianceModel.renders_compiled) takes the frame's rays in
    one batch, which it spreads over its own threads, and needs no pool."""
    if renders_compiled(model, origins.device):
        return render_rays_chunked(model, origins, directions, chunk=max(1, origins.shape[0]))
    if pool is None:
        return render_rays_chunked(model, origins, directions)

    def part(o, d):
        with torch.no_grad():
            return render_rays_chunked(model, o, d)

    chunks = zip(origins.chunk(parts), directions.chunk(parts))
    results = [future.result() for future in [pool.submit(part, o, d) for o, d in chunks]]
    return tuple(torch.cat(column) for column in zip(*results))


def lens_frame(model, cameras, index: int, samples: int, seed: int, pool, parts: int, device) -> tuple:
    """Frame `index` through its thin lens: premultiplied rgb [H*W, 3] and opacity [H*W]
    averaged over `samples` stratified lens samples (seeded by (seed, index)), and the depth
    [H*W] of the pinhole pixel-centre rays."""
    disk = lens_samples(samples, (seed, index))  # [S, 2]
    origins, directions = thin_lens_rays(cameras.c2w[index], cameras.intrinsics, cameras.lens(index), disk)
    o = torch.from_numpy(origins.reshape(-1, 3).astype(np.float32)).to(device)
    d = torch.from_numpy(directions.reshape(-1, 3).astype(np.float32)).to(device)
    rgb, opacity, _ = render_frame(model, o, d, pool, parts)
    pixels = cameras.intrinsics.width * cameras.intrinsics.height
    rgb, opacity = pixel_mean(rgb.view(samples, pixels, 3), opacity.view(samples, pixels))
    centre_o, centre_d = split_rays(cameras, index)
    _, _, depth = render_frame(model, centre_o.to(device), centre_d.to(device), pool, parts)
    return rgb, opacity, depth


def pixel_offsets(per_axis: int) -> np.ndarray:
    """The centres of a per_axis x per_axis grid of equal cells over a pixel, as offsets
    from its centre in pixels, row-major: [per_axis^2, 2] (x, y) in (-0.5, 0.5). Their mean
    is the midpoint rule of the pixel's box filter; 1 gives the centre alone."""
    centres = (np.arange(per_axis) + 0.5) / per_axis - 0.5
    y, x = np.meshgrid(centres, centres, indexing="ij")
    return np.stack([x.ravel(), y.ravel()], axis=-1)


def box_frame(model, cameras, index: int, per_axis: int, pool, parts: int, device,
              edges_only: bool = False, sub_rays: str = "changes", change_step: float = CHANGE_STEP) -> tuple:
    """Frame `index` box-filtered over each pixel as the ground truth is: premultiplied rgb
    [H*W, 3] and opacity [H*W], the means (in linear light: nerf.rendering.pixel_mean) over
    per_axis^2 rays through a regular grid of points in each pixel (`pixel_offsets`), and
    the depth [H*W] of the pixel-centre rays (as the dataset's ground truth is). per_axis 1
    renders the centre rays once.
    edges_only: only where the centre render changes do points get their own rays, by
    `sub_rays` (SUB_RAYS): "changes", the points between centres that differ
    (`changing_points_frame`, centres that differ by more than `change_step`); "edge-pixels",
    every point of the centre render's edge pixels (the render before issue 52)."""
    if sub_rays not in SUB_RAYS:
        raise ValueError(f"sub_rays must be one of {SUB_RAYS}, got {sub_rays!r}")
    origins, directions = cameras.rays(index)  # [H, W, 3] float64
    centre_o = torch.from_numpy(origins.reshape(-1, 3).astype(np.float32)).to(device)
    centre_d = torch.from_numpy(directions.reshape(-1, 3).astype(np.float32)).to(device)
    rgb, opacity, depth = render_frame(model, centre_o, centre_d, pool, parts)
    if per_axis == 1:
        return rgb, opacity, depth
    if edges_only and sub_rays == "changes":
        rgb, opacity = changing_points_frame(model, centre_o, centre_d, directions, cameras.c2w[index], rgb, opacity,
                                             per_axis, pool, parts, change_step)
        return rgb, opacity, depth
    footprint = torch.from_numpy(pixel_footprints(directions, cameras.c2w[index])).to(device)  # [P, 2, 3]
    chosen = slice(None)
    if edges_only:
        height, width = directions.shape[:2]
        straight = rgba_png(rgb.cpu().numpy(), opacity.cpu().numpy(), height, width).astype(np.float64) / 255
        chosen = torch.from_numpy(np.flatnonzero(edge_mask(straight, alpha_rounding=ALPHA_ROUNDING))).to(device)
        if not len(chosen):  # nothing steps inside any pixel: the centre render is the box render
            return rgb, opacity, depth
    offsets = pixel_offsets(per_axis)  # [S, 2]
    # an odd grid's middle point is the pixel's centre, whose ray the centre render holds
    centre_is_a_point = per_axis % 2 == 1
    if centre_is_a_point:
        offsets = np.delete(offsets, len(offsets) // 2, axis=0)
    offsets = torch.from_numpy(offsets.astype(np.float32)).to(device)
    sub_o, sub_d, sub_footprint = centre_o[chosen], centre_d[chosen], footprint[chosen]
    pixels = sub_d.shape[0]
    moved = torch.cat([jittered_direction(sub_d, sub_footprint, offset.expand(pixels, 2)) for offset in offsets])
    sub_rgb, sub_opacity, _ = render_frame(model, sub_o.repeat(len(offsets), 1), moved, pool, parts)
    sub_rgb, sub_opacity = sub_rgb.view(len(offsets), pixels, 3), sub_opacity.view(len(offsets), pixels)
    if centre_is_a_point:
        sub_rgb = torch.cat([sub_rgb, rgb[chosen][None]])
        sub_opacity = torch.cat([sub_opacity, opacity[chosen][None]])
    rgb, opacity = rgb.clone(), opacity.clone()
    rgb[chosen], opacity[chosen] = pixel_mean(sub_rgb, sub_opacity)
    return rgb, opacity, depth


def assembles_compiled(device) -> bool:
    """Whether an edges frame's host work on `device` runs as `nerf.frame_assembly`'s
    compiled loops (on the CPU) rather than as torch ops (on a GPU, where the frame is)."""
    return torch.device(device).type == "cpu"


def changing_points_frame(model, centre_o, centre_d, directions: np.ndarray, c2w: np.ndarray, rgb, opacity,
                          per_axis: int, pool, parts: int, step: float = CHANGE_STEP) -> tuple:
    """The box mean (in linear light) of per_axis x per_axis points over each pixel, with a
    ray only through the points where the centre render changes
    (`nerfgauge.core.pixel_edges.changes_towards` of its 8-bit RGBA, as the PNG holds it):
    the pixel centres around such a point differ by more than `step`, so an edge may pass
    it. Every other point takes the bilinear interpolation of the centres around it, which
    agree to within `step`; a pixel none of whose points changes keeps its centre ray's
    value.

    centre_o, centre_d: [P, 3] the pixel-centre rays (on the model's device); directions:
    [H, W, 3] float64 the same unit directions on the host; c2w: the view's camera-to-world; rgb [P, 3] (premultiplied), opacity [P]:
    their render. Returns rgb [P, 3], opacity [P]. On the CPU the work around the sub-rays'
    render is `nerf.frame_assembly`'s loops (`assembles_compiled`), elsewhere torch ops;
    both compute the same values (to float32 rounding)."""
    height, width = directions.shape[:2]
    offsets = pixel_offsets(per_axis)
    offsets = offsets[np.any(offsets != 0, axis=1)]  # the centre's ray is rendered already
    rgba8 = rgba_png(rgb.cpu().numpy(), opacity.cpu().numpy(), height, width)
    device = rgb.device
    if assembles_compiled(device):
        point, pixel = changing_points(rgba8, offsets, step)
        if not len(point):
            return rgb, opacity
        forward = -np.asarray(c2w, dtype=np.float64)[:3, 2]
        sub_d = torch.from_numpy(sub_directions(directions, forward, offsets, point, pixel))
        sub_rgb, sub_opacity, _ = render_frame(model, centre_o.index_select(0, torch.from_numpy(pixel)), sub_d, pool,
                                               parts)
        means = touched_box_means(rgb.numpy(), opacity.numpy(), height, width, offsets, per_axis % 2 == 1, point,
                                  pixel, sub_rgb.numpy(), sub_opacity.numpy())
        return tuple(torch.from_numpy(part) for part in means)
    changes = changes_towards(rgba8.astype(np.float64) / 255, offsets, step).reshape(len(offsets), -1)  # [S, P]
    touched = np.flatnonzero(changes.any(axis=0))  # pixels with a ray of their own beyond the centre
    if not len(touched):
        return rgb, opacity
    footprint = torch.from_numpy(pixel_footprints(directions, c2w)).to(device)  # [P, 2, 3]
    point, pixel = (torch.from_numpy(part).to(device) for part in np.nonzero(changes))  # row-major: by point
    offset_of = torch.from_numpy(offsets.astype(np.float32)).to(device)  # [S, 2]
    sub_d = jittered_direction(centre_d.index_select(0, pixel), footprint.index_select(0, pixel),
                               offset_of.index_select(0, point))
    sub_rgb, sub_opacity, _ = render_frame(model, centre_o.index_select(0, pixel), sub_d, pool, parts)
    # every point of the touched pixels: interpolated, then the rendered ones put in place
    centre = torch.cat([rgb, opacity[:, None]], dim=1)  # [P, 4]
    touched_t = torch.from_numpy(touched).to(device)
    values = interpolate_centres(centre, height, width, touched_t, offsets)  # [S, T, 4]
    slot = torch.full((height * width,), -1, dtype=torch.long, device=device)
    slot[touched_t] = torch.arange(len(touched), device=device)
    values[point, slot[pixel]] = torch.cat([sub_rgb, sub_opacity[:, None]], dim=1)
    if per_axis % 2 == 1:  # an odd grid's middle point is the centre
        values = torch.cat([values, centre.index_select(0, touched_t)[None]])
    mean_rgb, mean_opacity = pixel_mean(values[..., :3], values[..., 3])
    centre = centre.clone()
    centre[touched_t] = torch.cat([mean_rgb, mean_opacity[:, None]], dim=1)
    return centre[:, :3].contiguous(), centre[:, 3].contiguous()


def interpolate_centres(centre: torch.Tensor, height: int, width: int, pixels: torch.Tensor,
                        offsets: np.ndarray) -> torch.Tensor:
    """Values at `offsets` [S, 2] (x, y pixels) from the centres of `pixels` [T] (row-major
    indices), bilinear between the pixel centres around each point (the border pixels
    repeated beyond the image). centre: [H*W, C]. Returns [S, T, C].
    Every offset in one batch of gathers: a loop over the offsets cost a 4 x 4 render's
    128 px frame about 6 ms of host time (15 offsets, a dozen small ops each)."""
    row, column = (pixels // width)[None], (pixels % width)[None]  # [1, T]
    along = torch.from_numpy(offsets).to(device=centre.device, dtype=centre.dtype)  # [S, 2]
    step = torch.sign(along).long()  # [S, 2]: towards the neighbour the point leans to
    across = (column + step[:, :1]).clamp(0, width - 1)  # [S, T]
    down = (row + step[:, 1:]).clamp(0, height - 1)  # [S, T]
    ax, ay = along[:, 0].abs()[:, None, None], along[:, 1].abs()[:, None, None]  # [S, 1, 1]
    value = ((1 - ax) * (1 - ay)) * centre[row * width + column] + (ax * (1 - ay)) * centre[row * width + across]
    return value + ((1 - ax) * ay) * centre[down * width + column] + (ax * ay) * centre[down * width + across]
