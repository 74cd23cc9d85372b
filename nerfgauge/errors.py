"""The one error type for bad user input, shared by every stage.

Anything a user can get wrong (a scene name, a resolution, a path, a JSON file, a
checkpoint) raises `InputError` with a one-line message; the `nerfgauge` command prints it
and exits with code 2. Any other exception is a bug and keeps its traceback.
"""


class InputError(ValueError):
    """Bad user input: the message is one line and names the offending value."""
