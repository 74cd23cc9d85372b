"""The training stage's command-line options, defined once: `nerfgauge train` and
`nerfgauge run` both add them (`add_train_arguments`) and read them back as TrainConfig
fields (`train_fields`).

Every flag is a TrainConfig field's: its name is in the field's metadata (nerf.config.FLAGS),
its range is nerf.config.FIELD_RANGES's, its default the field's, and a flag whose words
are not the field's values (auto, on, off) maps them through the field's own `words`
(nerf.config.AUTO, SWITCH): one table, read the same way for every field. Everything but
the dataset, the run folder and the command's own switches (--out, --resume, --overwrite,
--quiet) is here.
"""

from __future__ import annotations

import argparse
import dataclasses

from nerfgauge.nerf.config import DEFAULT_BUDGET_SECONDS, FIELD_RANGES, FLAGS, MODELS, PIXEL_FILTERS, TrainConfig

WORDS = {item.name: item.metadata["words"] for item in dataclasses.fields(TrainConfig) if "words" in item.metadata}
# The fields `add_train_arguments` sets (all of FLAGS); `seed` where the command has its own
# --seed (`nerfgauge run`: the dataset's, which trains too).
OPTIONS = tuple(FLAGS)


def _word(name: str, value) -> object:
    """The flag's word for a field's value (None -> "auto", True -> "on"), else the value."""
    for word, meaning in WORDS.get(name, {}).items():
        if meaning is value:
            return word
    return value


def add_train_arguments(parser: argparse.ArgumentParser, defaults: TrainConfig | None = None, *,
                        seed: bool = True, models: tuple = MODELS) -> argparse.ArgumentParser:
    """Add the training options to `parser` (or an argument group of one; dest: the field's
    name). defaults: a TrainConfig whose values are the defaults, else TrainConfig's own.
    seed: add --seed (False where the command's --seed is another stage's and trains too).
    models: --model's choices (`nerfgauge train` adds splat, which its own runner trains)."""
    d = TrainConfig(dataset=".") if defaults is None else defaults

    def add(name: str, *more, **options) -> None:
        flag = FLAGS[name]
        if name in FIELD_RANGES and "action" not in options:
            options.setdefault("type", FIELD_RANGES[name])
        if "action" not in options:
            options.setdefault("default", _word(name, getattr(d, name)))
        (more[0] if more else parser).add_argument(flag, dest=name, **options)

    add("model", choices=models, help=f"which model trains (default {d.model})")
    length = parser.add_mutually_exclusive_group()
    # None: the config's own default budget, unless --steps
    add("budget_seconds", length, default=None, metavar="T",
        help=f"training time (default {DEFAULT_BUDGET_SECONDS:g})")
    add("steps", length, default=None, metavar="N", help="training steps instead of a time budget (reproducible)")
    if seed:
        add("seed", help=f"seed of the model's initial values and the rays each step draws (default {d.seed})")
    add("checkpoint_every", metavar="STEPS",
        help="write RUN/checkpoint.pt every STEPS steps (default: at most once a minute of wall time), and always "
             "at the end")
    add("view_dependent", choices=tuple(WORDS["view_dependent"]), help="view-dependent colour (auto: from scene.json)")
    add("parametrisation", metavar="KIND",
        help="where the grid lives: bounded (the scene's AABB), contracted (mip-NeRF 360 contraction: unbounded and "
             "inside-out scenes) or forward (angles and log-depth: forward-facing captures); auto (default) decides "
             "from the cameras and bounds and says why in RUN/config.json")
    add("final_resolution", metavar="RESOLUTION", help="final grid resolution (auto: pixel footprint)")
    add("step_ratio", metavar="VOXELS",
        help="ray-marching step while training, in voxels (auto: 0.5, 1 in contracted space)")
    add("batch_rays", metavar="N", help="rays per training step (auto: 4096, 2048 in contracted space)")
    add("pixel_filter", choices=tuple(WORDS["pixel_filter"]) + PIXEL_FILTERS,
        help="what a training pixel is compared as: box, the mean of 2 x 2 stratified rays through it, as the "
             "ground truth averages the pixel's area (4x the rays a step, as many pixels); edges, the box on the "
             "target's edge pixels and the centre ray elsewhere; centre, its centre ray; jitter, one ray through a "
             "random point of it; auto (default): edges (BENCHMARKS.md, \"Edge pixels\")")
    add("quantise", choices=("fp16", "int8"),
        help="saved model's grid values: fp16 (default) or int8 with a per-channel scale (~half size)")
    add("prune", action="store_false",
        help="keep and save every grid node, not only those of occupied cells (a dense grid: the ablation of "
             "sparse storage)")
    add("occupancy", action="store_false", help="disable empty-space skipping")
    add("tv_weight", help="total-variation weight on density")
    add("eval_every_seconds", metavar="SECONDS",
        help=f"training seconds between val PSNR points in log.jsonl (default {d.eval_every_seconds:g})")
    add("threads", help=f"torch CPU threads (default {d.threads})")
    add("device", help="auto (cuda when present), cpu, cuda or cuda:N")
    add("sparse", metavar="N",
        help="train on the dataset's fixed sparse list of N views (sparse_views.json: 3, 6, 9, 12 or 24, by "
             "farthest-point sampling on the camera centres)")
    add("sparse_priors", choices=tuple(WORDS["sparse_priors"]),
        help="priors on rays from unseen viewpoints (opacity entropy, distortion, total variation) for sparse "
             "captures; auto (default): on for an open capture from inside the scene whose points are each in fewer "
             "than 9 train images (BENCHMARKS.md, \"Sparse captures\")")
    add("colour_head", choices=tuple(WORDS["colour_head"]),
        help="a residual colour head (12 features and a small MLP, no view direction) added to a diffuse grid once "
             "its final size has trained 100 steps, for colour that varies inside a voxel; auto (default): off, "
             "since at equal time it gained nothing measured (BENCHMARKS.md, \"Colour that grows with the budget\")")
    add("refine_grid", choices=tuple(WORDS["refine_grid"]),
        help="grow the grid one coarse-to-fine stage past its final resolution (x1.59) at half the budget when the "
             "final grid has trained 1000 steps by then; auto (default): on for an edges run whose resolution the "
             "pixel footprint set (BENCHMARKS.md, \"A finer grid in the second half\")")
    add("surface_opacity", choices=tuple(WORDS["surface_opacity"]),
        help="from the half-budget refinement, a sample's opacity is the rise of occupancy along the ray (a ray "
             "grazing a surface takes its faint front once, not over the surface's width); auto (default): off, "
             "measured on primitives only (docs/results.md, \"Surface opacity\")")
    return parser


def train_fields(args: argparse.Namespace, *, seed: bool = True) -> dict:
    """The TrainConfig fields (all but dataset; seed only when `seed`) from arguments added by
    add_train_arguments, each flag's words mapped to the field's values."""
    names = [name for name in OPTIONS if seed or name != "seed"]
    return {name: WORDS[name].get(getattr(args, name), getattr(args, name)) if name in WORDS else getattr(args, name)
            for name in names}
