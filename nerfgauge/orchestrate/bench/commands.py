"""`nerfgauge bench NAME`: every benchmark (the modules of this package), one subcommand each.

Numeric flags use `core.arguments` types (NaN, inf and non-positive counts are argument
errors); comma-separated lists are checked item by item (`core.arguments.comma_separated`). Bench output
folders are claimed with `core.folders.claim_folder` as "bench" folders (marker and lock).
The bench modules generate datasets and train models; they import torch (nerf) inside
their functions, so importing them here keeps `nerfgauge --help` free of torch and Mitsuba.
"""

from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.generate.options import parse_resolution
from nerfgauge.orchestrate.bench.colmap import bench_colmap
from nerfgauge.orchestrate.bench.dask import bench_dask
from nerfgauge.orchestrate.bench.generate import bench_generate
from nerfgauge.orchestrate.bench.hard import HardConfig, bench_hard, table_markdown as hard_table_markdown
from nerfgauge.orchestrate.bench.lens import run_lens_bench
from nerfgauge.orchestrate.bench.lpips import bench_lpips
from nerfgauge.orchestrate.bench.lpips_cache import bench_lpips_cache, summary as lpips_cache_summary
from nerfgauge.orchestrate.bench.parametrisation import ParametrisationBenchConfig, bench_parametrisation
from nerfgauge.orchestrate.bench.parametrisation import table_markdown as parametrisation_markdown
from nerfgauge.orchestrate.bench.read import bench_read, table_markdown as read_table_markdown
from nerfgauge.orchestrate.bench.render import bench_render, table_markdown as render_table_markdown
from nerfgauge.orchestrate.bench.scaling import ScalingConfig, bench_scaling, report_markdown
from nerfgauge.orchestrate.bench.splat import METHODS as SPLAT_BENCH_METHODS, SplatBenchConfig, bench_splat
from nerfgauge.orchestrate.bench.splat import GEOMETRY_SAMPLES, report_markdown as splat_markdown
from nerfgauge.orchestrate.bench.targets import bench_targets, targets_command, targets_markdown
from nerfgauge.orchestrate.bench.train import VARIANTS, bench_train, speedups, table_markdown
from nerfgauge.scenes import HARD_SCENES


def register(subparsers) -> None:
    sides, view_counts = (arguments.comma_separated(arguments.IMAGE_SIDE, distinct=True),
                          arguments.comma_separated(arguments.VIEWS, distinct=True))
    parser = subparsers.add_parser("bench", help="speed against error: generator overhead, training variants, scaling",
                                   description="Benchmarks measured in one run on this machine (see BENCHMARKS.md). "
                                               "Each writes into its own --out folder (a nerfgauge bench folder).")
    kinds = parser.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    gen = kinds.add_parser("generate", help="generator time against Mitsuba's own render time")
    gen.add_argument("--scene", default="primitives")
    gen.add_argument("--views", type=arguments.VIEWS, default=100)
    gen.add_argument("--res", default="128")
    gen.add_argument("--spp", type=arguments.SPP, default=64)
    gen.add_argument("--repeats", type=arguments.REPEATS, default=1,
                     help="repeat and report each run (the machine is noisy)")
    gen.set_defaults(func=run_bench_generate)
    train = kinds.add_parser("train", help="scenes x variants x budgets: PSNR, SSIM, depth, time, size, memory")
    train.add_argument("--scenes", type=arguments.names, default=("primitives",), help="comma-separated scene names")
    train.add_argument("--variants", type=arguments.names, default=None,
                       help="comma-separated, from: " + ", ".join(_variant_names())
                            + " (default compact,vanilla; none with --methods unless named)")
    train.add_argument("--methods", type=arguments.names, default=(), metavar="A,B,...",
                       help="any methods the harness runs beside ours, on the same datasets in the same run: a "
                            "shipped spec's name (nerfacto, ...), a spec .toml, module:Class, a built-in name "
                            "(`nerfgauge methods`); each budget for a method that accepts one, else each --steps")
    train.add_argument("--steps", type=arguments.comma_separated(arguments.STEPS, distinct=True), default=(),
                       metavar="N,...", help="step counts for the --methods that take steps, not a time budget")
    train.add_argument("--budgets", type=arguments.comma_separated(arguments.SECONDS, distinct=True), default=(30.0, 120.0),
                       help="comma-separated training seconds (default 30,120)")
    train.add_argument("--res", default="128")
    train.add_argument("--views", type=arguments.VIEWS, default=100)
    train.add_argument("--out", type=arguments.path, default=Path("bench-out/train"),
                       help="bench folder (default bench-out/train): train.json/.md, pareto.png, datasets/, runs/")
    train.set_defaults(func=run_bench_train)
    scaling = kinds.add_parser("scaling", help="NeRF time-to-PSNR and render time against resolution and views; "
                                               "generation time against views and spp")
    scaling.add_argument("--scene", default="primitives")
    scaling.add_argument("--resolutions", type=sides, default=(64, 128, 256),
                         help="comma-separated square resolutions, each at --views views (default 64,128,256)")
    scaling.add_argument("--views", type=arguments.VIEWS, default=100,
                         help="train views of the --resolutions cases (default 100)")
    scaling.add_argument("--view-counts", type=view_counts, default=(25, 50, 100),
                         help="comma-separated train-view counts, each at --view-counts-res (default 25,50,100)")
    scaling.add_argument("--view-counts-res", type=arguments.IMAGE_SIDE, default=128,
                         help="resolution of the --view-counts cases (default 128)")
    scaling.add_argument("--budget-seconds", type=arguments.SECONDS, default=120.0, metavar="T",
                         help="training seconds per case (default 120)")
    scaling.add_argument("--target-psnr", type=arguments.TARGET_PSNR, default=30.0, metavar="DB",
                         help="report the time to this val PSNR (default 30)")
    scaling.add_argument("--gen-views", type=view_counts, default=(25, 50, 100),
                         help="generation: train-view counts at --gen-views-spp")
    scaling.add_argument("--gen-views-spp", type=arguments.SPP, default=64,
                         help="spp of the --gen-views cases (default 64)")
    scaling.add_argument("--gen-spp", type=arguments.comma_separated(arguments.SPP, distinct=True), default=(16, 64, 256),
                         help="generation: spp values at --gen-spp-views views")
    scaling.add_argument("--gen-spp-views", type=arguments.VIEWS, default=50,
                         help="views of the --gen-spp cases (default 50)")
    scaling.add_argument("--gen-res", type=arguments.IMAGE_SIDE, default=128,
                         help="resolution of the generation cases (default 128)")
    scaling.add_argument("--out", type=arguments.path, default=Path("bench-out/scaling"),
                         help="writes scaling.json/.md/.png; reruns replace the cases' datasets and runs")
    scaling.set_defaults(func=run_bench_scaling)
    hard = kinds.add_parser("hard", help="the hard scenes through generate, brief training and evaluate, "
                                         "audited for NaN/inf")
    hard.add_argument("--scenes", type=arguments.names, default=None, help="comma-separated scene names (default: every hard scene)")
    hard.add_argument("--res", default="64")
    hard.add_argument("--views", type=arguments.VIEWS, default=40)
    hard.add_argument("--test-views", type=arguments.VIEWS, default=8)
    hard.add_argument("--spp", type=arguments.SPP, default=64)
    hard.add_argument("--steps", type=arguments.STEPS, default=400, help="training steps per scene (default 400)")
    hard.add_argument("--out", type=arguments.path, default=Path("bench-out/hard"))
    hard.set_defaults(func=run_bench_hard)
    param = kinds.add_parser("parametrisation", help="the automatic parametrisation against each forced one, equal "
                                                     "steps and seed, on captures in no bench (issue 52)")
    pd = ParametrisationBenchConfig()
    param.add_argument("--scenes", type=arguments.names, default=pd.scenes,
                       help=f"comma-separated scene names (default {','.join(pd.scenes)})")
    param.add_argument("--res", default=f"{pd.width}", help=f"N or WxH (default {pd.width})")
    param.add_argument("--views", type=arguments.VIEWS, default=pd.views, help=f"train views (default {pd.views})")
    param.add_argument("--val-views", type=arguments.VIEWS, default=pd.val_views,
                       help=f"val views, which a trial scores on (default {pd.val_views})")
    param.add_argument("--test-views", type=arguments.VIEWS, default=pd.test_views,
                       help=f"test views, scored (default {pd.test_views})")
    param.add_argument("--spp", type=arguments.SPP, default=pd.spp, help=f"samples per pixel (default {pd.spp})")
    param.add_argument("--steps", type=arguments.STEPS, default=pd.steps,
                       help=f"training steps of every run (default {pd.steps})")
    param.add_argument("--seed", type=arguments.SEED, default=pd.seed, help=f"training seed (default {pd.seed})")
    param.add_argument("--out", type=arguments.path, default=Path("bench-out/parametrisation"),
                       help="bench folder: parametrisation.json/.md, each scene's dataset and runs")
    param.set_defaults(func=run_bench_parametrisation)
    targets = kinds.add_parser("targets", help="the reference NeRF's targets (issue 34) in one command: primitives "
                                               "at 120 and 600 s, geometry, exact scores, bench hard, a room")
    targets.add_argument("--skip", type=arguments.names, default=(),
                         help="comma-separated parts to leave out: train, geometry, exact_geometry, hard, inside_check")
    targets.add_argument("--out", type=arguments.path, default=Path("bench-out/targets"),
                         help="bench folder (default bench-out/targets): targets.json/.md and each part's folder")
    targets.set_defaults(func=run_bench_targets)
    lens = kinds.add_parser("lens", help="defocus: the NeRF through a thin lens against refocused light fields and "
                                         "the nearest view, at several apertures")
    lens.add_argument("--scene", default="primitives")
    lens.add_argument("--views", type=arguments.VIEWS, default=64, help="training grid (a square, default 64 = 8x8)")
    lens.add_argument("--test-views", type=arguments.VIEWS, default=6)
    lens.add_argument("--res", type=arguments.IMAGE_SIDE, default=96)
    lens.add_argument("--spp", type=arguments.SPP, default=64)
    lens.add_argument("--radius", type=arguments.DISTANCE, default=3.5, help="camera plane's distance from the scene centre")
    lens.add_argument("--focus-distance", type=arguments.DISTANCE, default=None, help="default: --radius")
    lens.add_argument("--apertures", type=arguments.comma_separated(arguments.DISTANCE), default=(0.1, 0.2),
                      help="comma-separated aperture radii, scene units (default 0.1,0.2)")
    lens.add_argument("--budget-seconds", type=arguments.SECONDS, default=120.0)
    lens.add_argument("--aperture-samples", type=arguments.LENS_SAMPLES, default=16)
    lens.add_argument("--threads", type=arguments.THREADS, default=2)
    lens.add_argument("--out", type=arguments.path, default=Path("bench-out/lens"))
    lens.set_defaults(func=run_bench_lens)
    read = kinds.add_parser("read", help="what validating a dataset on load costs: sizes only against sizes + sha256")
    read.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    read.add_argument("--split", default="train", help="split to read (default train)")
    read.add_argument("--repeats", type=arguments.REPEATS, default=15, help="best of this many (default 15)")
    read.set_defaults(func=run_bench_read)
    colmap = kinds.add_parser("colmap", help="what the COLMAP export adds to generate: runs with and without it, "
                                             "interleaved")
    colmap.add_argument("--pairs", type=arguments.REPEATS, default=3, help="(with, without) pairs (default 3)")
    colmap.add_argument("--res", type=arguments.IMAGE_SIDE, default=128)
    colmap.add_argument("--views", type=arguments.VIEWS, default=100)
    colmap.add_argument("--points", default="surface", help="the export's --points (default surface)")
    colmap.add_argument("--out", type=arguments.path, default=Path("bench-out/colmap"),
                        help="bench folder: colmap.json and the runs' datasets")
    colmap.set_defaults(func=run_bench_colmap)
    dask = kinds.add_parser("dask", help="views per second on a local dask cluster of 1 and of 2 workers")
    dask.add_argument("--views", type=arguments.VIEWS, default=60)
    dask.add_argument("--res", type=arguments.IMAGE_SIDE, default=96)
    dask.add_argument("--spp", type=arguments.SPP, default=64)
    dask.add_argument("--workers", type=arguments.comma_separated(arguments.WORKERS, distinct=True), default=(1, 2),
                      help="comma-separated worker counts (default 1,2)")
    dask.add_argument("--out", type=arguments.path, default=Path("bench-out/dask"),
                      help="bench folder: dask.json and the runs' datasets")
    dask.set_defaults(func=run_bench_dask)
    lpips = kinds.add_parser("lpips", help="LPIPS-Alex speed on random image pairs, as evaluate batches them")
    lpips.add_argument("--frames", type=arguments.VIEWS, default=100)
    lpips.add_argument("--res", type=arguments.IMAGE_SIDE, default=128)
    lpips.add_argument("--repeats", type=arguments.REPEATS, default=3)
    lpips.set_defaults(func=run_bench_lpips)
    splat = kinds.add_parser("splat", help="Gaussian splatting against the compact NeRF: PSNR, SSIM, LPIPS, depth, "
                                           "F-score, render time, model size, steps/s (issue 50)")
    defaults = SplatBenchConfig()
    splat.add_argument("--scenes", type=arguments.names, default=defaults.scenes,
                       help="comma-separated scene names (default primitives)")
    splat.add_argument("--res", default=f"{defaults.width}", help=f"N or WxH (default {defaults.width})")
    splat.add_argument("--views", type=arguments.VIEWS, default=defaults.views,
                       help=f"train views (default {defaults.views})")
    splat.add_argument("--test-views", type=arguments.VIEWS, default=defaults.test_views,
                       help=f"test views, scored (default {defaults.test_views})")
    splat.add_argument("--spp", type=arguments.SPP, default=defaults.spp, help=f"samples per pixel (default {defaults.spp})")
    splat.add_argument("--budgets", type=arguments.comma_separated(arguments.SECONDS, distinct=True),
                       default=defaults.budgets, help="comma-separated training seconds (default 120,600)")
    splat.add_argument("--seeds", type=arguments.comma_separated(arguments.SEED, distinct=True),
                       default=defaults.seeds, help="comma-separated training seeds (default 0)")
    splat.add_argument("--threads", type=arguments.THREADS, default=defaults.threads,
                       help=f"training and rendering threads (default {defaults.threads})")
    splat.add_argument("--methods", type=arguments.names, default=defaults.methods,
                       help=f"comma-separated, from {', '.join(SPLAT_BENCH_METHODS)} (default both)")
    splat.add_argument("--geometry-samples", type=GEOMETRY_SAMPLES, default=defaults.geometry_samples,
                       help=f"surface samples of the geometry scores (default {defaults.geometry_samples})")
    splat.add_argument("--out", type=arguments.path, default=Path("bench-out/splat"),
                       help="bench folder (default bench-out/splat): splat.json/.md/.png, datasets/, runs/")
    splat.set_defaults(func=run_bench_splat)
    cache = kinds.add_parser("lpips-cache", help="what the ground truth's LPIPS feature cache saves: a second method "
                                                 "scored against the same ground truth, against the first")
    cache.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    cache.add_argument("--protocol", default="nerfbaselines", help="evaluate's --protocol (default nerfbaselines)")
    cache.add_argument("--split", default="test", help="split to score (default test)")
    cache.add_argument("--repeats", type=arguments.REPEATS, default=1,
                       help="(first, second) pairs, each with a fresh cache; the median ratio (default 1)")
    cache.add_argument("--uncached", action="store_true", help="also time the first method with the cache off")
    cache.add_argument("--out", type=arguments.path, default=Path("bench-out/lpips-cache"),
                       help="bench folder (default bench-out/lpips-cache): lpips-cache.json/.png, the methods' "
                            "renders and evaluations")
    cache.set_defaults(func=run_bench_lpips_cache)
    render = kinds.add_parser("render", help="an edges run's default render against 3 x 3 rays on every edge pixel "
                                             "and the centre rays alone: ms a frame and test PSNR (issue 52)")
    render.add_argument("runs", nargs="+", type=arguments.path, metavar="RUN",
                        help="run folders of compact NeRFs trained with the edges pixel filter")
    render.add_argument("--split", choices=("train", "val", "test"), default="test", help="split to render (default test)")
    render.add_argument("--repeats", type=arguments.REPEATS, default=3,
                        help="renders of the split per render, in rotating order; the median time (default 3)")
    render.add_argument("--threads", type=arguments.THREADS, default=None, help="render threads (default: each run's)")
    render.add_argument("--out", type=arguments.path, default=Path("bench-out/render"),
                        help="bench folder (default bench-out/render): render.json/.md, each run's renders and metrics")
    render.set_defaults(func=run_bench_render)


def run_bench_splat(args) -> int:
    width, height = parse_resolution(args.res)
    config = SplatBenchConfig(scenes=tuple(args.scenes), width=width, height=height, views=args.views,
                              test_views=args.test_views, spp=args.spp, budgets=tuple(args.budgets),
                              seeds=tuple(args.seeds), threads=args.threads, methods=tuple(args.methods),
                              geometry_samples=args.geometry_samples)
    document = bench_splat(config, args.out)
    print(splat_markdown(document))
    print(f"data: {args.out / 'splat.json'}; table: {args.out / 'splat.md'}; plot: {args.out / 'splat.png'}")
    return 0 if all("error" not in row for row in document["rows"]) else 1


def run_bench_render(args) -> int:
    document = bench_render(list(args.runs), args.out, split=args.split, repeats=args.repeats, threads=args.threads)
    print(render_table_markdown(document))
    print(f"data: {args.out / 'render.json'}; table: {args.out / 'render.md'}")
    return 0


def run_bench_colmap(args) -> int:
    document = bench_colmap(args.out, args.pairs, args.res, args.views, args.points)
    print(f"export adds {100 * (document['ratio_of_means'] - 1):+.1f}% (ratio of means {document['ratio_of_means']:.3f}, "
          f"of medians {document['ratio_of_medians']:.3f}); the export's own share {100 * document['export_share']:.1f}%")
    return 0


def run_bench_dask(args) -> int:
    bench_dask(args.out, args.views, args.res, args.spp, tuple(args.workers))
    return 0


def run_bench_lpips(args) -> int:
    times = bench_lpips(args.frames, args.res, args.repeats)
    print(f"LPIPS-Alex, {args.frames} frames of {args.res} px: " + ", ".join(f"{t:.2f}" for t in times)
          + f" s (best {min(times):.2f} s)")
    return 0


def run_bench_lpips_cache(args) -> int:
    result = bench_lpips_cache(args.dataset, args.out, protocol=args.protocol, split=args.split,
                               uncached=args.uncached, repeats=args.repeats)
    print(lpips_cache_summary(result))
    print(f"bench lpips-cache: {args.out / 'lpips-cache.json'}, {args.out / 'lpips-cache.png'}")
    return 0


def run_bench_lens(args) -> int:
    run_lens_bench(args.out, scene=args.scene, views=args.views, test_views=args.test_views, res=args.res,
                   spp=args.spp, radius=args.radius, focus_distance=args.focus_distance, apertures=args.apertures,
                   budget_seconds=args.budget_seconds, aperture_samples=args.aperture_samples, threads=args.threads)
    print(f"bench lens: {args.out}")
    return 0


def _variant_names():
    return list(VARIANTS)


def run_bench_generate(args) -> int:
    width, height = parse_resolution(args.res)
    print("| run | views | res | spp | variant | s/view (generator) | s/view (Mitsuba render) | overhead ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for repeat in range(args.repeats):
        r = bench_generate(args.scene, args.views, width, height, args.spp)
        print(f"| {repeat + 1} | {r['views']} | {width}x{height} | {r['spp']} | {r['variant']} | "
              f"{r['seconds_per_view']:.4f} | {r['mitsuba_seconds_per_view']:.4f} | {r['overhead_ratio']:.3f} |")
    return 0


def run_bench_train(args) -> int:
    width, height = parse_resolution(args.res)
    variants = args.variants if args.variants is not None else () if args.methods else ("compact", "vanilla")
    rows = bench_train(args.out, list(args.scenes), list(variants), list(args.budgets), width, height, args.views,
                       methods=list(args.methods), steps=list(args.steps))
    print(table_markdown(rows))
    print("\n".join(speedups(rows)))
    print(f"table: {args.out / 'train.md'}; plots: {args.out / 'pareto.png'}")
    return 0


def run_bench_scaling(args) -> int:
    config = ScalingConfig(
        scene=args.scene, resolutions=args.resolutions, views=args.views, view_counts=args.view_counts,
        view_counts_res=args.view_counts_res, budget_seconds=args.budget_seconds, target_psnr=args.target_psnr,
        gen_views=args.gen_views, gen_views_spp=args.gen_views_spp, gen_spp=args.gen_spp,
        gen_spp_views=args.gen_spp_views, gen_res=args.gen_res)
    document = bench_scaling(config, args.out)
    print(report_markdown(document))
    print(f"data: {args.out / 'scaling.json'}; plots: {args.out / 'scaling.png'}")
    return 0


def run_bench_hard(args) -> int:
    width, height = parse_resolution(args.res)
    scenes = tuple(HARD_SCENES) if args.scenes is None else args.scenes
    config = HardConfig(scenes, width, height, args.views, args.test_views, args.spp, args.steps)
    rows = bench_hard(config, args.out)
    print(hard_table_markdown(rows, config.command(args.out)))
    return 0 if all(row["finite"] for row in rows) else 1


def run_bench_parametrisation(args) -> int:
    width, height = parse_resolution(args.res)
    config = ParametrisationBenchConfig(tuple(args.scenes), width, height, args.views, args.val_views, args.test_views,
                                        args.spp, args.steps, args.seed)
    rows = bench_parametrisation(config, args.out)
    print(parametrisation_markdown(rows, config.command(args.out)))
    return 0 if all(row.get("within") for row in rows) else 1


def run_bench_targets(args) -> int:
    rows = bench_targets(args.out, tuple(args.skip))
    print(targets_markdown(rows, targets_command(args.out, tuple(args.skip))))
    return 0


def run_bench_read(args) -> int:
    print(read_table_markdown(bench_read(args.dataset, args.split, args.repeats)))
    return 0
