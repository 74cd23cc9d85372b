"""eval's subcommands: `check` (the CI gate, format in `eval.check`), `evaluate` (`eval.evaluate`)
and `baseline` (`eval.baselines`)."""

from pathlib import Path


def register(subparsers) -> None:
    register_check(subparsers)
    register_evaluate(subparsers)
    register_baseline(subparsers)


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
    from eval.check import run_check as check

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
    from eval.evaluate import evaluate, format_means

    document = evaluate(args.dataset, args.pred, split=args.split, out=args.out,
                        background=args.background, depth_kind=args.depth_kind)
    out = args.out if args.out is not None else args.pred / "metrics.json"
    print(f"scene {document['scene']}, split {document['split']}, {len(document['frames'])} frames, "
          f"background {document['background']}, depth {document['depth_kind']} -> {out}")
    print(format_means(document))
    return 0


def register_baseline(subparsers) -> None:
    from eval.baselines import METHODS

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
    from eval.baselines import write_baseline

    timing = write_baseline(args.dataset, args.method, args.out, split=args.split)
    print(f"{args.out}: {timing['frames']} frames by {args.method} ({timing['ms_per_frame']:.1f} ms per frame)")
    if args.evaluate:
        args.pred, args.out, args.background, args.depth_kind = args.out, None, "white", "distance"
        return run_evaluate(args)
    return 0
