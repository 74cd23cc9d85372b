"""The evaluator's command-line options, defined once: `nerfgauge evaluate` adds them all
(`add_evaluate_arguments`), `nerfgauge run` the scoring ones (`add_scoring_arguments`:
how renders become scores; run renders the test split itself, as ray distance, in our
naming, so --split, --depth-kind and --pred-format are not its to choose). Both read them
back as EvaluateConfig fields (`evaluate_fields`).

What a command does with the scores (--pred, --out, --ns-eval, --overwrite, ...) stays in
its own module.
"""

from __future__ import annotations

import argparse

from nerfgauge.eval.evaluate import EvaluateConfig
from nerfgauge.eval.metrics import BACKGROUNDS
from nerfgauge.eval.predictions import DEPTH_SUFFIXES, FORMATS

SCORING = ("background", "protocol", "held_out")  # the EvaluateConfig fields `add_scoring_arguments` sets
OPTIONS = ("split", "depth_kind", "pred_format") + SCORING  # ... and `add_evaluate_arguments`


def add_scoring_arguments(parser: argparse.ArgumentParser, defaults: EvaluateConfig | None = None) -> None:
    """How renders are scored: --background, --protocol, --no-held-out."""
    d = EvaluateConfig() if defaults is None else defaults
    parser.add_argument("--background", choices=tuple(BACKGROUNDS), default=d.background,
                        help=f"composite RGBA onto this colour before PSNR/SSIM (default {d.background})")
    parser.add_argument("--protocol", default=d.protocol, metavar="NAME",
                        help="how renders are scored: nerfgauge (ours, default), "
                             "nerfbaselines (their Blender 'nerf' protocol: white, uint8, dm_pix SSIM, LPIPS-VGG), "
                             "ns-eval (nerfstudio's: black, float, torchmetrics SSIM, LPIPS-Alex); eval/protocols.py")
    parser.add_argument("--no-held-out", dest="held_out", action="store_false",
                        help="skip the co-visible and depth-resolved scores (psnr_covisible, psnr_capture_bound, "
                             "depth_absrel_resolved): their pass costs about 0.12 us per hit test pixel and train view")


def add_evaluate_arguments(parser: argparse.ArgumentParser, defaults: EvaluateConfig | None = None) -> None:
    """Every evaluate setting: the split, what predicted depth holds and how the folder
    names its files, and the scoring ones (`add_scoring_arguments`)."""
    d = EvaluateConfig() if defaults is None else defaults
    parser.add_argument("--split", default=d.split, help=f"split to score (default {d.split})")
    add_scoring_arguments(parser, d)
    parser.add_argument("--depth-kind", choices=tuple(DEPTH_SUFFIXES), default=d.depth_kind,
                        help=f"what predicted depth holds: ray distance (default {d.depth_kind}) or z-depth")
    parser.add_argument("--pred-format", choices=FORMATS, default=d.pred_format,
                        help="how DIR names its files: ours, ns-render dataset output, NerfBaselines predictions, "
                             "or a plain folder of images (default: detect; eval/predictions.py)")


def evaluate_fields(args: argparse.Namespace, names: tuple = OPTIONS) -> dict:
    """The EvaluateConfig fields `names` (OPTIONS, or SCORING for `run`) from the arguments
    the matching add_* function added."""
    return {name: getattr(args, name) for name in names}
