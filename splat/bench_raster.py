"""How the rasteriser was chosen: forward + backward of one 128 x 128 view, two designs.

    python -m nerfgauge.splat.bench_raster DATASET [--gaussians 20000,100000] [--threads 2]

(a) "torch-tiles": vectorised torch per batch of tiles, autograd for the backward. Each
    tile's front-to-back list is padded to the batch's longest, alpha is evaluated for
    [tiles, 256 pixels, K] pairs at once and composited with cumprod (the reference's masks),
    autograd keeps every batch's intermediates until backward (memory ~ tiles x 256 x K).
(b) "numba": `splat.raster`, compiled loops parallel over tiles, each Gaussian visited only
    on the pixels of its footprint box inside the tile, hand-written backward.

Both composite the same Gaussians: the DATASET's initial points (sparse/0/points3D.txt), a
random subset of the size asked, isotropic at the points' mean spacing, opacity 0.5,
random degree-3 colour, seen from the first train camera. Printed: wall-clock and process
CPU milliseconds per forward + backward (median of 5 after a warm-up), the (tile, Gaussian)
pairs, and the load average, since on a shared machine wall-clock time says little.
Projection and colour are included in neither figure: they are the same torch code in both.
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np
import torch

from nerfgauge.core.dataset import Dataset
from nerfgauge.splat.gaussians import read_dataset_points
from nerfgauge.splat.projection import Camera, project
from nerfgauge.splat.raster import ALPHA_MAX, T_MIN, rasterise
from nerfgauge.splat.tiles import ALPHA_MIN, TILE, bin_gaussians, footprint_box, tile_grid

TILES_PER_BATCH = 16  # design (a): tiles composited in one tensor


def torch_tiles(means2d, conics, opacities, features, binning, width, height):
    """Design (a): F [H, W, C], A [H, W] by batched torch ops over padded tile lists (autograd)."""
    tiles_x, tiles_y = tile_grid(width, height)
    offsets = torch.from_numpy(binning.offsets)
    ids = torch.from_numpy(binning.ids.astype(np.int64))
    channels = features.shape[1]
    out = torch.zeros(tiles_y * TILE, tiles_x * TILE, channels, dtype=features.dtype)
    alpha_out = torch.zeros(tiles_y * TILE, tiles_x * TILE, dtype=features.dtype)
    local = torch.arange(TILE * TILE)
    rows, cols = torch.div(local, TILE, rounding_mode="floor"), local % TILE  # [256] each
    pieces = []
    for first in range(0, tiles_x * tiles_y, TILES_PER_BATCH):
        tiles = torch.arange(first, min(first + TILES_PER_BATCH, tiles_x * tiles_y))  # [B]
        counts = offsets[tiles + 1] - offsets[tiles]  # [B]
        k_max = int(counts.max()) if len(counts) else 0
        if k_max == 0:
            continue
        slot = torch.arange(k_max)  # [K]
        valid = slot[None, :] < counts[:, None]  # [B, K]
        gathered = ids[(offsets[tiles][:, None] + slot[None, :]).clamp(max=len(ids) - 1)]  # [B, K]
        gathered = torch.where(valid, gathered, torch.zeros_like(gathered))
        px = ((tiles % tiles_x) * TILE)[:, None] + cols[None, :] + 0.5  # [B, 256]
        py = (torch.div(tiles, tiles_x, rounding_mode="floor") * TILE)[:, None] + rows[None, :] + 0.5  # [B, 256]
        dx = means2d[gathered][:, None, :, 0] - px[:, :, None]  # [B, 256, K]
        dy = means2d[gathered][:, None, :, 1] - py[:, :, None]  # [B, 256, K]
        conic = conics[gathered]  # [B, K, 3]
        power = -0.5 * (conic[:, None, :, 0] * dx * dx + conic[:, None, :, 2] * dy * dy) \
            - conic[:, None, :, 1] * dx * dy  # [B, 256, K]
        alpha = torch.clamp(opacities[gathered][:, None, :] * torch.exp(power), max=ALPHA_MAX)  # [B, 256, K]
        drawn = (alpha >= ALPHA_MIN) & (power <= 0) & valid[:, None, :]
        alpha = torch.where(drawn, alpha, torch.zeros_like(alpha))
        after = torch.cumprod(1 - alpha, dim=2)  # [B, 256, K]
        before = torch.cat([torch.ones_like(after[..., :1]), after[..., :-1]], dim=2)
        weights = alpha * before * (after >= T_MIN)  # [B, 256, K]
        pieces.append((tiles, torch.einsum("bpk,bkc->bpc", weights, features[gathered]), weights.sum(dim=2)))
    for tiles, colour, alpha in pieces:
        for b, t in enumerate(tiles.tolist()):
            y0, x0 = (t // tiles_x) * TILE, (t % tiles_x) * TILE
            out[y0:y0 + TILE, x0:x0 + TILE] = colour[b].reshape(TILE, TILE, channels)
            alpha_out[y0:y0 + TILE, x0:x0 + TILE] = alpha[b].reshape(TILE, TILE)
    return out[:height, :width], alpha_out[:height, :width]


def scene(dataset: Dataset, count: int, seed: int = 0):
    points, _ = read_dataset_points(dataset)
    generator = torch.Generator().manual_seed(seed)
    chosen = torch.randperm(len(points), generator=generator)[:count].numpy()
    means = torch.tensor(points[chosen], dtype=torch.float32)
    lo, hi = means.min(0).values, means.max(0).values
    spacing = float(((hi - lo).prod() / max(count, 1)) ** (1 / 3))
    scales = torch.full((len(means), 3), spacing)
    quats = torch.zeros(len(means), 4)
    quats[:, 0] = 1.0
    cameras = dataset.cameras("train")
    camera = Camera.from_c2w(cameras.c2w[0], cameras.intrinsics)
    projected = project(means, scales, quats, camera)
    opacities = torch.full((len(means),), 0.5)
    features = torch.rand(len(means), 4, generator=generator)
    half = footprint_box(projected.cov2d_diagonal, opacities)
    keep = projected.in_front & (half[:, 0] > 0)
    inputs = [projected.means2d[keep].detach(), projected.conics[keep].detach(), opacities[keep], features[keep]]
    binning = bin_gaussians(inputs[0], half[keep], projected.depths[keep].detach(), camera.width, camera.height)
    return inputs, binning, camera


def measure(design, inputs, binning, camera, repeats: int = 5) -> tuple[float, float]:
    """(wall ms, process CPU ms) per forward + backward, medians after one warm-up."""
    walls, cpus = [], []
    for repeat in range(repeats + 1):
        leaves = [t.clone().requires_grad_(True) for t in inputs]
        wall, cpu = time.perf_counter(), time.process_time()
        colour, alpha = design(*leaves, binning, camera.width, camera.height)
        (colour.sum() + alpha.sum()).backward()
        if repeat:
            walls.append(1000 * (time.perf_counter() - wall))
            cpus.append(1000 * (time.process_time() - cpu))
    return float(np.median(walls)), float(np.median(cpus))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--gaussians", default="20000,100000")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--designs", default="torch-tiles,numba")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    numba.set_num_threads(args.threads)
    designs = {"torch-tiles": torch_tiles, "numba": rasterise}
    dataset = Dataset(args.dataset)
    for count in (int(c) for c in args.gaussians.split(",")):
        inputs, binning, camera = scene(dataset, count)
        for name in args.designs.split(","):
            wall, cpu = measure(designs[name], inputs, binning, camera)
            print(f"{name:12s} {count:7d} Gaussians, {len(binning.ids):7d} pairs: {wall:8.1f} ms wall, "
                  f"{cpu:8.1f} ms CPU ({args.threads} threads, load average {os.getloadavg()[0]:.1f})", flush=True)


if __name__ == "__main__":
    main()
