"""eval's subcommands: `check` (the CI gate, format in `eval.check`), `evaluate` (`eval.evaluate`),
`geometry` (`eval.geometry`, `eval.normals`) and `lpips` (`eval.lpips_commands`). `baseline`
is the methods' (`nerfgauge.methods.commands`); `bench` and `suite` are registered by
`nerfgauge.orchestrate`, `mesh` by `nerf.commands`.

Numeric flags use `core.arguments` types (NaN, inf and non-positive counts are argument
errors); comma-separated lists are checked item by item (`comma_separated`). Output
folders are claimed with `core.folders.claim_folder` (marker and lock). Output files (`evaluate --out`, `--ns-eval`,
`--nerfbaselines`, `check --junit`, `mesh -o`, `geometry -o`) go through
`core.outputs.check_output_file` before anything is computed: a new path or a nerfgauge file
of the same kind; `--overwrite` also replaces a nerfgauge file of another kind.
"""

import dataclasses
from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic, write_json
from nerfgauge.core.outputs import check_output_file, claim_output_file, stamp
from nerfgauge.eval import lpips_commands
from nerfgauge.eval.calibrate import THRESHOLDS_KIND, calibrate, proposal_toml
from nerfgauge.eval.check import run_check as check
from nerfgauge.eval.evaluate import METRICS_KIND, EvaluateConfig, evaluate, format_means
from nerfgauge.eval.foreign_results import nerfbaselines_document, ns_eval_document
from nerfgauge.eval.geometry import format_geometry, score_geometry
from nerfgauge.eval.options import add_evaluate_arguments, evaluate_fields
from nerfgauge.eval.pose_scores import KIND as POSES_KIND, format_pose_scores, score_poses
from nerfgauge.nerf.runs import open_run_dataset


def register(subparsers) -> None:
    register_check(subparsers)
    register_evaluate(subparsers)
    register_geometry(subparsers)
    lpips_commands.register(subparsers)


FALSE_ALARM = arguments.bounded(float, 0, 1, above=True, below=True)  # a rate strictly between 0 and 1


def register_check(subparsers) -> None:
    parser = subparsers.add_parser(
        "check",
        help="compare a metrics.json against thresholds; exit 0 pass, 1 fail, 2 bad input, 4 fail under-trained",
        description="Compare a metrics.json (from `nerfgauge evaluate`) against per-scene min/max "
                    "bounds in a TOML file. Exit 0 when every check passes, 1 when any fails, "
                    "2 for malformed input, 4 when any fails and the run got under half the training steps "
                    "the thresholds' calibration recorded (under-trained: a slower machine, not a quality "
                    "verdict). With --calibrate RESULTS... --out FILE: propose thresholds from K >= 2 runs "
                    "for a stated false-alarm rate instead (eval/calibrate.py).",
    )
    parser.add_argument("metrics", type=arguments.path, metavar="METRICS.json", nargs="?",
                        help="metrics file written by `nerfgauge evaluate`")
    parser.add_argument("--thresholds", type=arguments.path, metavar="FILE",
                        help="TOML: [scene] tables of metric = { min = ..., max = ... }; [\"*\"] applies to all scenes "
                             "(required unless --calibrate)")
    parser.add_argument("--calibrate", type=arguments.path, nargs="+", metavar="RESULTS",
                        help="propose thresholds instead of checking: metrics.json files (or folders of them) of K >= 2 "
                             "runs with different seeds; writes --out (eval/calibrate.py)")
    parser.add_argument("--false-alarm", type=FALSE_ALARM, default=0.05, metavar="A",
                        help="--calibrate: the chance that a new good run fails each proposed bound (default 0.05)")
    parser.add_argument("--metrics", dest="calibrate_metrics", type=arguments.names, default=None,
                        metavar="LIST", help="--calibrate: only these metrics (default: every metric with a direction)")
    parser.add_argument("--out", type=arguments.path, metavar="FILE",
                        help="--calibrate: the proposed thresholds TOML (new, or one check --calibrate wrote)")
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
    if args.calibrate is not None:
        return run_calibrate(args)
    if args.metrics is None or args.thresholds is None:
        raise InputError("check needs METRICS.json and --thresholds FILE (or --calibrate RESULTS... --out FILE)")
    if args.out is not None or args.calibrate_metrics is not None:
        raise InputError("--out and --metrics go with --calibrate")
    return check(args.metrics, args.thresholds, junit_path=args.junit, scene=args.scene, overwrite=args.overwrite)


def run_calibrate(args) -> int:
    """check --calibrate: propose thresholds from measured runs into --out (eval.calibrate)."""
    if args.metrics is not None or args.thresholds is not None or args.junit is not None or args.scene is not None:
        raise InputError("--calibrate takes RESULTS... and --out FILE, not METRICS.json, --thresholds, --junit or "
                         "--scene")
    if args.out is None:
        raise InputError("--calibrate needs --out FILE (the proposed thresholds TOML)")
    check_output_file(args.out, THRESHOLDS_KIND, overwrite=args.overwrite)  # refused before anything is read
    if not args.out.parent.is_dir():
        raise InputError(f"cannot write {args.out}: directory {args.out.parent} does not exist")
    scenes = calibrate(args.calibrate, args.false_alarm, args.calibrate_metrics)
    text = proposal_toml(scenes, args.false_alarm)
    write_bytes_atomic(args.out, text.encode())
    for scene, data in scenes.items():
        bounds = ", ".join(f"{m} {b['kind']} {b['bound']:.4g}" for m, b in data["bounds"].items())
        print(f"{scene}: {len(data['runs'])} runs -> {bounds}")
    print(f"proposed thresholds (false-alarm rate {args.false_alarm:g} per bound) -> {args.out}")
    return 0


def register_evaluate(subparsers) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="score a folder of renders against a dataset split (PSNR, SSIM, depth, opacity)",
        description="Score predictions (a nerfgauge render folder or another method's renders named after the "
                    "dataset's frames) against a dataset split; write metrics.json and error maps. "
                    "Accepted file names: see eval/evaluate.py.",
    )
    parser.add_argument("dataset", type=arguments.path, metavar="DATASET", help="a complete nerfgauge dataset folder, or a NeRF-synthetic, nerfstudio or "
                             "COLMAP text-model folder nerfgauge did not write")
    parser.add_argument("--pred", type=arguments.path, metavar="DIR",
                        help="folder of predicted frames (required unless --poses is given)")
    parser.add_argument("--poses", type=arguments.path, metavar="POSES.json",
                        help="score a method's optimised train poses (transforms-style JSON, OpenGL camera-to-world, "
                             "by file_path) against the exact ones: rotation and translation error per camera and "
                             "ATE after a Sim(3) alignment, and the test cameras in the method's world "
                             "(eval/pose_scores.py)")
    parser.add_argument("--poses-out", type=arguments.path, metavar="FILE",
                        help="where --poses writes its document (default pose_errors.json beside POSES.json)")
    parser.add_argument("--out", type=arguments.path, metavar="FILE", help="metrics file (default DIR/metrics.json); "
                        "error maps go to error_maps/ beside it. FILE must be new or a metrics file nerfgauge "
                        "wrote (a rerun replaces it); never a user's file or a file in a dataset folder")
    add_evaluate_arguments(parser)  # the evaluate settings, defined once (eval.options; `run` takes the scoring ones)
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
    if args.pred is None and args.poses is None:
        raise InputError("the following arguments are required: --pred (or --poses POSES.json)")
    if args.poses is not None:
        poses_out = args.poses_out or Path(args.poses).parent / "pose_errors.json"
        check_output_file(poses_out, POSES_KIND, overwrite=args.overwrite)
        pose_document = score_poses(args.dataset, args.poses)  # before --pred's work: bad poses write nothing
        write_json(poses_out, stamp(pose_document, POSES_KIND))
        print(f"{format_pose_scores(pose_document)} -> {poses_out}")
        if args.pred is None:
            return 0
    return score_renders(args.dataset, args.pred, EvaluateConfig(**evaluate_fields(args)), args.out,
                         {"ns-eval": args.ns_eval, "nerfbaselines": args.nerfbaselines}, overwrite=args.overwrite,
                         method_name=args.method_name)


def score_renders(dataset, pred: Path, config: EvaluateConfig, out, extra: dict, *, overwrite: bool,
                  method_name: str | None = None) -> int:
    """Score `pred` against `dataset` as `config` says into `out` (default PRED/metrics.json),
    print the table, and write the `extra` documents ({"ns-eval" | "nerfbaselines": FILE or
    None}) naming the method `method_name` (default: PRED's name). Every output is checked
    (core.outputs) before anything is computed."""
    out = out if out is not None else pred / "metrics.json"
    check_output_file(out, METRICS_KIND, overwrite=overwrite)  # refused before anything is computed or written
    for name, target in extra.items():
        if target is not None:
            check_output_file(target, OUTPUT_KINDS[name], overwrite=overwrite)
    document = evaluate(dataset, pred, out=out, **dataclasses.asdict(config))
    print(f"scene {document['scene']}, split {document['split']}, {len(document['frames'])} frames, "
          f"protocol {document['protocol']} (colour on {document['protocol_background']}, "
          f"LPIPS-{document['lpips_net']}), "
          f"background {document['background']}, depth {document['depth_kind']} -> {out}")
    print(format_means(document))
    if any(path is not None for path in extra.values()):
        method = method_name or Path(pred).resolve().name
        model = Path(pred).resolve().parent / "model.pt"  # RUN/renders of `nerfgauge render`
        checkpoint = str(model) if model.is_file() else str(pred)
        if extra["ns-eval"] is not None:
            write_json(extra["ns-eval"], stamp(ns_eval_document(document, experiment_name=document["scene"],
                                                                method_name=method, checkpoint=checkpoint),
                                               OUTPUT_KINDS["ns-eval"]))
            print(f"ns-eval results -> {extra['ns-eval']}")
        if extra["nerfbaselines"] is not None:
            write_json(extra["nerfbaselines"], stamp(nerfbaselines_document(document, dataset_root=dataset,
                                                                            pred_dir=pred, method_name=method),
                                                     OUTPUT_KINDS["nerfbaselines"]))
            print(f"NerfBaselines results -> {extra['nerfbaselines']}")
    return 0


# --- geometry ----------------------------------------------------------------------------


def register_geometry(subparsers) -> None:
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
    geometry.add_argument("--tau", type=arguments.DISTANCE, action="append", default=[], metavar="T",
                          help="also score F-score at this distance in world units (repeatable); 0.5%% and 1%% of the "
                               "ground truth's bounding-box diagonal always")
    geometry.add_argument("--samples", type=arguments.SAMPLES, default=1_000_000,
                          help="points sampled on each surface (default 1000000)")
    geometry.add_argument("--seed", type=arguments.SEED, default=0, help="sampling seed (default 0)")
    geometry.add_argument("--whole-surface", action="store_true",
                          help="score all ground truth, not only what the reference cameras see")
    geometry.add_argument("--split", default="test", help="views of --pred-depth and of --run's normals (default test)")
    geometry.add_argument("--run", type=arguments.path, metavar="RUN_DIR",
                          help="also score this run's field normals on the --split views (DATASET must be the "
                               "dataset the run was trained on: its manifest.json hash is checked)")
    geometry.set_defaults(func=run_geometry)




def run_geometry(args) -> int:
    out = Path(args.out)
    recipe = {"geometry": str(args.dataset), "mesh": str(args.pred_mesh), "depth": str(args.pred_depth)}
    run = None
    if args.run is not None:  # the run and its dataset checked before any work (nerf.runs)
        from nerfgauge.nerf.checkpoint import load_model  # torch: kept off `nerfgauge --help`'s import path

        model, config = load_model(Path(args.run) / "model.pt")
        run = model, open_run_dataset(args.run, config, args.dataset)
    whole_surface, surface_note = args.whole_surface, None
    if not whole_surface:  # a foreign ground-truth folder has no depth to test visibility against
        probe = Dataset(args.dataset)
        if not probe.has("depth"):
            whole_surface = True
            surface_note = (f"unavailable: the surface the cameras see needs ground-truth depth "
                            f"({probe.unavailable_reason('depth')}); the whole surface is scored")
    with claim_output_file(out, recipe, "geometry", args.overwrite):
        document, _ = score_geometry(args.dataset, args.pred_mesh, args.pred_depth, split=args.split,
                                     taus=tuple(args.tau), samples=args.samples, seed=args.seed,
                                     whole_surface=whole_surface)
        if surface_note is not None:
            document.setdefault("notes", {})["visible_surface"] = surface_note
        if run is not None:
            from nerfgauge.eval.normals import score_normals  # torch: kept off `nerfgauge --help`'s import path

            document["normals"] = score_normals(*run, args.split)
        write_json(out, document)
    print(format_geometry(document))
    if surface_note is not None:
        print(f"visible surface {surface_note}")
    print(f"-> {out}")
    return 0
