"""`nerfgauge generate`: argument parsing only; the work is in generate.pipeline."""

from __future__ import annotations

import re

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError


def parse_resolution(text: str) -> tuple[int, int]:
    """"128" -> (128, 128); "160x120" -> (160, 120) as (width, height)."""
    match = re.fullmatch(r"\s*(-?\d{1,12})\s*(?:[xX]\s*(-?\d{1,12})\s*)?", text)  # 12 digits: int() never balks
    if not match:
        raise InputError(f"--res must be N or WxH (e.g. 128 or 160x120), got {text!r}")
    width = int(match.group(1))
    height = int(match.group(2)) if match.group(2) is not None else width
    if width <= 0 or height <= 0:
        raise InputError(f"--res must be positive, got {text!r}")
    if max(width, height) > arguments.IMAGE_SIDE.high:
        raise InputError(f"--res sides must be {arguments.IMAGE_SIDE.text} pixels, got {text!r}")
    return width, height


def register(subparsers) -> None:
    from nerfgauge.generate import options

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
    from nerfgauge.generate import options
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    config = GenerateConfig(scene=args.scene, **options.generate_fields(args))
    result = generate(config, args.out, workers=args.workers, overwrite=args.overwrite, progress=not args.quiet,
                      scheduler=args.scheduler)
    rendered = result["views_rendered"]
    print(f"{args.out}: {rendered} views rendered in {result['seconds']:.1f} s "
          f"({result['variant']}; Mitsuba render {result['render_seconds']:.1f} s)"
          if rendered else f"{args.out}: complete, nothing to render")
    return 0
