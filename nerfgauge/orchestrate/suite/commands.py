"""`nerfgauge suite`: benchmark suites (nerfgauge/orchestrate/suite/definition.py), run
(nerfgauge/orchestrate/suite/run.py) and the leaderboard (nerfgauge/orchestrate/suite/report.py).

    nerfgauge suite list
    nerfgauge suite generate SUITE --out DIR [--overwrite]
    nerfgauge suite evaluate SUITE DIR --method NAME --pred PRED_ROOT [--pred-format ...] [--seeds K|A,B,...]
    nerfgauge suite run SUITE --out DIR [--methods A,B,...] [--overwrite] [--seeds K|A,B,...]
                                        [--scheduler ADDRESS] [--threads T]
    nerfgauge suite report DIR [--suite SUITE]

SUITE is a built-in name (`suite list`) or a path to a .toml file. `suite report` without
--suite reads the suite from DIR/suite.json, checked as a suite file is and against the
folder's marker, suite manifest and datasets (orchestrate.suite.suite_from_folder).
A suite file in an older format is read with a one-line note on stderr (Suite.notes).
"""

from __future__ import annotations

import sys

from nerfgauge.core import arguments
from nerfgauge.orchestrate.suite.definition import builtin_suites, evaluate_suite, generate_suite, load_suite
from nerfgauge.orchestrate.suite.report import write_leaderboard
from nerfgauge.orchestrate.suite.run import run_suite


def register(subparsers) -> None:
    parser = subparsers.add_parser("suite", help="benchmark suites: versioned sets of datasets, a leaderboard",
                                   description="Versioned benchmark suites (suites/*.toml): generate their datasets, "
                                               "score any method's renders on all of them, and rank the methods.")
    kinds = parser.add_subparsers(dest="suite_command", metavar="ACTION", required=True)
    listing = kinds.add_parser("list", help="the built-in suites")
    listing.set_defaults(func=run_list)
    generate = kinds.add_parser("generate", help="render every dataset of a suite (resumable) and its manifest")
    generate.add_argument("suite", metavar="SUITE", help="built-in suite name or path to a .toml file")
    generate.add_argument("--out", type=arguments.path, required=True, metavar="DIR", help="suite folder")
    generate.add_argument("--overwrite", action="store_true", help="replace a suite folder of another suite or version")
    generate.add_argument("--progress", action="store_true", help="progress bars")
    generate.add_argument("--scheduler", default=None, metavar="ADDRESS",
                          help="render the views on a dask.distributed cluster: tcp://HOST:PORT or local:N "
                               "(needs the dask extra)")
    generate.set_defaults(func=run_generate)
    evaluate = kinds.add_parser("evaluate", help="score a method's renders on every dataset of a suite")
    evaluate.add_argument("suite", metavar="SUITE")
    evaluate.add_argument("dir", type=arguments.path, metavar="DIR", help="the suite folder (suite generate)")
    evaluate.add_argument("--method", required=True, metavar="NAME", help="the method's name on the leaderboard")
    evaluate.add_argument("--pred", type=arguments.path, required=True, metavar="PRED_ROOT",
                          help="PRED_ROOT/<dataset id>/ holds the renders of each dataset (any format evaluate reads)")
    evaluate.add_argument("--pred-format", choices=("auto", "nerfgauge", "nerfstudio", "nerfbaselines", "folder"),
                          default="auto", help="how the renders are named (default: detect per dataset)")
    evaluate.add_argument("--seeds", type=arguments.seeds, default=None, metavar="K|A,B,...",
                          help="the method was run once per seed: PRED_ROOT/seed-<s>/<id>/ per seed (K: seeds "
                               "0..K-1); scored per seed and aggregated with intervals over seeds and views")
    evaluate.set_defaults(func=run_evaluate)
    run = kinds.add_parser("run", help="every method of a suite over its datasets and seeds, then the leaderboard")
    run.add_argument("suite", metavar="SUITE")
    run.add_argument("--out", type=arguments.path, required=True, metavar="DIR", help="suite folder")
    run.add_argument("--methods", default=None, metavar="A,B,...",
                     help="run these methods instead of the suite's [[methods]]: a method of the suite (by name, "
                          "with its settings), a built-in or shipped method's name, module:Class or a spec .toml "
                          "(`nerfgauge methods` lists them)")
    run.add_argument("--overwrite", action="store_true", help="replace a suite folder of another suite or version")
    run.add_argument("--progress", action="store_true", help="progress bars")
    run.add_argument("--seeds", type=arguments.seeds, default=None, metavar="K|A,B,...",
                     help="train each learned method K times (seeds 0..K-1) or with the listed seeds; every run is "
                          "kept, the leaderboard gives 95%% intervals over seeds and views (default: once, the "
                          "entry's seed)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run generation and every (dataset, method, seed) job on a dask.distributed cluster: "
                          "tcp://HOST:PORT or local:N (needs the dask extra)")
    run.add_argument("--threads", type=arguments.THREADS, default=None, metavar="T",
                     help="threads per job (default: the suite's [train] threads; on local:N a share of the cores "
                          "when N workers would oversubscribe them). Per-run metrics repeat for equal T")
    run.set_defaults(func=run_run)
    report = kinds.add_parser("report", help="the leaderboard (Markdown, HTML, JSON) and per-dataset reports")
    report.add_argument("dir", type=arguments.path, metavar="DIR", help="the suite folder")
    report.add_argument("--suite", default=None, metavar="SUITE",
                        help="check the folder against this suite (built-in name or .toml) instead of the definition "
                             "its suite.json records")
    report.set_defaults(func=run_report)


def run_list(args) -> int:
    for name in builtin_suites():
        suite = _load(name)
        print(f"{name:10s} v{suite.version}  {len(suite.scenes):2d} datasets  {suite.description}")
    return 0


def run_generate(args) -> int:
    suite = _load(args.suite)
    manifest = generate_suite(suite, args.out, overwrite=args.overwrite, progress=args.progress,
                              scheduler=args.scheduler)
    files = sum(len(record["files"]) for record in manifest["datasets"].values())
    print(f"suite {suite.name} v{suite.version}: {len(manifest['datasets'])} datasets, {files} files -> "
          f"{args.out / 'suite-manifest.json'}")
    return 0


def run_evaluate(args) -> int:
    suite = _load(args.suite)
    result = evaluate_suite(suite, args.dir, args.method, args.pred, pred_format=args.pred_format, seeds=args.seeds)
    print(f"{args.method}: {len(result['datasets'])} datasets scored -> {args.dir / 'results' / args.method}")
    return 0


def run_run(args) -> int:
    run_suite(_load(args.suite), args.out, overwrite=args.overwrite, progress=args.progress, seeds=args.seeds,
              scheduler=args.scheduler, threads=args.threads, methods=args.methods)
    return 0


def run_report(args) -> int:
    write_leaderboard(_load(args.suite) if getattr(args, "suite", None) else None, args.dir)
    return 0


def _load(spec):
    """load_suite, its notes (an older file's names) one line each on stderr."""
    suite = load_suite(spec)
    for note in suite.notes:
        print(note, file=sys.stderr)
    return suite
