"""`nerfgauge render`: a trained run's views, named after the dataset's frames.

For frame "test/r_007" it writes OUT/test/r_007.png (RGBA, sRGB, straight alpha =
opacity) and OUT/test/r_007_depth.exr (expected ray distance, 0 where opacity is 0),
plus OUT/timing.json with milliseconds per frame (model time only, after one warm-up
frame; wall time, and every thread's CPU time), the render settings and what the frames show: the dataset's path and the sha256
of its transforms_<split>.json and scene.json (the cameras and the scene), which
`nerfgauge evaluate` copies into its metrics and checks (it refuses to score these
renders against a dataset with other cameras or another scene).

The dataset is the run's own, checked against the manifest hash the run recorded
(nerf.runs.open_run_dataset): a dataset folder regenerated or edited since training is
refused, naming both hashes.

A frame whose transforms entry has a thin lens ("lens": aperture_radius, focus_distance;
see docs/conventions.md) is rendered through it: its colour is the mean of
`aperture_samples` renders of thin-lens rays (nerfgauge.core.camera.thin_lens_rays), one
per stratified concentric-disc lens sample seeded by (lens_seed, frame index), so a
rerender is identical; its depth is still that of the pinhole pixel-centre rays (as the
dataset's ground truth is). A lens with aperture 0 renders the pinhole path unchanged.
The cost is aperture_samples + 1 pinhole renders per lens frame.

OUT is claimed as a nerfgauge "renders" folder whose recipe is the model file's hash and
the step ratio: frames of another model are never mixed in (replaced only with overwrite),
and a folder nerfgauge did not make is never written into.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from nerfgauge.nerf.checkpoint import load_model
from nerfgauge.nerf.config import CHANGE_STEP, RENDER_FILTERS, SUB_RAYS, pixel_filter_for
from nerfgauge.nerf.data import split_rays
from nerfgauge.nerf.frames import (EDGES_ONLY, PARTS_PER_THREAD, PIXEL_SAMPLES, box_frame, compiled_render_threads,
                                   lens_frame, render_frame, renders_compiled, rgba_png)
from nerfgauge.nerf.runs import open_run_dataset
from nerfgauge.nerf.train import pick_device
from nerfgauge.core.progress import progress as progress_bar

from nerfgauge.core import arguments, owned
from nerfgauge.core.dataset import DEPTH_CHANNEL
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import sha256_file, write_json
from nerfgauge.core.folders import claim_folder, recipe_hash
from nerfgauge.core.images import write_exr, write_png
from nerfgauge.core.provenance import renders_record

# Marching step at render time, in voxels; None: the step the run trained with (half a voxel
# in bounded and forward space, one in contracted space). A whole voxel once rendered ~1.6x
# faster for -0.2 dB; since coarse to fine sharpens the surfaces (nerf.grid_field.
# SHARPEN_ALPHA) it costs 0.9-1.1 dB: primitives 128 px, 120 s, 38.74 against 39.64 dB
# (centre rays), 41.06 against 42.12 (edges filter), 600 s 40.88 against 43.15 (BENCHMARKS.md,
# "Edge pixels"), for about the same render time there (33.6 ms at 128 px, centre rays).
RENDER_STEP_RATIO = None
APERTURE_SAMPLES = 16  # lens samples per pixel of a thin-lens frame (--aperture-samples)


def render_split(run_dir, split: str = "test", out=None, *, threads: int | None = None,
                 step_ratio: float | None = RENDER_STEP_RATIO, overwrite: bool = False, progress: bool = True,
                 aperture_samples: int = APERTURE_SAMPLES, lens_seed: int = 0, dataset=None,
                 other_dataset: bool = False, pixel_samples: int | None = None, sub_rays: str = SUB_RAYS[0],
                 change_step: float | None = None) -> dict:
    """Render every view of `split` into `out` (default RUN/renders). step_ratio: marching
    step in voxels for the compact model (None: the run's training step).
    aperture_samples, lens_seed: lens samples per pixel and their seed for frames with a
    thin lens. dataset: render this dataset's views instead of the training dataset's: one
    with the manifest the run recorded (a moved copy), or with other_dataset=True another
    dataset of the scene the run was trained on (e.g. the same cameras through a lens);
    see nerf.runs.open_run_dataset, which refuses any other. pixel_samples: rays per pixel
    along each axis (`box_frame`); None: the run's pixel filter's (PIXEL_SAMPLES). sub_rays:
    which points an edges run gives rays of their own (nerf.config.SUB_RAYS, `box_frame`);
    change_step: with "changes", how far apart two centres must be for the points between
    them to get rays (nerf.config.CHANGE_STEP says what smaller steps give and cost); None:
    the step the run chose on its val views (render_change_step), else CHANGE_STEP."""
    if isinstance(run_dir, str) and not run_dir.strip() or isinstance(out, str) and not out.strip():
        raise InputError("the run folder and --out must be non-empty paths")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    if step_ratio is not None:
        arguments.STEP_RATIO.check(step_ratio, "--step-ratio")
    if threads is not None:
        arguments.THREADS.check(threads, "--threads")
    arguments.LENS_SAMPLES.check(aperture_samples, "--aperture-samples")
    arguments.SEED.check(lens_seed, "--lens-seed")
    if pixel_samples is not None:
        arguments.PIXEL_SAMPLES.check(pixel_samples, "--pixel-samples")
    if sub_rays not in SUB_RAYS:
        raise InputError(f"--sub-rays must be one of {', '.join(SUB_RAYS)}, got {sub_rays!r}")
    if change_step is not None:
        arguments.CHANGE_STEP.check(change_step, "--change-step")
    model, config = load_model(run_dir / "model.pt")
    if change_step is None:
        change_step = CHANGE_STEP if config.render_change_step is None else config.render_change_step
    pixel_filter = pixel_filter_for(config)[0]
    per_axis = PIXEL_SAMPLES[pixel_filter]
    if pixel_filter in EDGES_ONLY and config.render_filter is not None:  # chosen on the val views (nerf.train)
        per_axis = RENDER_FILTERS[config.render_filter]
        pixel_filter = "centre" if per_axis == 1 else pixel_filter
    pixel_samples = per_axis if pixel_samples is None else pixel_samples
    threads = threads or config.threads
    device = pick_device(config.device)
    if other_dataset and dataset is None:
        raise InputError("--other-dataset goes with --dataset DATASET (the dataset whose cameras to render)")
    source = open_run_dataset(run_dir, config, dataset, other_dataset=other_dataset)
    cameras = source.cameras(split)
    lens = {"aperture_samples": aperture_samples, "lens_seed": lens_seed} if cameras.lenses else None
    out = Path(out) if out is not None else run_dir / "renders"
    # The lens settings and another dataset are part of the recipe only when used, so a
    # pinhole render keeps the recipe it always had.
    recipe = recipe_hash({"model_sha256": sha256_file(run_dir / "model.pt"), "step_ratio": step_ratio}
                         | ({"lens": lens} if lens else {}) | ({"dataset": str(dataset)} if dataset is not None else {})
                         | ({"pixel_samples": pixel_samples} if pixel_samples != 1 else {})
                         | ({"edges_only": True} if pixel_filter in EDGES_ONLY else {})
                         | ({"sub_rays": sub_rays} if pixel_filter in EDGES_ONLY and sub_rays != "edge-pixels" else {})
                         | ({"change_step": change_step} if pixel_filter in EDGES_ONLY and sub_rays == "changes"
                            and change_step != CHANGE_STEP else {}))
    with claim_folder(out, "renders", recipe, overwrite=overwrite):
        return _render_into(out, model, config, cameras, split, device, threads, step_ratio, progress, lens,
                            source, pixel_samples, edges_only=pixel_filter in EDGES_ONLY, sub_rays=sub_rays,
                            change_step=change_step)


def _render_into(out: Path, model, config, cameras, split, device, threads, step_ratio, progress, lens=None,
                 source=None, pixel_samples: int = 1, edges_only: bool = False, sub_rays: str = SUB_RAYS[0],
                 change_step: float = CHANGE_STEP) -> dict:
    model = model.to(device).eval()
    if model.has_grid and step_ratio is not None:
        model.field.step_ratio = step_ratio
    # torch ops on part of the rays in each of a pool's threads, or one compiled kernel that
    # spreads every batch of rays over the threads itself (CompactNeRF.renders_compiled)
    compiled = renders_compiled(model, device)
    pool = ThreadPoolExecutor(threads) if device.type == "cpu" and threads > 1 and not compiled else None
    parts = threads * PARTS_PER_THREAD
    torch.set_num_threads(1 if pool is not None else threads)
    with compiled_render_threads(model, device, threads):
        return _render_frames(out, model, config, cameras, split, device, threads, pool, parts, progress, lens,
                              source, pixel_samples, edges_only, sub_rays, change_step)


def _render_frames(out: Path, model, config, cameras, split, device, threads, pool, parts, progress, lens, source,
                   pixel_samples: int, edges_only: bool, sub_rays: str, change_step: float) -> dict:
    height, width = cameras.intrinsics.height, cameras.intrinsics.width
    seconds, lens_seconds, cpu_seconds = [], [], []
    try:
        for index, stem in enumerate(progress_bar(cameras.stems, desc=f"render {split}", unit="frame", enabled=progress)):
            through_lens = lens is not None and cameras.lens(index) is not None and not cameras.lens(index).is_pinhole
            if index == 0:  # warm-up, the frame's whole render: first-call allocations are not the model's speed
                if through_lens:
                    origins, directions = split_rays(cameras, index)
                    render_frame(model, origins.to(device), directions.to(device), pool, parts)
                else:
                    box_frame(model, cameras, index, pixel_samples, pool, parts, device, edges_only, sub_rays,
                              change_step)
            start, cpu_start = time.perf_counter(), time.process_time()
            if through_lens:
                rgb, opacity, depth = lens_frame(model, cameras, index, lens["aperture_samples"], lens["lens_seed"],
                                                 pool, parts, device)
            else:
                rgb, opacity, depth = box_frame(model, cameras, index, pixel_samples, pool, parts, device, edges_only,
                                                sub_rays, change_step)
            if device.type == "cuda":
                torch.cuda.synchronize()
            (lens_seconds if through_lens else seconds).append(time.perf_counter() - start)
            cpu_seconds.append(time.process_time() - cpu_start)
            rgb, opacity, depth = (t.cpu().numpy() for t in (rgb, opacity, depth))
            target = out / stem
            owned.make_folder(target.parent)
            # Expected depth wherever anything was hit (it is normalised by opacity); silhouette
            # pixels with little opacity still carry the depth of what they partly see.
            depth = depth.astype(np.float32).reshape(height, width)
            write_exr(target.with_name(target.name + "_depth.exr"), {DEPTH_CHANNEL: depth},
                      {"nerfgauge_depth": "ray_distance", "nerfgauge_miss": "0"})
            write_png(target.with_name(target.name + ".png"), rgba_png(rgb, opacity, height, width))
    finally:
        if pool is not None:
            pool.shutdown()
    all_seconds = seconds + lens_seconds
    # CPU time of every thread of this process: the work a frame took, which a shared
    # machine's load does not inflate as it does the wall time
    timing = {"ms_per_frame": 1000 * float(np.mean(all_seconds)) if all_seconds else None, "frames": len(all_seconds),
              "cpu_ms_per_frame": 1000 * float(np.mean(cpu_seconds)) if cpu_seconds else None,
              "resolution": [width, height], "device": device.type, "threads": threads,
              "model": config.model, "step_ratio": getattr(getattr(model, "field", None), "step_ratio", None),
              "pixel_samples": pixel_samples} | ({"edges_only": True} if edges_only else {})
    if edges_only and pixel_samples > 1:
        timing["sub_rays"] = sub_rays
        if sub_rays == "changes":
            timing["change_step"] = change_step
    if source is not None:  # what the frames show, which `evaluate` checks (core.provenance.check_renders_dataset)
        timing |= {"dataset": str(source.root), "dataset_files": renders_record(source, split)}
    if lens is not None:  # the thin-lens frames' own cost, beside the pinhole frames'
        timing |= {"aperture_samples": lens["aperture_samples"], "lens_seed": lens["lens_seed"],
                   "lens_frames": len(lens_seconds),
                   "ms_per_lens_frame": 1000 * float(np.mean(lens_seconds)) if lens_seconds else None,
                   "ms_per_pinhole_frame": 1000 * float(np.mean(seconds)) if seconds else None}
    write_json(out / "timing.json", timing)
    return timing
