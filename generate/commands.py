"""`nerfgauge generate`: argument parsing only; the work is in generate.pipeline."""

from __future__ import annotations

from nerfgauge.core import arguments
from nerfgauge.generate import options
from nerfgauge.generate.export import export_command
from nerfgauge.generate.pipeline import GenerateConfig, generate


def register(subparsers) -> None:
    parser = subparsers.add_parser("generate", help="render a scene into a NeRF dataset",
                                   description="Render posed views of a procedural scene with Mitsuba 3, with "
                                               "exact depth, normals and masks, into a NeRF-synthetic + nerfstudio dataset.")
    parser.add_argument("scene", help="scene name (see `nerfgauge scenes`), mesh:PATH or a scene file (.toml/.json)")
    parser.add_argument("--out", required=True, type=arguments.path, help="dataset folder (created; resumed if it holds the same recipe)")
    options.add_generate_arguments(parser)
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="render on a dask.distributed cluster: tcp://HOST:PORT of a running scheduler, or "
                             "local:N to start N local worker processes (needs the dask extra)")
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset nerfgauge made in --out from another recipe or other inputs "
                             "(never a folder nerfgauge did not make)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_points_argument(parser)
    parser.set_defaults(func=run)
    register_export(subparsers)


def add_points_argument(parser) -> None:
    parser.add_argument("--points", default="surface", metavar="KIND[:COUNT]",
                        help="initial points of the COLMAP model (sparse/0) and of transforms.json's ply_file_path: "
                             "surface (default: 100000 mesh samples some train view sees, or one per 16 train "
                             "pixels if fewer), random (as many, in the scene bounds), sfm (features triangulated with the exact poses; needs pycolmap) or none")


def register_export(subparsers) -> None:
    parser = subparsers.add_parser("export", help="add an export to an existing dataset (colmap)",
                                   description="Write a dataset's COLMAP sparse model (sparse/0, binary and text), "
                                               "images/ and initial points into it, and update its manifest.")
    parser.add_argument("format", choices=("colmap",), help="colmap: sparse/0 + images/ + points (docs/conventions.md)")
    parser.add_argument("dataset", type=arguments.path, help="a dataset folder nerfgauge generated")
    add_points_argument(parser)
    parser.set_defaults(func=run_export)


def run_export(args) -> int:
    result = export_command(args.dataset, args.points)
    points = result["without_points"] or f"with {result['points']} {result['kind']} points"
    print(f"{args.dataset}: COLMAP model in sparse/0 {points} ({result['seconds']:.1f} s)")
    return 0


def run(args) -> int:
    config = GenerateConfig(scene=args.scene, **options.generate_fields(args))
    result = generate(config, args.out, workers=args.workers, overwrite=args.overwrite, progress=not args.quiet,
                      scheduler=args.scheduler, points=args.points)
    rendered, export = result["views_rendered"], result.get("export")
    points = export and (export.get("without_points") or f"with {export['points']} {export['kind']} points")
    exported = f"; COLMAP model {points} in {export['seconds']:.1f} s" if export else ""
    print(f"{args.out}: {rendered} views rendered in {result['seconds']:.1f} s "
          f"({result['variant']}; Mitsuba render {result['render_seconds']:.1f} s{exported})"
          if rendered else f"{args.out}: complete, nothing to render{exported}")
    return 0
