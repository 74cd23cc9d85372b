"""`nerfgauge train DATASET --model splat`: the splatting training loop.

    train(dataset, out, config)  ->  {"steps", "seconds", "val_psnr", "gaussians", "model_bytes"}

A dataset folder in (read with core.dataset.Dataset, checked against its manifest), a run
folder out, claimed with core.folders.claim_folder as kind "run" under a recipe (the
dataset's manifest hash and every setting that shapes the trajectory, the stopping rule
included: the schedule is in fractions of the run). RUN/ holds:

    config.json     SplatConfig (splat.config) with "model": "splat", the reasons for "auto"
                    choices, and the recipe (nerf.runs and `nerfgauge render` read it)
    log.jsonl       val PSNR (on white, the first eval_views val views) against training
                    seconds, steps/s, loss, Gaussian count
    gaussians.ply   the trained Gaussians in the 3DGS PLY layout (splat.ply), written last:
                    a run without it is unfinished

Each step renders one training view (the views in a seeded random order, a new order each
pass, as the 3DGS code draws them) on a background colour (random per step by default, so
opacity is learnt: the target is the RGBA image composited on the same colour), takes the
loss (splat.loss), steps Adam (splat.gaussians.GaussianAdam, the paper's learning rates and
the exponential position schedule), and runs the density control on its schedule
(splat.density). Training seconds exclude validation. A non-finite loss or gradient stops the
run before the parameters change, and NaN in the parameters after a step stops it too:
`NumericalError` (exit 3).

Devices: a CPU trains with the tiled numba rasteriser (splat.raster); a CUDA device with
gsplat's `rasterization` (splat.render's "gsplat" backend) when gsplat imports. The
CUDA path is not exercised by the tests (no GPU where they ran).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import torch
from tqdm import tqdm

from nerfgauge.core.dataset import Dataset, manifest_sha256, open_dataset
from nerfgauge.core.errors import InputError, NumericalError
from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.core.folders import claim_folder, recipe_hash
from nerfgauge.splat.config import CONFIG, GAUSSIANS, LOG, SplatConfig
from nerfgauge.splat.density import DensityStats, cameras_extent, densify_and_prune, reset_opacity
from nerfgauge.splat.gaussians import GaussianAdam, Gaussians, initial_gaussians, initial_points
from nerfgauge.splat.loss import photometric_loss
from nerfgauge.splat.ply import ply_bytes
from nerfgauge.splat.projection import Camera
from nerfgauge.splat.render import backend_for

# Settings that do not shape the trajectory: the dataset's path (its manifest hash stands for
# it), logging, threads and device.
NOT_RECIPE = ("dataset", "eval_every_seconds", "eval_views", "threads", "device")


def pick_device(name: str) -> torch.device:
    """The torch device for --device: auto (CUDA when present and gsplat imports, else the
    CPU), cpu, cuda or cuda:N (the forms SplatConfig.validate accepts); one line when the
    device cannot be used."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() and _gsplat_imports() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise InputError(f"device {name!r}: no CUDA GPU is available here; use --device cpu or auto")
    if not _gsplat_imports():
        raise InputError(f"device {name!r}: splatting on CUDA rasterises with gsplat, which does not import here "
                         "(pip install gsplat); use --device cpu")
    device = torch.device(name)
    if device.type != "cuda" or (device.index or 0) >= torch.cuda.device_count():
        raise InputError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")
    return device


def _gsplat_imports() -> bool:
    try:
        import gsplat  # noqa: F401  gsplat: optional, the CUDA rasteriser; only asked about here
    except ImportError:
        return False
    return True


def set_threads(threads: int) -> None:
    """`threads` for the compiled kernels (numba: projection, binning, compositing, each parallel
    over Gaussians or tiles; at most the cores numba started with) and one for torch. torch
    does the small per-Gaussian steps here (activations, Adam, the loss), and at 2 threads
    its OpenMP team and numba's took turns spinning on the same two cores: under load a step
    of 50,000 Gaussians at 128 px cost 770 ms CPU against 205 with torch on one thread
    (2 cores, load average 13; one thread each: 169 ms)."""
    torch.set_num_threads(1)
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


@dataclass
class Views:
    """One split's cameras and images: cameras [n] (splat.projection.Camera), rgba [n, H, W, 4]
    float32 straight-alpha sRGB in [0, 1]."""

    cameras: list
    rgba: torch.Tensor


def check_pinhole(ds: Dataset, split: str) -> None:
    """InputError unless the split's frames are plain pinhole views (no lens distortion, no
    thin lens): what the projection models."""
    cameras = ds.cameras(split)
    if cameras.distortion is not None:
        raise InputError(f"dataset {ds.root}: the {split} views have lens distortion; splatting here projects "
                         "through a pinhole (undistort them first)")
    if any(lens is not None and not lens.is_pinhole for lens in cameras.lenses):
        raise InputError(f"dataset {ds.root}: {split} views were rendered through a thin lens; splatting here "
                         "renders pinhole views")


def load_views(ds: Dataset, split: str, device, limit: int | None = None) -> Views:
    check_pinhole(ds, split)
    cameras = ds.cameras(split)
    count = len(cameras.stems) if limit is None else min(limit, len(cameras.stems))
    views = [Camera.from_c2w(cameras.c2w[i], cameras.intrinsics, device=device) for i in range(count)]
    images = [torch.from_numpy(ds.image(split, i)) for i in range(count)]
    rgba = torch.stack(images).to(device) if images else torch.zeros((0, 1, 1, 4), device=device)
    return Views(views, rgba)


def composite(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Straight-alpha [H, W, 4] on a background [3]: rgb a + (1 - a) background. [H, W, 3]."""
    return rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * background


@torch.no_grad()
def psnr_on_white(gaussians: Gaussians, views: Views, sh_degree: int, backend: str) -> float:
    """Mean PSNR over the views, rendered and compared on white (as the evaluator scores)."""
    if not views.cameras:
        return float("nan")
    white = torch.ones(3, device=views.rgba.device)
    scores = []
    for camera, rgba in zip(views.cameras, views.rgba):
        rgb = gaussians.render(camera, white, sh_degree, backend).rgb.clamp(0, 1)
        mse = float(((rgb - composite(rgba, white)) ** 2).mean())
        scores.append(-10 * math.log10(max(mse, 1e-10)))
    return float(np.mean(scores))


def recipe_of(config: SplatConfig, dataset_sha256: str) -> dict:
    return {"dataset_sha256": dataset_sha256} | {k: v for k, v in config.to_json().items() if k not in NOT_RECIPE}


def position_rate(config: SplatConfig, extent: float, progress: float) -> float:
    """lr(t) = extent exp((1 - t) ln lr_position + t ln lr_position_final): the 3DGS code's
    get_expon_lr_func without the delay, over the run's progress t in [0, 1]."""
    t = min(max(progress, 0.0), 1.0)
    if config.lr_position_final <= 0 or config.lr_position <= 0:
        return extent * ((1 - t) * config.lr_position + t * config.lr_position_final)
    return extent * math.exp((1 - t) * math.log(config.lr_position) + t * math.log(config.lr_position_final))


def sh_degree_at(config: SplatConfig, progress: float) -> int:
    """One degree more every sh_degree_every of the run, up to config.sh_degree."""
    if config.sh_degree_every <= 0:
        return config.sh_degree
    return min(config.sh_degree, int(progress / config.sh_degree_every))


def train(dataset, out, config: SplatConfig | None = None, *, overwrite: bool = False, progress: bool = True) -> dict:
    """Train Gaussians on `dataset` (a folder or core.dataset.Dataset) into the run folder `out`.

    config: SplatConfig (its dataset field is set from `dataset`); None: the defaults with a
    120-second budget. overwrite: replace a run of another recipe in `out` (only a nerfgauge
    run folder). A folder holding this recipe's finished run is refused (pass overwrite);
    one whose earlier attempt was stopped before finishing starts over.
    Returns {"steps", "seconds", "val_psnr", "gaussians", "model_bytes"}."""
    if isinstance(out, str) and not out.strip():
        raise InputError("the run folder is an empty path; give --out RUN")
    root = dataset.root if isinstance(dataset, Dataset) else dataset
    config = dataclasses.replace(config or SplatConfig(budget_seconds=120.0), dataset=str(root))
    config.validate()
    device = pick_device(config.device)
    backend = backend_for(device)
    ds = open_dataset(dataset)
    if not ds.cameras("train").stems:
        raise InputError(f"dataset {ds.root} has no training views")
    check_pinhole(ds, "train")
    points, colours, init_reason = initial_points(ds, config)
    recipe = recipe_of(config, manifest_sha256(ds.root) if ds.manifest_sha256 else "foreign")
    out = Path(out)
    with claim_folder(out, "run", recipe_hash(recipe), overwrite=overwrite) as claimed:
        if claimed == "resume":
            if (out / GAUSSIANS).is_file() and not overwrite:
                raise InputError(f"{out} already holds this finished run; pass --overwrite to train it again, or "
                                 "choose another --out")
            for name in (GAUSSIANS, LOG, CONFIG):  # an earlier attempt of this recipe, stopped: start over
                (out / name).unlink(missing_ok=True)
        set_threads(config.threads)
        train_views = load_views(ds, "train", device)
        val_split = "val" if ds.cameras("val").stems else "test"
        val_views = load_views(ds, val_split, device, limit=config.eval_views)
        extent = cameras_extent(ds.cameras("train").c2w[:, :3, 3])
        reasons = {"init": init_reason, "extent": f"{extent:.4g}: 1.1 x the largest distance of a train camera "
                                                  "from their mean (positions' learning rate and size limits)",
                   "backend": f"{backend} ({device.type})", "val_split": f"{val_split}: first {config.eval_views} views"}
        write_json(out / CONFIG, {**config.to_json(), "auto_reasons": reasons, "recipe": recipe})
        gaussians = Gaussians.from_arrays(initial_gaussians(points, colours), device=device)
        return _train_in(out, config, gaussians, train_views, val_views, extent, backend, progress)


def _rates(config: SplatConfig, extent: float) -> dict:
    return {"means": position_rate(config, extent, 0.0), "log_scales": config.lr_scale, "quats": config.lr_rotation,
            "opacity_logits": config.lr_opacity, "sh_dc": config.lr_sh_dc, "sh_rest": config.lr_sh_rest}


def warm_up(gaussians: Gaussians, camera: Camera, backend: str) -> None:
    """Render a copy of the first few Gaussians and take its gradients, so that numba loads
    (or, after an upgrade, compiles: a minute on a loaded 2-core machine) every kernel before
    the training clock starts. Touches nothing the run reads afterwards."""
    count = min(len(gaussians), 64)
    copy = Gaussians(*(tensor.detach()[:count].clone().requires_grad_(True) for tensor in gaussians.tensors().values()))
    rendered = copy.render(camera, torch.zeros(3, device=gaussians.means.device), 3, backend, retain_means2d_grad=True)
    (rendered.rgb.sum() + rendered.depth.sum() + rendered.opacity.sum()).backward()


def _train_in(out: Path, config: SplatConfig, gaussians: Gaussians, train_views: Views, val_views: Views,
              extent: float, backend: str, progress: bool) -> dict:
    warm_up(gaussians, train_views.cameras[0], backend)
    generator = torch.Generator().manual_seed(config.seed)
    adam = GaussianAdam(gaussians, _rates(config, extent))
    stats = DensityStats.zeros(len(gaussians), gaussians.means.device)
    device = gaussians.means.device
    n_views = len(train_views.cameras)
    order: list = []
    step, seconds, next_eval, losses, last_psnr = 0, 0.0, 0.0, [], float("nan")
    total = config.steps if config.steps is not None else config.budget_seconds
    time_format = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
    bar = tqdm(total=total, unit="step" if config.steps else "s", desc="train splat", disable=not progress,
               dynamic_ncols=True, bar_format=None if config.steps else time_format)
    log = (out / LOG).open("a")
    try:
        while True:
            fraction = step / config.steps if config.steps else seconds / config.budget_seconds
            degree = sh_degree_at(config, fraction)
            if seconds >= next_eval or fraction >= 1:
                last_psnr = psnr_on_white(adam.gaussians, val_views, degree, backend)
                entry = {"step": step, "seconds": round(seconds, 3), "val_psnr": last_psnr,
                         "steps_per_second": step / max(seconds, 1e-9), "gaussians": len(adam.gaussians),
                         "sh_degree": degree, "loss": sum(losses) / len(losses) if losses else None}
                losses.clear()
                log.write(json.dumps(entry) + "\n")
                log.flush()
                next_eval = seconds + config.eval_every_seconds
                bar.set_postfix(psnr=f"{last_psnr:.2f}", steps_per_s=f"{entry['steps_per_second']:.1f}",
                                gaussians=len(adam.gaussians), refresh=False)
            if fraction >= 1:
                break
            start = time.perf_counter()
            if not order:
                order = torch.randperm(n_views, generator=generator).tolist()
            view = order.pop()
            densifying = config.densify_from <= fraction < config.densify_until
            adam.group("means")["lr"] = position_rate(config, extent, fraction)
            background = (torch.rand(3, generator=generator) if config.background == "random" else
                          torch.full((3,), 1.0 if config.background == "white" else 0.0)).to(device)
            camera = train_views.cameras[view]
            rendered = adam.gaussians.render(camera, background, degree, backend, retain_means2d_grad=densifying)
            loss = photometric_loss(rendered.rgb, composite(train_views.rgba[view], background), config.ssim_weight)
            adam.zero_grad()
            loss.backward()
            _check_finite(loss, adam, step, "gradient")
            if densifying and rendered.means2d.grad is not None:
                stats.add_view(rendered.means2d.grad, rendered.radii, rendered.visible, camera.width, camera.height)
            adam.step()
            _check_finite(loss, adam, step, "parameter")
            losses.append(float(loss.detach()))
            step += 1
            if densifying and step % config.densify_every == 0:
                densify_and_prune(adam, stats, config, extent, step > config.opacity_reset_every, generator)
                stats = DensityStats.zeros(len(adam.gaussians), device)
            if densifying and step % config.opacity_reset_every == 0:
                reset_opacity(adam)
            elapsed = time.perf_counter() - start
            seconds += elapsed
            bar.update(1 if config.steps else min(elapsed, total - bar.n))
    finally:
        bar.close()
        log.close()
    data = ply_bytes(adam.gaussians.to_arrays())
    write_bytes_atomic(out / GAUSSIANS, data)
    return {"steps": step, "seconds": seconds, "val_psnr": last_psnr, "gaussians": len(adam.gaussians),
            "model_bytes": len(data)}


def _check_finite(loss: torch.Tensor, adam: GaussianAdam, step: int, what: str) -> None:
    """NumericalError when the loss, or every tensor's gradient (what="gradient") or value
    ("parameter"), holds NaN or inf: one sum per tensor."""
    tensors = [getattr(adam.gaussians, name) for name in adam.gaussians.tensors()]
    values = [t.grad for t in tensors if t.grad is not None] if what == "gradient" else tensors
    total = sum(float(v.detach().sum()) for v in values) + float(loss.detach())
    if not math.isfinite(total):
        where = "before the step (the parameters were not updated)" if what == "gradient" else "after the step"
        raise NumericalError(f"splatting diverged at step {step}: NaN or inf in the loss or a {what} {where}")
