"""nerfgauge as a library: each pipeline stage as one function, exported from `nerfgauge`.

    import nerfgauge
    data = nerfgauge.generate_dataset("primitives", "data/prim", views=4, width=32, height=32, spp=4)
    summary = nerfgauge.train(data, "runs/prim", steps=50)
    renders = nerfgauge.render("runs/prim")
    metrics = nerfgauge.evaluate(data, renders)
    results = nerfgauge.check(metrics, "thresholds.toml")

`generate_dataset` and `run_pipeline` are not called `generate` and `run`: the package
already has modules of those names (the stage nerfgauge.generate, the command module
nerfgauge.run), and one attribute of `nerfgauge` cannot be both a module and a function.

These call the same stage functions as the `nerfgauge` command, so they write the same
files and refuse the same input: every user error is a `nerfgauge.InputError` whose
message is the one line the command prints (and exits 2 on); NaN or inf in training is a
`nerfgauge.NumericalError` (exit 3). Keyword options are the fields of the stage's config
dataclass (GenerateConfig, TrainConfig, RunConfig) plus a few run settings; an unknown
one is an InputError naming it. Unlike the command, progress bars are off by default.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError, os_errors_as_input_errors
from nerfgauge.core.outputs import check_output_file
from nerfgauge.eval import check as gate
from nerfgauge.eval.evaluate import METRICS_KIND, EvaluateConfig, evaluate as evaluate_split
from nerfgauge.eval.options import SCORING


def _split_options(function: str, options: dict, config_class, run_settings: dict,
                   first: str) -> tuple[dict, dict]:
    """(config fields, run settings) from `options`; unknown names are an InputError.

    run_settings: {name: default} accepted beside the config's fields. first: the config
    field given as the first argument (scene, dataset): repeating it as an option is an
    InputError too, not Python's TypeError."""
    if first in options:
        raise InputError(f"{function}: {first} is the first argument; do not repeat it as an option")
    fields = {field.name for field in dataclasses.fields(config_class)} - {first}
    unknown = sorted(name for name in options if name not in fields and name not in run_settings)
    if unknown:
        known = sorted(fields | set(run_settings))
        raise InputError(f"{function}: unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}; "
                         f"known: {', '.join(known)}")
    config = {name: value for name, value in options.items() if name in fields}
    settings = {name: options.get(name, default) for name, default in run_settings.items()}
    return config, settings


def _folder(dataset):
    """A dataset argument as a path: a folder, or the root of a `Dataset` already open."""
    return dataset.root if isinstance(dataset, Dataset) else dataset


@os_errors_as_input_errors()  # an OSError on the user's paths: the CLI's one line
def generate_dataset(scene: str, /, out, **options) -> Path:
    """Render `scene` into a dataset folder `out` (resumed if it holds the same recipe).

    options: GenerateConfig fields (seed, views, val_views, test_views, width, height, spp,
    max_depth, fov, layout, sampling, elevation, radius, variant; the train-view degradations
    pose_noise_rotation, pose_noise_translation, exposure_ev, white_balance, vignetting,
    degrade_seed: docs/conventions.md "Degradations") and workers=1,
    overwrite=False, progress=False, points="surface" (the COLMAP export's initial points,
    KIND[:COUNT]: docs/conventions.md "COLMAP"). Returns the dataset folder.
    """
    from nerfgauge.generate import pipeline  # trimesh (scenes), mitsuba: each stage loads on first use

    fields, settings = _split_options("generate_dataset", options, pipeline.GenerateConfig,
                                      {"workers": 1, "overwrite": False, "progress": False, "points": "surface"},
                                      first="scene")
    pipeline.generate(pipeline.GenerateConfig(scene=scene, **fields), out, **settings)
    return Path(out)


@os_errors_as_input_errors()
def train(dataset, /, out, **options) -> dict:
    """Train a NeRF on `dataset` into the run folder `out`.

    options: TrainConfig fields (model, seed, steps or budget_seconds (at most one; neither:
    nerf.config.DEFAULT_BUDGET_SECONDS), batch_rays,
    view_dependent, final_resolution, threads, device, ...) and resume=False, progress=False.
    Returns the summary: {"steps", "seconds", "val_psnr", "model_bytes", "resolution", "render_filter",
    "render_val_psnr"} (nerf.train.train).
    """
    from nerfgauge.nerf.config import TrainConfig  # each stage loads on first use
    from nerfgauge.nerf.train import train as train_run  # torch

    fields, settings = _split_options("train", options, TrainConfig, {"resume": False, "progress": False},
                                      first="dataset")
    return train_run(TrainConfig(dataset=str(_folder(dataset)), **fields), out, **settings)


@os_errors_as_input_errors()
def render(run_dir, split: str = "test", *, out=None, threads=None, progress: bool = False) -> Path:
    """Render every view of `split` with the trained model in `run_dir`.

    Writes <out>/<split>/r_000.png (straight-alpha sRGB), r_000_depth.exr (ray distance)
    and <out>/timing.json; out defaults to RUN/renders. Returns the renders folder.
    """
    from nerfgauge.nerf.render_views import render_split  # torch: each stage loads on first use

    render_split(run_dir, split, out, threads=threads, progress=progress)
    return Path(run_dir) / "renders" if out is None else Path(out)


@os_errors_as_input_errors()
def evaluate(dataset, pred, out=None, split: str = EvaluateConfig.split, *,
             background: str = EvaluateConfig.background, depth_kind: str = EvaluateConfig.depth_kind,
             pred_format: str = EvaluateConfig.pred_format, held_out: bool = EvaluateConfig.held_out,
             overwrite: bool = False, protocol: str = EvaluateConfig.protocol) -> dict:
    """Score the renders in `pred` against `dataset`'s `split`; write metrics.json (to `out`,
    default PRED/metrics.json) and error maps beside it. Returns the metrics document
    ({"schema", "scene", "split", "mean", "std", "ci95", "count", "frames", "timing", ...}).
    pred_format: auto (detected), nerfgauge, nerfstudio, nerfbaselines or folder.
    held_out=False skips the co-visible and depth-resolved scores (their pass costs about
    0.12 us per hit test pixel and train view). `out` must be a new path or a metrics file
    nerfgauge wrote (overwrite=True: also another nerfgauge file), as for `evaluate --out`.
    protocol: nerfgauge, nerfbaselines or ns-eval (eval.protocols), as `evaluate --protocol`.
    `dataset` may be a NeRF-synthetic, nerfstudio or COLMAP text-model folder."""
    check_output_file(Path(pred) / "metrics.json" if out is None else out, METRICS_KIND, overwrite=overwrite)
    return evaluate_split(_folder(dataset), pred, split=split, out=out, background=background, depth_kind=depth_kind,
                          pred_format=pred_format, held_out=held_out, protocol=protocol)


@os_errors_as_input_errors()
def check(metrics, thresholds, *, scene: str | None = None) -> list:
    """The CI gate: one `CheckResult` per bound (see nerfgauge.eval.check for the format).

    metrics: a metrics.json path or the document `evaluate` returned. thresholds: a
    thresholds.toml path or the same tables as a dict ({"primitives": {"psnr": {"min": 30}}}).
    scene: use that scene's bounds instead of the metrics' own scene. Every result has
    `.passed`, `.metric`, `.kind` ("min"/"max"), `.bound`, `.value`, `.margin` and `.reason`;
    the gate passes when `all(result.passed for result in results)`.
    """
    document = gate.validate_metrics(metrics) if isinstance(metrics, dict) else gate.load_metrics(metrics)
    tables = gate.parse_thresholds(thresholds) if isinstance(thresholds, dict) else gate.load_thresholds(thresholds)
    if scene is not None and not gate.known_scene(scene):
        from nerfgauge.scenes.registry import RECIPES  # trimesh: only to list the known scenes

        known = ", ".join(list(RECIPES) + [gate.MESH_PREFIX + "PATH", repr(gate.DEFAULT_TABLE)])
        raise InputError(f"unknown scene {scene!r} for --scene; known: {known}")
    source = "thresholds" if isinstance(thresholds, dict) else str(thresholds)
    bounds = gate.bounds_for_scene(tables, document["scene"] if scene is None else scene, source)
    return gate.check_metrics(document, bounds, source)


@os_errors_as_input_errors()
def run_pipeline(scene: str = "primitives", out="nerfgauge-run", **options) -> dict:
    """The whole pipeline, as `nerfgauge run`: generate, train, render, evaluate,
    baselines and report under `out`.

    options: RunConfig fields (width, height, views, val_views, test_views, spp, layout,
    model, budget_seconds (default: TrainConfig's), steps, seed, variant, workers,
    generate_options, train_options, evaluate_options), every other GenerateConfig field
    (fov, elevation, radius, sampling, max_depth, noise_psnr, max_spp, ...: as for
    generate_dataset), the scoring EvaluateConfig fields (background, protocol, held_out: as
    for evaluate), every other TrainConfig field (threads, final_resolution, pixel_filter,
    ...: as for train; TrainConfig's width and background, which a RunConfig or scoring
    field of that name shadows, go in train_options) and overwrite=False, progress=False.
    Returns {"metrics": path of metrics.json, "report": path of report.html, "train": summary}.
    """
    from nerfgauge.generate.pipeline import GenerateConfig  # trimesh: each stage loads on first use
    from nerfgauge.nerf.config import TrainConfig  # each stage loads on first use
    from nerfgauge.run import RunConfig  # trimesh, and torch when it runs
    from nerfgauge.run import run_pipeline as run_stages  # (the same module)

    def field_names(config_class) -> set:
        return {field.name for field in dataclasses.fields(config_class)}

    # each stage's options dict and the names it takes: a name goes to the first that has it
    generator = field_names(GenerateConfig) - field_names(RunConfig) - {"scene"}
    trainer = field_names(TrainConfig) - field_names(RunConfig) - generator - set(SCORING) - {"dataset"}
    stages = {"generate_options": generator, "evaluate_options": set(SCORING), "train_options": trainer}
    fields, settings = _split_options("run_pipeline", options, RunConfig,
                                      {"overwrite": False, "progress": False,
                                       **dict.fromkeys(generator | set(SCORING) | trainer)}, first="scene")
    config = RunConfig(scene=scene, out=str(out), **fields)
    config = dataclasses.replace(config, **{stage: {**getattr(config, stage),
                                                    **{name: options[name] for name in names if name in options}}
                                            for stage, names in stages.items()})
    return run_stages(config, overwrite=settings["overwrite"], progress=settings["progress"])
