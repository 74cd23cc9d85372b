"""`nerfgauge run`: generate, train, render, evaluate, baselines, report, in one command.

Each stage is called through its public entry point; this module only decides where
things go:
  OUT/dataset/            the generated dataset (resumed if the same recipe is there)
  OUT/run/                the trained model, its log.jsonl and renders/
  OUT/eval/<method>/      metrics.json and error maps per method (the NeRF and baselines)
  OUT/report.html         table, speed-vs-error curve and image grid (also as PNGs in OUT/report/)
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

from nerfgauge.core.errors import InputError


@dataclass(frozen=True)
class RunConfig:
    scene: str = "primitives"
    out: str = "nerfgauge-run"
    width: int = 128
    height: int = 128
    views: int = 100
    val_views: int = 10
    test_views: int = 20
    spp: int = 64
    layout: str = "auto"  # the scene's suggested cameras, else the hemisphere
    model: str = "compact"
    budget_seconds: float = 90.0
    steps: int | None = None  # instead of the time budget: reproducible across machines (CI gates)
    seed: int = 0
    variant: str = "auto"


def run_pipeline(config: RunConfig, *, overwrite: bool = False, progress: bool = True) -> dict:
    from nerfgauge.core.files import read_json
    from nerfgauge.eval.baselines import write_baseline
    from nerfgauge.eval.evaluate import evaluate, format_means
    from nerfgauge.eval.report import (
        image_grid,
        metrics_table,
        plot_curves,
        read_log,
        write_html,
    )
    from nerfgauge.generate.pipeline import GenerateConfig, generate
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.render_views import render_split
    from nerfgauge.nerf.train import train

    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output path {out} is a file, not a folder")
    generate_config = GenerateConfig(scene=config.scene, seed=config.seed, views=config.views,
                                     val_views=config.val_views, test_views=config.test_views, width=config.width,
                                     height=config.height, spp=config.spp, layout=config.layout, variant=config.variant)
    train_config = TrainConfig(dataset=str(out / "dataset"), model=config.model, seed=config.seed,
                               budget_seconds=None if config.steps else config.budget_seconds, steps=config.steps)
    generate_config.validate()
    train_config.validate()
    if config.test_views < 1:
        raise InputError(f"--test-views must be at least 1: the pipeline evaluates on them, got {config.test_views}")
    run_dir = out / "run"
    if run_dir.exists():
        if not overwrite:
            raise InputError(f"{run_dir} exists from an earlier run; pass --overwrite to train again")
        for stale in (run_dir, out / "eval", out / "baselines", out / "report", out / "report.html"):
            shutil.rmtree(stale, ignore_errors=True) if stale.is_dir() else stale.unlink(missing_ok=True)

    print(f"[1/5] generate {config.scene} -> {out / 'dataset'}")
    generate(generate_config, out / "dataset", overwrite=overwrite, progress=progress)
    length = f"{config.steps} steps" if config.steps else f"{config.budget_seconds:g} s"
    print(f"[2/5] train {config.model} for {length} -> {run_dir}")
    summary = train(train_config, run_dir, progress=progress)
    print("[3/5] render test views")
    render_split(run_dir, "test", progress=progress)
    print("[4/5] evaluate and baselines")
    documents = {f"{config.model} NeRF": evaluate(out / "dataset", run_dir / "renders", "test",
                                                  out / "eval" / config.model / "metrics.json")}
    layout = read_json(out / "dataset" / "scene.json")["camera"]["layout"]
    baselines = ["nearest"] + (["lightfield-nearest", "lightfield-quadrilinear"] if layout == "lightfield" else [])
    for method in baselines:
        write_baseline(out / "dataset", method, out / "baselines" / method, "test")
        documents[f"baseline: {method}"] = evaluate(out / "dataset", out / "baselines" / method, "test",
                                                    out / "eval" / method / "metrics.json")
    print("[5/5] report")
    (out / "report").mkdir(parents=True, exist_ok=True)
    plot_curves({f"{config.model} NeRF": read_log(run_dir / "log.jsonl")}, out / "report" / "curve.png")
    image_grid(out / "dataset", run_dir / "renders", out / "report" / "grid.png")
    table = metrics_table(documents)
    notes = [f"scene {config.scene}, {config.width}x{config.height}, {config.views} train / {config.test_views} test views, "
             f"{config.spp} spp; {config.model} trained {summary['steps']} steps in {summary['seconds']:.1f} s, "
             f"saved model {summary['model_bytes'] / 1e6:.2f} MB",
             "PSNR and SSIM on colour composited onto white; depth metrics on pixels whose centre ray hits "
             "geometry, on ray distance.",
             "Image grid columns: ground truth, prediction, colour error (0-0.2), predicted depth, depth error (0-10%)."]
    write_html(out / "report.html", f"nerfgauge: {config.scene}", table,
               {"speed against error": out / "report" / "curve.png",
                "test views": out / "report" / "grid.png"}, notes)
    print(format_means(documents[f"{config.model} NeRF"]))
    print(f"report: {out / 'report.html'}")
    return {"metrics": str(out / "eval" / config.model / "metrics.json"), "report": str(out / "report.html"),
            "train": summary}


def register(subparsers) -> None:
    defaults = RunConfig()
    parser = subparsers.add_parser("run", help="generate, train, render, evaluate, baselines and report in one go",
                                   description="The train-and-evaluate pipeline (about 3 minutes on 2 CPU cores "
                                               "with the defaults).")
    parser.add_argument("scene", nargs="?", default=defaults.scene, help="scene (default primitives)")
    parser.add_argument("--out", default=defaults.out, help=f"output folder (default {defaults.out})")
    parser.add_argument("--res", default=str(defaults.width), help="N or WxH (default 128)")
    parser.add_argument("--views", type=int, default=defaults.views)
    parser.add_argument("--test-views", type=int, default=defaults.test_views)
    parser.add_argument("--spp", type=int, default=defaults.spp)
    parser.add_argument("--layout", default=defaults.layout)
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--budget-seconds", type=float, default=defaults.budget_seconds, help="training time (default 90)")
    length.add_argument("--steps", type=int, default=None, help="training steps instead of time (reproducible)")
    parser.add_argument("--model", default=defaults.model, choices=("compact", "vanilla"))
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--variant", default=defaults.variant)
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    from nerfgauge.generate.commands import parse_resolution

    width, height = parse_resolution(args.res)
    config = dataclasses.replace(RunConfig(), scene=args.scene, out=args.out, width=width, height=height,
                                 views=args.views, test_views=args.test_views, spp=args.spp, layout=args.layout,
                                 budget_seconds=args.budget_seconds, steps=args.steps, model=args.model, seed=args.seed,
                                 variant=args.variant)
    run_pipeline(config, overwrite=args.overwrite, progress=not args.quiet)
    return 0
