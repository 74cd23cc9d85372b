"""The splatting stage's place in `nerfgauge train` and `nerfgauge render` (nerf/commands.py
calls these, so one `train` and one `render` command serve every model):

    nerfgauge train DATASET --model splat --out RUN [--budget-seconds T | --steps N] [--init ...]
    nerfgauge render RUN|GAUSSIANS.ply [--dataset DATASET] [--split test] [--out DIR]

The splat-only flags are defined once, beside SplatConfig (splat.config.OWN_FLAGS); the train
and render parsers' other flags belong to the NeRF models, and giving one of them a value
other than its default with a splatting run is refused in one line (exit 2), as is a splat
flag with a NeRF model. torch is imported inside the run functions so `nerfgauge --help`
stays instant.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.splat import config as splat_config

MODEL = splat_config.MODEL
TRAIN_SHARED = splat_config.SHARED + ("model",)
RENDER_SHARED = ("run", "split", "out", "overwrite", "threads", "dataset", "quiet")
NOT_OURS = "splat_not_ours"  # parser default: {dest: (flag, default)} of the NeRF-only flags


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """After the NeRF models' train flags: note which are theirs, add the splat-only ones."""
    _note_not_ours(parser, TRAIN_SHARED)
    splat_config.add_arguments(parser)


def note_render_parser(parser: argparse.ArgumentParser) -> None:
    """After the NeRF render flags: note which a splatting run does not take."""
    _note_not_ours(parser, RENDER_SHARED)


def _note_not_ours(parser: argparse.ArgumentParser, shared: tuple) -> None:
    not_ours = {action.dest: (action.option_strings[-1], action.default) for action in parser._actions
                if action.option_strings and action.dest not in shared and action.dest != "help"}
    parser.set_defaults(**{NOT_OURS: not_ours})


def _refuse_not_ours(args: argparse.Namespace) -> None:
    for dest, (flag, default) in getattr(args, NOT_OURS, {}).items():
        if getattr(args, dest, default) != default:
            raise InputError(f"{flag} is not a splatting flag (a NeRF model's); drop it for a splatting run")


def refuse_splat_flags(args: argparse.Namespace) -> None:
    """For a NeRF model: one line when a splat-only flag was given."""
    splat_config.refuse_own_flags(args, args.model)


def is_splat_source(path) -> bool:
    """Whether `nerfgauge render`'s RUN is a .ply file (Gaussians) or a splatting run folder
    (its config.json says "model": "splat"). Reads config.json only."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() == ".ply"
    config = path / splat_config.CONFIG
    if not config.is_file():
        return False
    try:
        return read_json(config).get("model") == splat_config.MODEL
    except InputError:
        return False


def run_train(args: argparse.Namespace, default_budget: float) -> int:
    """`nerfgauge train --model splat`; a run given neither --steps nor --budget-seconds trains
    `default_budget` seconds (the caller's: nerf.config's one default budget)."""
    _refuse_not_ours(args)
    from nerfgauge.splat.train import train  # torch: kept off `nerfgauge --help`'s import path

    config = splat_config.config_from_arguments(args, default_budget)
    summary = train(args.dataset, args.out, config, overwrite=args.overwrite, progress=not args.quiet)
    print(f"{args.out}: {summary['steps']} steps in {summary['seconds']:.1f} s, val PSNR {summary['val_psnr']:.2f} dB, "
          f"{summary['gaussians']} Gaussians ({summary['model_bytes'] / 1e6:.2f} MB)")
    return 0


def run_render(args: argparse.Namespace) -> int:
    _refuse_not_ours(args)
    from nerfgauge.splat.render_views import render_split  # torch: kept off `nerfgauge --help`'s import path

    timing = render_split(args.run, args.split, args.out, dataset=args.dataset, threads=args.threads,
                          overwrite=args.overwrite, progress=not args.quiet)
    print(f"rendered {timing['frames']} frames at {timing['ms_per_frame']:.1f} ms per frame, {timing['gaussians']} "
          f"Gaussians ({timing['device']}, {timing['threads']} threads) -> {args.out or args.run / 'renders'}")
    return 0
