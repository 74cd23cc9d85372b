"""`nerfgauge train`: the one training loop, for both models.

RUN/ holds config.json (resolved, with the reasons for each automatic choice and the run's
recipe), log.jsonl (val PSNR against training seconds: the speed-vs-error curve of this
run), checkpoint.pt (full state, for --resume) and model.pt (the saved, pruned model).
Training seconds exclude validation and checkpointing, so curves from different runs
compare.

The run folder is claimed (nerfgauge.core.folders) under a recipe: the dataset's
manifest.json hash and every setting that shapes the trajectory, not the stopping rule
(--resume may train further), logging, threads or device. Resuming a `--steps N` run from
any checkpoint gives the same model.pt, tensor for tensor, as an uninterrupted run at the
same thread count: the checkpoint holds every piece of state the step reads, and nothing
scheduled on wall-clock time (val PSNR points, the default checkpoint rule) changes the
trajectory of a steps-run.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from nerfgauge.nerf import checkpoint
from nerfgauge.nerf.checkpoint import LoopState
from nerfgauge.nerf.config import (RENDER_CHANGE_STEPS, RENDER_DB_PER_DOUBLING, RENDER_GAIN_DB,
                                   RENDER_FILTERS, TRAIN_PIXEL_SAMPLES, TrainConfig, refined_resolution, resolve)
from nerfgauge.nerf.data import aabb_from_cameras, jittered_direction, load_split_rays, scene_info, sparse_train_views
from nerfgauge.nerf.frames import pixel_offsets
from nerfgauge.nerf.grid_field import node_mask
from nerfgauge.nerf.models import CompactNeRF, RadianceModel
from nerfgauge.nerf.parametrisation import check_targets, make_space
from nerfgauge.nerf.rendering import composite, pixel_mean, render_rays_chunked
from nerfgauge.nerf.schedule import (FINE_EDGE_POINTS_PER_AXIS, FINER_EDGE_POINTS_PER_AXIS, MIN_STEPS_AT_FINER,
                                    SURFACE_RISE_STEPS, RateScales, Schedule, TrialTiming, upsample_count)
from nerfgauge.nerf.sparse_priors import PRIOR_RAYS, origin_spread, prior_loss, unseen_rays, views_per_point
from nerfgauge.nerf.trials import (Trial, candidate_config, parametrisation_trial, pick, render_path, trial_reason,
                                   trial_record, trial_recipe, val_psnr)

from nerfgauge.core import bounded, owned
from nerfgauge.core.dataset import manifest_sha256, open_dataset
from nerfgauge.core.progress import note, progress as progress_bar
from nerfgauge.core.errors import InputError, NumericalError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import claim_folder, read_marker, recipe_hash, remove_owned

HEAD_SEED_OFFSET = 2  # the residual colour head's hidden layer: seed + 2 (seed + 1 draws the model's)
# When the grid grows, when a growth is on trial, when hidden cells are measured and what is
# refined at half the budget: nerf.schedule.
VISIBILITY_RAY_STRIDE = 4  # every 4th training ray is enough to see every visible cell ...
# ... up to this many rays (100 views of 128 px). Beyond it, measuring costs more than the
# steps it saves (25 s a measurement at 256 px, of a 120 s budget): the stride grows and
# visibility is measured per block of cells, so each block still gets as many rays per view.
VISIBILITY_RAYS = 409_600
# ... and up to this many marched samples (those rays at 16 samples each): a contracted
# grid keeps ~126 samples per ray on far-reaching, where a measurement took 30-50 s
VISIBILITY_SAMPLES = 16 * VISIBILITY_RAYS
VISIBILITY_PROBE_RAYS = 4096  # rays marched first to count samples per ray
# checkpoint.pt (grid + Adam state: ~0.5 GB at 220^3) is rewritten, without
# --checkpoint-every, only when this much wall time has passed since the last one, and
# always at the end: with dense logging (bench scaling logs every 2 s) writing it at every
# log point doubled wall time.
CHECKPOINT_EVERY_WALL_SECONDS = 60.0
CHECKPOINT, MODEL, CONFIG, LOG = "checkpoint.pt", "model.pt", "config.json", "log.jsonl"
# Config fields that do not shape the trajectory, so not part of the run's recipe: the
# dataset's path (its manifest hash stands for it), the stopping rule (resume trains
# further), logging, checkpointing, threads, device and how model.pt is stored.
NOT_RECIPE = ("dataset", "steps", "budget_seconds", "eval_every_seconds", "eval_views", "eval_rays",
              "checkpoint_every", "threads", "device", "quantise", "render_filter")


def pick_device(name: str) -> torch.device:
    """The torch device for --device (auto, cpu, cuda, cuda:N); one line when it is absent."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise InputError(f"unknown device {name!r}; choose auto, cpu or cuda") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"device {name!r}: no CUDA GPU is available here; use --device cpu or auto")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")
    elif device.type != "cpu":
        raise InputError(f"unsupported device {name!r}; choose auto, cpu or cuda")
    return device


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


def logged_val_psnr(path: Path, step: int) -> float:
    """The val PSNR that log.jsonl at `path` holds for `step` (its last entry of that step);
    NaN when it holds none that is a finite number. Read on resume, after the log is cut
    back to the checkpoint: a finished run resumed reported `val PSNR nan` for want of it."""
    found = math.nan
    for line in (path.read_text(errors="replace").splitlines() if path.is_file() else []):
        try:
            entry = bounded.loads_json(line, path) if line.strip() else None
        except (json.JSONDecodeError, InputError):  # a torn last line (resume cut the rest back)
            continue
        value = entry.get("val_psnr") if isinstance(entry, dict) and entry.get("step") == step else None
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            found = float(value)
    return found


def visibility_sampling(n_rays: int, samples_per_ray: float = 0.0) -> tuple[int, int]:
    """(ray stride, cell block) for a visibility measurement over `n_rays` training rays
    that march about `samples_per_ray` samples each: every VISIBILITY_RAY_STRIDE-th ray
    per cell while that stays within VISIBILITY_RAYS rays and VISIBILITY_SAMPLES samples;
    beyond, an odd stride (a lattice across each image, not whole columns) and blocks of
    b^3 cells with b^2 = stride / VISIBILITY_RAY_STRIDE, so rays per block per view stay
    as they were per cell."""
    affordable = min(VISIBILITY_RAYS, VISIBILITY_SAMPLES / max(samples_per_ray, 1.0))
    stride = max(VISIBILITY_RAY_STRIDE, math.ceil(n_rays / affordable))
    if stride == VISIBILITY_RAY_STRIDE:
        return stride, 1
    return stride | 1, max(1, round(math.sqrt(stride / VISIBILITY_RAY_STRIDE)))


def make_optimizer(model: RadianceModel, config: TrainConfig) -> torch.optim.Adam:
    """Adam over the model's parameter groups, each starting at its base learning rate."""
    return torch.optim.Adam(model.parameter_groups(config.lr, config.lr_mlp), **model.adam_options)


def free_unoccupied(model: CompactNeRF, optimizer: torch.optim.Adam) -> None:
    """Free the grid rows of nodes that no occupied (and visible) cell touches, so storage
    and each Adam step shrink with the scene; Adam's moments move along with their rows."""
    old = model.field.grid_parameters()
    rows = model.field.keep_rows(node_mask(model.occupancy))
    new = {id(before): after for before, after in zip(old, model.field.grid_parameters())}
    for group in optimizer.param_groups:
        group["params"] = [new.get(id(p), p) for p in group["params"]]
    for before in old:
        moments = optimizer.state.pop(before, None)
        if moments:
            optimizer.state[new[id(before)]] = {k: v[rows] if torch.is_tensor(v) and v.dim() > 0 else v
                                                for k, v in moments.items()}


def run_recipe(config: TrainConfig, dataset_sha256: str) -> dict:
    """What a run is made from: the dataset (by content) and the resolved settings that
    shape its trajectory. Two runs of one recipe (and stopping rule) train the same model."""
    return {"dataset_sha256": dataset_sha256} | {k: v for k, v in config.to_json().items() if k not in NOT_RECIPE}


def opaque_share(rays) -> float | None:
    """The share of rays whose target alpha is 1 (within 8-bit rounding): 1.0 for a capture
    whose every ray ends on content. None without targets."""
    if rays.rgba is None or not len(rays.rgba):
        return None
    return float((rays.rgba[:, 3] >= 1 - 0.5 / 255).float().mean())


@dataclass
class Candidate:
    """One way to train a run: its resolved config and the reason for each automatic
    choice, its space (nerf.parametrisation) and its training rays (with the footprints and
    edge flags its pixel filter reads)."""

    config: TrainConfig
    reasons: dict
    space: object
    train_rays: object


@dataclass
class Prepared:
    """A run before anything is written: its candidates (one, or a trial's, in the trial's
    order: the rule's own pick first), the trial (nerf.trials) or None, the scene box as a
    tensor, the val views (val_cameras, val_rays: the first eval_views views of the val
    split, test without one), the device and the run's recipe."""

    candidates: list
    trial: Trial | None
    aabb: torch.Tensor
    val: tuple
    device: torch.device
    recipe: dict


def prepare_run(config: TrainConfig):
    """Validate input, load data, resolve the config. Nothing is written here.
    Returns (config, reasons, (aabb, space), train_rays, val_rays, device, recipe, val_cameras)
    of the run, or of the rule's own pick where a choice goes to trial (`prepare`)."""
    prepared = prepare(config)
    first = prepared.candidates[0]
    return (first.config, first.reasons, (prepared.aabb, first.space), first.train_rays, prepared.val[1],
            prepared.device, prepared.recipe, prepared.val[0])


def prepare(config: TrainConfig) -> Prepared:
    """Validate input, load data, resolve the config, and where the parametrisation's rule
    is unsure (nerf.trials.parametrisation_trial) each candidate's config. Nothing is written."""
    config.validate()
    device = pick_device(config.device)
    ds = open_dataset(config.dataset)
    root = ds.root
    train_cams = ds.cameras("train")
    if not train_cams.stems:
        raise InputError(f"dataset {root} has no training views")
    sparse = None if config.sparse is None else sparse_train_views(ds, config.sparse)
    if sparse is not None:  # only the listed views: their cameras bound the scene and place the grid
        train_cams = dataclasses.replace(train_cams, stems=tuple(train_cams.stems[i] for i in sparse),
                                         c2w=train_cams.c2w[sparse],
                                         lenses=tuple(train_cams.lenses[i] for i in sparse) if train_cams.lenses else ())
    needs, aabb = scene_info(root)
    if aabb is None:
        aabb = aabb_from_cameras(train_cams.c2w)
    check_targets(aabb, train_cams.c2w)
    # footprints unless the filter is set to centre, edge flags when it may be edges (the
    # automatic choice reads their share); each dropped when the resolved filter needs none
    may_be_edges = config.pixel_filter in (None, "edges")
    _, train_rays = load_split_rays(root, "train", views=sparse, footprint=config.pixel_filter != "centre",
                                    edges=may_be_edges)
    edge_share = float(train_rays.edges.float().mean()) if may_be_edges and len(train_rays.edges) else None
    coverage = views_per_point(aabb, train_cams.c2w, train_cams.intrinsics) if config.sparse_priors is None else None
    opaque = opaque_share(train_rays)
    trial = parametrisation_trial(config, aabb, train_cams.c2w, opaque)
    requests = [config] if trial is None else [candidate_config(config, trial, value) for value in trial.candidates]
    stride = max(1, train_rays.origins.shape[0] // 65536)
    intrinsics = train_cams.intrinsics
    tan_half_fov = min(0.5 * intrinsics.width / intrinsics.fx, 0.5 * intrinsics.height / intrinsics.fy)
    candidates = []
    for request in requests:
        resolved, reasons = resolve(request, needs, aabb, train_cams.c2w, intrinsics.fx, intrinsics.width, opaque,
                                    edge_share, coverage)
        rays = dataclasses.replace(train_rays, footprint=None if resolved.pixel_filter == "centre" else train_rays.footprint,
                                   edges=train_rays.edges if resolved.pixel_filter == "edges" else None)
        space = make_space(resolved.parametrisation, aabb, train_cams.c2w, rays.origins[::stride],
                           rays.directions[::stride], tan_half_fov)
        candidates.append(Candidate(resolved, reasons, space, rays))
    dataset_sha256 = manifest_sha256(root)
    recipes = [run_recipe(candidate.config, dataset_sha256) for candidate in candidates]
    val_split = "val" if ds.cameras("val").stems else "test"
    val_cameras, val_rays = load_split_rays(root, val_split, limit=config.eval_views)
    return Prepared(candidates, trial, torch.tensor(aabb, dtype=torch.float32), (val_cameras, val_rays), device,
                    recipes[0] if trial is None else trial_recipe(trial, recipes))


def _check_resumable(run_dir: Path, recipe: dict) -> None:
    """Before anything is created: a --resume needs a run of this recipe in `run_dir`; say
    which setting differs when it is another one."""
    marker = read_marker(run_dir) if run_dir.is_dir() and not run_dir.is_symlink() else None
    if marker is None or marker["kind"] != "run":
        if run_dir.is_dir() and marker is None and not any(run_dir.iterdir()):
            raise InputError(f"nothing to resume in {run_dir}: the folder is empty")
        if marker is None and not run_dir.exists():
            raise InputError(f"nothing to resume: {run_dir} does not exist")
        return  # claim_folder names what is there instead
    if marker.get("recipe") != recipe_hash(recipe):
        saved = _saved_recipe(run_dir)
        difference = checkpoint.recipe_difference(saved, recipe) if saved else "other settings"
        raise InputError(f"{run_dir} holds a run of {difference}; refusing to resume it "
                         "(drop --resume and pass --overwrite to start over, or choose another --out)")


def _saved_recipe(run_dir: Path) -> dict | None:
    try:
        saved = read_json(run_dir / CONFIG).get("recipe")
    except InputError:
        return None
    return saved if isinstance(saved, dict) else None


def _start_over(run_dir: Path) -> None:
    """Remove an earlier attempt's files from our run folder (we hold its lock): its
    model, checkpoint, log and config, and renders folders nerfgauge made inside it."""
    for name in (MODEL, CHECKPOINT, LOG, CONFIG):
        owned.remove_file(run_dir / name)
    for entry in run_dir.iterdir():
        marker = read_marker(entry) if entry.is_dir() and not entry.is_symlink() else None
        if marker is not None and marker["kind"] == "renders":
            remove_owned(entry, "renders")


def train(config: TrainConfig, run_dir, *, resume: bool = False, overwrite: bool = False,
          progress: bool = True) -> dict:
    """Train into `run_dir`. A new or empty folder starts a run; a folder holding this
    recipe's run whose earlier attempt was killed before its first checkpoint starts over;
    resume=True continues from checkpoint.pt; overwrite=True replaces a run of ours (any
    recipe). Returns {"steps", "seconds", "val_psnr" (the log's last: pixel centres, a strided
    subset of the val views), "model_bytes", "resolution", "render_filter" and "render_val_psnr"
    (an `edges` run's render on whole val frames, as `choose_render_filter` measured it; None
    for other runs)}."""
    if isinstance(run_dir, str) and not run_dir.strip():
        raise InputError("the run folder is an empty path; give --out RUN")
    if resume and overwrite:
        raise InputError("--resume continues a run and --overwrite starts it over; give one of them")
    run_dir = Path(run_dir)
    prepared = prepare(config)
    if resume:
        _check_resumable(run_dir, prepared.recipe)
    with claim_folder(run_dir, "run", recipe_hash(prepared.recipe), overwrite=overwrite) as claimed:
        saved = None
        if claimed == "resume":
            has_checkpoint = (run_dir / CHECKPOINT).is_file()
            if resume and has_checkpoint:
                saved = checkpoint.load_training_checkpoint(run_dir / CHECKPOINT, prepared.recipe)
            elif not resume and not overwrite and (run_dir / MODEL).is_file():
                raise InputError(f"{run_dir} already holds a finished run; pass --resume to train it further, "
                                 "--overwrite to start over, or choose another --out")
            elif not resume and not overwrite and has_checkpoint:
                raise InputError(f"{run_dir} holds an interrupted run; pass --resume to continue it, "
                                 "--overwrite to start over, or choose another --out")
            if saved is None:  # --overwrite of this recipe, or killed before its first checkpoint
                _start_over(run_dir)
        return _train_in(run_dir, prepared, saved, progress)


@dataclass
class Training:
    """What one training step reads and updates: the model, its optimiser (replaced when
    the grid grows), the ray-sampling generator and the loop's counters. All of it is in
    checkpoint.pt, so a resumed run continues exactly."""

    model: RadianceModel
    optimizer: torch.optim.Adam
    generator: torch.Generator
    loop: LoopState


@dataclass
class GrowthTrial:
    """A growth on trial: the coarser grid's model, optimiser and loop counters as they were
    before it (restored when the growth is undone), and the finer grid's clock
    (nerf.schedule.TrialTiming)."""

    model: RadianceModel
    optimizer: torch.optim.Adam
    loop: LoopState
    timing: TrialTiming = TrialTiming()


def begin_growth_trial(training: Training) -> GrowthTrial:
    """Snapshot what a growth changes; one deepcopy keeps the optimiser on the copied
    parameters. (Not in checkpoint.pt: a run resumed during a trial keeps the growth.)"""
    model, optimizer = copy.deepcopy((training.model, training.optimizer))
    return GrowthTrial(model, optimizer, dataclasses.replace(training.loop))


def undo_growth(training: Training, trial: GrowthTrial) -> None:
    """Back to the coarser grid as it was before the trial, which becomes the final one.
    The step count, training seconds and ray generator run on: the trial's time was spent."""
    state = training.loop
    training.model, training.optimizer = trial.model, trial.optimizer
    for name in ("stage", "stage_steps", "stage_seconds", "visibility_done", "colour_head"):
        setattr(state, name, getattr(trial.loop, name))
    state.last_stage = state.stage


def _start_training(run_dir: Path, config: TrainConfig, aabb, space, device, saved: dict | None) -> Training:
    """A new run's model, optimiser and generator from the config's seeds, or a resumed
    run's from its checked checkpoint `saved`."""
    generator = torch.Generator(device="cpu").manual_seed(config.seed)
    loop = LoopState(last_stage=upsample_count(config.start_resolution, config.final_resolution))
    if saved is not None:
        path = run_dir / CHECKPOINT
        model = checkpoint.restore_model(saved, config, aabb, path, space=space).to(device)
        optimizer = make_optimizer(model, config)
        checkpoint.restore_optimizer(optimizer, saved["optimizer"], path)
        checkpoint.restore_generator(generator, saved["generator"], path)
        loop = LoopState.from_saved(saved["loop"])
        if loop.surface_step:  # a setting of the model's rendering, not one of its tensors
            model.rise_steps = SURFACE_RISE_STEPS
        return Training(model, optimizer, generator, loop)
    torch_init = torch.Generator().manual_seed(config.seed + 1)
    init_seed = int(torch.randint(2**31, (1,), generator=torch_init))
    model = checkpoint.build_model(config, aabb, init_seed=init_seed, space=space).to(device)
    return Training(model, make_optimizer(model, config), generator, loop)


def _measure_visibility(training: Training, train_rays, device) -> None:
    """Mark the grid cells training rays can see; with a sparse grid, free the rest. Counted
    as one of the schedule's measurements (LoopState.visibility_done) and as training time:
    it speeds training up."""
    start = time.perf_counter()
    model = training.model
    probe = max(1, train_rays.origins.shape[0] // VISIBILITY_PROBE_RAYS)
    samples_per_ray = model.samples_per_ray(train_rays.origins[::probe].to(device),
                                            train_rays.directions[::probe].to(device))
    stride, block = visibility_sampling(train_rays.origins.shape[0], samples_per_ray)
    model.measure_visibility(train_rays.origins[::stride].to(device), train_rays.directions[::stride].to(device),
                             block=block)
    if model.sparse:
        free_unoccupied(model, training.optimizer)
    training.loop.visibility_done += 1
    training.loop.seconds += time.perf_counter() - start


def _write_config(run_dir: Path, config: TrainConfig, reasons: dict, space, recipe: dict,
                  trials: dict | None = None) -> None:
    """RUN/config.json: the resolved settings, why each automatic one was chosen, the space,
    the recipe and, where a trial made a choice, what it measured (nerf.trials.trial_record)."""
    write_json(run_dir / CONFIG, {**config.to_json(), "auto_reasons": reasons, "space": space.to_json(),
                                  "recipe": recipe} | ({"trials": trials} if trials else {}))


def _progress_bar(config: TrainConfig, state: LoopState, progress: bool):
    """Steps for a --steps run; a time budget advances the bar in training seconds, with
    steps/s and PSNR in the postfix (core.progress: plain lines when not on a terminal)."""
    time_format = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
    return progress_bar(total=config.steps if config.steps is not None else config.budget_seconds,
                        unit="step" if config.steps else "s", desc=f"train {config.model}", enabled=progress,
                        initial=state.step if config.steps else 0, bar_format=None if config.steps else time_format)


def _log_point(log, bar, training: Training, config: TrainConfig, schedule: Schedule, val_rays, device,
               losses: list) -> float:
    """One log.jsonl entry: val PSNR at this step, the mean loss since the last entry (then
    cleared), and the grid's state. Val PSNR points are scheduled on training seconds; they
    only read the model (no generator, no parameter, no cached state the step uses), so where
    they fall never changes a steps-run's trajectory. Returns the PSNR."""
    model, state = training.model, training.loop
    psnr = psnr_on_white(model, val_rays, device, config.eval_rays)
    entry = {"step": state.step, "seconds": round(state.seconds, 3), "val_psnr": psnr,
             "steps_per_second": state.step / max(state.seconds, 1e-9),
             "loss": sum(losses) / len(losses) if losses else None}
    losses.clear()
    if config.pixel_filter == "edges":
        entry["edge_points"] = state.edge_points
    if model.has_grid:
        entry |= {"resolution": model.field.resolution, "occupied": float(model.occupancy.float().mean()),
                  "final_resolution": schedule.resolution_at(state.last_stage)}
    log.write(json.dumps(entry) + "\n"), log.flush()
    state.next_eval = state.seconds + config.eval_every_seconds
    state.logged_step = state.step
    bar.set_postfix(psnr=f"{psnr:.2f}", steps_per_s=f"{entry['steps_per_second']:.1f}", refresh=False)
    return psnr


@dataclass
class CheckpointClock:
    """When checkpoint.pt was last written: its step (None: not in this attempt) and the
    wall-clock time (time.monotonic)."""

    step: int | None
    wall: float

    def save_if_due(self, run_dir: Path, training: Training, config: TrainConfig, recipe: dict,
                    finished: bool) -> None:
        """Every --checkpoint-every steps, else once CHECKPOINT_EVERY_WALL_SECONDS of wall
        time have passed; always at the end (`finished`); never twice at one step."""
        state = training.loop
        if config.checkpoint_every is not None:
            due = state.step % config.checkpoint_every == 0
        else:
            due = time.monotonic() - self.wall >= CHECKPOINT_EVERY_WALL_SECONDS
        if (due or finished) and self.step != state.step:
            _save_checkpoint(run_dir, training, config, recipe)
            self.step, self.wall = state.step, time.monotonic()


def _follow_schedule(training: Training, schedule: Schedule, trial: GrowthTrial | None, fraction_done: float,
                     progress: bool) -> GrowthTrial | None:
    """Apply what the schedule decides before this step: grow the grid (a time budget's last
    growth on trial), judge a growth on trial, decide the colour head, and at half the budget
    refine (finer edge points, a grid past the final one). Returns the growth on trial, if any."""
    state = training.loop
    if schedule.growth_due(state, fraction_done):
        if schedule.growth_on_trial(state):
            trial = begin_growth_trial(training)
        state.stage += 1
        state.stage_steps, state.stage_seconds = 0, 0.0
    elif trial is not None:
        trial.timing, projected = schedule.steps_on_trial(state, trial.timing)
        if projected is not None:
            if not schedule.keeps_growth(projected):
                finer = training.model.field.resolution
                undo_growth(training, trial)
                if progress:
                    note(f"keeping the {training.model.field.resolution}-voxel grid: the budget would give "
                               f"the {finer}-voxel one about {projected:.0f} steps at its measured rate "
                               f"(< {MIN_STEPS_AT_FINER})")
            trial = None  # judged: the growth stands or is undone
    if schedule.colour_head_due(state):  # the final grid has settled: add the head now, or never
        state.colour_head = 1 if schedule.colour_head else -1
        if progress and schedule.colour_head:
            note(f"adding the residual colour head at step {state.step}")
    if (refine := schedule.refinement_due(state, fraction_done, trial is not None)) is not None:
        state.edge_points_step = state.step  # decided, either way
        if refine and schedule.edges:
            state.edge_points = FINE_EDGE_POINTS_PER_AXIS
            if progress:
                note(f"training edge pixels through {state.edge_points} x {state.edge_points} points "
                           f"from step {state.step}")
        if refine and schedule.surface_opacity:
            training.model.rise_steps = SURFACE_RISE_STEPS
            state.surface_step = state.step
            state.anneal_from = fraction_done
            if progress:
                note(f"surface opacity from step {state.step}")
        if refine and schedule.grows_past_final(state):
            # the growth comes as any other at the next step (`growth_due`), on trial for a
            # time budget like the last growth
            state.last_stage += 1
            if progress:
                note(f"growing the grid to {schedule.refined_resolution} voxels from step {state.step}")
    if (finer := schedule.finer_points_due(state, fraction_done)) is not None:
        state.finer_points_step = state.step  # decided, either way
        if finer:
            state.edge_points = FINER_EDGE_POINTS_PER_AXIS
            if progress:
                note(f"training edge pixels through {state.edge_points} x {state.edge_points} points "
                     f"from step {state.step}")
    return trial


def _step(training: Training, config: TrainConfig, schedule: Schedule, train_rays, n_rays: int, device,
          fraction_done: float, priors, run_dir: Path) -> float:
    """One training step at the grid the schedule's stage wants (occupancy refreshed when
    due): its loss. A non-finite loss or gradient is a NumericalError (nothing updated)."""
    if training.model.has_grid:
        _grow_grid(training, config, schedule.resolution_at(training.loop.stage))
        if schedule.occupancy_due(training.loop):
            training.model.update_occupancy()
    lr_scales = schedule.lr_scales(training.loop, fraction_done)
    loss, gradients_finite = _train_step(training, config, train_rays, n_rays, device, lr_scales, priors)
    if not (math.isfinite(loss) and gradients_finite):
        raise NumericalError(
            f"training diverged at step {training.loop.step}: loss {loss}, gradients "
            f"{'finite' if gradients_finite else 'not finite'}; the parameters were not updated and "
            f"{run_dir / CHECKPOINT} holds the last saved state")
    return loss


@dataclass
class RunLoop:
    """One candidate's training loop, between calls of `_advance`: its Training and what
    the loop reads besides (the resolved config, its reasons, space and schedule, rays,
    val views, the sparse-capture priors' spread, rays a step), where it logs (log.jsonl, or
    a buffer while on trial), its progress bar, its checkpoint clock (None while on trial:
    nothing is written), and what runs on between steps (the latest val PSNR, the losses
    since the last log entry, a time budget's growth on trial)."""

    run_dir: Path
    recipe: dict
    training: Training
    candidate: Candidate
    schedule: Schedule
    val: tuple
    device: torch.device
    priors: float | None
    n_rays: int
    log: object
    bar: object
    progress: bool
    checkpoints: CheckpointClock | None = None
    last_psnr: float = math.nan
    losses: list = dataclasses.field(default_factory=list)
    growth: GrowthTrial | None = None
    trials: dict = dataclasses.field(default_factory=dict)


def _open_loop(run_dir: Path, candidate: Candidate, prepared: Prepared, saved: dict | None, log,
               progress: bool) -> RunLoop:
    """A candidate's loop from its seeds, or from a resumed run's checked checkpoint `saved`."""
    config = candidate.config
    training = _start_training(run_dir, config, prepared.aabb, candidate.space, prepared.device, saved)
    if training.loop.colour_head == 1 and config.colour_head is None:  # resumed: an earlier rule added the head
        config = candidate.config = dataclasses.replace(config, colour_head=True)
        candidate.reasons["colour_head"] = "added before the run was resumed (checkpoint.pt's loop state)"
    schedule = Schedule.for_run(config, grid=training.model.has_grid,
                                refined_resolution=refined_resolution(config.final_resolution))
    # the scale of the unseen viewpoints' offsets, when the sparse-capture priors are on
    priors = origin_spread(candidate.train_rays.origins) if config.sparse_priors else None
    n_rays = config.batch_rays if config.model == "compact" else config.vanilla_batch_rays
    return RunLoop(run_dir, prepared.recipe, training, candidate, schedule, prepared.val, prepared.device, priors, n_rays, log,
                   _progress_bar(config, training.loop, progress), progress)


def _advance(loop: RunLoop, until: float) -> None:
    """Train until `until` of the steps or budget is done (1: the run's end). Val PSNR points
    and checkpoints only read the state, so stopping at a fraction and going on later is
    the same trajectory as not stopping."""
    training, config, schedule, state = loop.training, loop.candidate.config, loop.schedule, loop.training.loop
    while True:
        fraction_done = schedule.fraction_done(state)
        if schedule.visibility_due(state, fraction_done):
            _measure_visibility(training, loop.candidate.train_rays, loop.device)
        if state.logged_step != state.step and (state.seconds >= state.next_eval or fraction_done >= until):
            loop.last_psnr = _log_point(loop.log, loop.bar, training, config, schedule, loop.val[1], loop.device,
                                        loop.losses)
        if loop.checkpoints is not None:
            loop.checkpoints.save_if_due(loop.run_dir, training, config, loop.recipe,
                                         finished=fraction_done >= 1)
        if fraction_done >= until:
            return
        start = time.perf_counter()
        loop.growth = _follow_schedule(training, schedule, loop.growth, fraction_done, loop.progress)
        loop.losses.append(_step(training, config, schedule, loop.candidate.train_rays, loop.n_rays, loop.device,
                                 fraction_done, loop.priors, loop.run_dir))
        elapsed = time.perf_counter() - start
        state.step += 1
        state.stage_steps += 1
        state.stage_seconds += elapsed
        state.seconds += elapsed
        loop.bar.update(1 if config.steps else min(elapsed, loop.bar.total - loop.bar.n))


def _train_in(run_dir: Path, prepared: Prepared, saved: dict | None, progress: bool) -> dict:
    """The loop, in a claimed run folder; from `saved` (a checked checkpoint) when given,
    after the trial when a choice is on trial (`_run_trial`). progress: show a progress bar."""
    torch.set_num_threads(prepared.candidates[0].config.threads)
    if prepared.trial is not None and saved is None:
        loop = _run_trial(run_dir, prepared, progress)
    else:
        candidate = prepared.candidates[0] if prepared.trial is None else _resumed_candidate(run_dir, prepared, saved)
        loop = _open_loop(run_dir, candidate, prepared, saved, None, progress)
        state = loop.training.loop
        if saved is None:
            write_bytes_atomic(run_dir / LOG, b"")
        else:  # resumed: its latest val PSNR point is in the log (a finished run has nothing left to measure)
            _truncate_log(run_dir / LOG, state.step)
            loop.last_psnr = logged_val_psnr(run_dir / LOG, state.logged_step)
            if state.logged_step == state.step and not math.isfinite(loop.last_psnr):
                state.logged_step = -1  # the log lost that point: measured again below (it only reads the model)
            loop.trials = _earlier(run_dir, "trials") if prepared.trial is not None else {}
    candidate = loop.candidate
    # this attempt's settings (the stopping rule may differ)
    _write_config(run_dir, candidate.config, candidate.reasons, candidate.space, prepared.recipe, loop.trials)
    loop.log = owned.open_append(run_dir / LOG)
    loop.checkpoints = (CheckpointClock(loop.training.loop.step, time.monotonic()) if saved is not None
                        else CheckpointClock(None, -math.inf))
    try:
        _advance(loop, 1.0)
    finally:
        loop.bar.close()
        loop.log.close()
    return _finish(run_dir, loop, prepared.recipe)


def _run_trial(run_dir: Path, prepared: Prepared, progress: bool) -> RunLoop:
    """Each candidate trains the trial's share of the run from the run's seed (nothing
    written), is scored on the val views through the render path, and the best (ties: the
    rule's own pick; nerf.trials.pick) is returned to continue, its log entries so far in
    log.jsonl and the trial in its reasons and `trials`."""
    trial, (cameras, val_rays) = prepared.trial, prepared.val
    loops, scores = {}, {}
    for candidate in prepared.candidates:
        value = getattr(candidate.config, trial.field)
        loop = loops[value] = _open_loop(run_dir, candidate, prepared, None, io.StringIO(), progress)
        try:
            _advance(loop, trial.share)
        except NumericalError:  # a candidate that diverges loses; the others may not
            scores[value] = -math.inf
            continue
        finally:
            loop.bar.close()
        scores[value] = val_psnr(loop.training.model, cameras, val_rays, prepared.device,
                                 render_path(candidate.config))["render"]
    if all(score == -math.inf for score in scores.values()):
        raise NumericalError(f"training diverged in the {trial.field} trial for every candidate "
                             f"({', '.join(map(str, trial.candidates))})")
    chosen = pick(trial, scores)
    loop = loops.pop(chosen)
    loops.clear()  # the others' models and optimisers go
    config = loop.candidate.config
    loop.candidate.reasons[trial.field] = trial_reason(trial, config, scores, chosen, val_rays.n_views, cameras.split)
    loop.trials = {trial.field: trial_record(trial, config, scores, chosen)}
    if progress:
        note(f"{trial.field}: {chosen} by trial (" + ", ".join(f"{v} {scores[v]:.2f} dB" for v in trial.candidates)
             + " on the val views)")
    write_bytes_atomic(run_dir / LOG, loop.log.getvalue().encode())
    loop.bar = _progress_bar(config, loop.training.loop, progress)
    return loop


def _resumed_candidate(run_dir: Path, prepared: Prepared, saved: dict) -> Candidate:
    """The candidate a resumed run's trial chose: the one whose setting its checked
    checkpoint holds (the trial is not run again), with the reason config.json gave."""
    field = prepared.trial.field
    value = (saved.get("config") or {}).get(field) if isinstance(saved.get("config"), dict) else None
    for candidate in prepared.candidates:
        if getattr(candidate.config, field) == value:
            earlier = _earlier(run_dir, "trials").get(field)
            earlier_reason = _earlier(run_dir, "auto_reasons").get(field)
            candidate.reasons[field] = (earlier_reason if isinstance(earlier, dict) and isinstance(earlier_reason, str)
                                        else f"{value} by a trial before the run was resumed ({CHECKPOINT} holds it)")
            return candidate
    raise InputError(f"{run_dir / CHECKPOINT} holds {field} {value!r}, none of its trial's candidates "
                     f"({', '.join(map(str, prepared.trial.candidates))}); pass --overwrite to start over")


def _earlier(run_dir: Path, key: str) -> dict:
    """config.json's table `key` ("trials", "auto_reasons") of the attempt being resumed
    ({} when it has none or the file is unreadable)."""
    try:
        document = read_json(run_dir / CONFIG)
    except InputError:
        return {}
    table = document.get(key) if isinstance(document, dict) else None
    return table if isinstance(table, dict) else {}


def _finish(run_dir: Path, loop: RunLoop, recipe: dict) -> dict:
    """After the loop: config.json's account of what the schedule decided and, for an
    `edges` run, its render filter; model.pt. Returns train's summary."""
    training, candidate = loop.training, loop.candidate
    model, state, config, reasons = training.model, training.loop, candidate.config, candidate.reasons
    if config.refine_grid:
        reasons["refine_grid"] = loop.schedule.refine_grid_reason(state, model.field.resolution)
    render_psnr = None
    if config.pixel_filter == "edges":
        reasons["edge_points"] = loop.schedule.edge_points_reason(state)
        config, reasons["render_filter"], render_psnr = choose_render_filter(model, config, *loop.val, loop.device)
    if config.surface_opacity:
        reasons["surface_opacity"] = (
            f"on from step {state.surface_step} (occupancy over {SURFACE_RISE_STEPS:g} marching steps): the "
            f"half-budget refinement" if state.surface_step else
            "set, but never on: the run made no half-budget refinement (its final grid had not converged, or the "
            "run ended first)")
    if config.refine_grid or config.pixel_filter == "edges" or config.surface_opacity:
        _write_config(run_dir, config, reasons, candidate.space, recipe, loop.trials)
    size = checkpoint.save_atomic(checkpoint.model_payload(model, config, prune=config.prune), run_dir / MODEL)
    return {"steps": state.step, "seconds": state.seconds, "val_psnr": loop.last_psnr, "model_bytes": size,
            "resolution": model.field.resolution if model.has_grid else None,
            "render_filter": config.render_filter, "render_val_psnr": render_psnr}


def choose_render_filter(model, config: TrainConfig, cameras, val_rays, device) -> tuple[TrainConfig, str, float]:
    """An `edges` run's render filter, by measurement on its val views (whole frames, the
    eval_views of psnr_on_white; nerf.trials.val_psnr): of RENDER_FILTERS (the centre ray
    alone, 2 x 2, 3 x 3 or 4 x 4 rays on the centre render's edge pixels), cheapest first,
    each kept when its gain over the last one kept pays for its rays (`rays_pay`). The box
    render assumes the field resolves what lies inside a pixel; where it cannot (bench
    hard's tiny: a 3-pixel sphere in a 53-voxel grid), averaging sub-pixel rays blurs the
    blur again: 56.99 dB against 58.32 through the centres of the same model (BENCHMARKS.md,
    "Edge pixels"); where it does, 3 x 3 integrates a sharp edge better. cameras, val_rays:
    the val views' cameras and rays (`prepare_run`). Returns (config with render_filter set,
    the reason, the chosen render's val PSNR: what `nerfgauge render` gives on whole val
    frames, where the log's val PSNR goes through pixel centres on a strided subset)."""
    rays = {}
    psnr = val_psnr(model, cameras, val_rays, device,
                    {name: (per_axis, per_axis > 1) for name, per_axis in RENDER_FILTERS.items()}, rays)
    chosen = next(iter(RENDER_FILTERS))
    for name in list(RENDER_FILTERS)[1:]:
        if rays_pay(psnr[name] - psnr[chosen], rays[name], rays[chosen]):
            chosen = name
    scores = ", ".join(f"{name} {value:.2f} dB, {rays[name]:.2f} rays a pixel" for name, value in psnr.items())
    reason = (f"{chosen}: on {val_rays.n_views} {cameras.split} views ({RENDER_FILTERS[chosen]} x "
              f"{RENDER_FILTERS[chosen]} rays on edge pixels; 1: the centre ray; a costlier render kept where "
              f"its rays pay): {scores}")
    per_axis, step, best = RENDER_FILTERS[chosen], RENDER_CHANGE_STEPS[0], psnr[chosen]
    if per_axis > 1:
        step, best, tried = choose_change_step(model, cameras, val_rays, device, per_axis, best, rays[chosen])
        reason += f"; change step {step:g} ({tried})"
    config = dataclasses.replace(config, render_filter=chosen,
                                 render_change_step=None if step == RENDER_CHANGE_STEPS[0] else step)
    return config, reason, best


def rays_pay(gain: float, rays: float, cost: float) -> bool:
    """Whether a render of `rays` per pixel pays over one of `cost` rays that scores `gain` dB
    less on the val views: a gain of at least RENDER_GAIN_DB, and of RENDER_DB_PER_DOUBLING
    per doubling of the frame's rays (a render's time follows its rays)."""
    return gain >= max(RENDER_GAIN_DB, RENDER_DB_PER_DOUBLING * math.log2(max(rays, 1e-9) / cost))


def choose_change_step(model, cameras, val_rays, device, per_axis: int, default_psnr: float,
                       default_rays: float) -> tuple:
    """The change step of an edges render of `per_axis` points (nerf.config.RENDER_CHANGE_STEPS):
    down from the default, each smaller step kept while its gain on the val views over the
    last one kept pays for its rays (`rays_pay`). default_psnr,
    default_rays: the default step's val PSNR and rays per pixel. Returns (step, its val
    PSNR, the scores as text)."""
    step, best, cost = RENDER_CHANGE_STEPS[0], default_psnr, default_rays
    tried = [f"{step:g} {best:.2f} dB, {cost:.2f} rays a pixel"]
    for smaller in RENDER_CHANGE_STEPS[1:]:
        rays = {}
        score = val_psnr(model, cameras, val_rays, device, {"step": (per_axis, True, smaller)}, rays)["step"]
        tried.append(f"{smaller:g} {score:.2f} dB, {rays['step']:.2f}")
        if not rays_pay(score - best, rays["step"], cost):
            break
        step, best, cost = smaller, score, rays["step"]
    return step, best, ", ".join(tried)


def _grow_grid(training: Training, config: TrainConfig, wanted: int) -> None:
    """Coarse to fine: upsample the grid to its stage's resolution (`wanted`) when it is not
    there yet, add the residual colour head once it is decided (LoopState.colour_head), and
    give Adam the new parameters (fresh moments) at the current learning rates."""
    model = training.model
    add_head = training.loop.colour_head == 1 and model.field.head is None
    if wanted == model.field.resolution and not add_head:
        return
    if wanted != model.field.resolution:
        model.upsample(wanted)
    if add_head:  # its hidden layer drawn from the run's seed, the caller's RNG untouched
        with torch.random.fork_rng(devices=[]):
            torch.random.manual_seed(config.seed + HEAD_SEED_OFFSET)
            model.field.add_residual_head(config.feature_channels)
    rates = [group["lr"] for group in training.optimizer.param_groups]
    training.optimizer = make_optimizer(model, config)
    for group, rate in zip(training.optimizer.param_groups, rates):
        group["lr"] = rate


def _train_step(training: Training, config: TrainConfig, rays, n_rays: int, device,
                lr_scales: RateScales, priors: float | None = None) -> tuple[float, bool]:
    """One optimiser step on `n_rays` random training rays. lr_scales: each parameter
    group's learning rate as a fraction of its base, by group name (nerf.schedule's
    `lr_scales`). priors:
    the spread of the train cameras when the sparse-capture priors are on (nerf.sparse_priors), else None.
    Returns (loss, whether every gradient was finite); a step with a non-finite gradient
    leaves the parameters alone."""
    model, generator, state = training.model, training.generator, training.loop
    optimizer = training.optimizer
    for group in optimizer.param_groups:
        group["lr"] = group["base_lr"] * lr_scales[group["name"]]
    # TrainConfig.pixel_filter: per pixel one ray through its centre or a random point of
    # it, or (box) the mean of 2 x 2 rays through the box render's points, so the loss
    # compares the pixel's box-filtered colour with the ground truth's (pixel_sample_offsets
    # says why fixed points); n_rays counts rays either way.
    # edges: k x k rays through the box render's points on the target's edge pixels only
    # (LoopState.edge_points: 2 x 2, later 3 x 3), one centre ray on the rest (a pixel's box
    # mean equals its centre's value where nothing steps inside it); n_rays counts pixels,
    # the edge pixels' extra rays come on top.
    per_pixel = TRAIN_PIXEL_SAMPLES[config.pixel_filter]
    n_pixels = max(1, n_rays // per_pixel)
    index = torch.randint(rays.origins.shape[0], (n_pixels,), generator=generator)
    origins, directions, rgba = (t[index].to(device) for t in (rays.origins, rays.directions, rays.rgba))
    if config.background == "random":
        background = torch.rand((n_pixels, 3), generator=generator).to(device)
    else:
        background = torch.full((3,), 1.0 if config.background == "white" else 0.0, device=device)
    target = rgba[:, :3] * rgba[:, 3:] + background * (1 - rgba[:, 3:])
    if config.pixel_filter == "edges":
        (origins, directions), pixels = _edge_rays(rays, index, origins, directions, state.edge_points ** 2, generator,
                                                   device)
    else:
        if config.pixel_filter != "centre":
            offsets = pixel_sample_offsets(n_pixels, per_pixel, generator).to(device)  # [per_pixel * n_pixels, 2]
            origins = origins.repeat(per_pixel, 1)
            directions = jittered_direction(directions.repeat(per_pixel, 1),
                                            rays.footprint[index].to(device).repeat(per_pixel, 1, 1), offsets)
        pixels = MeanOfRepeats(per_pixel, n_pixels)
    out = model.render(origins, directions, generator=generator, training=True)

    # [n_pixels, 3]: each pixel's rays averaged (in linear light), composited, minus the target
    def pixel_error(rgb, opacity):
        return composite(*pixels.gather(rgb, opacity), background) - target

    loss = (pixel_error(out.rgb, out.opacity) ** 2).mean()
    if out.coarse is not None:
        loss = loss + (pixel_error(out.coarse.rgb, out.coarse.opacity) ** 2).mean()
    loss = loss + model.regularisation(config.tv_weight)
    if out.distortion is not None and config.distortion_weight > 0:
        loss = loss + config.distortion_weight * out.distortion.mean()
    if priors is not None:
        unseen_origins, unseen_directions = unseen_rays(rays.origins, rays.directions, priors, PRIOR_RAYS, generator)
        loss = loss + prior_loss(model, unseen_origins.to(device), unseen_directions.to(device), generator)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    # One reduction per parameter: NaN or inf anywhere makes the total non-finite. Checked
    # before the step so a bad gradient never reaches the parameters or Adam's moments.
    total = sum(p.grad.sum() for group in optimizer.param_groups for p in group["params"] if p.grad is not None)
    gradients_finite = bool(torch.isfinite(torch.as_tensor(total)))
    if gradients_finite:
        optimizer.step()
    return float(loss.detach()), gradients_finite


class MeanOfRepeats:
    """Pixels from rays laid out as `per_pixel` blocks of `n_pixels` rays (ray r of pixel p
    at row r * n_pixels + p): each pixel's mean in linear light (nerf.rendering.pixel_mean)."""

    def __init__(self, per_pixel: int, n_pixels: int):
        self.per_pixel, self.n_pixels = per_pixel, n_pixels

    def gather(self, rgb: torch.Tensor, opacity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb [per_pixel * n_pixels, 3] premultiplied, opacity [per_pixel * n_pixels] ->
        [n_pixels, 3], [n_pixels]."""
        if self.per_pixel == 1:
            return rgb, opacity
        return pixel_mean(rgb.view(self.per_pixel, self.n_pixels, 3), opacity.view(self.per_pixel, self.n_pixels))


class EdgeSplit:
    """Pixels from rays laid out as one centre ray for each plain pixel (`plain`, indices
    into the batch's pixels) followed by `per_pixel` blocks of one ray for each edge pixel
    (`edge`): a plain pixel's ray, an edge pixel's mean in linear light (nerf.rendering.pixel_mean)."""

    def __init__(self, plain: torch.Tensor, edge: torch.Tensor, n_pixels: int, per_pixel: int):
        self.plain, self.edge, self.n_pixels, self.per_pixel = plain, edge, n_pixels, per_pixel

    def gather(self, rgb: torch.Tensor, opacity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """rgb [rays, 3] premultiplied, opacity [rays] -> [n_pixels, 3], [n_pixels]."""
        n_plain = len(self.plain)
        pixel_rgb, pixel_opacity = rgb.new_empty((self.n_pixels, 3)), opacity.new_empty(self.n_pixels)
        pixel_rgb[self.plain], pixel_opacity[self.plain] = rgb[:n_plain], opacity[:n_plain]
        if len(self.edge):  # a batch may hold no edge pixel (an empty scene has none at all)
            edge_rgb, edge_opacity = pixel_mean(rgb[n_plain:].reshape(self.per_pixel, len(self.edge), 3),
                                                opacity[n_plain:].reshape(self.per_pixel, len(self.edge)))
            pixel_rgb[self.edge], pixel_opacity[self.edge] = edge_rgb, edge_opacity
        return pixel_rgb, pixel_opacity


def _edge_rays(rays, index: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, per_pixel: int,
               generator: torch.Generator, device) -> tuple[tuple[torch.Tensor, torch.Tensor], EdgeSplit]:
    """The `edges` filter's rays for the batch's pixels `index` (their centre rays
    origins, directions [n_pixels, 3]), `per_pixel` (a square) on each edge pixel:
    ((origins, directions) [rays, 3], EdgeSplit)."""
    is_edge = rays.edges[index].to(device)
    plain, edge = (~is_edge).nonzero().squeeze(1), is_edge.nonzero().squeeze(1)
    offsets = pixel_sample_offsets(len(edge), per_pixel, generator).to(device)
    moved = jittered_direction(directions[edge].repeat(per_pixel, 1),
                               rays.footprint[index[edge.cpu()]].to(device).repeat(per_pixel, 1, 1), offsets)
    return ((torch.cat([origins[plain], origins[edge].repeat(per_pixel, 1)]),
             torch.cat([directions[plain], moved])), EdgeSplit(plain, edge, len(index), per_pixel))


def pixel_sample_offsets(n_pixels: int, per_pixel: int, generator: torch.Generator) -> torch.Tensor:
    """Offsets from the pixel centre (pixels, x then y, in [-0.5, 0.5)) of `per_pixel` rays
    for each of n_pixels pixels: one uniform random point of the pixel when per_pixel is 1
    (`jitter`); else the centres of a k x k grid of cells (k^2 = per_pixel), the points the
    box render averages (nerf.frames.pixel_offsets), the same in every pixel and step.

    Why not a random point in each cell: the squared error of a pixel's mean over random
    rays is the error of their expectation plus their variance, and that variance is the
    spread of the field inside the pixel, so the loss rewards a silhouette or texture edge
    for blurring. Through fixed points the loss sees only what the render averages, across
    views the points fall everywhere on the surfaces, and the model keeps edges sharp:
    primitives 128 px, 300 s, 42.94 dB against 42.18 with random points (edge pixels 34.62
    against 33.79; BENCHMARKS.md, "Train through the render's points").
    Returns [per_pixel * n_pixels, 2], ray r of pixel p at row r * n_pixels + p."""
    if per_pixel == 1:
        return torch.rand((n_pixels, 2), generator=generator) - 0.5
    centres = torch.from_numpy(pixel_offsets(math.isqrt(per_pixel)).astype(np.float32))  # [per_pixel, 2]
    return centres[:, None, :].expand(per_pixel, n_pixels, 2).reshape(-1, 2)


def _truncate_log(path: Path, last_step: int) -> None:
    """Drop log entries past the checkpoint being resumed (checkpoints are rarer than log
    points), so the resumed run's entries continue the curve instead of repeating steps.
    A torn last line (the writer was killed mid-line) is dropped; a damaged line before
    it is an InputError."""
    lines = [line for line in (path.read_text(errors="replace").split("\n") if path.is_file() else [])
             if line.strip()]
    kept = []
    for number, line in enumerate(lines, 1):
        try:
            entry = bounded.loads_json(line, path)
        except json.JSONDecodeError:
            if number == len(lines):
                break  # torn by a kill mid-write
            raise InputError(f"{path} line {number} is not JSON; fix or delete the line to resume") from None
        step = entry.get("step") if isinstance(entry, dict) else None
        if type(step) is not int or step < 0:  # as the loop writes it: a non-negative int (not a bool)
            raise InputError(f"{path} line {number} has no integer step; fix or delete the line to resume")
        if entry["step"] <= last_step:
            kept.append(line)
    write_bytes_atomic(path, "".join(line + "\n" for line in kept).encode())


def _save_checkpoint(run_dir: Path, training: Training, config: TrainConfig, recipe: dict) -> None:
    checkpoint.save_atomic(checkpoint.training_checkpoint(training.model, training.optimizer, training.generator,
                                                          config, recipe, training.loop), run_dir / CHECKPOINT)
