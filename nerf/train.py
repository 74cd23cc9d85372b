"""`nerfgauge train`: the one training loop, for both models.

RUN/ holds config.json (resolved, with the reasons for each automatic choice), log.jsonl
(val PSNR against training seconds: the speed-vs-error curve of this run), checkpoint.pt
(full state, for --resume) and model.pt (the saved, pruned model). Training seconds
exclude validation and checkpointing, so curves from different runs compare.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import torch
from nerfgauge.nerf import checkpoint
from nerfgauge.nerf.config import TrainConfig, resolve
from nerfgauge.nerf.data import aabb_from_cameras, load_split_rays, scene_info
from nerfgauge.nerf.rendering import composite
from tqdm import tqdm

from nerfgauge.core.dataset import read_split, require_complete
from nerfgauge.core.errors import InputError, NumericalError
from nerfgauge.core.files import write_bytes_atomic, write_json

OCCUPANCY_EVERY = 16  # steps between occupancy-grid updates
UPSAMPLE_AT = (0.1, 0.2, 0.3)  # fractions of the budget where the grid resolution grows ...
MIN_STAGE_STEPS = 100  # ... once the coarser grid had this many steps (short budgets need them)
VISIBILITY_AT = (0.4, 0.7, 1.0)  # fractions where hidden cells are measured and skipped
VISIBILITY_RAY_STRIDE = 4  # every 4th training ray is enough to see every visible cell
LR_FINAL_FRACTION = 0.1  # learning rate decays exponentially to this fraction
# checkpoint.pt (grid + Adam state: ~0.5 GB at 220^3) is rewritten at a log point only
# when this much wall time has passed since the last one, and always at the end: with
# dense logging (bench scaling logs every 2 s) writing it at every point doubled wall time.
CHECKPOINT_EVERY_WALL_SECONDS = 60.0


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(name)
    except RuntimeError:
        raise InputError(f"unknown device {name!r}") from None


@torch.no_grad()
def render_rays_chunked(model, origins, directions, chunk: int = 16384):
    """Render many rays in chunks. Returns premultiplied rgb [n, 3], opacity [n], depth [n]."""
    rgb, opacity, depth = [], [], []
    for start in range(0, origins.shape[0], chunk):
        out = model.render(origins[start:start + chunk], directions[start:start + chunk])
        rgb.append(out.rgb), opacity.append(out.opacity), depth.append(out.depth)
    return torch.cat(rgb), torch.cat(opacity), torch.cat(depth)


def psnr_on_white(model, rays, device, max_rays: int) -> float:
    """Mean PSNR over the views in `rays` (composited on white), on an evenly strided subset
    of at most `max_rays` pixels per evaluation: the same pixels every time, so the curve
    is consistent, and cheap enough to log often even for the vanilla NeRF."""
    stride = max(1, -(-rays.origins.shape[0] // max_rays))
    pixels = rays.origins.shape[0] // rays.n_views
    keep = torch.arange(0, pixels, stride)
    index = (torch.arange(rays.n_views)[:, None] * pixels + keep[None, :]).reshape(-1)
    rgb, opacity, _ = render_rays_chunked(model, rays.origins[index].to(device), rays.directions[index].to(device))
    pred = composite(rgb, opacity, torch.ones(3, device=device)).clamp(0, 1).cpu()
    rgba = rays.rgba[index]
    target = rgba[:, :3] * rgba[:, 3:] + (1 - rgba[:, 3:])
    per_view = ((pred - target) ** 2).view(rays.n_views, -1).mean(dim=1).clamp_min(1e-10)
    return float((-10 * torch.log10(per_view)).mean())


def resolution_at(config: TrainConfig, stage: int) -> int:
    """Coarse to fine: geometric steps from start (stage 0) to final resolution."""
    ratio = config.final_resolution / config.start_resolution
    return int(round(config.start_resolution * ratio ** (stage / len(UPSAMPLE_AT))))


def make_optimizer(model, config: TrainConfig):
    from nerfgauge.nerf.models import CompactNeRF

    if isinstance(model, CompactNeRF):
        groups = [{"params": [model.field.grid], "lr": config.lr, "base_lr": config.lr}]
        if model.field.head is not None:
            groups.append({"params": model.field.head.parameters(), "lr": config.lr_mlp, "base_lr": config.lr_mlp})
        return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)
    return torch.optim.Adam([{"params": model.parameters(), "lr": 5e-4, "base_lr": 5e-4}])


def prepare_run(config: TrainConfig, run_dir: Path, resume: bool):
    """Validate input, load data, resolve the config. Nothing is written before this ends."""
    config.validate()
    root = require_complete(config.dataset)
    train_cams = read_split(root, "train")
    if not train_cams.stems:
        raise InputError(f"dataset {root} has no training views")
    needs, aabb = scene_info(root)
    if aabb is None:
        aabb = aabb_from_cameras(train_cams.c2w)
    config, reasons = resolve(config, needs, aabb, train_cams.c2w, train_cams.intrinsics.fx)
    if run_dir.exists() and not run_dir.is_dir():
        raise InputError(f"run path {run_dir} is a file, not a folder")
    if (run_dir / "config.json").exists() and not resume:
        raise InputError(f"{run_dir} already holds a run; pass --resume to continue it or choose another --out")
    if resume and not (run_dir / "checkpoint.pt").is_file():
        raise InputError(f"nothing to resume in {run_dir} (no checkpoint.pt)")
    _, train_rays = load_split_rays(root, "train")
    val_split = "val" if read_split(root, "val").stems else "test"
    _, val_rays = load_split_rays(root, val_split, limit=config.eval_views)
    return config, reasons, torch.tensor(aabb, dtype=torch.float32), train_rays, val_rays


def train(config: TrainConfig, run_dir, *, resume: bool = False, progress: bool = True) -> dict:
    run_dir = Path(run_dir)
    config, reasons, aabb, train_rays, val_rays = prepare_run(config, run_dir, resume)
    torch.set_num_threads(config.threads)
    device = pick_device(config.device)
    generator = torch.Generator(device="cpu").manual_seed(config.seed)
    torch_init = torch.Generator().manual_seed(config.seed + 1)
    state = {"step": 0, "seconds": 0.0, "next_eval": 0.0, "visibility_done": 0, "stage": 0, "stage_steps": 0}
    if resume:
        saved = checkpoint.load_checked(run_dir / "checkpoint.pt", "checkpoint")
        # the saved run's settings, with the stopping rule given now (train further)
        config = dataclasses.replace(TrainConfig(**saved["config"]), steps=config.steps,
                                     budget_seconds=config.budget_seconds)
        model = checkpoint.model_from_payload(saved["model_payload"]).to(device)
        optimizer = make_optimizer(model, config)
        optimizer.load_state_dict(saved["optimizer"])
        generator.set_state(saved["generator"])
        state.update(step=saved["step"], seconds=saved["seconds"], next_eval=saved["next_eval"],
                     visibility_done=saved["visibility_done"], stage=saved["stage"], stage_steps=saved["stage_steps"])
        _truncate_log(run_dir / "log.jsonl", saved["step"])
    else:
        with torch.random.fork_rng(devices=[]):
            torch.random.manual_seed(int(torch.randint(2**31, (1,), generator=torch_init)))  # init only
            model = checkpoint.build_model(config, aabb).to(device)
        optimizer = make_optimizer(model, config)
        run_dir.mkdir(parents=True, exist_ok=True)
        write_json(run_dir / "config.json", {**config.to_json(), "auto_reasons": reasons})
        write_bytes_atomic(run_dir / "log.jsonl", b"")
    log = (run_dir / "log.jsonl").open("a")
    n_rays = config.batch_rays if config.model == "compact" else config.vanilla_batch_rays
    total = config.steps if config.steps is not None else config.budget_seconds
    # A time budget advances the bar in training seconds; steps/s and PSNR ride in the postfix.
    time_format = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
    bar = tqdm(total=total, unit="step" if config.steps else "s", desc=f"train {config.model}",
               disable=not progress, dynamic_ncols=True, initial=state["step"] if config.steps else 0,
               bar_format=None if config.steps else time_format)
    last_psnr = float("nan")
    losses = []  # since the last log entry
    last_checkpoint = -math.inf  # wall clock: the first log point (step 0) writes one
    try:
        while True:
            done = state["step"] / config.steps if config.steps else state["seconds"] / config.budget_seconds
            if hasattr(model, "measure_visibility") and state["visibility_done"] < len(VISIBILITY_AT) \
                    and done >= VISIBILITY_AT[state["visibility_done"]]:
                start = time.perf_counter()
                model.measure_visibility(train_rays.origins[::VISIBILITY_RAY_STRIDE].to(device),
                                         train_rays.directions[::VISIBILITY_RAY_STRIDE].to(device))
                state["visibility_done"] += 1
                state["seconds"] += time.perf_counter() - start  # part of training: it speeds it up
            if state["seconds"] >= state["next_eval"] or done >= 1:
                last_psnr = psnr_on_white(model, val_rays, device, config.eval_rays)
                entry = {"step": state["step"], "seconds": round(state["seconds"], 3), "val_psnr": last_psnr,
                         "steps_per_second": state["step"] / max(state["seconds"], 1e-9),
                         "loss": sum(losses) / len(losses) if losses else None}
                losses.clear()
                if hasattr(model, "occupancy"):
                    entry |= {"resolution": model.field.resolution, "occupied": float(model.occupancy.float().mean())}
                log.write(json.dumps(entry) + "\n"), log.flush()
                state["next_eval"] = state["seconds"] + config.eval_every_seconds
                if done >= 1 or time.monotonic() - last_checkpoint >= CHECKPOINT_EVERY_WALL_SECONDS:
                    _save_checkpoint(run_dir, model, optimizer, config, generator, state)
                    last_checkpoint = time.monotonic()
                bar.set_postfix(psnr=f"{last_psnr:.2f}", steps_per_s=f"{entry['steps_per_second']:.1f}", refresh=False)
                if done >= 1:
                    break
            start = time.perf_counter()
            if state["stage"] < len(UPSAMPLE_AT) and done >= UPSAMPLE_AT[state["stage"]] \
                    and state["stage_steps"] >= MIN_STAGE_STEPS:
                state["stage"] += 1
                state["stage_steps"] = 0
            loss, gradients_finite = _train_step(model, optimizer, config, train_rays, n_rays, generator, device,
                                                 done, state)
            if not (math.isfinite(loss) and gradients_finite):
                raise NumericalError(
                    f"training diverged at step {state['step']}: loss {loss}, gradients "
                    f"{'finite' if gradients_finite else 'not finite'}; the parameters were not updated and "
                    f"{run_dir / 'checkpoint.pt'} holds the last saved state")
            losses.append(loss)
            elapsed = time.perf_counter() - start
            state["step"] += 1
            state["stage_steps"] += 1
            state["seconds"] += elapsed
            bar.update(1 if config.steps else min(elapsed, total - bar.n))
    finally:
        bar.close()
        log.close()
    size = checkpoint.save_atomic(checkpoint.model_payload(model, config, prune=config.prune), run_dir / "model.pt")
    return {"steps": state["step"], "seconds": state["seconds"], "val_psnr": last_psnr, "model_bytes": size}


def _train_step(model, optimizer, config, rays, n_rays, generator, device, progress, state):
    from nerfgauge.nerf.models import CompactNeRF

    compact = isinstance(model, CompactNeRF)
    if compact:
        wanted = resolution_at(config, state["stage"])
        if wanted != model.field.resolution:
            model.upsample(wanted)
            lrs = [group["lr"] for group in optimizer.param_groups]
            optimizer.__init__(make_optimizer(model, config).param_groups, **optimizer.defaults)
            for group, lr in zip(optimizer.param_groups, lrs):
                group["lr"] = lr
        if state["step"] % OCCUPANCY_EVERY == 0 and state["stage"] >= 1:  # all cells live while coarse
            model.update_occupancy()
    for group in optimizer.param_groups:
        group["lr"] = group["base_lr"] * LR_FINAL_FRACTION ** progress
    index = torch.randint(rays.origins.shape[0], (n_rays,), generator=generator)
    origins, directions, rgba = (t[index].to(device) for t in (rays.origins, rays.directions, rays.rgba))
    if config.background == "random":
        background = torch.rand((n_rays, 3), generator=generator).to(device)
    else:
        background = torch.full((3,), 1.0 if config.background == "white" else 0.0, device=device)
    target = rgba[:, :3] * rgba[:, 3:] + background * (1 - rgba[:, 3:])
    out = model.render(origins, directions, generator=generator, training=True)
    loss = ((composite(out.rgb, out.opacity, background) - target) ** 2).mean()
    if out.coarse is not None:
        loss = loss + ((composite(out.coarse.rgb, out.coarse.opacity, background) - target) ** 2).mean()
    loss = loss + model.regularisation(config.tv_weight)
    if out.distortion is not None and config.distortion_weight > 0:
        loss = loss + config.distortion_weight * out.distortion.mean()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    # One reduction per parameter: NaN or inf anywhere makes the total non-finite. Checked
    # before the step so a bad gradient never reaches the parameters or Adam's moments.
    total = sum(p.grad.sum() for group in optimizer.param_groups for p in group["params"] if p.grad is not None)
    gradients_finite = bool(torch.isfinite(torch.as_tensor(total)))
    if gradients_finite:
        optimizer.step()
    return float(loss.detach()), gradients_finite


def _truncate_log(path: Path, last_step: int) -> None:
    """Drop log entries past the checkpoint being resumed (checkpoints are rarer than log
    points), so the resumed run's entries continue the curve instead of repeating steps."""
    lines = path.read_text().splitlines() if path.is_file() else []
    kept = [line for line in lines if line.strip() and json.loads(line)["step"] <= last_step]
    write_bytes_atomic(path, "".join(line + "\n" for line in kept).encode())


def _save_checkpoint(run_dir, model, optimizer, config, generator, state):
    checkpoint.save_atomic({"format": checkpoint.FORMAT, "version": checkpoint.VERSION, "config": config.to_json(),
                            "model_payload": checkpoint.model_payload(model, config, prune=False),
                            "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
                            "step": state["step"], "seconds": state["seconds"], "next_eval": state["next_eval"],
                            "visibility_done": state["visibility_done"], "stage": state["stage"],
                            "stage_steps": state["stage_steps"]},
                           run_dir / "checkpoint.pt")
