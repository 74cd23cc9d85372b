"""eval's subcommands: `check` (the CI gate, format in `eval.check`), `evaluate` (`eval.evaluate`),
`baseline` (`eval.baselines`), `bench` (`eval.bench`), and `mesh` (`nerf.mesh`) and
`geometry` (`eval.geometry`, `eval.normals`), and `suite` (`eval.suite_commands`).

Numeric flags use `core.arguments` types (NaN, inf and non-positive counts are argument
errors); comma-separated lists are checked item by item (`comma_separated`). Output
folders are claimed with `core.folders.claim_folder` (marker and lock): `baseline --out
DIR` as a "baseline", bench folders as "bench". Output files (`evaluate --out`, `--ns-eval`,
`--nerfbaselines`, `check --junit`, `mesh -o`, `geometry -o`) go through
`core.outputs.check_output_file` before anything is computed: a new path or a nerfgauge file
of the same kind; `--overwrite` also replaces a nerfgauge file of another kind.
"""

import argparse
import contextlib
from pathlib import Path

from nerfgauge.core import arguments


def comma_separated(item_type, *, distinct: bool = False):
    """An argparse type: "a,b,c" -> a tuple of item_type(each), at least one item; with
    distinct=True a repeated value is refused. Item errors name the item and the list."""
    def parse(text: str) -> tuple:
        parts = [part.strip() for part in text.split(",")]
        if not all(parts):
            raise argparse.ArgumentTypeError(f"expected comma-separated values, got {text!r}")
        values = []
        for part in parts:
            try:
                values.append(item_type(part))
            except argparse.ArgumentTypeError as error:
                raise argparse.ArgumentTypeError(f"{error} (in {text!r})" if len(parts) > 1 else str(error)) from None
        if distinct and len(set(values)) < len(values):
            repeated = next(v for v in values if values.count(v) > 1)
            raise argparse.ArgumentTypeError(f"{repeated} appears more than once in {text!r}")
        return tuple(values)

    parse.__name__ = f"comma-separated {item_type.__name__.replace('_', ' ')}s"  # argparse's fallback message
    return parse


def names(text: str) -> tuple:
    """ "a, b" -> ("a", "b"): comma-separated names, at least one, none empty."""
    parts = tuple(part.strip() for part in text.split(","))
    if not all(parts):
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    return parts


def register(subparsers) -> None:
    register_check(subparsers)
    register_evaluate(subparsers)
    register_baseline(subparsers)
    register_bench(subparsers)
    register_geometry(subparsers)
    from nerfgauge.eval import lpips_commands, sfm, suite_commands

    suite_commands.register(subparsers)
    lpips_commands.register(subparsers)
    sfm.register(subparsers)


def register_check(subparsers) -> None:
    parser = subparsers.add_parser(
        "check",
        help="compare a metrics.json against thresholds; exit 0 pass, 1 fail, 2 bad input",
        description="Compare a metrics.json (from `nerfgauge evaluate`) against per-scene min/max "
                    "bounds in a TOML file. Exit 0 when every check passes, 1 when any fails, "
                    "2 for malformed input.",
    )
    parser.add_argument("metrics", type=arguments.path, metavar="METRICS.json",
                        help="metrics file written by `nerfgauge evaluate`")
    parser.add_argument("--thresholds", type=arguments.path, required=True, metavar="FILE",
                        help="TOML: [scene] tables of metric = { min = ..., max = ... }; [\"*\"] applies to all scenes")
    parser.add_argument("--junit", type=arguments.path, metavar="FILE",
                        help="also write the checks as JUnit XML; FILE must be new or a JUnit file nerfgauge wrote "
                             "(a rerun replaces it), never a user's file or a file in a dataset folder")
    parser.add_argument("--overwrite", action="store_true",
                        help="let --junit replace a nerfgauge file of another kind (never a file nerfgauge did not "
                             "write)")
    parser.add_argument("--scene", metavar="NAME",
                        help="use the bounds of scene NAME instead of the scene named in the metrics file")
    parser.set_defaults(func=run_check)


def run_check(args) -> int:
    from nerfgauge.eval.check import run_check as check

    return check(args.metrics, args.thresholds, junit_path=args.junit, scene=args.scene,
                 overwrite=getattr(args, "overwrite", False))


def register_evaluate(subparsers) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="score a folder of renders against a dataset split (PSNR, SSIM, depth, opacity)",
        description="Score predictions (a nerfgauge render folder or another method's renders named after the "
                    "dataset's frames) against a dataset split; write metrics.json and error maps. "
                    "Accepted file names: see eval/evaluate.py.",
    )
    parser.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    parser.add_argument("--pred", type=arguments.path, required=True, metavar="DIR", help="folder of predicted frames")
    parser.add_argument("--split", default="test", help="split to score (default test)")
    parser.add_argument("--out", type=arguments.path, metavar="FILE", help="metrics file (default DIR/metrics.json); "
                        "error maps go to error_maps/ beside it. FILE must be new or a metrics file nerfgauge "
                        "wrote (a rerun replaces it); never a user's file or a file in a dataset folder")
    parser.add_argument("--background", choices=("white", "black"), default="white",
                        help="composite RGBA onto this colour before PSNR/SSIM (default white)")
    parser.add_argument("--depth-kind", choices=("distance", "z"), default="distance",
                        help="what predicted depth holds: ray distance (default) or z-depth")
    parser.add_argument("--pred-format", choices=("auto", "nerfgauge", "nerfstudio", "nerfbaselines", "folder"),
                        default="auto", help="how DIR names its files: ours, ns-render dataset output, NerfBaselines "
                                             "predictions, or a plain folder of images (default: detect; eval/foreign.py)")
    parser.add_argument("--no-held-out", dest="held_out", action="store_false",
                        help="skip the co-visible and depth-resolved scores (psnr_covisible, psnr_capture_bound, "
                             "depth_absrel_resolved): "
                             "their pass costs about 0.12 us per hit test pixel and train view")
    parser.add_argument("--ns-eval", type=arguments.path, metavar="FILE",
                        help="also write nerfstudio's ns-eval JSON (checkpoint: RUN/model.pt for RUN/renders); "
                             "new, or one nerfgauge wrote, as for --out")
    parser.add_argument("--nerfbaselines", type=arguments.path, metavar="FILE",
                        help="also write the scores as NerfBaselines' results.json; new, or one nerfgauge wrote")
    parser.add_argument("--overwrite", action="store_true",
                        help="let --out, --ns-eval, --nerfbaselines replace a nerfgauge file of another kind "
                             "(never a file nerfgauge did not write, nor a run's or a dataset's files)")
    parser.add_argument("--method-name", default=None, metavar="NAME",
                        help="method named in --ns-eval / --nerfbaselines output (default: DIR's name)")
    parser.set_defaults(func=run_evaluate)


OUTPUT_KINDS = {"ns-eval": "ns-eval", "nerfbaselines": "nerfbaselines-results"}  # core.outputs kinds


def run_evaluate(args) -> int:
    from nerfgauge.core.files import write_json
    from nerfgauge.core.outputs import check_output_file, stamp
    from nerfgauge.eval.evaluate import METRICS_KIND, evaluate, format_means

    out = args.out if args.out is not None else args.pred / "metrics.json"
    extra = {"ns-eval": getattr(args, "ns_eval", None), "nerfbaselines": getattr(args, "nerfbaselines", None)}
    overwrite = getattr(args, "overwrite", False)
    check_output_file(out, METRICS_KIND, overwrite=overwrite)  # refused before anything is computed or written
    for name, target in extra.items():
        if target is not None:
            check_output_file(target, OUTPUT_KINDS[name], overwrite=overwrite)
    document = evaluate(args.dataset, args.pred, split=args.split, out=out, background=args.background,
                        depth_kind=args.depth_kind, pred_format=getattr(args, "pred_format", "auto"),
                        held_out=getattr(args, "held_out", True))
    print(f"scene {document['scene']}, split {document['split']}, {len(document['frames'])} frames, "
          f"background {document['background']}, depth {document['depth_kind']} -> {out}")
    print(format_means(document))
    if any(path is not None for path in extra.values()):
        from nerfgauge.eval.foreign_results import nerfbaselines_document, ns_eval_document

        method = getattr(args, "method_name", None) or Path(args.pred).resolve().name
        model = Path(args.pred).resolve().parent / "model.pt"  # RUN/renders of `nerfgauge render`
        checkpoint = str(model) if model.is_file() else str(args.pred)
        if extra["ns-eval"] is not None:
            write_json(extra["ns-eval"], stamp(ns_eval_document(document, experiment_name=document["scene"],
                                                                method_name=method, checkpoint=checkpoint),
                                               OUTPUT_KINDS["ns-eval"]))
            print(f"ns-eval results -> {extra['ns-eval']}")
        if extra["nerfbaselines"] is not None:
            write_json(extra["nerfbaselines"], stamp(nerfbaselines_document(document, dataset_root=args.dataset,
                                                                            pred_dir=args.pred, method_name=method),
                                                     OUTPUT_KINDS["nerfbaselines"]))
            print(f"NerfBaselines results -> {extra['nerfbaselines']}")
    return 0


def register_baseline(subparsers) -> None:
    from nerfgauge.eval.baselines import METHODS

    parser = subparsers.add_parser(
        "baseline",
        help="render a split with a non-learned baseline (nearest view, two-plane light field)",
        description="Render a split with a baseline from the lecture and write the frames as PNG named after "
                    "the dataset's frames, plus timing.json; score them with `nerfgauge evaluate`.",
    )
    parser.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    parser.add_argument("--method", choices=METHODS, required=True,
                        help="nearest: closest training view; lightfield-*: two-plane light field "
                             "(datasets made with --layout lightfield)")
    parser.add_argument("--out", type=arguments.path, required=True, metavar="DIR",
                        help="folder for the renders (new, empty, or an earlier baseline folder)")
    parser.add_argument("--split", default="test", help="split to render (default test)")
    parser.add_argument("--evaluate", action="store_true", help="then score the renders (writes DIR/metrics.json)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a baseline folder made from another dataset, method or split")
    parser.add_argument("--aperture", type=arguments.finite_float, default=None, metavar="RADIUS",
                        help="refocus: lens radius for every frame (default: each frame's own lens)")
    parser.add_argument("--focus-distance", type=arguments.finite_float, default=None, metavar="D",
                        help="refocus: focus distance for every frame (with --aperture)")
    parser.add_argument("--lens-samples", type=arguments.positive_int, default=64, metavar="N",
                        help="refocus: lens samples per pixel (default 64)")
    parser.set_defaults(func=run_baseline)


@contextlib.contextmanager
def baseline_folder(root, method: str, out, split: str, *, overwrite: bool = False, options=None):
    """Claim `out` as a "baseline" folder (core.folders.claim_folder) for the block. Its
    recipe is the method, the split and the dataset's content (manifest.json's hash), so a
    rerun on the same dataset continues and another one needs overwrite."""
    from nerfgauge.core import dataset
    from nerfgauge.core.folders import claim_folder, recipe_hash, remove_owned

    root, out = dataset.require_complete(root), Path(out)
    recipe = recipe_hash({"method": method, "split": split, "dataset": dataset.manifest_sha256(root)}
                         | ({"options": options} if options else {}))
    made = [folder for folder in (out, *out.parents) if not folder.exists()]  # what claiming creates
    state = None
    try:
        with claim_folder(out, "baseline", recipe, overwrite=overwrite) as state:
            yield state
    except BaseException:
        if state == "new" and made:  # the baseline failed (bad input, interrupted): leave no folder behind
            remove_owned(out, "baseline")
            for parent in made[1:]:
                with contextlib.suppress(OSError):  # not empty any more: someone else's now
                    parent.rmdir()
        raise


def run_baseline(args) -> int:
    from nerfgauge.eval.baselines import write_baseline

    from nerfgauge.core.camera import ThinLens
    from nerfgauge.core.errors import InputError

    lens = None
    if args.aperture is not None or args.focus_distance is not None:
        if args.method != "refocus" or args.aperture is None or args.focus_distance is None:
            raise InputError("--aperture and --focus-distance go together, with --method refocus")
        lens = ThinLens(args.aperture, args.focus_distance)
    with baseline_folder(args.dataset, args.method, args.out, args.split, overwrite=args.overwrite,
                         options=None if lens is None else lens.to_json() | {"samples": args.lens_samples}):
        timing = write_baseline(args.dataset, args.method, args.out, split=args.split, lens=lens,
                                samples=args.lens_samples)
        print(f"{args.out}: {timing['frames']} frames by {args.method} ({timing['ms_per_frame']:.1f} ms per frame)")
        if args.evaluate:
            args.pred, args.out, args.background, args.depth_kind = args.out, None, "white", "distance"
            return run_evaluate(args)
    return 0


def register_bench(subparsers) -> None:
    positive_ints = comma_separated(arguments.positive_int, distinct=True)
    parser = subparsers.add_parser("bench", help="speed against error: generator overhead, training variants, scaling",
                                   description="Benchmarks measured in one run on this machine (see BENCHMARKS.md). "
                                               "Each writes into its own --out folder (a nerfgauge bench folder).")
    kinds = parser.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    gen = kinds.add_parser("generate", help="generator time against Mitsuba's own render time")
    gen.add_argument("--scene", default="primitives")
    gen.add_argument("--views", type=arguments.positive_int, default=100)
    gen.add_argument("--res", default="128")
    gen.add_argument("--spp", type=arguments.positive_int, default=64)
    gen.add_argument("--repeats", type=arguments.positive_int, default=1,
                     help="repeat and report each run (the machine is noisy)")
    gen.set_defaults(func=run_bench_generate)
    train = kinds.add_parser("train", help="scenes x variants x budgets: PSNR, SSIM, depth, time, size, memory")
    train.add_argument("--scenes", type=names, default=("primitives",), help="comma-separated scene names")
    train.add_argument("--variants", type=names, default=("compact", "vanilla"),
                       help="comma-separated, from: " + ", ".join(_variant_names()))
    train.add_argument("--budgets", type=comma_separated(arguments.positive_float, distinct=True), default=(30.0, 120.0),
                       help="comma-separated training seconds (default 30,120)")
    train.add_argument("--res", default="128")
    train.add_argument("--views", type=arguments.positive_int, default=100)
    train.add_argument("--out", type=arguments.path, default=Path("bench-out/train"),
                       help="bench folder (default bench-out/train): train.json/.md, pareto.png, datasets/, runs/")
    train.set_defaults(func=run_bench_train)
    scaling = kinds.add_parser("scaling", help="NeRF time-to-PSNR and render time against resolution and views; "
                                               "generation time against views and spp")
    scaling.add_argument("--scene", default="primitives")
    scaling.add_argument("--resolutions", type=positive_ints, default=(64, 128, 256),
                         help="comma-separated square resolutions, each at --views views (default 64,128,256)")
    scaling.add_argument("--views", type=arguments.positive_int, default=100,
                         help="train views of the --resolutions cases (default 100)")
    scaling.add_argument("--view-counts", type=positive_ints, default=(25, 50, 100),
                         help="comma-separated train-view counts, each at --view-counts-res (default 25,50,100)")
    scaling.add_argument("--view-counts-res", type=arguments.positive_int, default=128,
                         help="resolution of the --view-counts cases (default 128)")
    scaling.add_argument("--budget-seconds", type=arguments.positive_float, default=120.0, metavar="T",
                         help="training seconds per case (default 120)")
    scaling.add_argument("--target-psnr", type=arguments.positive_float, default=30.0, metavar="DB",
                         help="report the time to this val PSNR (default 30)")
    scaling.add_argument("--gen-views", type=positive_ints, default=(25, 50, 100),
                         help="generation: train-view counts at --gen-views-spp")
    scaling.add_argument("--gen-views-spp", type=arguments.positive_int, default=64,
                         help="spp of the --gen-views cases (default 64)")
    scaling.add_argument("--gen-spp", type=positive_ints, default=(16, 64, 256),
                         help="generation: spp values at --gen-spp-views views")
    scaling.add_argument("--gen-spp-views", type=arguments.positive_int, default=50,
                         help="views of the --gen-spp cases (default 50)")
    scaling.add_argument("--gen-res", type=arguments.positive_int, default=128,
                         help="resolution of the generation cases (default 128)")
    scaling.add_argument("--out", type=arguments.path, default=Path("bench-out/scaling"),
                         help="writes scaling.json/.md/.png; reruns replace the cases' datasets and runs")
    scaling.set_defaults(func=run_bench_scaling)
    hard = kinds.add_parser("hard", help="the hard scenes through generate, brief training and evaluate, "
                                         "audited for NaN/inf")
    hard.add_argument("--scenes", type=names, default=None, help="comma-separated scene names (default: every hard scene)")
    hard.add_argument("--res", default="64")
    hard.add_argument("--views", type=arguments.positive_int, default=40)
    hard.add_argument("--test-views", type=arguments.positive_int, default=8)
    hard.add_argument("--spp", type=arguments.positive_int, default=64)
    hard.add_argument("--steps", type=arguments.positive_int, default=400, help="training steps per scene (default 400)")
    hard.add_argument("--out", type=arguments.path, default=Path("bench-out/hard"))
    hard.set_defaults(func=run_bench_hard)
    lens = kinds.add_parser("lens", help="defocus: the NeRF through a thin lens against refocused light fields and "
                                         "the nearest view, at several apertures")
    lens.add_argument("--scene", default="primitives")
    lens.add_argument("--views", type=arguments.positive_int, default=64, help="training grid (a square, default 64 = 8x8)")
    lens.add_argument("--test-views", type=arguments.positive_int, default=6)
    lens.add_argument("--res", type=arguments.positive_int, default=96)
    lens.add_argument("--spp", type=arguments.positive_int, default=64)
    lens.add_argument("--radius", type=arguments.positive_float, default=3.5, help="camera plane's distance from the scene centre")
    lens.add_argument("--focus-distance", type=arguments.positive_float, default=None, help="default: --radius")
    lens.add_argument("--apertures", type=positive_floats, default=(0.1, 0.2),
                      help="comma-separated aperture radii, scene units (default 0.1,0.2)")
    lens.add_argument("--budget-seconds", type=arguments.positive_float, default=120.0)
    lens.add_argument("--aperture-samples", type=arguments.positive_int, default=16)
    lens.add_argument("--threads", type=arguments.positive_int, default=2)
    lens.add_argument("--out", type=arguments.path, default=Path("bench-out/lens"))
    lens.set_defaults(func=run_bench_lens)
    read = kinds.add_parser("read", help="what validating a dataset on load costs: sizes only against sizes + sha256")
    read.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    read.add_argument("--split", default="train", help="split to read (default train)")
    read.add_argument("--repeats", type=arguments.positive_int, default=15, help="best of this many (default 15)")
    read.set_defaults(func=run_bench_read)


def run_bench_lens(args) -> int:
    from nerfgauge.eval.bench_lens import run_lens_bench

    run_lens_bench(args.out, scene=args.scene, views=args.views, test_views=args.test_views, res=args.res,
                   spp=args.spp, radius=args.radius, focus_distance=args.focus_distance, apertures=args.apertures,
                   budget_seconds=args.budget_seconds, aperture_samples=args.aperture_samples, threads=args.threads)
    print(f"bench lens: {args.out}")
    return 0


def positive_floats(text: str) -> tuple:
    """"0.1,0.2" -> (0.1, 0.2): comma-separated positive finite numbers."""
    return tuple(arguments.positive_float(part) for part in text.split(","))


def _variant_names():
    from nerfgauge.eval.bench import VARIANTS

    return list(VARIANTS)


def run_bench_generate(args) -> int:
    from nerfgauge.eval.bench import bench_generate
    from nerfgauge.generate.commands import parse_resolution

    width, height = parse_resolution(args.res)
    print("| run | views | res | spp | variant | s/view (generator) | s/view (Mitsuba render) | overhead ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for repeat in range(args.repeats):
        r = bench_generate(args.scene, args.views, width, height, args.spp)
        print(f"| {repeat + 1} | {r['views']} | {width}x{height} | {r['spp']} | {r['variant']} | "
              f"{r['seconds_per_view']:.4f} | {r['mitsuba_seconds_per_view']:.4f} | {r['overhead_ratio']:.3f} |")
    return 0


def run_bench_train(args) -> int:
    from nerfgauge.eval.bench import bench_train, speedups, table_markdown
    from nerfgauge.generate.commands import parse_resolution

    width, height = parse_resolution(args.res)
    rows = bench_train(args.out, list(args.scenes), list(args.variants), list(args.budgets), width, height, args.views)
    print(table_markdown(rows))
    print("\n".join(speedups(rows)))
    print(f"table: {args.out / 'train.md'}; plots: {args.out / 'pareto.png'}")
    return 0


def run_bench_scaling(args) -> int:
    from nerfgauge.eval.bench_scaling import ScalingConfig, bench_scaling, report_markdown

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
    from nerfgauge.eval.bench_hard import HardConfig, bench_hard, table_markdown
    from nerfgauge.generate.commands import parse_resolution
    from nerfgauge.scenes import HARD_SCENES

    width, height = parse_resolution(args.res)
    scenes = tuple(HARD_SCENES) if args.scenes is None else args.scenes
    config = HardConfig(scenes, width, height, args.views, args.test_views, args.spp, args.steps)
    rows = bench_hard(config, args.out)
    print(table_markdown(rows, config.command(args.out)))
    return 0 if all(row["finite"] for row in rows) else 1


def run_bench_read(args) -> int:
    from nerfgauge.eval.bench_read import bench_read, table_markdown

    print(table_markdown(bench_read(args.dataset, args.split, args.repeats)))
    return 0


# --- geometry: `mesh` and `geometry` (issue 13) -------------------------------------------


def register_geometry(subparsers) -> None:
    mesh = subparsers.add_parser(
        "mesh", help="a mesh (PLY) from a trained run's density by marching cubes",
        description="Marching cubes on the field's density over the scene bounds, at the density where the model "
                    "renders its surface on training rays; triangles no training camera sees are dropped "
                    "(nerf/mesh.py). The bounds and cameras come from the dataset the run was trained on, checked "
                    "against the manifest.json hash the run recorded (a changed dataset is refused, exit 2).")
    mesh.add_argument("run", type=arguments.path, metavar="RUN_DIR", help="a finished training run (model.pt)")
    mesh.add_argument("-o", "--out", type=arguments.path, required=True, metavar="OUT.ply",
                      help="mesh file to write: a new path or a mesh nerfgauge wrote (a rerun replaces it), never "
                           "a user's file or a file in a dataset folder")
    mesh.add_argument("--resolution", type=arguments.positive_int, default=256,
                      help="grid cells along the scene's longest side (default 256)")
    mesh.add_argument("--no-cull", action="store_true", help="keep triangles no training camera sees")
    mesh.add_argument("--level", type=arguments.positive_float, metavar="SIGMA",
                      help="density of the surface (default: the median density where the model renders its "
                           "surface on training rays)")
    mesh.add_argument("--overwrite", action="store_true",
                      help="let -o replace a nerfgauge file of another kind (never a file nerfgauge did not write)")
    mesh.set_defaults(func=run_mesh)
    geometry = subparsers.add_parser(
        "geometry", help="score a mesh, point cloud or rendered depth against the dataset's exact meshes",
        description="Accuracy, completeness, Chamfer-L1, normal consistency and F-score at distance thresholds "
                    "against DATASET/meshes/*.ply (eval/geometry.py); with --run, also the field's normals "
                    "against the exact normal images (eval/normals.py).")
    geometry.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder")
    source = geometry.add_mutually_exclusive_group(required=True)
    source.add_argument("--pred-mesh", type=arguments.path, metavar="FILE", help="mesh or point cloud (PLY, OBJ, ...)")
    source.add_argument("--pred-depth", type=arguments.path, metavar="DIR",
                        help="folder of rendered ray-distance depth (r_000_depth.exr) of the --split views")
    geometry.add_argument("-o", "--out", type=arguments.path, default=Path("geometry.json"), metavar="FILE",
                          help="scores (default geometry.json): a new path or a geometry file nerfgauge wrote "
                               "(a rerun replaces it), never a user's file or a file in a dataset folder")
    geometry.add_argument("--overwrite", action="store_true",
                          help="let -o replace a nerfgauge file of another kind (never a file nerfgauge did not write)")
    geometry.add_argument("--tau", type=arguments.positive_float, action="append", default=[], metavar="T",
                          help="also score F-score at this distance in world units (repeatable); 0.5%% and 1%% of the "
                               "ground truth's bounding-box diagonal always")
    geometry.add_argument("--samples", type=arguments.positive_int, default=1_000_000,
                          help="points sampled on each surface (default 1000000)")
    geometry.add_argument("--seed", type=arguments.nonnegative_int, default=0, help="sampling seed (default 0)")
    geometry.add_argument("--whole-surface", action="store_true",
                          help="score all ground truth, not only what the reference cameras see")
    geometry.add_argument("--split", default="test", help="views of --pred-depth and of --run's normals (default test)")
    geometry.add_argument("--run", type=arguments.path, metavar="RUN_DIR",
                          help="also score this run's field normals on the --split views (DATASET must be the "
                               "dataset the run was trained on: its manifest.json hash is checked)")
    geometry.set_defaults(func=run_geometry)


def _output_file(out: Path, recipe: dict, kind: str, overwrite: bool):
    """Refuse a target that is not new nor a `kind` file nerfgauge wrote (core.outputs);
    claim a parent folder this command creates as an "evaluation" folder (marker and lock)."""
    from nerfgauge.core.folders import claim_folder, recipe_hash
    from nerfgauge.core.outputs import check_output_file

    check_output_file(out, kind, overwrite=overwrite)
    if out.parent.exists():
        return contextlib.nullcontext()
    return claim_folder(out.parent, "evaluation", recipe_hash(recipe))


def run_mesh(args) -> int:
    from nerfgauge.core.files import write_bytes_atomic
    from nerfgauge.nerf.mesh import mesh_from_run, ply_bytes

    out = Path(args.out)
    if out.suffix.lower() != ".ply":
        from nerfgauge.core.errors import InputError

        raise InputError(f"-o {out}: the mesh is written as PLY; name it *.ply")
    with _output_file(out, {"mesh": str(args.run), "resolution": args.resolution}, "mesh",
                      getattr(args, "overwrite", False)):
        mesh = mesh_from_run(args.run, args.resolution, cull=not args.no_cull, level=args.level)
        write_bytes_atomic(out, ply_bytes(mesh.vertices, mesh.faces))
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces ({mesh.faces_culled} unseen dropped), "
          f"level sigma = {mesh.level:.4g} ({mesh.level_source}), {args.resolution} cells, "
          f"{mesh.seconds:.1f} s")
    return 0


def run_geometry(args) -> int:
    from nerfgauge.core.files import write_json
    from nerfgauge.eval.geometry import format_geometry, score_geometry

    out = Path(args.out)
    recipe = {"geometry": str(args.dataset), "mesh": str(args.pred_mesh), "depth": str(args.pred_depth)}
    run = None
    if args.run is not None:  # the run and its dataset checked before any work (nerf.runs)
        from nerfgauge.nerf.checkpoint import load_model
        from nerfgauge.nerf.runs import open_run_dataset

        model, config = load_model(Path(args.run) / "model.pt")
        run = model, open_run_dataset(args.run, config, args.dataset)
    with _output_file(out, recipe, "geometry", getattr(args, "overwrite", False)):
        document, _ = score_geometry(args.dataset, args.pred_mesh, args.pred_depth, split=args.split,
                                     taus=tuple(args.tau), samples=args.samples, seed=args.seed,
                                     whole_surface=args.whole_surface)
        if run is not None:
            from nerfgauge.eval.normals import score_normals

            document["normals"] = score_normals(*run, args.split)
        write_json(out, document)
    print(format_geometry(document))
    print(f"-> {out}")
    return 0
