"""`nerfgauge render`: a trained run's views, named after the dataset's frames.

For frame "test/r_007" it writes OUT/test/r_007.png (RGBA, sRGB, straight alpha =
opacity) and OUT/test/r_007_depth.exr (expected ray distance, 0 where opacity is 0),
plus OUT/timing.json with milliseconds per frame (model time only, after one warm-up
frame), which `nerfgauge evaluate` copies into its metrics.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from generate.dataset import read_split, write_json
from generate.image_files import write_exr, write_png
from nerf.checkpoint import load_model
from nerf.data import split_rays
from nerf.train import pick_device, render_rays_chunked
from nerfgauge.errors import InputError


def rgba_png(rgb_premultiplied: np.ndarray, opacity: np.ndarray, height: int, width: int) -> np.ndarray:
    """Premultiplied sRGB [n, 3] and opacity [n] -> straight-alpha uint8 [H, W, 4]."""
    alpha = np.clip(opacity, 0, 1)[:, None]
    straight = np.divide(rgb_premultiplied, alpha, out=np.zeros_like(rgb_premultiplied), where=alpha > 1e-6)
    rgba = np.concatenate([np.clip(straight, 0, 1), alpha], axis=1).reshape(height, width, 4)
    return np.round(rgba * 255).astype(np.uint8)


def render_split(run_dir, split: str = "test", out=None, *, threads: int | None = None, progress: bool = True) -> dict:
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    model, config = load_model(run_dir / "model.pt")
    torch.set_num_threads(threads or config.threads)
    device = pick_device(config.device)
    model = model.to(device).eval()
    cameras = read_split(config.dataset, split)
    out = Path(out) if out is not None else run_dir / "renders"
    if out.exists() and not out.is_dir():
        raise InputError(f"output path {out} is a file, not a folder")
    height, width = cameras.intrinsics.height, cameras.intrinsics.width
    seconds = []
    for index, stem in enumerate(tqdm(cameras.stems, desc=f"render {split}", unit="frame", disable=not progress)):
        origins, directions = split_rays(cameras, index)
        if index == 0:  # warm-up: first-call allocations are not the model's speed
            render_rays_chunked(model, origins.to(device), directions.to(device))
        start = time.perf_counter()
        rgb, opacity, depth = render_rays_chunked(model, origins.to(device), directions.to(device))
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
        rgb, opacity, depth = (t.cpu().numpy() for t in (rgb, opacity, depth))
        target = out / stem
        target.parent.mkdir(parents=True, exist_ok=True)
        # Expected depth wherever anything was hit (it is normalised by opacity); silhouette
        # pixels with little opacity still carry the depth of what they partly see.
        depth = depth.astype(np.float32).reshape(height, width)
        write_exr(target.with_name(target.name + "_depth.exr"), {"Z": depth},
                  {"nerfgauge_depth": "ray_distance", "nerfgauge_miss": "0"})
        write_png(target.with_name(target.name + ".png"), rgba_png(rgb, opacity, height, width))
    timing = {"ms_per_frame": 1000 * float(np.mean(seconds)) if seconds else None, "frames": len(seconds),
              "resolution": [width, height], "device": device.type, "threads": torch.get_num_threads(),
              "model": config.model}
    write_json(out / "timing.json", timing)
    return timing
