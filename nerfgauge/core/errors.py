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
"""

from __future__ import annotations

import contextlib
import errno as errno_codes


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
