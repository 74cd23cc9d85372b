"""eval's subcommands: `check` (the CI gate, format in `eval.check`), `evaluate` (`eval.evaluate`),
`baseline` (`eval.baselines`) and `bench` (`eval.bench`)."""

from pathlib import Path


def register(subparsers) -> None:
    register_check(subparsers)
    register_evaluate(subparsers)
    register_baseline(subparsers)
    register_bench(subparsers)


def register_check(subparsers) -> None:
    parser = subparsers.add_parser(
        "check",
        help="compare a metrics.json against thresholds; exit 0 pass, 1 fail, 2 bad input",
        description="Compare a metrics.json (from `nerfgauge evaluate`) against per-scene min/max "
                    "bounds in a TOML file. Exit 0 when every check passes, 1 when any fails, "
                    "2 for malformed input.",
    )
    parser.add_argument("metrics", type=Path, metavar="METRICS.json", help="metrics file written by `nerfgauge evaluate`")
    parser.add_argument("--thresholds", type=Path, required=True, metavar="FILE",
                        help="TOML: [scene] tables of metric = { min = ..., max = ... }; [\"*\"] applies to all scenes")
    parser.add_argument("--junit", type=Path, metavar="FILE", help="also write the checks as JUnit XML")
    parser.add_argument("--scene", metavar="NAME",
                        help="use the bounds of scene NAME instead of the scene named in the metrics file")
    parser.set_defaults(func=run_check)


def run_check(args) -> int:
    from nerfgauge.eval.check import run_check as check

    return check(args.metrics, args.thresholds, junit_path=args.junit, scene=args.scene)


def register_evaluate(subparsers) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="score a folder of renders against a dataset split (PSNR, SSIM, depth, opacity)",
        description="Score predictions (a nerfgauge render folder or another method's renders named after the "
                    "dataset's frames) against a dataset split; write metrics.json and error maps. "
                    "Accepted file names: see eval/evaluate.py.",
    )
    parser.add_argument("dataset", type=Path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    parser.add_argument("--pred", type=Path, required=True, metavar="DIR", help="folder of predicted frames")
    parser.add_argument("--split", default="test", help="split to score (default test)")
    parser.add_argument("--out", type=Path, metavar="FILE", help="metrics file (default DIR/metrics.json); "
                        "error maps go to error_maps/ beside it")
    parser.add_argument("--background", choices=("white", "black"), default="white",
                        help="composite RGBA onto this colour before PSNR/SSIM (default white)")
    parser.add_argument("--depth-kind", choices=("distance", "z"), default="distance",
                        help="what predicted depth holds: ray distance (default) or z-depth")
    parser.set_defaults(func=run_evaluate)


def run_evaluate(args) -> int:
    from nerfgauge.eval.evaluate import evaluate, format_means

    document = evaluate(args.dataset, args.pred, split=args.split, out=args.out,
                        background=args.background, depth_kind=args.depth_kind)
    out = args.out if args.out is not None else args.pred / "metrics.json"
    print(f"scene {document['scene']}, split {document['split']}, {len(document['frames'])} frames, "
          f"background {document['background']}, depth {document['depth_kind']} -> {out}")
    print(format_means(document))
    return 0


def register_baseline(subparsers) -> None:
    from nerfgauge.eval.baselines import METHODS

    parser = subparsers.add_parser(
        "baseline",
        help="render a split with a non-learned baseline (nearest view, two-plane light field)",
        description="Render a split with a baseline from the lecture and write the frames as PNG named after "
                    "the dataset's frames, plus timing.json; score them with `nerfgauge evaluate`.",
    )
    parser.add_argument("dataset", type=Path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    parser.add_argument("--method", choices=METHODS, required=True,
                        help="nearest: closest training view; lightfield-*: two-plane light field "
                             "(datasets made with --layout lightfield)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the renders")
    parser.add_argument("--split", default="test", help="split to render (default test)")
    parser.add_argument("--evaluate", action="store_true", help="then score the renders (writes DIR/metrics.json)")
    parser.set_defaults(func=run_baseline)


def run_baseline(args) -> int:
    from nerfgauge.eval.baselines import write_baseline

    timing = write_baseline(args.dataset, args.method, args.out, split=args.split)
    print(f"{args.out}: {timing['frames']} frames by {args.method} ({timing['ms_per_frame']:.1f} ms per frame)")
    if args.evaluate:
        args.pred, args.out, args.background, args.depth_kind = args.out, None, "white", "distance"
        return run_evaluate(args)
    return 0


def register_bench(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="speed against error: generator overhead, training variants, scaling",
                                   description="Benchmarks measured in one run on this machine (see BENCHMARKS.md).")
    kinds = parser.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    gen = kinds.add_parser("generate", help="generator time against Mitsuba's own render time")
    gen.add_argument("--scene", default="primitives")
    gen.add_argument("--views", type=int, default=100)
    gen.add_argument("--res", default="128")
    gen.add_argument("--spp", type=int, default=64)
    gen.add_argument("--repeats", type=int, default=1, help="repeat and report each run (the machine is noisy)")
    gen.set_defaults(func=run_bench_generate)
    train = kinds.add_parser("train", help="scenes x variants x budgets: PSNR, SSIM, depth, time, size, memory")
    train.add_argument("--scenes", default="primitives", help="comma-separated scene names")
    train.add_argument("--variants", default="compact,vanilla",
                       help="comma-separated, from: " + ", ".join(_variant_names()))
    train.add_argument("--budgets", default="30,120", help="comma-separated training seconds")
    train.add_argument("--res", default="128")
    train.add_argument("--views", type=int, default=100)
    train.add_argument("--out", type=Path, default=Path("bench-out"))
    train.set_defaults(func=run_bench_train)
    scaling = kinds.add_parser("scaling", help="NeRF time-to-PSNR and render time against resolution and views; "
                                               "generation time against views and spp")
    scaling.add_argument("--scene", default="primitives")
    scaling.add_argument("--resolutions", default="64,128,256",
                         help="comma-separated square resolutions, each at --views views (default 64,128,256)")
    scaling.add_argument("--views", default="100", help="train views of the --resolutions cases (default 100)")
    scaling.add_argument("--view-counts", default="25,50,100", help="comma-separated train-view counts, each at "
                                                                    "--view-counts-res (default 25,50,100)")
    scaling.add_argument("--view-counts-res", default="128", help="resolution of the --view-counts cases (default 128)")
    scaling.add_argument("--budget-seconds", default="120", metavar="T", help="training seconds per case (default 120)")
    scaling.add_argument("--target-psnr", default="30", metavar="DB",
                         help="report the time to this val PSNR (default 30)")
    scaling.add_argument("--gen-views", default="25,50,100", help="generation: train-view counts at --gen-views-spp")
    scaling.add_argument("--gen-views-spp", default="64", help="spp of the --gen-views cases (default 64)")
    scaling.add_argument("--gen-spp", default="16,64,256", help="generation: spp values at --gen-spp-views views")
    scaling.add_argument("--gen-spp-views", default="50", help="views of the --gen-spp cases (default 50)")
    scaling.add_argument("--gen-res", default="128", help="resolution of the generation cases (default 128)")
    scaling.add_argument("--out", type=Path, default=Path("bench-out/scaling"),
                         help="writes scaling.json/.md/.png; reruns replace the cases' datasets and runs")
    scaling.set_defaults(func=run_bench_scaling)
    hard = kinds.add_parser("hard", help="the hard scenes through generate, brief training and evaluate, "
                                         "audited for NaN/inf")
    hard.add_argument("--scenes", default=None, help="comma-separated scene names (default: every hard scene)")
    hard.add_argument("--res", default="64")
    hard.add_argument("--views", type=int, default=40)
    hard.add_argument("--test-views", type=int, default=8)
    hard.add_argument("--spp", type=int, default=64)
    hard.add_argument("--steps", type=int, default=400, help="training steps per scene (default 400)")
    hard.add_argument("--out", type=Path, default=Path("bench-out/hard"))
    hard.set_defaults(func=run_bench_hard)


def _variant_names():
    from nerfgauge.eval.bench import VARIANTS

    return list(VARIANTS)


def run_bench_generate(args) -> int:
    from nerfgauge.eval.bench import bench_generate
    from nerfgauge.generate.commands import parse_resolution

    from nerfgauge.core.errors import InputError

    if args.repeats < 1:
        raise InputError(f"--repeats must be a positive integer, got {args.repeats}")
    width, height = parse_resolution(args.res)
    print("| run | views | res | spp | variant | s/view (generator) | s/view (Mitsuba render) | overhead ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for repeat in range(args.repeats):
        r = bench_generate(args.scene, args.views, width, height, args.spp)
        print(f"| {repeat + 1} | {r['views']} | {width}x{height} | {r['spp']} | {r['variant']} | "
              f"{r['seconds_per_view']:.4f} | {r['mitsuba_seconds_per_view']:.4f} | {r['overhead_ratio']:.3f} |")
    return 0


def run_bench_train(args) -> int:
    from nerfgauge.eval.bench import (
        VARIANTS,
        bench_train,
        pareto_plots,
        speedups,
        table_markdown,
    )
    from nerfgauge.generate.commands import parse_resolution

    from nerfgauge.core.errors import InputError

    width, height = parse_resolution(args.res)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise InputError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    try:
        budgets = [float(b) for b in args.budgets.split(",")]
    except ValueError:
        raise InputError(f"--budgets must be comma-separated seconds, got {args.budgets!r}") from None
    if not budgets or min(budgets) <= 0:
        raise InputError(f"--budgets must be positive, got {args.budgets!r}")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    args.out.mkdir(parents=True, exist_ok=True)
    rows = bench_train(args.out, scenes, variants, budgets, width, height, args.views)
    table = table_markdown(rows)
    notes = speedups(rows)
    (args.out / "train.md").write_text(table + "\n\n" + "\n".join(notes) + "\n")
    pareto_plots(rows, args.out)
    print(table)
    print("\n".join(notes))
    print(f"plots: {args.out / 'pareto.png'}")
    return 0


def run_bench_scaling(args) -> int:
    from nerfgauge.eval.bench_scaling import (
        ScalingConfig,
        bench_scaling,
        parse_count,
        parse_counts,
        parse_positive,
        report_markdown,
        scaling_plots,
    )

    config = ScalingConfig(
        scene=args.scene, resolutions=parse_counts(args.resolutions, "resolutions"),
        views=parse_count(args.views, "views"), view_counts=parse_counts(args.view_counts, "view-counts"),
        view_counts_res=parse_count(args.view_counts_res, "view-counts-res"),
        budget_seconds=parse_positive(args.budget_seconds, "budget-seconds"),
        target_psnr=parse_positive(args.target_psnr, "target-psnr"),
        gen_views=parse_counts(args.gen_views, "gen-views"),
        gen_views_spp=parse_count(args.gen_views_spp, "gen-views-spp"),
        gen_spp=parse_counts(args.gen_spp, "gen-spp"), gen_spp_views=parse_count(args.gen_spp_views, "gen-spp-views"),
        gen_res=parse_count(args.gen_res, "gen-res"))
    config.validate()
    document = bench_scaling(config, args.out)
    report = report_markdown(document)
    (args.out / "scaling.md").write_text(report)
    scaling_plots(document, args.out / "scaling.png")
    print(report)
    print(f"data: {args.out / 'scaling.json'}; plots: {args.out / 'scaling.png'}")
    return 0


def run_bench_hard(args) -> int:
    from nerfgauge.eval.bench_hard import HardConfig, bench_hard, table_markdown
    from nerfgauge.generate.commands import parse_resolution
    from nerfgauge.scenes import HARD_SCENES

    width, height = parse_resolution(args.res)
    scenes = tuple(HARD_SCENES) if args.scenes is None else tuple(s.strip() for s in args.scenes.split(",") if s.strip())
    config = HardConfig(scenes, width, height, args.views, args.test_views, args.spp, args.steps)
    rows = bench_hard(config, args.out)
    print(table_markdown(rows, config.command(args.out)))
    return 0 if all(row["finite"] for row in rows) else 1
