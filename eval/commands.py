"""`nerfgauge check`: the CI gate on metric thresholds (format in `eval.check`)."""

from pathlib import Path


def register(subparsers) -> None:
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
