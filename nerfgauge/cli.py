"""`nerfgauge`: one command, subcommands registered by the stage packages.

Each stage package has a `commands.py` with `register(subparsers)`, which adds its
subcommands and sets `func` (called with the parsed arguments, returns an exit code);
so do the methods (`nerfgauge.methods.commands`, `nerfgauge.methods.sfm`), the benches
(`nerfgauge.orchestrate.bench.commands`), the suites (`nerfgauge.orchestrate.suite.commands`) and
`nerfgauge.run` (run). Heavy imports (mitsuba, torch) happen inside those functions, so
`nerfgauge --help` and argument errors are instant.

Exit codes: 0 done; 2 bad input, one line on stderr: an argument error, an `InputError`,
an OS error on the user's paths (no space, permission, read-only, not a folder ...,
naming the path and the reason), or an allocation too large for this machine; 3 NaN or inf
where finite numbers are required (`NumericalError`), one line, and so is a numpy
floating-point overflow, invalid value or division by zero that no code expected (every
command runs in core.errors.floating_point_warnings_raise: the warning is raised where it
happens instead of printing lines and letting NaN travel on); 130 interrupted; 141
(silently) when stdout's reader has gone, as `| head` does.
Commands may return 1 for "ran, and the result failed" (`check`, `bench hard`), and `check`
4 for "failed, but the run was under-trained": it got fewer than half the training steps the
thresholds' calibration recorded (a time budget on a slower machine), so the failure is
not a verdict on quality (eval/check.py).
Set NERFGAUGE_DEBUG=1 to see the traceback instead of the one line.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from nerfgauge import run
from nerfgauge.core import errors
from nerfgauge.core.arguments import document_ranges
from nerfgauge.core.errors import InputError, NumericalError, input_error_from_os
from nerfgauge.methods import commands as methods
from nerfgauge.methods import sfm
from nerfgauge.orchestrate.suite import commands as suite_commands
from nerfgauge.orchestrate.bench import commands as bench

STAGES = ("scenes", "generate", "nerf", "eval")  # then orchestration (bench, suite), then run


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error: `nerfgauge COMMAND: error: MESSAGE`, exit 2, no usage
    block (`--help` still prints it). Subcommand parsers inherit the class."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {_one_line(message)}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
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
    methods.register(subparsers)
    bench.register(subparsers)
    suite_commands.register(subparsers)
    sfm.register(subparsers)
    run.register(subparsers)
    document_ranges(parser)  # every numeric flag's range in its --help
    return parser


def _one_line(text: str) -> str:
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    return lines[0] if lines else ""


def _fail(command: str, kind: str, message: str, code: int) -> int:
    print(f"nerfgauge {command}: {kind}: {message}", file=sys.stderr)
    return code


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout is not a file (captured in tests)
        pass


def main(argv=None) -> int:
    """Run `nerfgauge ARGV`; returns the exit code (argument errors and --help included)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help (0) or an argument error (2), already printed
        return stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 2
    command = " ".join(str(part) for part in (args.command, getattr(args, "bench_kind", None)) if part)
    debug = bool(os.environ.get("NERFGAUGE_DEBUG"))
    try:
        with errors.floating_point_warnings_raise():
            code = args.func(args)
        sys.stdout.flush()  # a reader that left shows here (BrokenPipeError), not at interpreter exit
    except KeyboardInterrupt:
        print(f"nerfgauge {command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        if debug:
            raise
        _silence_stdout()  # the reader left (`nerfgauge scenes | head -1`): nothing to report, as for SIGPIPE
        return 141
    except Exception as error:
        if debug:
            raise
        if isinstance(error, OSError):
            error = input_error_from_os(error)
        if isinstance(error, InputError):
            return _fail(command, "error", _one_line(error) or type(error).__name__, 2)
        if isinstance(error, NumericalError):
            return _fail(command, "numerical error", _one_line(error), 3)
        if errors.is_floating_point_error(error):
            return _fail(command, "numerical error", f"{_one_line(error)} (NaN or inf where nerfgauge expected none: "
                                                      "a bug, please report it; NERFGAUGE_DEBUG=1 shows where)", 3)
        if isinstance(error, MemoryError):
            detail = _one_line(error)
            return _fail(command, "error", f"out of memory{': ' + detail if detail else ''} "
                                           "(use smaller sizes: resolution, views, batch)", 2)
        raise
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
