"""`nerfgauge render RUN` for a splatting run (or a PLY): a split's views as `evaluate` reads them.

For frame "test/r_007" it writes OUT/test/r_007.png (RGBA 8-bit sRGB, straight alpha =
accumulated opacity, colour = F / A: splat.render without its background), OUT/test/r_007_depth.exr
(expected ray distance, 0 where nothing was hit; the EXR says which depth it holds) and
OUT/timing.json: milliseconds per frame (after one warm-up frame), the device, threads and
Gaussian count, and what the frames show (the dataset and the sha256 of its
transforms_<split>.json and scene.json, core.provenance.renders_record), which `evaluate`
checks. The same files, names and headers as nerf/render_views.py writes for a NeRF.

The source is a run folder (splat.train: config.json with "model": "splat", gaussians.ply)
read with the dataset it was trained on, checked against the manifest hash the run recorded
(a dataset regenerated or edited since is refused, naming both hashes), or a PLY in the 3DGS
layout made by any tool (splat.ply) with a dataset to render the cameras of. OUT is claimed as
a nerfgauge "renders" folder whose recipe is the PLY's hash and the dataset's cameras: frames
of other Gaussians are never mixed in (replaced only with overwrite).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from nerfgauge.core import arguments
from nerfgauge.core.dataset import Dataset, open_dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, sha256_file, write_json
from nerfgauge.core.folders import MARKER, claim_folder, read_marker, recipe_hash
from nerfgauge.core.images import write_exr, write_png
from nerfgauge.core.provenance import renders_record, short_hash
from nerfgauge.splat.config import CONFIG, GAUSSIANS, MODEL, SplatConfig
from nerfgauge.splat.gaussians import Gaussians
from nerfgauge.splat.ply import read_ply, sh_degree_of
from nerfgauge.splat.projection import Camera
from nerfgauge.splat.render import backend_for, render
from nerfgauge.splat.train import check_pinhole, pick_device, set_threads


@dataclass(frozen=True)
class Source:
    """What to render: the PLY, the dataset whose cameras to use, the run's config (None for
    a bare PLY)."""

    ply: Path
    dataset: Dataset
    config: SplatConfig | None


def open_source(path, dataset=None) -> Source:
    """A run folder with its own dataset (or `dataset`, which must hold the manifest the run
    recorded), or a PLY file with `dataset` (required)."""
    path = Path(path)
    if path.is_file():
        if dataset is None:
            raise InputError(f"{path} is a PLY of Gaussians: give the dataset whose cameras to render (--dataset)")
        return Source(path, open_dataset(dataset), None)
    if not path.is_dir():
        raise InputError(f"run folder not found: {path}")
    marker = read_marker(path) if not path.is_symlink() else None
    if marker is None or marker["kind"] != "run":
        raise InputError(f"{path} is not a nerfgauge run folder (no {MARKER} of kind run)")
    document = read_json(path / CONFIG)
    config = SplatConfig.from_json(document, str(path / CONFIG))
    recipe = document.get("recipe")
    if not isinstance(recipe, dict) or recipe_hash(recipe) != marker.get("recipe"):
        raise InputError(f"{path / CONFIG} does not hold the recipe {path / MARKER} names (edited or damaged); "
                         "train it again")
    if not (path / GAUSSIANS).is_file():
        raise InputError(f"{path} holds no {GAUSSIANS}: the run did not finish; train it again")
    ds = open_dataset(config.dataset if dataset is None else dataset)
    recorded = recipe.get("dataset_sha256")
    if ds.manifest_sha256 != recorded:
        raise InputError(f"{path} was trained on a dataset with manifest sha256 {short_hash(recorded)} "
                         f"({config.dataset}), but {ds.root / 'manifest.json'} has {short_hash(ds.manifest_sha256)}: "
                         "the dataset changed since training; train again on it, or give the dataset the run was "
                         "trained on")
    return Source(path / GAUSSIANS, ds, config)


def rgba_png(colour: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """Premultiplied colour [H, W, 3] (F, without background) and opacity [H, W] ->
    straight-alpha uint8 [H, W, 4] (colour / opacity where opacity > 1e-6)."""
    alpha = np.clip(opacity, 0, 1)[..., None]
    straight = np.divide(colour, alpha, out=np.zeros_like(colour), where=alpha > 1e-6)
    return np.round(np.concatenate([np.clip(straight, 0, 1), alpha], axis=-1) * 255).astype(np.uint8)


def render_split(source, split: str = "test", out=None, *, dataset=None, threads: int | None = None,
                 device: str | None = None, overwrite: bool = False, progress: bool = True) -> dict:
    """Render every view of `split` from a splatting run folder or a PLY (`source`) into `out`
    (default RUN/renders; required for a PLY). dataset: another copy of the run's dataset (the
    same manifest), or the dataset whose cameras a PLY is rendered with. threads, device:
    default the run's (2 and auto for a PLY). Returns what timing.json holds."""
    if isinstance(source, str) and not source.strip() or isinstance(out, str) and not out.strip():
        raise InputError("the run (or PLY) and --out must be non-empty paths")
    if threads is not None:
        arguments.THREADS.check(threads, "--threads")
    opened = open_source(source, dataset)
    if out is None:
        if opened.config is None:
            raise InputError(f"give --out DIR for the renders of {opened.ply} (a PLY has no run folder)")
        out = Path(source) / "renders"
    threads = threads or (opened.config.threads if opened.config else 2)
    torch_device = pick_device(device or (opened.config.device if opened.config else "auto"))
    cameras = opened.dataset.cameras(split)
    if not cameras.stems:
        raise InputError(f"dataset {opened.dataset.root} has no {split} views")
    check_pinhole(opened.dataset, split)
    recipe = recipe_hash({"gaussians_sha256": sha256_file(opened.ply), "split": split,
                          "cameras": opened.dataset.file_sha256(f"transforms_{split}.json")})
    gaussians = Gaussians.from_arrays(read_ply(opened.ply), device=torch_device)
    with claim_folder(Path(out), "renders", recipe, overwrite=overwrite):
        return _render_into(Path(out), gaussians, opened, split, torch_device, threads, progress)


@torch.no_grad()
def _render_into(out: Path, gaussians: Gaussians, source: Source, split: str, device, threads: int,
                 progress: bool) -> dict:
    set_threads(threads)
    backend = backend_for(device)
    degree = sh_degree_of(gaussians.to_arrays())
    cameras = source.dataset.cameras(split)
    black = torch.zeros(3, device=device)
    activated = gaussians.activated()  # once: the Gaussians do not change between frames
    seconds = []
    for index, stem in enumerate(tqdm(cameras.stems, desc=f"render {split}", unit="frame", disable=not progress)):
        camera = Camera.from_c2w(cameras.c2w[index], cameras.intrinsics, device=device)
        if index == 0:  # warm-up: first-call allocations (and numba's cache load) are not the speed
            render(*activated, camera, black, degree, backend=backend)
        start = time.perf_counter()
        rendered = render(*activated, camera, black, degree, backend=backend)
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
        target = out / stem
        target.parent.mkdir(parents=True, exist_ok=True)
        write_exr(target.with_name(target.name + "_depth.exr"), {"Z": rendered.depth.cpu().numpy().astype(np.float32)},
                  {"nerfgauge_depth": "ray_distance", "nerfgauge_miss": "0"})
        write_png(target.with_name(target.name + ".png"),
                  rgba_png(rendered.rgb.cpu().numpy(), rendered.opacity.cpu().numpy()))
    timing = {"ms_per_frame": 1000 * float(np.mean(seconds)), "frames": len(seconds),
              "resolution": [cameras.intrinsics.width, cameras.intrinsics.height], "device": device.type,
              "threads": threads, "model": MODEL, "gaussians": len(gaussians), "sh_degree": degree,
              "gaussians_file": str(source.ply), "dataset": str(source.dataset.root),
              "dataset_files": renders_record(source.dataset, split)}
    write_json(out / "timing.json", timing)
    return timing
