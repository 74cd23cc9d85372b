"""`nerfgauge generate`: argument parsing only; the work is in generate.pipeline."""

from __future__ import annotations

from nerfgauge.core import arguments
from nerfgauge.generate import options
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
    parser.set_defaults(func=run)


def run(args) -> int:
    config = GenerateConfig(scene=args.scene, **options.generate_fields(args))
    result = generate(config, args.out, workers=args.workers, overwrite=args.overwrite, progress=not args.quiet,
                      scheduler=args.scheduler)
    rendered = result["views_rendered"]
    print(f"{args.out}: {rendered} views rendered in {result['seconds']:.1f} s "
          f"({result['variant']}; Mitsuba render {result['render_seconds']:.1f} s)"
          if rendered else f"{args.out}: complete, nothing to render")
    return 0
