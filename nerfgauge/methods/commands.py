"""`nerfgauge methods`: every method the harness can run (the built-in ones and the specs
nerfgauge ships for other tools' methods), with what it needs from a dataset, what its
renders hold and, for another tool's method, how its environment is installed;
`nerfgauge methods install METHOD [--env DIR]` builds that environment
(nerfgauge.methods.install). `nerfgauge baseline`: a non-learned baseline's renders of a split."""

from __future__ import annotations

import json

from nerfgauge.core import arguments
from nerfgauge.core.camera import ThinLens
from nerfgauge.core.errors import InputError
from nerfgauge.eval.commands import score_renders
from nerfgauge.eval.evaluate import EvaluateConfig
from nerfgauge.methods.baselines import METHODS, baseline_folder, write_baseline
from nerfgauge.methods.builtin import builtin_methods
from nerfgauge.methods.external import ExternalMethod
from nerfgauge.methods.install import install_environment, where_it_looks
from nerfgauge.methods.registry import resolve, shipped_specs

INSTALL = "install"  # the verb: `nerfgauge methods install METHOD`


def register(subparsers) -> None:
    register_baseline(subparsers)
    parser = subparsers.add_parser(
        "methods", help="list the methods the harness runs, with what each needs and produces; install one's tool",
        description="The methods nerfgauge runs through one interface (train on a dataset into a run folder, "
                    "render a split): its own, and other tools' methods from the specs it ships (nerfacto, "
                    "splatfacto, gsplat, nerfbaselines). Name one in a suite's [[methods]] or on the command line; "
                    "a Python class of yours as module:Class, another tool's method as a spec .toml. "
                    "`nerfgauge methods install METHOD [--env DIR]` builds the environment another tool's method "
                    "runs in, from its spec's install lines.")
    parser.add_argument("specs", nargs="*", metavar="METHOD",
                        help="describe these (names, module:Class or spec files) instead of every method; "
                             "or `install METHOD`")
    parser.add_argument("--env", metavar="DIR",
                        help="with install: build the environment here (default: where the method looks for it, "
                             "$NERFGAUGE_ENV_<NAME> or ~/.local/share/nerfgauge/envs/<name>)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    if args.specs[:1] == [INSTALL]:
        return _install(args)
    if args.env is not None:
        raise InputError("--env is for `nerfgauge methods install METHOD --env DIR`")
    if args.specs:
        methods = [resolve(spec) for spec in args.specs]
    else:
        methods = [*builtin_methods().values(), *(resolve(name) for name in shipped_specs())]
    rows = [method.describe() for method in methods]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    width = max(len(row["name"]) for row in rows)
    for row in rows:
        needs = ", ".join(row["needs"]) or "-"
        kind = "trains" if row["learned"] else "no training"
        print(f"{row['name']:<{width}}  {row['summary']}")
        print(f"{'':<{width}}  {kind}; needs: {needs}; produces: {', '.join(row['produces'])}")
        if row.get("install"):
            print(f"{'':<{width}}  install: nerfgauge methods install {row['name']}   (environment: {row['environment']})")
            for line in row["install"]:
                print(f"{'':<{width}}    {line}")
    return 0


def _install(args) -> int:
    if len(args.specs) != 2:
        raise InputError("give one method: nerfgauge methods install METHOD [--env DIR]")
    method = resolve(args.specs[1])
    if not isinstance(method, ExternalMethod):
        raise InputError(f"method {method.name} is nerfgauge's own: it has no environment to install")
    folder, built = install_environment(method, args.env)
    print(f"{method.name}: environment {'installed' if built else 'already installed'}: {folder}")
    note = where_it_looks(method, folder)
    if note:
        print(note)
    return 0


# --- baseline ---------------------------------------------------------------------------


def register_baseline(subparsers) -> None:
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
    parser.add_argument("--aperture", type=arguments.APERTURE, default=None, metavar="RADIUS",
                        help="refocus: lens radius for every frame (default: each frame's own lens)")
    parser.add_argument("--focus-distance", type=arguments.DISTANCE, default=None, metavar="D",
                        help="refocus: focus distance for every frame (with --aperture)")
    parser.add_argument("--lens-samples", type=arguments.LENS_SAMPLES, default=64, metavar="N",
                        help="refocus: lens samples per pixel (default 64)")
    parser.set_defaults(func=run_baseline)


def run_baseline(args) -> int:
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
        if args.evaluate:  # the renders just written, ours in naming and depth: only the split is the baseline's
            return score_renders(args.dataset, args.out, EvaluateConfig(split=args.split), None, {},
                                 overwrite=args.overwrite)
    return 0
