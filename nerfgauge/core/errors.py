"""The error types shared by every stage.

Anything a user can get wrong (a scene name, a resolution, a path, a JSON file, a
checkpoint) raises `InputError` with a one-line message; the `nerfgauge` command prints it
and exits with code 2. A computation that produced NaN or inf where the harness promises
finite numbers (a diverging training) raises `NumericalError`: one line, exit code 3.
Any other exception is a bug and keeps its traceback.
"""


class InputError(ValueError):
    """Bad user input: the message is one line and names the offending value."""


class NumericalError(RuntimeError):
    """NaN or inf where a finite value was required: the message says where and when."""
