"""`nerfgauge` subcommands of the nerf stage (train, render, toy-pe, mesh): one `_add_<name>` and
one `_run_<name>` per subcommand.

Add a subcommand by writing its pair and listing `_add_<name>` in `register`. torch is
imported inside the run functions so `nerfgauge --help` stays instant.
"""

from __future__ import annotations

from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.core.arguments import path
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic
from nerfgauge.core.outputs import check_output_file, claim_output_file
from nerfgauge.nerf.config import CHANGE_STEP, DEFAULT_BUDGET_SECONDS, MODELS, SUB_RAYS, TrainConfig
from nerfgauge.nerf.mesh import mesh_from_run, ply_bytes
from nerfgauge.nerf.options import add_train_arguments, train_fields
import nerfgauge.splat.commands as splat_commands  # --model splat's flags and runs (no torch)


def register(subparsers) -> None:
    for add in (_add_train, _add_render, _add_toy_pe, _add_mesh):
        add(subparsers)


# --------------------------------------------------------------------------------------
# toy-pe


TOY_STEPS = arguments.bounded(int, 1, 1_000_000)  # full-batch steps on a 64x64 image: 10^6 is hours
# Marching-cubes cells along the longest side: 2048^3 float32 densities are already 32 GiB.
MESH_RESOLUTION = arguments.bounded(int, 8, 2048)
DENSITY = arguments.bounded(float, 0, 1e6, above=True)  # sigma per scene unit; 1e6 is opaque within 1e-5


def _add_toy_pe(subparsers) -> None:
    parser = subparsers.add_parser(
        "toy-pe",
        help="the lecture's 2D experiment: memorise an image with an MLP, with and without positional encoding",
        description="Fit an MLP (x, y) -> rgb to a procedural high-frequency image, once on raw coordinates and "
                    "once on their positional encoding; print both PSNRs and the gap, and with --out write "
                    "toy_pe.png (target | no PE | PE) and toy_pe.json.",
    )
    parser.add_argument("--out", type=path, default=None, metavar="DIR",
                        help="directory for toy_pe.png and toy_pe.json (each new, or written by an earlier toy-pe: "
                             "a rerun replaces them; never a user's files, never inside a dataset folder)")
    parser.add_argument("--steps", type=TOY_STEPS, default=None, metavar="N", help="Adam steps per fit (default 200)")
    parser.add_argument("--seed", type=arguments.SEED, default=0, help="seed of the image and the initial weights (default 0)")
    parser.set_defaults(func=_run_toy_pe)


def _run_toy_pe(args) -> int:
    if args.steps is not None and args.steps < 1:
        raise InputError(f"--steps must be a positive integer, got {args.steps}")
    if args.seed < 0:
        raise InputError(f"--seed must be a non-negative integer, got {args.seed}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise InputError(f"--out must be a directory, but {args.out} is a file")

    from nerfgauge.nerf.toy_pe import TOY_PE_KIND, ToyPEConfig, run_toy_pe  # torch: kept off `nerfgauge --help`'s import path

    if args.out is not None:  # before the fits: both files new or our own (core.outputs)
        for name in ("toy_pe.png", "toy_pe.json"):
            check_output_file(args.out / name, TOY_PE_KIND, flag=None)

    overrides = {"seed": args.seed} | ({} if args.steps is None else {"steps": args.steps})
    config = ToyPEConfig(**overrides)
    out_path = None if args.out is None else args.out / "toy_pe.png"
    result = run_toy_pe(config, out_path)
    print(f"PSNR without positional encoding: {result.psnr_no_pe:6.2f} dB")
    print(f"PSNR with positional encoding:    {result.psnr_pe:6.2f} dB (L = {config.n_frequencies})")
    print(f"gap:                              {result.gap:+6.2f} dB  ({config.size}x{config.size} image, "
          f"{config.steps} steps, seed {config.seed})")
    if out_path is not None:
        print(f"wrote {out_path} and {out_path.with_suffix('.json')}")
    return 0


# --------------------------------------------------------------------------------------
# train


def _add_train(subparsers) -> None:
    parser = subparsers.add_parser(
        "train", help="train a radiance field on a dataset",
        description="Train `compact` (voxel grid, empty-space skipping, only what scene.json says the scene "
                    "needs) or `vanilla` (the lecture's NeRF) for a time budget or a number of steps. Writes "
                    "RUN/config.json, RUN/log.jsonl (val PSNR against training seconds), RUN/checkpoint.pt and "
                    "RUN/model.pt. Rerunning the same command in RUN starts over only when the earlier attempt "
                    "was stopped before its first checkpoint; otherwise pass --resume or --overwrite.")
    parser.add_argument("dataset", type=path, help="a complete dataset folder (with manifest.json)")
    parser.add_argument("--out", type=path, required=True, metavar="RUN", help="run folder")
    # every training option, defined once (nerf.options; `run` adds them too); --model also splat
    add_train_arguments(parser, models=(*MODELS, splat_commands.MODEL))
    again = parser.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue RUN from its checkpoint (with --steps N: bit-identical to an uninterrupted "
                            "N-step run at the same --threads)")
    again.add_argument("--overwrite", action="store_true", help="replace the run in RUN (only a nerfgauge run folder)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    splat_commands.add_train_arguments(parser)
    parser.set_defaults(func=_run_train)


def _run_train(args) -> int:
    if args.model == splat_commands.MODEL:
        return splat_commands.run_train(args, DEFAULT_BUDGET_SECONDS)
    splat_commands.refuse_splat_flags(args)
    from nerfgauge.nerf.train import train  # torch: kept off `nerfgauge --help`'s import path

    config = TrainConfig(dataset=str(args.dataset), **train_fields(args))
    summary = train(config, args.out, resume=args.resume, overwrite=args.overwrite, progress=not args.quiet)
    # the log's val PSNR goes through pixel centres; an `edges` run renders edge pixels through
    # several rays, several dB higher on sharp outlines, so its summary shows both
    through_render = (f" ({summary['render_val_psnr']:.2f} dB through its render, {summary['render_filter']})"
                      if summary.get("render_val_psnr") is not None else "")
    print(f"{args.out}: {summary['steps']} steps in {summary['seconds']:.1f} s, val PSNR {summary['val_psnr']:.2f} dB"
          f"{through_render}, model {summary['model_bytes'] / 1e6:.2f} MB"
          + (f", grid {summary['resolution']}" if summary.get("resolution") else ""))
    return 0


# --------------------------------------------------------------------------------------
# render


def _add_render(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="render a trained run's views (PNG, depth EXR, timing)",
        description="Render every view of a split with RUN/model.pt, named after the dataset's frames: "
                    "<frame>.png (RGBA, alpha = opacity), <frame>_depth.exr (ray distance) and timing.json "
                    "(milliseconds per frame). DIR is a nerfgauge renders folder: one made from another "
                    "model or step ratio is replaced only with --overwrite. The dataset must be the one the run "
                    "was trained on: its manifest.json hash is compared with the one the run recorded, and a "
                    "dataset regenerated or edited since training is refused (exit 2).")
    parser.add_argument("run", type=path, metavar="RUN", help="a run folder made by nerfgauge train (or a "
                        "splatting PLY in the 3DGS layout, with --dataset)")
    parser.add_argument("--split", choices=("train", "val", "test"), default="test")
    parser.add_argument("--out", type=path, default=None, metavar="DIR", help="output folder (default RUN/renders)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace DIR when it holds renders of another model (only a nerfgauge renders folder)")
    parser.add_argument("--threads", type=arguments.THREADS, default=None, help="CPU threads (default: the run's)")
    parser.add_argument("--step-ratio", type=arguments.STEP_RATIO, default=None, metavar="VOXELS",
                        help="compact model's marching step in voxels (default: the step the run trained with; "
                             "1 renders faster and softer)")
    parser.add_argument("--aperture-samples", type=arguments.LENS_SAMPLES, default=16, metavar="N",
                        help="lens samples per pixel for frames rendered through a thin lens (their transforms "
                             "entry has \"lens\"): stratified on the lens disc, seeded (default 16)")
    parser.add_argument("--pixel-samples", type=arguments.PIXEL_SAMPLES, default=None, metavar="N",
                        help="rays per pixel along each axis, averaged as the ground truth's box filter averages "
                             "the pixel (default: 2 for a run trained with --pixel-filter box or edges, on an edges run's edge "
                             "pixels only; 1 for centre)")
    parser.add_argument("--sub-rays", choices=SUB_RAYS, default=SUB_RAYS[0],
                        help="an edges run's points with rays of their own: changes (default), the points between "
                             "pixel centres of the centre render that differ, the rest interpolated; edge-pixels, "
                             "every point of the centre render's edge pixels (slower; the render before issue 52)")
    parser.add_argument("--change-step", type=arguments.CHANGE_STEP, default=None, metavar="S",
                        help=f"with --sub-rays changes: centres that differ by more than S in colour or alpha give "
                             f"the points between them rays (default: the step the run chose on its val views, "
                             f"render_change_step in its config.json, else {CHANGE_STEP}); smaller is slower and, "
                             f"on a converged model, truer")
    parser.add_argument("--lens-seed", type=arguments.SEED, default=0, help="seed of the lens samples (default 0)")
    parser.add_argument("--dataset", type=path, default=None, metavar="DATASET",
                        help="render the views of this dataset instead of those of the dataset the run was "
                             "trained on: it must hold the manifest.json the run recorded (the same dataset, "
                             "e.g. moved), unless --other-dataset")
    parser.add_argument("--other-dataset", action="store_true",
                        help="with --dataset: accept another dataset of the same scene (e.g. the test cameras "
                             "through a lens); the run's own dataset must still match its record, and DATASET "
                             "must show its scene (scene.json recipe, seed and bounds)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    splat_commands.note_render_parser(parser)
    parser.set_defaults(func=_run_render)


def _run_render(args) -> int:
    if splat_commands.is_splat_source(args.run):
        return splat_commands.run_render(args)
    from nerfgauge.nerf.render_views import render_split  # torch: kept off `nerfgauge --help`'s import path

    timing = render_split(args.run, args.split, args.out, threads=args.threads, step_ratio=args.step_ratio,
                          overwrite=args.overwrite, progress=not args.quiet, aperture_samples=args.aperture_samples,
                          lens_seed=args.lens_seed, dataset=args.dataset, other_dataset=args.other_dataset,
                          pixel_samples=args.pixel_samples, sub_rays=args.sub_rays, change_step=args.change_step)
    if timing.get("lens_frames"):
        print(f"{timing['lens_frames']} frames through their thin lens at {timing['aperture_samples']} lens samples: "
              f"{timing['ms_per_lens_frame']:.1f} ms per frame")
    rays = (f"up to {timing['pixel_samples'] ** 2} rays per pixel where the centre render changes "
            f"(by more than {timing['change_step']})"
            if timing.get("sub_rays") == "changes" else f"{timing['pixel_samples'] ** 2} rays per pixel")
    print(f"rendered {timing['frames']} frames at {timing['ms_per_frame']:.1f} ms per frame, {rays} "
          f"({timing['device']}, {timing['threads']} threads) -> {args.out or args.run / 'renders'}")
    return 0


# --------------------------------------------------------------------------------------
# mesh


def _add_mesh(subparsers) -> None:
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
    mesh.add_argument("--resolution", type=MESH_RESOLUTION, default=256,
                      help="grid cells along the scene's longest side (default 256)")
    mesh.add_argument("--no-cull", action="store_true", help="keep triangles no training camera sees")
    mesh.add_argument("--level", type=DENSITY, metavar="SIGMA",
                      help="density of the surface (default: the median density where the model renders its "
                           "surface on training rays)")
    mesh.add_argument("--overwrite", action="store_true",
                      help="let -o replace a nerfgauge file of another kind (never a file nerfgauge did not write)")
    mesh.set_defaults(func=_run_mesh)


def _run_mesh(args) -> int:
    out = Path(args.out)
    if out.suffix.lower() != ".ply":
        raise InputError(f"-o {out}: the mesh is written as PLY; name it *.ply")
    with claim_output_file(out, {"mesh": str(args.run), "resolution": args.resolution}, "mesh", args.overwrite):
        mesh = mesh_from_run(args.run, args.resolution, cull=not args.no_cull, level=args.level)
        write_bytes_atomic(out, ply_bytes(mesh.vertices, mesh.faces))
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces ({mesh.faces_culled} unseen dropped), "
          f"level sigma = {mesh.level:.4g} ({mesh.level_source}), {args.resolution} cells, "
          f"{mesh.seconds:.1f} s")
    return 0
