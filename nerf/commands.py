"""`nerfgauge` subcommands of the nerf stage: one `_add_<name>` and one `_run_<name>` per subcommand.

Add a subcommand by writing its pair and listing `_add_<name>` in `register`. torch is
imported inside the run functions so `nerfgauge --help` stays instant.
"""

from __future__ import annotations

from pathlib import Path

from nerfgauge.errors import InputError


def register(subparsers) -> None:
    for add in (_add_toy_pe,):
        add(subparsers)


# --------------------------------------------------------------------------------------
# toy-pe


def _add_toy_pe(subparsers) -> None:
    parser = subparsers.add_parser(
        "toy-pe",
        help="the lecture's 2D experiment: memorise an image with an MLP, with and without positional encoding",
        description="Fit an MLP (x, y) -> rgb to a procedural high-frequency image, once on raw coordinates and "
                    "once on their positional encoding; print both PSNRs and the gap, and with --out write "
                    "toy_pe.png (target | no PE | PE) and toy_pe.json.",
    )
    parser.add_argument("--out", type=Path, default=None, metavar="DIR", help="directory for toy_pe.png and toy_pe.json")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="Adam steps per fit (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the image and the initial weights (default 0)")
    parser.set_defaults(func=_run_toy_pe)


def _run_toy_pe(args) -> int:
    if args.steps is not None and args.steps < 1:
        raise InputError(f"--steps must be a positive integer, got {args.steps}")
    if args.seed < 0:
        raise InputError(f"--seed must be a non-negative integer, got {args.seed}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise InputError(f"--out must be a directory, but {args.out} is a file")

    from nerf.toy_pe import ToyPEConfig, run_toy_pe

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
