"""`nerfgauge`: one command, subcommands registered by the stage packages.

Each stage package has a `commands.py` with `register(subparsers)`, which adds its
subcommands and sets `func` (called with the parsed arguments, returns an exit code).
Heavy imports (mitsuba, torch) happen inside those functions, so `nerfgauge --help` and
argument errors are instant. Bad input (`InputError`) prints one line and exits 2, NaN or
inf where finite numbers are required (`NumericalError`) one line and exits 3; set
NERFGAUGE_DEBUG=1 to see the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from nerfgauge.core.errors import InputError, NumericalError

STAGES = ("scenes", "generate", "nerf", "eval")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nerfgauge",
        description="Ground-truth NeRF datasets with Mitsuba 3, a compact NeRF, and an evaluation harness.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for stage in STAGES:
        try:
            module = importlib.import_module(f"nerfgauge.{stage}.commands")
        except ModuleNotFoundError as error:
            if error.name != f"nerfgauge.{stage}.commands":
                raise
            continue  # a stage without commands yet
        module.register(subparsers)
    from nerfgauge import run

    run.register(subparsers)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except InputError as error:
        if os.environ.get("NERFGAUGE_DEBUG"):
            raise
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"nerfgauge {args.command}: error: {message}", file=sys.stderr)
        return 2
    except NumericalError as error:
        if os.environ.get("NERFGAUGE_DEBUG"):
            raise
        print(f"nerfgauge {args.command}: numerical error: {str(error).splitlines()[0]}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"nerfgauge {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
