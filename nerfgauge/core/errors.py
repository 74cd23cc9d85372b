"""The error types shared by every stage, and the one translation of OS errors into them.

Anything a user can get wrong (a scene name, a resolution, a path, a JSON file, a
checkpoint) raises `InputError` with a one-line message; the `nerfgauge` command prints it
and exits with code 2. A computation that produced NaN or inf where the harness promises
finite numbers (a diverging training) raises `NumericalError`: one line, exit code 3.
Any other exception is a bug and keeps its traceback.

An `OSError` met while reading or writing the user's paths (no space left, permission
denied, read-only file system, a path under a regular file, a missing folder) is the
user's environment, not a bug: `input_error_from_os` turns it into an `InputError` naming
the path and the reason, and `os_errors_as_input_errors()` does so for a block. The CLI and
the Python API both use them, so both report the same line.

numpy's floating-point warnings ("overflow encountered in multiply", "invalid value
encountered in divide", "divide by zero encountered in log") printed extra stderr lines
beside the one line, and let a NaN or inf travel on. Inside `floating_point_warnings_raise()`
(the `nerfgauge` command runs every command in it; worker processes call
`raise_floating_point_warnings()`) each is raised where it happens, in every thread, as a
RuntimeWarning exception (`is_floating_point_error`): an overflow nobody expected is a bug,
reported as one line (exit 3; NERFGAUGE_DEBUG=1: the traceback). Code that expects inf or
NaN says so where it computes them, with `np.errstate(...="ignore")`.
"""

from __future__ import annotations

import contextlib
import errno as errno_codes
import re
import warnings


class InputError(ValueError):
    """Bad user input: the message is one line and names the offending value."""


class NumericalError(RuntimeError):
    """NaN or inf where a finite value was required: the message says where and when."""


def input_error_from_os(error: OSError) -> InputError:
    """One-line InputError for an OSError: "PATH: reason" ("SRC -> DST: reason" for a rename).

    The reason is the C library's text (strerror), e.g. "No space left on device"; without
    one (an OSError raised by hand) the error's own text, first line. The result keeps the
    errno as `.errno` and the original as `__cause__` once raised `from` it."""
    reason = error.strerror or (str(error).splitlines() or [""])[0] or type(error).__name__
    if error.errno in errno_codes.errorcode and error.strerror:
        reason = f"{reason} ({errno_codes.errorcode[error.errno]})"
    paths = [str(name) for name in (error.filename, error.filename2) if name is not None]
    text = f"{' -> '.join(paths)}: {reason}" if paths else reason
    converted = InputError(text.replace("\r", "\\r").replace("\n", "\\n"))  # one line whatever a path holds
    converted.errno = error.errno
    return converted


@contextlib.contextmanager
def os_errors_as_input_errors():
    """Re-raise any OSError inside the block as `input_error_from_os(error)` (from the original)."""
    try:
        yield
    except OSError as error:
        raise input_error_from_os(error) from error


FLOATING_POINT_WARNING = r"(overflow|invalid value|divide by zero) encountered"  # numpy's messages' start


def raise_floating_point_warnings() -> None:
    """From now on, in this process: numpy's floating-point warnings are raised (module docstring)."""
    warnings.filterwarnings("error", message=FLOATING_POINT_WARNING, category=RuntimeWarning)


@contextlib.contextmanager
def floating_point_warnings_raise():
    """numpy's floating-point warnings raised inside the block, in every thread; the
    warning filters as they were afterwards."""
    with warnings.catch_warnings():
        raise_floating_point_warnings()
        yield


def is_floating_point_error(error: BaseException) -> bool:
    """A numpy floating-point warning raised as an exception, or numpy's FloatingPointError."""
    return isinstance(error, FloatingPointError) or (
        isinstance(error, RuntimeWarning) and re.match(FLOATING_POINT_WARNING, str(error)) is not None)
