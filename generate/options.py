"""The generator's command-line options, defined once: `nerfgauge generate` and
`nerfgauge run` both add them (`add_generate_arguments`) and read them back as
GenerateConfig fields (`generate_fields`).

Everything but the scene, the output folder and the commands' own switches (--out,
--overwrite, --quiet) is here. Range options take negative values as written
(`--elevation -15,25`).
"""

from __future__ import annotations

import argparse
import re

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.generate import degrade, motion
from nerfgauge.generate.holdout import SCALE, parse_scales
from nerfgauge.generate.layouts import LAYOUTS
from nerfgauge.generate.pipeline import MAX_NOISE_PSNR, NOISE_PSNR, GenerateConfig
from nerfgauge.generate.variant import CHOICES

# Options of the dataset itself (GenerateConfig fields), not of how it is rendered.
CONFIG_OPTIONS = ("views", "val_views", "test_views", "spp", "max_depth", "fov", "seed", "layout", "sampling",
                  "elevation", "radius", "variant", "noise_psnr", "max_spp", "aperture", "focus_distance", "lens_splits",
                  "units", "envmap", "envmap_rotation", "distortion", "motion_blur", "holdout", "test_scales",
                  "transients", "transient_fraction") + degrade.FIELDS


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


def _scales(text: str) -> tuple:
    """--test-scales's argparse type: generate.holdout.parse_scales, its message kept."""
    try:
        return parse_scales(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


_scales.range = SCALE  # each scale's range, shown in --help


def _motion_blur(text: str) -> str:
    """--motion-blur's argparse type: the spec checked (generate.motion.MotionBlur: travel and
    rotation within their ranges, the shutter inside the frame) and kept as written."""
    try:
        motion.parse_motion_blur(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--motion-blur").lstrip(": ")) from None
    return text


_motion_blur.range = motion.TRAVEL  # shown in --help; the fuzz of numeric flags draws travels outside it


def add_generate_arguments(parser: argparse.ArgumentParser, defaults=None, *,
                           need_test_views: bool = False) -> argparse.ArgumentParser:
    """Add the generator's options to `parser`. defaults: a GenerateConfig whose values
    are the defaults (a command may default to fewer views), else GenerateConfig().
    need_test_views: --test-views must be positive (a command that evaluates on them)."""
    d = GenerateConfig() if defaults is None else defaults
    arguments.allow_negative_values(parser)
    parser.add_argument("--views", type=arguments.VIEWS, default=d.views, help=f"training views (default {d.views})")
    parser.add_argument("--val-views", type=arguments.SPLIT_VIEWS, default=d.val_views)
    parser.add_argument("--test-views", type=arguments.VIEWS if need_test_views else arguments.SPLIT_VIEWS,
                        default=d.test_views)
    parser.add_argument("--res", default=str(d.width) if d.width == d.height else f"{d.width}x{d.height}",
                        help=f"N or WxH, sides {arguments.IMAGE_SIDE.text} (default {d.width if d.width == d.height else f'{d.width}x{d.height}'})")
    parser.add_argument("--spp", type=arguments.spp, default=d.spp,
                        help=f"samples per pixel, rendered as two half passes whose difference estimates the noise "
                             f"(default {d.spp}); or auto with --noise-psnr")
    parser.add_argument("--noise-psnr", type=NOISE_PSNR, default=d.noise_psnr,
                        help=f"with --spp auto: add samples per view until its sRGB noise PSNR reaches this many dB "
                             f"(at most {MAX_NOISE_PSNR:g})")
    parser.add_argument("--max-spp", type=arguments.SPP, default=d.max_spp,
                        help=f"with --spp auto: at most this many samples per view (default {d.max_spp})")
    parser.add_argument("--max-depth", type=arguments.MAX_PATH_DEPTH, default=d.max_depth,
                        help=f"path tracer's maximum depth (default {d.max_depth})")
    parser.add_argument("--fov", type=arguments.FOV_DEGREES, default=d.fov,
                        help=f"horizontal field of view, degrees (default {d.fov:g})")
    parser.add_argument("--seed", type=arguments.SEED, default=d.seed)
    parser.add_argument("--layout", choices=("auto",) + LAYOUTS, default=d.layout,
                        help="camera layout (default auto: the scene's suggestion, else hemisphere)")
    parser.add_argument("--sampling", choices=("fibonacci", "random"), default=d.sampling,
                        help="camera directions on the (hemi)sphere: even or seeded random")
    parser.add_argument("--elevation", type=arguments.number_pair("--elevation", "10,75 or -15,25", arguments.ELEVATION_DEGREES),
                        default=d.elevation,
                        help="MIN,MAX camera elevation in degrees, negative below the horizon (default: the scene's "
                             "suggestion, else 10,75; inside: -20,20)")
    parser.add_argument("--radius", type=arguments.DISTANCE, default=d.radius,
                        help="camera distance from the AABB centre (default: fit)")
    parser.add_argument("--variant", choices=CHOICES, default=d.variant)
    parser.add_argument("--aperture", type=arguments.APERTURE, default=d.aperture, metavar="RADIUS",
                        help="thin-lens aperture radius in scene units (default 0: pinhole); needs --focus-distance")
    parser.add_argument("--focus-distance", type=arguments.DISTANCE, default=d.focus_distance, metavar="D",
                        help="distance of the plane in focus along the optical axis, scene units")
    parser.add_argument("--units", choices=("normalise", "keep"), default=d.units,
                        help="user assets: normalise into [-1, 1]^3 (default; the transform is in scene.json) or "
                             "keep the files' coordinates, so depth and meshes/ are in the asset's units")
    parser.add_argument("--envmap", type=arguments.path, default=d.envmap, metavar="FILE",
                        help="light the scene with an equirectangular .exr/.hdr instead of its own lights")
    parser.add_argument("--envmap-rotation", type=arguments.ROTATION_DEGREES, default=d.envmap_rotation, metavar="DEG",
                        help="turn the --envmap about +Z by DEG degrees (default 0)")
    parser.add_argument("--lens-splits", choices=("test", "all"), default=d.lens_splits,
                        help="views rendered through the lens: test (default) or all splits; depth, normals and "
                             "masks stay those of the pinhole pixel-centre rays")
    add_degradation_arguments(parser, d)
    parser.add_argument("--distortion", default=d.distortion, metavar="MODEL:COEFFS",
                        help="lens distortion of the train views, rendered exactly (each sample's ray through the "
                             "distorted pixel grid): opencv:K1,K2,P1,P2[,K3] (OpenCV radial-tangential) or "
                             "fisheye:K1,K2,K3,K4 (OpenCV fisheye); depth, normals and masks follow the same rays; "
                             "val and test views stay pinhole")
    parser.add_argument("--motion-blur", type=_motion_blur, default=d.motion_blur, metavar="SPEC",
                        help=f"train views taken by a moving camera: TRAVEL (the path over the frame as a fraction of "
                             f"the scene's diagonal, {motion.TRAVEL.text}) or travel=T,rotation=DEG,exposure=E,readout=R "
                             f"(rotation in degrees, {motion.ROTATION_DEGREES.text}; exposure and rolling-shutter "
                             f"readout as fractions of the frame); the colour integrates the exposure over at most "
                             f"{motion.MAX_SUBFRAMES} sub-frames of {motion.MAX_SUBFRAME_MOTION_PX:g} px of image motion "
                             f"each (more is refused), the transform and depth are the sharp mid-frame pose's")
    parser.add_argument("--holdout", default=d.holdout, metavar="AXIS:MIN:MAX",
                        help="hold out a sector of camera directions, azimuth:A:B or elevation:A:B degrees: train and "
                             "val views outside it; test views half inside (extrapolation), half outside "
                             "(interpolation); hemisphere and sphere layouts (docs/conventions.md)")
    parser.add_argument("--test-scales", type=_scales, default=d.test_scales, metavar="S,S,...",
                        help="add --test-views test views per scale s != 1 at distance radius/s (s=2: twice as close, "
                             "Mip-Splatting-style zoom), e.g. 0.5,1,2")
    parser.add_argument("--transients", type=arguments.bounded(int, 0, 64), default=d.transients, metavar="N",
                        help="add N small objects (spheres, cubes) to some training views only, with their masks "
                             "(train/r_XXX_transient.png); val and test views never show them")
    parser.add_argument("--transient-fraction", type=arguments.bounded(float, 0, 1, above=True),
                        default=d.transient_fraction, metavar="F",
                        help=f"share of the training views each transient is in (default {d.transient_fraction:g})")
    parser.add_argument("--workers", type=arguments.WORKERS, default=1, help="worker processes (default 1)")
    return parser


def add_degradation_arguments(parser: argparse.ArgumentParser, d: GenerateConfig) -> None:
    """The train-view degradations (generate.degrade; docs/conventions.md "Degradations")."""
    group = parser.add_argument_group("degraded training views (train split only; val/test, depth, normals, "
                                      "masks and meshes stay exact)")
    group.add_argument("--pose-noise-rotation", type=degrade.ROTATION_NOISE_DEGREES, default=d.pose_noise_rotation,
                       metavar="DEG", help="RMS rotation angle of the noise on the train poses the transforms hold "
                                           "(axis uniform; the images are rendered from the exact poses)")
    group.add_argument("--pose-noise-translation", type=degrade.TRANSLATION_NOISE_FRACTION,
                       default=d.pose_noise_translation, metavar="FRAC",
                       help="RMS offset of the train camera centres, as a fraction of their RMS distance from "
                            "their mean")
    group.add_argument("--exposure-ev", type=degrade.EXPOSURE_SIGMA_EV, default=d.exposure_ev, metavar="SIGMA",
                       help="std of each train view's exposure in EV (gain 2^EV on the linear render)")
    group.add_argument("--white-balance", type=degrade.WHITE_BALANCE_SIGMA, default=d.white_balance,
                       metavar="SIGMA", help="std of each train view's log2 red and blue gains (green 1)")
    group.add_argument("--vignetting", type=degrade.VIGNETTING_K, default=d.vignetting, metavar="K",
                       help="train views' vignetting 1 - K r^2, r = 1 at the corners")
    group.add_argument("--degrade-seed", type=arguments.SEED, default=d.degrade_seed,
                       help="seed of the degradations' draws (default: --seed)")


def generate_fields(args: argparse.Namespace) -> dict:
    """The GenerateConfig fields (all but scene) from arguments added by
    add_generate_arguments."""
    width, height = parse_resolution(args.res)
    fields = {name: getattr(args, name) for name in CONFIG_OPTIONS}
    if fields["envmap"] is not None:
        fields["envmap"] = str(fields["envmap"])
    return {"width": width, "height": height, **fields}
