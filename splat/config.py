"""The splatting stage's one config, `SplatConfig`, and its command-line flags, defined once.

Frozen, saved as RUN/config.json beside the run (with the choices made for "auto" values and
why, and the run's recipe), as nerf/config.py's TrainConfig is. Defaults are those of
Kerbl et al. 2023 (the 3DGS reference code's OptimizationParams), except that the schedule is
in fractions of the run ("progress": steps done / steps, or seconds / budget) instead of
iterations of a 30,000-step run, so a short CPU budget keeps the paper's proportions, except
for what counts views (how many steps gradient statistics gather over, and how many an opacity
reset needs to recover from), which stays in steps:

    position lr   1.6e-4 -> 1.6e-6 (x the cameras' extent), exponential in progress
    SH lr         2.5e-3 (DC), 2.5e-3 / 20 (the rest); opacity 0.05; scale 5e-3; rotation 1e-3
    SH degree     raised by one every 1/30 of the run (1000 of 30,000 iterations) up to 3
    densify       every 100 steps from 1/60 to 1/2 of the run (500 and 15,000 of 30,000):
                  clone or split where the view-space positional gradient averages >= 2e-4
    opacity reset every 3000 steps while densifying (a 30,000-step run: the paper's 4 resets;
                  a shorter one fewer or none: each costs ~5 dB and hundreds of steps to win
                  back, measured at 128 px, where a run of 400 steps with resets every tenth
                  of it never recovered)
    prune         opacity < 0.005; after 3000 steps (the first reset) also world size > 0.1 x
                  extent or screen radius > 20 px
    loss          0.8 L1 + 0.2 (1 - SSIM)

`add_arguments` adds the splat-only flags to a parser (`nerfgauge train --model splat`
shares dataset, --out, --steps, --budget-seconds, --seed, --threads, --device, --overwrite,
--quiet and --eval-every with the NeRF models); `config_from_arguments` reads them back.
Nothing here imports torch.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
from dataclasses import dataclass
from typing import Optional

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError

MODEL = "splat"  # config.json's "model": what `nerfgauge render RUN` recognises a splatting run by
CONFIG, LOG, GAUSSIANS = "config.json", "log.jsonl", "gaussians.ply"  # a run folder's files (splat.train)
INITS = ("auto", "surface", "sfm", "random", "none")
BACKGROUNDS = ("random", "white", "black")
MAX_SH_DEGREE = 3
# init_count's automatic value: one initial Gaussian per this many pixels of a training view.
# The 3DGS code starts its 800 x 800 synthetic scenes from 100,000 random points (one per 6.4
# pixels); densification adds Gaussians where the views need them. Measured at 128 px
# (primitives, 100 views, 120 s, 2 threads, seed 0; BENCHMARKS.md, "Gaussian splatting"):
# 100,000 surface points 34.94 dB test PSNR at 3.6 steps/s and 94 ms a frame; 20,000 38.71 dB
# at 14.5 steps/s; 5,000 38.90 dB at 20.8 steps/s and 16 ms. A step costs time in proportion to
# the Gaussians, and more than a view's pixels can constrain buy nothing in a short budget.
PIXELS_PER_INITIAL_GAUSSIAN = 4


@dataclass(frozen=True)
class SplatConfig:
    dataset: str = ""  # set by splat.train.train from its dataset argument
    seed: int = 0
    steps: Optional[int] = None  # stop after this many steps ...
    budget_seconds: Optional[float] = None  # ... or after this much training time
    # initial Gaussians: the dataset's COLMAP points of this kind (sparse/0/points3D.txt; auto:
    # whatever kind the dataset holds, none if it holds none; at most init_count of them), or
    # `none`: init_count points uniform in the scene bounds. init_count None: one per
    # PIXELS_PER_INITIAL_GAUSSIAN pixels of a training view (`initial_count`)
    init: str = "auto"
    init_count: Optional[int] = None
    sh_degree: int = MAX_SH_DEGREE
    sh_degree_every: float = 1 / 30  # progress between degree raises
    lr_position: float = 1.6e-4  # x the cameras' extent, decaying exponentially ...
    lr_position_final: float = 1.6e-6  # ... to this, at the end of the run
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scale: float = 5e-3
    lr_rotation: float = 1e-3
    ssim_weight: float = 0.2
    densify_from: float = 1 / 60  # progress
    densify_until: float = 0.5
    densify_every: int = 100  # steps
    densify_grad: float = 2e-4  # mean view-space positional gradient (NDC units) that clones or splits
    percent_dense: float = 0.01  # clone when the largest scale is at most this x extent, else split
    prune_opacity: float = 0.005
    opacity_reset_every: int = 3000  # steps (while densifying): a reset needs hundreds of steps to recover
    max_screen_radius: float = 20.0  # pixels
    max_world_scale: float = 0.1  # x extent
    max_gaussians: int = 1_000_000  # densification stops growing past this many
    background: str = "random"  # training background colour per step (random: opacity is learnt)
    eval_every_seconds: float = 10.0  # val PSNR points in log.jsonl (training clock)
    eval_views: int = 4
    threads: int = 2
    device: str = "auto"

    def validate(self) -> None:
        """One-line InputError for anything a run cannot use."""
        if not isinstance(self.dataset, str) or not self.dataset.strip():
            raise InputError(f"dataset must be a non-empty path, got {self.dataset!r}")
        if (self.steps is None) == (self.budget_seconds is None):
            raise InputError("give exactly one of --steps N or --budget-seconds T")
        if self.init not in INITS:
            raise InputError(f"unknown --init {self.init!r}; choose one of {', '.join(INITS)}")
        if self.background not in BACKGROUNDS:
            raise InputError(f"unknown background {self.background!r}; choose one of {', '.join(BACKGROUNDS)}")
        arguments.check_fields(self, FIELD_RANGES, flags=FLAGS)
        if self.densify_from > self.densify_until:
            raise InputError(f"densify_from ({self.densify_from}) must not be after --densify-until "
                             f"({self.densify_until})")
        if self.lr_position_final > self.lr_position:
            raise InputError(f"lr_position_final ({self.lr_position_final}) must not exceed lr_position "
                             f"({self.lr_position}): the schedule decays")
        if not isinstance(self.device, str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", self.device):
            raise InputError(f"unknown device {self.device!r}; choose auto, cpu, cuda or cuda:N")

    def initial_count(self, width: int, height: int) -> int:
        """init_count, or its automatic value for training views of width x height pixels."""
        if self.init_count is not None:
            return self.init_count
        return max(1, (width * height) // PIXELS_PER_INITIAL_GAUSSIAN)

    def to_json(self) -> dict:
        return {"model": MODEL, **dataclasses.asdict(self)}

    @classmethod
    def from_json(cls, document: dict, where: str) -> "SplatConfig":
        """The config a run saved (config.json), checked; InputError naming `where`."""
        if not isinstance(document, dict) or document.get("model") != MODEL:
            raise InputError(f"{where} is not a splatting run's config (no \"model\": \"{MODEL}\")")
        fields = {f.name for f in dataclasses.fields(cls)}
        try:
            config = cls(**{k: v for k, v in document.items() if k in fields})
            config.validate()
        except (TypeError, InputError) as error:
            raise InputError(f"{where}: {error}") from None
        return config


FRACTION = arguments.bounded(float, 0, 1)
LEARNING_RATE = arguments.bounded(float, 0, 10)
FIELD_RANGES = {
    "steps": arguments.STEPS, "budget_seconds": arguments.SECONDS, "seed": arguments.SEED,
    "init_count": arguments.bounded(int, 1, 10_000_000), "sh_degree": arguments.bounded(int, 0, MAX_SH_DEGREE),
    "sh_degree_every": FRACTION, "lr_position": LEARNING_RATE, "lr_position_final": LEARNING_RATE,
    "lr_sh_dc": LEARNING_RATE, "lr_sh_rest": LEARNING_RATE, "lr_opacity": LEARNING_RATE, "lr_scale": LEARNING_RATE,
    "lr_rotation": LEARNING_RATE, "ssim_weight": FRACTION, "densify_from": FRACTION, "densify_until": FRACTION,
    "densify_every": arguments.STEPS, "densify_grad": arguments.bounded(float, 0, 1e6, above=True),
    "percent_dense": FRACTION, "prune_opacity": FRACTION, "opacity_reset_every": arguments.STEPS,
    "max_screen_radius": arguments.bounded(float, 0, 1e6, above=True),
    "max_world_scale": arguments.bounded(float, 0, 1e6, above=True),
    "max_gaussians": arguments.bounded(int, 1, 20_000_000), "eval_every_seconds": arguments.SECONDS,
    "eval_views": arguments.VIEWS, "threads": arguments.THREADS,
}
# CLI flag of a config field, where it is not --field-with-dashes (messages name what was typed)
FLAGS = {"eval_every_seconds": "--eval-every"}


# --------------------------------------------------------------------------------------
# flags: the splat-only ones (the rest are shared with `nerfgauge train`'s NeRF models)

# argparse dests of the flags `nerfgauge train` shares with the NeRF models (nerf.options names
# each after its TrainConfig field)
SHARED = ("dataset", "out", "budget_seconds", "steps", "seed", "threads", "device", "overwrite", "quiet",
          "eval_every_seconds")
# field: (flag, type, help); each default is SplatConfig's, shown in --help
OWN_FLAGS = {
    "init": ("--init", None, "splat: initial Gaussians from the dataset's COLMAP points of this kind (surface, sfm, "
                             "random: `nerfgauge export colmap DS --points KIND` makes them), none (--init-count "
                             "random points in the scene bounds), or auto: whatever the dataset holds"),
    "init_count": ("--init-count", FIELD_RANGES["init_count"], "splat: initial Gaussians: at most this many of the "
                                                               "dataset's points (a seeded subset), or --init none's "
                                                               "random points; default one per "
                                                               f"{PIXELS_PER_INITIAL_GAUSSIAN} pixels of a training "
                                                               "view"),
    "sh_degree": ("--sh-degree", FIELD_RANGES["sh_degree"], "splat: highest spherical-harmonic degree of the colour"),
    "densify_until": ("--densify-until", FRACTION, "splat: fraction of the run after which Gaussians are no longer "
                                                   "cloned, split or reset"),
    "densify_grad": ("--densify-grad", FIELD_RANGES["densify_grad"],
                     "splat: mean view-space positional gradient that clones or splits a Gaussian"),
    "max_gaussians": ("--max-gaussians", FIELD_RANGES["max_gaussians"], "splat: densification stops at this count"),
    "background": ("--background", None, "splat: training background (random, white, black)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the splat-only flags (OWN_FLAGS) to `parser`, each defaulting to None ("not
    given": SplatConfig's default), so a NeRF run can refuse them (`refuse_own_flags`)."""
    defaults = SplatConfig()
    for field, (flag, kind, text) in OWN_FLAGS.items():
        choices = {"init": INITS, "background": BACKGROUNDS}.get(field)
        parser.add_argument(flag, dest=f"splat_{field}", type=kind, choices=choices, default=None,
                            help=f"{text} (default {getattr(defaults, field)})")


def refuse_own_flags(args: argparse.Namespace, model: str) -> None:
    """InputError when a splat-only flag was given to another model."""
    given = [flag for field, (flag, _, _) in OWN_FLAGS.items() if getattr(args, f"splat_{field}", None) is not None]
    if given:
        raise InputError(f"{given[0]} is a --model splat flag; --model {model} does not use it")


def config_from_arguments(args: argparse.Namespace, default_budget: float) -> SplatConfig:
    """SplatConfig from the shared flags and OWN_FLAGS (`add_arguments`); a time budget of
    `default_budget` seconds when neither --steps nor --budget-seconds is given."""
    budget = args.budget_seconds
    if budget is None and args.steps is None:
        budget = default_budget
    own = {field: getattr(args, f"splat_{field}") for field in OWN_FLAGS if getattr(args, f"splat_{field}") is not None}
    return SplatConfig(dataset=str(args.dataset), seed=args.seed, steps=args.steps, budget_seconds=budget,
                       threads=args.threads, device=args.device, eval_every_seconds=args.eval_every_seconds, **own)
