"""The training stage's one config, and how "model only what the scene needs" is decided.

`TrainConfig` is frozen and saved as RUN/config.json. Fields left as None ("auto") are
resolved from the dataset's scene.json by `resolve`, and every resolved choice is written
with the reason it was made, so a run states what it modelled and why. A field the command
line sets names its flag in its metadata (`FLAGS`; nerf.options adds the flags, and
`nerfgauge train` and `nerfgauge run` both take them). This module imports no torch, so
the flags' defaults come from here without slowing `nerfgauge --help`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.nerf.schedule import (FINE_EDGE_POINTS_AT, FINE_EDGE_POINTS_MIN_STEPS, STAGE_RATIO, START_VOXELS,
                                     start_resolution_for, upsample_count)

MODELS = ("compact", "vanilla")
BACKGROUNDS = ("random", "white", "black")
# TrainConfig.pixel_filter -> training rays per pixel, averaged before the loss (nerf.train)
TRAIN_PIXEL_SAMPLES = {"box": 4, "jitter": 1, "centre": 1, "edges": 1}
# The automatic filter is `edges` while edge pixels are at most this share of the training
# pixels: their extra rays then at most double the rays a step (1 + 3 x 1/3). Bench and
# suite scenes hold 9-24% (primitives 128 px 12.6%); forward-near at 64 px 75% and
# far-reaching 52% (textures finer than the pixels), where the extra rays cost more steps
# than they gain (`pixel_filter_for`).
EDGE_SHARE_MAX = 1 / 3
PIXEL_FILTERS = tuple(TRAIN_PIXEL_SAMPLES)
# An `edges` run's render filters, cheapest first: rays per axis on the centre render's edge
# pixels (nerf.frames.box_frame), 1 for the centre ray alone. 3 x 3: a model trained through
# fixed points keeps edges sharp (nerf.train.pixel_sample_offsets), and the box mean of a
# sharp edge wants more than 2 x 2 points (primitives 128 px, 300 s: 43.09 dB against 42.94;
# far-object 64 px: 45.04 against 43.70; BENCHMARKS.md, "Train through the render's points").
# 4 x 4 renders a run whose edge pixels trained through them (nerf.schedule.FINER_EDGE_POINTS_AT).
RENDER_FILTERS = {"centre": 1, "edges": 2, "edges-3x3": 3, "edges-4x4": 4}
# Which of those points an edges render gives rays of their own (`nerfgauge render --sub-rays`,
# nerf.frames.box_frame): "changes" (the default), the points between centres of the centre
# render that differ; "edge-pixels", every point of its edge pixels (the render before issue 52).
SUB_RAYS = ("changes", "edge-pixels")
# Centres that differ by more than this in premultiplied colour or alpha (any channel, on
# [0, 1]) give the points between them rays; closer, the points are interpolated. Measured
# against 3 x 3 rays on every edge pixel (primitives 128 px, 600-s model, 20 test views,
# 17,139 extra rays a frame): 0.1 -0.81 dB (5,566 rays), 0.05 -0.19 dB (7,451), 0.04
# -0.06 dB (8,240), 0.03 +0.16 dB (10,178), 0.025 +0.24 dB (11,230): the model's texture
# holds steps inside a pixel that its centres show only as a few hundredths
# (docs/results.md, "Render time"). 0.04 keeps a margin to the 0.2 dB.
# `nerfgauge render --change-step` sets it for one render. Smaller steps give the rays a
# converged model's texture and interior need (its centres differ there by a few hundredths,
# the noise it learned): the 600-s primitives model with surface opacity, 46.54 dB at 0.04,
# 46.85 at 0.02, 47.01 at 0.01, 47.07 at 0 (38.7, 40.6, 49.3, 65.9 ms a 128 px frame, 2
# threads; its 1200-s twin 42.5 ms at 0.04, 56.6 at 0.01); thin 64 px +0.57 dB at 0.01; but
# a fuzzy 1000-step 256 px model gains 0.06 dB for 1.5x the time (225 ms a frame, over the
# issue's 200): 0.04 stays the default, and a run takes a smaller step where its val views
# show the gain (RENDER_CHANGE_STEPS below; docs/results.md, "The render's change step").
CHANGE_STEP = 0.04
# A render's extra rays pay when its gain on the val views is at least RENDER_GAIN_DB and at
# least RENDER_DB_PER_DOUBLING times log2 of the growth of the frame's rays (a render's time
# follows its rays: about 1.6 us a ray on 2 threads, at 128 and at 256 px;
# nerf.train.rays_pay). An edges run's render filter is found by walking RENDER_FILTERS
# cheapest first, each kept where its rays pay over the last one kept
# (nerf.train.choose_render_filter: the fresh 600-s primitives model, trained through 3 x 3
# points, gains 0.33 dB on its val views through 4 x 4 for 44% more rays (needed 0.53);
# through them its frame takes 74-81 ms against 45). Its render then takes a smaller step
# where the rays pay: from CHANGE_STEP down these steps, each halving kept while they do
# (nerf.train.choose_change_step). Measured
# (docs/results.md, "The render's change step"): the shipped 600-s primitives model gains
# 0.36 dB on its val views for 12% more rays at 0.02 (needed 0.16) and 0.18 for 19% more at
# 0.01 (needed 0.25): 0.02; a 600-s 256 px run gains 0.12 for 29% more (needed 0.37), whose
# frame would take 191-200 ms against 134-146, and keeps 0.04.
RENDER_CHANGE_STEPS = (CHANGE_STEP, 0.02, 0.01)
RENDER_GAIN_DB = 0.1
RENDER_DB_PER_DOUBLING = 1.0
# The sparse grid stores values only where cells are occupied, but its node index (4 bytes
# a node: 67 MB at 256^3, 537 MB at 512^3) and the marching samples per ray still grow with
# the resolution. Cameras inside the scene's bounding sphere (rooms, forward-facing
# captures) ask for an unbounded resolution: they get this cap.
MAX_AUTO_RESOLUTION = 256
MAX_BATCH_RAYS = arguments.BATCH_RAYS.high  # a batch's samples must fit in memory: ~126 per contracted ray
# Marching step in voxels while training, by parametrisation. Contracted space takes a
# whole voxel: its rays cross the inner ball and the disparity-uniform shell, ~126 samples
# at half a voxel on far-reaching, and at 120 s on 2 cores twice the steps beat the finer
# step (128 px: 26.22 dB at 1.0 voxel, 24.71 at 0.5, 25.34 at 2.0; BENCHMARKS.md).
STEP_RATIOS = {"bounded": 0.5, "contracted": 1.0, "forward": 0.5}
# Rays per training step, by parametrisation. Contracted rays keep ~126 samples (bounded
# ~12): at 4096 rays a far-reaching step took 0.37 s at the 192 grid, and 2048 rays buy
# 2.6x the steps in 120 s: 28.45 dB against 27.01 (1024: 28.34). Bounded space keeps
# 4096: primitives 128 px scored 38.66 dB with 2048 against 38.85 (BENCHMARKS.md part 6).
BATCH_RAYS = {"bounded": 4096, "contracted": 2048, "forward": 4096}
# The settings whose auto value is the parametrisation's: {field: (value by kind, reason)}
BY_PARAMETRISATION = {"step_ratio": (STEP_RATIOS, "marching steps of {} voxel"),
                      "batch_rays": (BATCH_RAYS, "{} rays a step")}
UNBOUNDED_MAX_RESOLUTION = 192  # contracted / forward grids (every cell of them is in view)
DEFAULT_LEARNING_RATE = 0.1  # TrainConfig.lr's default: voxel grids take DVGO-style large steps
# The one default budget: a run given neither a step count nor a time budget trains this
# many seconds (`nerfgauge train`, `nerfgauge run`, the API and the benches alike).
DEFAULT_BUDGET_SECONDS = 120.0
# A flag's words for a field's values that are not plain: "auto" is None, which `resolve`
# decides from the data; a switch's on and off are True and False.
AUTO = {"auto": None}
SWITCH = {"auto": None, "on": True, "off": False}


def _flag(flag: str, default=None, words: Optional[dict] = None):
    """A TrainConfig field the command line sets with `flag` (nerf.options adds it; messages
    name it, `FLAGS`); words: the flag's words for values that are not plain (AUTO, SWITCH)."""
    return field(default=default, metadata={"flag": flag, **({"words": words} if words else {})})


@dataclass(frozen=True)
class TrainConfig:
    dataset: str
    model: str = _flag("--model", "compact")
    seed: int = _flag("--seed", 0)
    steps: Optional[int] = _flag("--steps")  # stop after this many steps ...
    # ... or after this much training time; with neither, DEFAULT_BUDGET_SECONDS (`__post_init__`)
    budget_seconds: Optional[float] = _flag("--budget-seconds")
    batch_rays: Optional[int] = _flag("--batch-rays")  # rays per compact step; None: BATCH_RAYS[parametrisation]
    lr: float = DEFAULT_LEARNING_RATE  # voxel grids; MLP heads use lr_mlp; sparse-capture priors: `resolve`
    lr_mlp: float = 5e-3
    background: str = "random"  # training background per ray: random makes alpha learnable
    # compact: None = decide from scene.json (see `resolve`)
    view_dependent: Optional[bool] = _flag("--view-dependent", words=SWITCH)
    # bounded | contracted | forward (nerf.parametrisation); None = from cameras and bounds
    parametrisation: Optional[str] = _flag("--parametrisation", words=AUTO)
    final_resolution: Optional[int] = _flag("--resolution")  # voxels along the AABB's longest side
    start_resolution: Optional[int] = None
    prune: bool = _flag("--no-prune", True)
    quantise: str = _flag("--quantise", "fp16")  # saved model's grid values: fp16, or int8 with a per-channel scale
    occupancy: bool = _flag("--no-occupancy", True)  # empty-space skipping
    tv_weight: float = _flag("--tv-weight", 0.0)
    distortion_weight: float = 1e-3  # mip-NeRF 360 distortion loss: solid surfaces, exact depth
    # ray-marching step in voxels; None: STEP_RATIOS[parametrisation]
    step_ratio: Optional[float] = _flag("--step-ratio")
    # What a training pixel's colour is compared as: "centre", its centre ray; "box", the mean
    # of 2 x 2 stratified rays through the pixel, as the ground truth's box filter averages its
    # area; "edges", the box on the target's edge pixels and the centre ray elsewhere;
    # "jitter", one ray through a random point of it. None: `pixel_filter_for`.
    pixel_filter: Optional[str] = _flag("--pixel-filter", words=AUTO)
    feature_channels: int = 12  # view-dependent colour: grid features fed to a small MLP
    # vanilla (the original NeRF, Mildenhall et al. 2020)
    n_coarse: int = 64
    n_fine: int = 128
    width: int = 256
    depth: int = 8
    vanilla_batch_rays: int = 1024
    # logging
    eval_every_seconds: float = _flag("--eval-every", 10.0)  # val PSNR points along the way (training clock)
    eval_views: int = 4
    eval_rays: int = 8192  # val pixels per PSNR point (a fixed strided subset of eval_views)
    # checkpoint.pt every this many steps (and at step 0 and the end); None: at most once a
    # minute of wall time (and at the end)
    checkpoint_every: Optional[int] = _flag("--checkpoint-every")
    threads: int = _flag("--threads", 2)
    device: str = _flag("--device", "auto")
    # train on the dataset's sparse list of this many views (sparse_views.json; nerf.data);
    # None: every train view. Left out of config.json when None, so older runs keep their recipe.
    sparse: Optional[int] = _flag("--sparse")
    # How an `edges` run's frames are rendered, chosen at the end of training on the val
    # views (nerf.train.choose_render_filter), one of RENDER_FILTERS. None: not chosen (any
    # other filter renders by its own rule). Left out of config.json when None; not part of
    # the recipe (it follows from it).
    render_filter: Optional[str] = None
    # With it, the change step its render gives sub-rays by (RENDER_CHANGE_STEPS), chosen on
    # the same views. None: CHANGE_STEP. Left out of config.json when None, as render_filter.
    render_change_step: Optional[float] = None
    # priors on rays from unseen viewpoints (nerf.sparse_priors; the compact model's): None:
    # on for a sparse capture from inside the scene (`sparse_priors_for`). Left out of
    # config.json when False, so runs made before the mode keep their recipe.
    sparse_priors: Optional[bool] = _flag("--sparse-priors", words=SWITCH)
    # a residual colour head on a diffuse grid (nerf.grid_field.add_residual_head), added
    # once the final grid has trained nerf.schedule.MIN_STAGE_STEPS steps. None (auto): not
    # added (`colour_head_for` says why). Left out of config.json while None, so older runs
    # keep their recipe.
    colour_head: Optional[bool] = _flag("--colour-head", words=SWITCH)
    # one coarse-to-fine stage past final_resolution (`refined_resolution`) from half the
    # budget, when the final grid has converged by then (nerf.schedule.Schedule.refinement_due;
    # a time budget's growth trial still judges it). None: `refine_grid_for`. Left out of
    # config.json when None or False, so runs made before it keep their recipe.
    refine_grid: Optional[bool] = _flag("--refine-grid", words=SWITCH)
    # surface opacity (nerf.packed.occupancy_rise_taus) from the half-budget refinement of a
    # compact run, when that refines (nerf.schedule.SURFACE_RISE_STEPS). None (auto): off
    # (`surface_opacity_for` says why). Left out of config.json while None, so older runs keep
    # their recipe.
    surface_opacity: Optional[bool] = _flag("--surface-opacity", words=SWITCH)

    def __post_init__(self) -> None:
        if self.steps is None and self.budget_seconds is None:  # the one default budget
            object.__setattr__(self, "budget_seconds", DEFAULT_BUDGET_SECONDS)

    def validate(self) -> None:
        """One-line InputError for anything a run cannot use (the API path: the CLI's
        argument types already refuse NaN, inf and non-positive counts)."""
        from nerfgauge.nerf.parametrisation import PARAMETRISATIONS  # torch: kept off `nerfgauge --help`'s import path

        if not isinstance(self.dataset, str) or not self.dataset.strip():
            raise InputError(f"dataset must be a non-empty path, got {self.dataset!r}")
        if self.model not in MODELS:
            raise InputError(f"unknown model {self.model!r}; choose one of {', '.join(MODELS)}")
        if self.steps is not None and self.budget_seconds is not None:
            raise InputError("give one of --steps N or --budget-seconds T, not both")
        if self.quantise not in ("fp16", "int8"):
            raise InputError(f"unknown --quantise {self.quantise!r}; choose fp16 or int8")
        if self.pixel_filter is not None and self.pixel_filter not in PIXEL_FILTERS:
            raise InputError(f"unknown pixel filter {self.pixel_filter!r}; choose {', '.join(PIXEL_FILTERS)}")
        if self.render_filter is not None and self.render_filter not in RENDER_FILTERS:
            raise InputError(f"unknown render filter {self.render_filter!r}; choose {', '.join(RENDER_FILTERS)}")
        if self.render_change_step is not None and self.render_change_step not in RENDER_CHANGE_STEPS:
            raise InputError(f"unknown render change step {self.render_change_step!r}; choose one of "
                             f"{', '.join(map(str, RENDER_CHANGE_STEPS))}")
        if self.background not in BACKGROUNDS:
            raise InputError(f"unknown background {self.background!r}; choose one of {', '.join(BACKGROUNDS)}")
        # every number through its range: the command line's (core.arguments) where it has a flag
        arguments.check_fields(self, FIELD_RANGES, flags=FLAGS)
        if self.parametrisation is not None and self.parametrisation not in PARAMETRISATIONS:
            raise InputError(f"unknown parametrisation {self.parametrisation!r}; choose one of "
                             f"{', '.join(PARAMETRISATIONS)}")
        if not (self.view_dependent is None or isinstance(self.view_dependent, bool)):
            raise InputError(f"--view-dependent must be true, false or None (auto), got {self.view_dependent!r}")
        if not (self.sparse_priors is None or isinstance(self.sparse_priors, bool)):
            raise InputError(f"--sparse-priors must be true, false or None (auto), got {self.sparse_priors!r}")
        if not (self.colour_head is None or isinstance(self.colour_head, bool)):
            raise InputError(f"--colour-head must be true, false or None (auto), got {self.colour_head!r}")
        if self.colour_head and self.model != "compact":
            raise InputError("--colour-head on needs the compact model (the head reads its grid's features)")
        if self.colour_head and self.view_dependent:
            raise InputError("--colour-head on is for a diffuse grid; --view-dependent on has its own colour head")
        if not (self.refine_grid is None or isinstance(self.refine_grid, bool)):
            raise InputError(f"--refine-grid must be true, false or None (auto), got {self.refine_grid!r}")
        if self.refine_grid and self.model != "compact":
            raise InputError("--refine-grid on needs the compact model (it grows its voxel grid)")
        if not (self.surface_opacity is None or isinstance(self.surface_opacity, bool)):
            raise InputError(f"--surface-opacity must be true, false or None (auto), got {self.surface_opacity!r}")
        if self.surface_opacity and self.model != "compact":
            raise InputError("--surface-opacity on needs the compact model (it switches at its grid's half-budget "
                             "refinement)")
        if self.sparse_priors and self.model != "compact":
            raise InputError("--sparse-priors on needs the compact model (they act on its voxel grid)")
        for name in ("prune", "occupancy"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if not isinstance(self.device, str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device):
            raise InputError(f"unknown device {self.device!r}; choose auto, cpu, cuda or cuda:N")

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        for optional in ("sparse", "render_filter", "render_change_step", "sparse_priors", "colour_head", "refine_grid",
                         "surface_opacity"):
            if out[optional] is None or (optional in ("sparse_priors", "refine_grid") and out[optional] is False):
                del out[optional]
        return out


# {field: its command-line flag} (the fields' metadata), for messages that name what the user typed
FLAGS = {item.name: item.metadata["flag"] for item in dataclasses.fields(TrainConfig) if "flag" in item.metadata}


SAMPLES_PER_RAY = arguments.bounded(int, 1, 4096)  # the vanilla NeRF's coarse and fine samples
LEARNING_RATE = arguments.bounded(float, 0, 10, above=True)  # Adam's step; 10 overshoots any grid value
# Every numeric field of TrainConfig and its range (None-valued fields are optional).
FIELD_RANGES = {
    "steps": arguments.STEPS, "budget_seconds": arguments.SECONDS, "checkpoint_every": arguments.STEPS,
    "seed": arguments.SEED, "sparse": arguments.VIEWS, "threads": arguments.THREADS, "eval_every_seconds": arguments.SECONDS,
    "batch_rays": arguments.BATCH_RAYS, "vanilla_batch_rays": arguments.BATCH_RAYS,
    "final_resolution": arguments.GRID_RESOLUTION, "start_resolution": arguments.GRID_RESOLUTION,
    "step_ratio": arguments.STEP_RATIO, "tv_weight": arguments.WEIGHT, "distortion_weight": arguments.WEIGHT,
    "lr": LEARNING_RATE, "lr_mlp": LEARNING_RATE, "eval_views": arguments.VIEWS, "eval_rays": arguments.BATCH_RAYS,
    "feature_channels": arguments.bounded(int, 1, 256), "n_coarse": SAMPLES_PER_RAY, "n_fine": SAMPLES_PER_RAY,
    "width": arguments.bounded(int, 1, 4096), "depth": arguments.bounded(int, 1, 64),
}


def footprint_resolution(aabb: np.ndarray, c2w: np.ndarray, focal: float,
                         nyquist_period: Optional[float]) -> tuple[int, str, str]:
    """Voxels along the AABB's longest side so a voxel is no smaller than what a pixel
    resolves: the pixel footprint at the nearest content (camera distance to the AABB's
    bounding sphere), and no coarser than half the finest texture period (Nyquist).
    Returns (resolution, reason, what set it: "footprint", "texture" or "cap")."""
    centre = (aabb[0] + aabb[1]) / 2
    bound = float(np.linalg.norm(aabb[1] - aabb[0])) / 2
    nearest = float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).min()) - bound
    longest = float((aabb[1] - aabb[0]).max())
    if nearest <= 0:  # content may sit at any distance from such a camera: no footprint bounds it
        voxel, reason, set_by = 0.0, "a camera stands within the AABB's bounding sphere", "cap"
    else:
        voxel = nearest / focal  # scene units per pixel at the nearest content
        reason, set_by = f"pixel footprint {voxel:.4g} at distance {nearest:.3g}", "footprint"
    if nyquist_period is not None and nyquist_period / 2 < voxel:
        voxel = nyquist_period / 2
        reason, set_by = f"half the finest texture period {nyquist_period:.4g}", "texture"
    wanted = math.ceil(longest / voxel) if voxel > 0 else math.inf
    resolution = int(min(max(wanted, 16), MAX_AUTO_RESOLUTION))
    if wanted > MAX_AUTO_RESOLUTION:
        reason += (f" asks for {wanted} voxels" if voxel > 0 else "") + \
            f"; capped at {MAX_AUTO_RESOLUTION} (node index and samples per ray)"
        set_by = "cap"
    return resolution, reason, set_by


def resolve(config: TrainConfig, needs: Optional[dict], aabb: np.ndarray, train_c2w: np.ndarray,
            focal: float, width: Optional[int] = None, opaque: Optional[float] = None,
            edge_share: Optional[float] = None, views_per_point: Optional[float] = None) -> tuple[TrainConfig, dict]:
    """Fill the automatic choices. Returns the resolved config and {choice: reason}.
    width: the training images' width in pixels (the unbounded grids' resolution follows it).
    opaque: the share of training pixels with alpha 1 (whether the capture is closed; see
    choose_parametrisation), None when unknown. edge_share: the share of training pixels
    that are edge pixels (`pixel_filter_for`), None when unknown. views_per_point: the
    median number of train images holding a point of the box (nerf.sparse_priors), None
    when unknown."""
    from nerfgauge.nerf.parametrisation import choose_parametrisation  # torch: kept off `nerfgauge --help`'s import path
    from nerfgauge.nerf.sparse_priors import PRIOR_LEARNING_RATE, cameras_inside, sparse_priors_for  # torch

    reasons = {}
    updates = {}
    kind, reasons["parametrisation"] = choose_parametrisation(config.parametrisation, aabb, train_c2w, opaque)
    updates["parametrisation"] = kind
    if config.view_dependent is None:
        if needs is None:
            updates["view_dependent"] = True
            reasons["view_dependent"] = "no scene.json: a safe general default"
        else:
            updates["view_dependent"] = bool(needs.get("view_dependent", True))
            reasons["view_dependent"] = f"scene.json needs.view_dependent = {needs.get('view_dependent')}"
    else:
        reasons["view_dependent"] = "set on the command line"
    if config.colour_head and updates.get("view_dependent", config.view_dependent):
        raise InputError("--colour-head on is for a diffuse grid; this scene's is view-dependent "
                         "(its own colour head); pass --view-dependent off with it")
    if config.model == "compact":
        reasons["colour_head"] = colour_head_for(dataclasses.replace(config, **updates))[1]
        reasons["surface_opacity"] = surface_opacity_for(config)[1]
    resolution_set_by = None  # what set an automatic bounded grid's resolution (footprint_resolution)
    if config.final_resolution is None and kind != "bounded":
        # the contracted cube's inner ball, or the frustum's angles, get about one cell per
        # pixel across the image: twice the width along the grid's longest side
        wanted = 2 * (width or 64)
        updates["final_resolution"] = int(min(max(wanted, 32), UNBOUNDED_MAX_RESOLUTION))
        reasons["final_resolution"] = (f"{kind} grid: twice the image width ({width} px)"
                                       + (f", capped at {UNBOUNDED_MAX_RESOLUTION}" if wanted > UNBOUNDED_MAX_RESOLUTION else ""))
    elif config.final_resolution is None:
        period = None if needs is None else needs.get("finest_texture_period")
        updates["final_resolution"], why, resolution_set_by = footprint_resolution(aabb, train_c2w, focal, period)
        reasons["final_resolution"] = why
    else:
        reasons["final_resolution"] = "set on the command line"
    updates["pixel_filter"], reasons["pixel_filter"] = pixel_filter_for(config, edge_share, kind)
    if config.model == "compact":
        updates["sparse_priors"], reasons["sparse_priors"] = sparse_priors_for(
            config.sparse_priors, views_per_point, kind, cameras_inside(aabb, train_c2w), opaque)
        if updates["sparse_priors"] and config.lr == DEFAULT_LEARNING_RATE:  # not one the API set
            updates["lr"] = PRIOR_LEARNING_RATE
            reasons["lr"] = (f"{PRIOR_LEARNING_RATE} with the sparse-capture priors (otherwise "
                             f"{DEFAULT_LEARNING_RATE}): nerf.sparse_priors.PRIOR_LEARNING_RATE says why")
    per_pixel = TRAIN_PIXEL_SAMPLES[updates["pixel_filter"]]
    for name, (by_kind, reason) in BY_PARAMETRISATION.items():
        if getattr(config, name) is None:
            updates[name] = by_kind[kind]
            reasons[name] = f"{kind} space: {reason.format(by_kind[kind])}"
            if name == "batch_rays" and per_pixel > 1:  # as many pixels a step as one ray a pixel gets
                updates[name] *= per_pixel
                reasons[name] += f" x {per_pixel} rays a pixel ({updates['pixel_filter']} filter)"
        else:
            reasons[name] = "set on the command line"
    final = updates.get("final_resolution", config.final_resolution)
    updates["refine_grid"], reasons["refine_grid"] = refine_grid_for(dataclasses.replace(config, **updates),
                                                                      resolution_set_by)
    if config.start_resolution is None:
        updates["start_resolution"] = start_resolution_for(final, config.steps)
        reasons["start_resolution"] = (f"coarse to fine: {upsample_count(updates['start_resolution'], final)} "
                                       f"stages of about x{STAGE_RATIO:.2f} from about {START_VOXELS} voxels")
    return dataclasses.replace(config, **updates), reasons


def pixel_filter_for(config: TrainConfig, edge_share: Optional[float] = None,
                     kind: Optional[str] = None) -> tuple[str, str]:
    """The pixel filter a run trains with, and why: as set; else `edges` in bounded space
    (`kind`) when at most EDGE_SHARE_MAX of the training pixels are edge pixels
    (`edge_share`); `centre` otherwise or when either is unknown. The ground truth
    box-filters every pixel; only on edge pixels does that differ from the centre ray's
    colour, so the box's 2 x 2 rays go there alone (BENCHMARKS.md, "Edge pixels":
    primitives 128 px, 120 s, 42.12 dB against 39.64 with centre rays; far-object 64 px,
    30 s, 45.31 against 40.14). Where most pixels are edges (a texture finer than the
    pixels), the extra rays cost more steps than they gain. Both forward captures measured
    lost with it: forward-near 64 px, 60 s (75% edge pixels) 25.8 against 34.2 dB, and
    depth-range at bench hard's 400 steps (27%) 31.73 against 33.66, where `box` and
    `jitter` lost too (33.04, 32.04); no contracted capture with few edges was measured.
    `box` (2 x 2 rays on every pixel) lost 2.1 dB to centre rays at 128 px, 90 s: its
    steps cost 3.6x, so the budget kept a 68-voxel grid where centre rays reached 109."""
    if config.pixel_filter is not None:
        return config.pixel_filter, "set on the command line"
    if edge_share is None or kind is None:
        return "centre", "the default without the training images' edge share: one ray through each pixel's centre"
    share = f"{100 * edge_share:.1f}% of training pixels are edge pixels"
    if kind != "bounded":
        return "centre", (f"{share}, but in {kind} space rays through points of a pixel lost to centre rays "
                          "wherever measured: one ray through each pixel's centre")
    if edge_share <= EDGE_SHARE_MAX:
        return "edges", (f"{share} (<= {100 * EDGE_SHARE_MAX:.0f}%): 2 x 2 rays on them (where the box filter "
                         "differs from the centre ray), the centre ray elsewhere")
    return "centre", (f"{share} (> {100 * EDGE_SHARE_MAX:.0f}%): their extra rays would cost more steps than they "
                      "gain; one ray through each pixel's centre")


def colour_head_for(config: TrainConfig) -> tuple[bool, str]:
    """Whether a run adds the residual colour head to its final grid (once that grid has
    trained MIN_STAGE_STEPS steps), and why: as set; never for a view-dependent grid (its
    head models colour already); not by default. Measured at equal time (BENCHMARKS.md,
    "Colour that grows with the budget"): primitives 128 px, 600 s, 42.85 dB with it
    against 42.86 without (its steps cost 1.4x, it grows the model 3x to 4.02 MB and a
    render by 35%), far-object 64 px, 300 s, 44.92 against 44.84, and under load (fewer
    steps) 41.81 against 42.10: what it adds inside a voxel its slower steps take back."""
    if config.colour_head is not None:
        return config.colour_head, "set on the command line"
    if config.view_dependent:
        return False, "the view-dependent grid's colour head models colour already"
    return False, ("not by default: at equal time it gained nothing measured (primitives 128 px, 600 s: 42.85 dB "
                   "with it, 42.86 without) and tripled the model; --colour-head on adds it")


def surface_opacity_for(config: TrainConfig) -> tuple[bool, str]:
    """Whether a compact run turns surface opacity on at its half-budget refinement, and
    why: as set; not by default while it is measured on primitives only (the figures are
    beside nerf.schedule.SURFACE_RISE_STEPS)."""
    if config.surface_opacity is not None:
        return config.surface_opacity, "set on the command line"
    return False, ("not by default: measured on primitives 128 px only (docs/results.md, \"Surface opacity\"); "
                   "--surface-opacity on turns it on at the half-budget refinement")


def refined_resolution(final: int) -> int:
    """The grid a converged run grows to past its final one (TrainConfig.refine_grid): one
    coarse-to-fine stage finer, at most MAX_AUTO_RESOLUTION (the final grid when at the cap)."""
    return max(final, min(round(final * STAGE_RATIO), MAX_AUTO_RESOLUTION))


def refine_grid_for(config: TrainConfig, resolution_set_by: Optional[str]) -> tuple[bool, str]:
    """Whether a run grows its grid past the final resolution once it has converged (at
    half the budget; nerf.schedule.Schedule.refinement_due), and why: as set; else for a compact `edges`
    run whose final resolution is the pixel footprint's (`resolution_set_by`, from
    `footprint_resolution`; None when set on the command line or not a bounded grid).
    `config`: resolved (its pixel filter and final resolution). The footprint's grid is
    what one ray a pixel resolves; a model trained through several points on its edge
    pixels resolves finer. A grid set by the texture is finer than the pixels already:
    far-object 64 px (31 voxels where its footprint asks for 18), 600 s, lost 0.64 dB
    refined to 49 (BENCHMARKS.md, "A finer grid in the second half")."""
    if config.refine_grid is not None:
        return config.refine_grid, "set on the command line"
    if config.model != "compact":
        return False, "the compact model's grid only"
    if config.pixel_filter != "edges":
        return False, f"measured only with the edges filter (this run's: {config.pixel_filter})"
    if resolution_set_by != "footprint":
        why = {None: "the final resolution is not the pixel footprint's automatic one",
               "texture": "the final grid is finer than the pixels already (set by the texture)",
               "cap": f"the final grid is at the cap ({MAX_AUTO_RESOLUTION})"}[resolution_set_by]
        return False, why
    finer = refined_resolution(config.final_resolution)
    if finer == config.final_resolution:
        return False, f"the final grid is at the cap ({MAX_AUTO_RESOLUTION})"
    return True, (f"{config.final_resolution} -> {finer} voxels at {100 * FINE_EDGE_POINTS_AT:.0f}% of the budget if "
                  f"the final grid has trained {FINE_EDGE_POINTS_MIN_STEPS} steps by then (the footprint's grid "
                  f"is what one ray a pixel resolves)")


def step_ratio_of(config: TrainConfig) -> float:
    """The marching step in voxels: the config's, or its parametrisation's default
    (bounded when that is not chosen yet)."""
    if config.step_ratio is not None:
        return config.step_ratio
    return STEP_RATIOS[config.parametrisation or "bounded"]
