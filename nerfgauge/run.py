"""`nerfgauge run`: generate, train, render, evaluate, baselines, report, in one command.

Each stage is called through its public entry point; this module only decides where
things go:
  OUT/                    a nerfgauge "pipeline" folder (.nerfgauge.json: the RunConfig's
                          hash), locked for the whole run
  OUT/dataset/            the generated dataset (resumed if the same recipe is there)
  OUT/run/                the trained model, its log.jsonl and renders/
  OUT/baselines/<method>/ the baselines' renders
  OUT/eval/<method>/      metrics.json and error maps per method (the NeRF and baselines)
  OUT/report.html         metrics table, speed-vs-error curve with the baselines, labelled image grid, camera
                          frusta and a sortable per-view table (figures also as PNGs in OUT/report/)

Each subfolder is claimed (marked and locked) by the stage that writes it. A rerun with the
same settings needs --overwrite once OUT/run exists, and then removes the earlier run's
outputs only through their markers (`core.folders.remove_owned`) and by their known file
names; other settings in the same OUT need --overwrite, which replaces the whole pipeline
folder (only ever one that nerfgauge made).
"""

from __future__ import annotations

import dataclasses
import errno
import math
from dataclasses import dataclass, field
from pathlib import Path

from nerfgauge.core import arguments, owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, write_bytes_atomic, write_json
from nerfgauge.core.folders import claim_folder, recipe_hash, remove_owned
from nerfgauge.methods.baselines import METHODS, baseline_folder, write_baseline
from nerfgauge.eval.evaluate import EvaluateConfig, evaluate, format_means
from nerfgauge.eval.geometry import format_geometry, score_geometry, summary as geometry_summary
from nerfgauge.eval.options import SCORING, add_scoring_arguments, evaluate_fields
from nerfgauge.eval.protocols import DEFAULT as DEFAULT_PROTOCOL, format_rows, sensitivity, sensitivity_rows
from nerfgauge.eval.report import geometry_histogram, geometry_table, write_report
from nerfgauge.generate.options import add_generate_arguments, generate_fields
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.nerf.config import TrainConfig
from nerfgauge.nerf.mesh import NoSurface, mesh_from_run, ply_bytes
from nerfgauge.nerf.options import add_train_arguments, train_fields
from nerfgauge.nerf.runs import open_run_dataset
from nerfgauge.eval.metrics import METRIC_NAMES
from nerfgauge.eval.uncertainty import aggregate_runs
from nerfgauge.scenes import make_scene

REPORT_FILES = ("report.html", "report/curve.png", "report/grid.png", "report/cameras.png", "report/geometry.png")
GEOMETRY_RESOLUTION = 256  # marching-cubes cells along the scene's longest side
GEOMETRY_SAMPLES = 200_000  # points per surface (the scoring cost grows with their square off the surface)


@dataclass(frozen=True)
class RunConfig:
    """The pipeline's settings: the three stages' configs, each field defined by its stage.
    The capture's headline fields (scene, width, ... variant) are GenerateConfig's, with its
    defaults, and every other generator field goes through generate_options; model,
    budget_seconds and steps are TrainConfig's (budget_seconds None: its default budget,
    unless steps), and every other training field through train_options (but the dataset,
    which is OUT/dataset, and the seed: `seed`, or each of `seeds`); the scoring settings
    (eval.options.SCORING: background, protocol, held_out) go through evaluate_options.
    Each options dict holds what differs from its stage's defaults and is checked against
    that stage's fields (`generate_config`, `train_config`, `evaluate_config`)."""

    scene: str = GenerateConfig.scene
    out: str = "nerfgauge-run"
    width: int = GenerateConfig.width
    height: int = GenerateConfig.height
    views: int = GenerateConfig.views
    val_views: int = GenerateConfig.val_views
    test_views: int = GenerateConfig.test_views
    spp: int = GenerateConfig.spp
    layout: str = GenerateConfig.layout
    model: str = TrainConfig.model
    budget_seconds: float | None = TrainConfig.budget_seconds
    steps: int | None = TrainConfig.steps  # instead of the time budget: reproducible across machines (CI gates)
    seed: int = GenerateConfig.seed
    variant: str = GenerateConfig.variant
    # Every other GenerateConfig field (fov, elevation, radius, sampling, max_depth,
    # noise_psnr, max_spp, ...), passed to the generator as given.
    generate_options: dict = field(default_factory=dict)
    # Every other TrainConfig field (threads, final_resolution, pixel_filter, refine_grid, ...)
    train_options: dict = field(default_factory=dict)
    # EvaluateConfig's scoring fields (background, protocol, held_out): the NeRF's and the baselines' scores
    evaluate_options: dict = field(default_factory=dict)
    workers: int = 1  # the generator's worker processes (not part of the recipe: same dataset)
    # Training seeds (`--seeds K|A,B,...`): None trains once with `seed`; a tuple trains once per
    # seed on the one dataset of `seed` (OUT/run: the first; OUT/seeds/seed-<s>/run: the others)
    seeds: tuple | None = None

    def recipe(self) -> str:
        """The hash in OUT's marker: every setting but where OUT is and how many workers render
        (seeds, train_options and evaluate_options only when given, so a run without them keeps
        the recipe it had before they existed)."""
        return recipe_hash({key: (list(value) if isinstance(value, tuple) else value)
                            for key, value in dataclasses.asdict(self).items()
                            if key not in ("out", "workers") and not (key == "seeds" and value is None)
                            and not (key in ("train_options", "evaluate_options") and not value)})

    def generate_config(self) -> GenerateConfig:
        """The dataset's GenerateConfig: this config's shared fields plus generate_options."""
        options = _stage_options(self.generate_options, "generate_options", "generator", GenerateConfig,
                                 CAPTURE_FIELDS)
        return GenerateConfig(**{name: getattr(self, name) for name in sorted(CAPTURE_FIELDS)}, **options)

    def train_config(self, seed: int | None = None) -> TrainConfig:
        """The training's TrainConfig on OUT/dataset: model, budget_seconds and steps plus
        train_options, trained with `seed` (default: this config's)."""
        options = _stage_options(self.train_options, "train_options", "training", TrainConfig,
                                 TRAIN_FIELDS | {"dataset", "seed"})
        return TrainConfig(dataset=str(Path(self.out) / "dataset"), seed=self.seed if seed is None else seed,
                           **{name: getattr(self, name) for name in sorted(TRAIN_FIELDS)}, **options)

    def evaluate_config(self) -> EvaluateConfig:
        """How the test renders (the NeRF's and the baselines') are scored: EvaluateConfig with
        evaluate_options (its scoring fields only: `run` renders the test split, in our naming)."""
        unscored = {item.name for item in dataclasses.fields(EvaluateConfig)} - set(SCORING)
        return EvaluateConfig(**_stage_options(self.evaluate_options, "evaluate_options", "scoring", EvaluateConfig,
                                               unscored))

    def validate(self) -> None:
        """What the stages' own configs do not check (they check the rest, before anything is written)."""
        if not isinstance(self.test_views, int) or self.test_views < 1:
            raise InputError(f"--test-views must be at least 1: the pipeline evaluates on them, got {self.test_views!r}")
        if not str(self.out).strip():
            raise InputError("--out must name a folder, got an empty path")
        make_scene(self.scene, self.seed)  # unknown names and unreadable meshes: InputError, before OUT exists


# RunConfig's fields that are GenerateConfig's (the rest of the generator's go through
# generate_options) and TrainConfig's (the rest through train_options): read from the
# dataclasses, not listed by hand.
RUN_FIELDS = frozenset(item.name for item in dataclasses.fields(RunConfig))
CAPTURE_FIELDS = RUN_FIELDS & frozenset(item.name for item in dataclasses.fields(GenerateConfig))
TRAIN_FIELDS = (RUN_FIELDS & frozenset(item.name for item in dataclasses.fields(TrainConfig))) - CAPTURE_FIELDS


def _stage_options(options, name: str, stage: str, config_class, own) -> dict:
    """A RunConfig options dict (`name`), checked: a dict whose keys are `config_class`'s
    fields but `own` (those RunConfig holds itself, or sets)."""
    if not isinstance(options, dict):
        raise InputError(f"{name} must be a dict of {stage} settings, got {options!r}")
    known = {item.name for item in dataclasses.fields(config_class)} - set(own)
    unknown = sorted(set(options) - known)
    if unknown:
        raise InputError(f"unknown {stage} option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}; "
                         f"known: {', '.join(sorted(known))}")
    return options


def remove_earlier_outputs(out: Path, model: str) -> None:
    """Delete what an earlier pipeline in OUT (ours, locked) wrote after generating, so
    nothing stale sits beside a new run: each stage's folder through its marker, the rest
    by its known file name; folders are removed only once empty (anything the user put
    there stays)."""
    remove_owned(out / "run", "run")
    for folder in sorted((out / "seeds").glob("seed-*")) if (out / "seeds").is_dir() else []:  # run --seeds
        remove_owned(folder / "run" / "renders", "renders")
        remove_owned(folder / "run", "run")
        owned.remove_empty_folder(folder)
    owned.remove_empty_folder(out / "seeds")
    for folder in sorted((out / "eval" / model).glob("seed-*")) if (out / "eval" / model).is_dir() else []:
        _remove_file(folder / "metrics.json")
        remove_owned(folder / "error_maps", "evaluation")
        owned.remove_empty_folder(folder)
    _remove_file(out / "eval" / model / "aggregate.json")
    for method in (model, *METHODS):
        remove_owned(out / "baselines" / method, "baseline")
        remove_owned(out / "eval" / method / "error_maps", "evaluation")
        _remove_file(out / "eval" / method / "metrics.json")
        _remove_file(out / "eval" / method / "geometry.json")
        _remove_file(out / "eval" / method / "protocols.json")
        _remove_file(out / "eval" / method / "mesh.ply")
        owned.remove_empty_folder(out / "eval" / method)
    for name in REPORT_FILES:
        _remove_file(out / name)
    for folder in ("eval", "baselines", "report"):
        owned.remove_empty_folder(out / folder)


def _remove_file(path: Path) -> None:
    if path.exists() and not path.is_symlink() and not path.is_file():
        raise InputError(f"refusing to delete {path}: nerfgauge writes a file there, and it is not one")
    owned.remove_file(path)


def run_pipeline(config: RunConfig, *, overwrite: bool = False, progress: bool = True) -> dict:
    from nerfgauge.nerf.render_views import render_split  # torch: kept off `nerfgauge --help`'s import path
    from nerfgauge.nerf.train import train  # torch

    out = Path(config.out)
    generate_config = config.generate_config()
    seeds = None if config.seeds is None else tuple(arguments.check_seeds(config.seeds))
    train_config = config.train_config(seed=None if seeds is None else seeds[0])
    evaluate_config = config.evaluate_config()
    scoring = dataclasses.asdict(evaluate_config)  # evaluate's keywords
    generate_config.validate()
    train_config.validate()
    evaluate_config.validate()
    config.validate()
    run_dir = out / "run"
    with claim_folder(out, "pipeline", config.recipe(), overwrite=overwrite) as state:
        if state == "resume" and run_dir.exists():
            if not overwrite:
                raise InputError(f"{run_dir} exists from an earlier run; pass --overwrite to train again")
            remove_earlier_outputs(out, config.model)

        print(f"[1/5] generate {config.scene} -> {out / 'dataset'}")
        generate(generate_config, out / "dataset", workers=config.workers, overwrite=overwrite, progress=progress)
        length = f"{train_config.steps} steps" if train_config.steps else f"{train_config.budget_seconds:g} s"
        print(f"[2/5] train {config.model} for {length} -> {run_dir}")
        summary = train(train_config, run_dir, progress=progress)
        print("[3/5] render test views")
        render_split(run_dir, "test", progress=progress)
        print("[4/5] evaluate and baselines")
        documents = {f"{config.model} NeRF": evaluate(out / "dataset", run_dir / "renders",
                                                      out=out / "eval" / config.model / "metrics.json", **scoring)}
        # what the training got, beside its scores: `check` prints the machine's speed and flags an
        # under-trained run against a calibration (eval.check)
        documents[f"{config.model} NeRF"]["training"] = training_record(summary, train_config)
        geometry, no_geometry = None, None
        if config.model == "compact":
            try:
                geometry = geometry_step(out / "dataset", run_dir, out / "eval" / config.model)
            except NoSurface as reason:  # a fact about the model: scored n/a (nulls), and a geometry gate fails on it
                no_geometry = f"geometry n/a: {reason}"
                print(no_geometry)
            documents[f"{config.model} NeRF"]["geometry"] = geometry_summary(None if geometry is None else geometry[0])
        write_json(out / "eval" / config.model / "metrics.json", documents[f"{config.model} NeRF"])
        layout = read_json(out / "dataset" / "scene.json")["camera"]["layout"]
        baselines = ["nearest"] + (["lightfield-nearest", "lightfield-quadrilinear"] if layout == "lightfield" else [])
        for method in baselines:
            with baseline_folder(out / "dataset", method, out / "baselines" / method, "test", overwrite=overwrite):
                write_baseline(out / "dataset", method, out / "baselines" / method, "test")
            documents[f"baseline: {method}"] = evaluate(out / "dataset", out / "baselines" / method,
                                                        out=out / "eval" / method / "metrics.json", **scoring)
        if seeds is not None:
            more_seeds(out, train_config, evaluate_config, seeds, documents[f"{config.model} NeRF"], progress)
        print("[5/5] report")
        owned.make_folder(out / "report")
        ours_name = f"{config.model} NeRF"
        background = evaluate_config.background  # the "nerfgauge" rows' (the other protocols fix their own)
        protocol_tables = {ours_name: sensitivity(out / "dataset", run_dir / "renders", "test", background=background)}
        for method in baselines:
            protocol_tables[f"baseline: {method}"] = sensitivity(out / "dataset", out / "baselines" / method, "test",
                                                                 background=background)
        write_json(out / "eval" / config.model / "protocols.json", protocol_tables[ours_name])
        notes = [f"scene {config.scene}, {config.width}x{config.height}, {config.views} train / {config.test_views} "
                 f"test views, {config.spp} spp; {config.model} trained {summary['steps']} steps in "
                 f"{summary['seconds']:.1f} s, saved model {summary['model_bytes'] / 1e6:.2f} MB",
                 scoring_note(documents[ours_name]) + "; depth metrics on pixels whose centre ray hits "
                 "geometry, on ray distance. LPIPS: AlexNet, v0.1 linear layers (nerfgauge lpips install). "
                 "Protocol sensitivity: the same renders under nerfgauge, NerfBaselines' and ns-eval's scoring."]
        images = {}
        if no_geometry is not None:
            notes.append(no_geometry)
        if geometry is not None:
            geometry_histogram(geometry[1], geometry[0], out / "report" / "geometry.png")
            images["geometry: distances to the exact meshes"] = out / "report" / "geometry.png"
            notes.append(geometry_table(geometry[0]))
        write_report(out / "report.html", f"nerfgauge: {config.scene}", out / "dataset", run_dir / "renders", documents,
                     log_path=run_dir / "log.jsonl", ours=f"{config.model} NeRF", train_seconds=summary["seconds"],
                     notes=notes, figures=out / "report", extra_images=images, protocol_tables=protocol_tables)
        print(format_rows(sensitivity_rows({ours_name: protocol_tables[ours_name]})))
    print(format_means(documents[f"{config.model} NeRF"]))
    print(f"report: {out / 'report.html'}")
    return {"metrics": str(out / "eval" / config.model / "metrics.json"), "report": str(out / "report.html"),
            "train": summary}


def scoring_note(document: dict) -> str:
    """The report's line on how colour was scored (evaluate's document says)."""
    if document["protocol"] == DEFAULT_PROTOCOL:
        return f"PSNR and SSIM on colour composited onto {document['protocol_background']}"
    return (f"PSNR, SSIM and LPIPS by the {document['protocol']} protocol (eval/protocols.py: colour on "
            f"{document['protocol_background']}, LPIPS-{document['lpips_net']})")


def more_seeds(out: Path, train_config, evaluate_config, seeds: tuple, first: dict, progress: bool) -> dict:
    """`run --seeds`: train, render and score seeds[1:] on the same dataset (OUT/seeds/seed-<s>/run,
    OUT/eval/<model>/seed-<s>/metrics.json, scored as `evaluate_config` says; seeds[0] is OUT/run, its metrics copied to
    eval/<model>/seed-<s0>/), then OUT/eval/<model>/aggregate.json (eval.uncertainty.aggregate_runs:
    every run's means, the two-level bootstrap interval over seeds and views, the per-seed
    spread, the variance split). Returns the aggregate."""
    from nerfgauge.nerf.render_views import render_split  # torch: kept off `nerfgauge --help`'s import path
    from nerfgauge.nerf.train import train  # torch

    model_eval = out / "eval" / train_config.model
    owned.make_folder(model_eval / f"seed-{seeds[0]}")
    write_json(model_eval / f"seed-{seeds[0]}" / "metrics.json", first)
    documents = [first]
    for index, seed in enumerate(seeds[1:], 2):
        run_dir = out / "seeds" / f"seed-{seed}" / "run"
        config = dataclasses.replace(train_config, seed=seed)
        print(f"      seed {seed} ({index}/{len(seeds)}): train, render, evaluate -> {run_dir}")
        summary = train(config, run_dir, progress=progress, overwrite=True)
        render_split(run_dir, "test", progress=progress, overwrite=True)
        document = evaluate(out / "dataset", run_dir / "renders", out=model_eval / f"seed-{seed}" / "metrics.json",
                            **dataclasses.asdict(evaluate_config))
        document["training"] = training_record(summary, config)
        write_json(model_eval / f"seed-{seed}" / "metrics.json", document)
        documents.append(document)
    names = [name for name in METRIC_NAMES if name in first["mean"]]
    aggregate = aggregate_runs(documents, list(seeds), names)
    write_json(model_eval / "aggregate.json", {"method": train_config.model, "scene": first.get("scene"), **aggregate})
    interval, std = aggregate["ci95"].get("psnr"), aggregate["seed_std"].get("psnr")
    if interval is not None:
        print(f"      PSNR over {len(seeds)} seeds x {aggregate['n_views']} views: {aggregate['mean']['psnr']:.2f} dB, "
              f"95% CI [{interval[0]:.2f}, {interval[1]:.2f}]"
              + ("" if std is None else f", per-seed std {std:.2f} dB") + f" -> {model_eval / 'aggregate.json'}")
    return aggregate


def training_record(summary: dict, train_config) -> dict:
    """metrics.json's `training`: steps, seconds, steps_per_second, the time budget (None when
    step-counted), the training seed and threads."""
    return {"steps": summary["steps"], "seconds": summary["seconds"],
            "steps_per_second": summary["steps"] / max(summary["seconds"], 1e-9),
            "budget_seconds": train_config.budget_seconds, "seed": train_config.seed, "threads": train_config.threads}


def geometry_step(dataset_root: Path, run_dir: Path, eval_dir: Path) -> tuple[dict, dict]:
    """Mesh the field (eval_dir/mesh.ply), score it and the field's test-view normals
    against the exact ground truth (eval_dir/geometry.json). Returns (document, distances)."""
    from nerfgauge.eval.normals import score_normals  # torch: kept off `nerfgauge --help`'s import path
    from nerfgauge.nerf.checkpoint import load_model  # torch

    mesh = mesh_from_run(run_dir, GEOMETRY_RESOLUTION)
    write_bytes_atomic(eval_dir / "mesh.ply", ply_bytes(mesh.vertices, mesh.faces))
    document, distances = score_geometry(dataset_root, eval_dir / "mesh.ply", samples=GEOMETRY_SAMPLES)
    document["mesh"] = {"resolution": mesh.resolution, "level": mesh.level, "level_source": mesh.level_source,
                        "faces": int(len(mesh.faces)), "seconds": mesh.seconds}
    model, config = load_model(run_dir / "model.pt")
    document["normals"] = score_normals(model, open_run_dataset(run_dir, config, dataset_root), "test")
    write_json(eval_dir / "geometry.json", document)
    print(format_geometry(document))
    return document, distances


def register(subparsers) -> None:
    defaults = RunConfig()
    parser = subparsers.add_parser("run", help="generate, train, render, evaluate, baselines and report in one go",
                                   description="The train-and-evaluate pipeline (about 3.5 minutes on 2 CPU cores "
                                               "with the defaults). Takes every generator and training option "
                                               "(as `nerfgauge generate` and `nerfgauge train`) and evaluate's "
                                               "scoring ones.")
    parser.add_argument("scene", nargs="?", default=defaults.scene, help="scene (default primitives)")
    parser.add_argument("--out", type=arguments.path, default=Path(defaults.out),
                        help=f"output folder (default {defaults.out})")
    add_generate_arguments(parser, defaults.generate_config(), need_test_views=True)  # every generator option, defined once
    # ... every training option (--seed is the generator's: it seeds the training too)
    add_train_arguments(parser.add_argument_group("training (as nerfgauge train)"), seed=False)
    add_scoring_arguments(parser.add_argument_group("scoring (as nerfgauge evaluate)"))  # ... and how renders are scored
    parser.add_argument("--seeds", type=arguments.seeds, default=None, metavar="K|A,B,...",
                        help="train K times (training seeds 0..K-1) or with the listed seeds, on the one dataset of "
                             "--seed; every run is kept and eval/MODEL/aggregate.json gives the 95%% interval over "
                             "seeds and views (default: once, with --seed)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier run in --out (only a folder nerfgauge made)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    generator, training = generate_fields(args), train_fields(args, seed=False)
    scoring = evaluate_fields(args, SCORING)
    generator_defaults = RunConfig().generate_config()

    def changed(fields: dict, default_of) -> dict:  # only what the user changed: the same settings keep the recipe
        return {name: value for name, value in fields.items() if name not in RUN_FIELDS and value != default_of(name)}

    config = dataclasses.replace(
        RunConfig(), scene=args.scene, out=str(args.out), workers=args.workers,
        generate_options=changed(generator, lambda name: getattr(generator_defaults, name)),
        train_options=changed(training, lambda name: getattr(TrainConfig, name)),
        evaluate_options=changed(scoring, lambda name: getattr(EvaluateConfig, name)),
        seeds=None if args.seeds is None else tuple(args.seeds),
        **{name: value for name, value in {**generator, **training}.items() if name in RUN_FIELDS})
    run_pipeline(config, overwrite=args.overwrite, progress=not args.quiet)
    return 0
