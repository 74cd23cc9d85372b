"""`nerfgauge generate`: argument parsing only; the work is in generate.pipeline."""

from __future__ import annotations

import math
import re

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError


def parse_resolution(text: str) -> tuple[int, int]:
    """"128" -> (128, 128); "160x120" -> (160, 120) as (width, height)."""
    match = re.fullmatch(r"\s*(-?\d+)\s*(?:[xX]\s*(-?\d+)\s*)?", text)
    if not match:
        raise InputError(f"--res must be N or WxH (e.g. 128 or 160x120), got {text!r}")
    width = int(match.group(1))
    height = int(match.group(2)) if match.group(2) is not None else width
    if width <= 0 or height <= 0:
        raise InputError(f"--res must be positive, got {text!r}")
    return width, height


def parse_band(text: str) -> tuple[float, float]:
    """"10,75" -> (10.0, 75.0): two finite numbers (float() alone would take "nan")."""
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"--elevation must be MIN,MAX in degrees (e.g. 10,75), got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"--elevation must be two finite numbers of degrees, got {text!r}")
    return lo, hi


def register(subparsers) -> None:
    from nerfgauge.generate.layouts import LAYOUTS
    from nerfgauge.generate.variant import CHOICES

    parser = subparsers.add_parser("generate", help="render a scene into a NeRF dataset",
                                   description="Render posed views of a procedural scene with Mitsuba 3, with "
                                               "exact depth, normals and masks, into a NeRF-synthetic + nerfstudio dataset.")
    parser.add_argument("scene", help="scene name (see `nerfgauge scenes`), mesh:PATH or a scene file (.toml/.json)")
    parser.add_argument("--out", required=True, type=arguments.path, help="dataset folder (created; resumed if it holds the same recipe)")
    parser.add_argument("--views", type=arguments.positive_int, default=100, help="training views (default 100)")
    parser.add_argument("--val-views", type=arguments.nonnegative_int, default=10)
    parser.add_argument("--test-views", type=arguments.nonnegative_int, default=20)
    parser.add_argument("--res", default="128", help="N or WxH (default 128)")
    parser.add_argument("--spp", type=arguments.positive_int, default=64, help="samples per pixel (default 64)")
    parser.add_argument("--max-depth", type=arguments.positive_int, default=8, help="path tracer's maximum depth (default 8)")
    parser.add_argument("--fov", type=arguments.finite_float, default=40.0, help="horizontal field of view, degrees (default 40)")
    parser.add_argument("--seed", type=arguments.nonnegative_int, default=0)
    parser.add_argument("--layout", choices=("auto",) + LAYOUTS, default="auto",
                        help="camera layout (default auto: the scene's suggestion, else hemisphere)")
    parser.add_argument("--sampling", choices=("fibonacci", "random"), default="fibonacci",
                        help="camera directions on the (hemi)sphere: even or seeded random")
    parser.add_argument("--elevation", default=None,
                        help="MIN,MAX camera elevation in degrees (default: the scene's suggestion, else 10,75)")
    parser.add_argument("--radius", type=arguments.positive_float, default=None, help="camera distance from the AABB centre (default: fit)")
    parser.add_argument("--variant", choices=CHOICES, default="auto")
    parser.add_argument("--units", choices=("normalise", "keep"), default="normalise",
                        help="user assets: normalise into [-1, 1]^3 (default; the transform is in scene.json) or "
                             "keep the files' coordinates, so depth and meshes/ are in the asset's units")
    parser.add_argument("--envmap", type=arguments.path, default=None, metavar="FILE",
                        help="light the scene with an equirectangular .exr/.hdr instead of its own lights")
    parser.add_argument("--envmap-rotation", type=arguments.finite_float, default=0.0, metavar="DEG",
                        help="turn the --envmap about +Z by DEG degrees (default 0)")
    parser.add_argument("--workers", type=arguments.positive_int, default=1, help="worker processes (default 1)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="render on a dask.distributed cluster: tcp://HOST:PORT of a running scheduler, or "
                             "local:N to start N local worker processes (needs the dask extra)")
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset nerfgauge made in --out from another recipe or other inputs "
                             "(never a folder nerfgauge did not make)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args) -> int:
    from nerfgauge.generate.pipeline import GenerateConfig, generate

    width, height = parse_resolution(args.res)
    config = GenerateConfig(scene=args.scene, seed=args.seed, views=args.views, val_views=args.val_views,
                            test_views=args.test_views, width=width, height=height, spp=args.spp,
                            max_depth=args.max_depth, fov=args.fov, layout=args.layout, sampling=args.sampling,
                            elevation=args.elevation and parse_band(args.elevation), radius=args.radius, variant=args.variant,
                            units=args.units, envmap=args.envmap and str(args.envmap),
                            envmap_rotation=args.envmap_rotation)
    result = generate(config, args.out, workers=args.workers, overwrite=args.overwrite, progress=not args.quiet,
                      scheduler=args.scheduler)
    rendered = result["views_rendered"]
    print(f"{args.out}: {rendered} views rendered in {result['seconds']:.1f} s "
          f"({result['variant']}; Mitsuba render {result['render_seconds']:.1f} s)"
          if rendered else f"{args.out}: complete, nothing to render")
    return 0
