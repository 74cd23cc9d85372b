"""Files as every stage writes and reads them: atomic writes, canonical JSON, hashes.

Every write goes to a temporary name in the same folder and is renamed into place, so a
file that exists is complete.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path

from nerfgauge.core.errors import InputError


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary sibling of `path`; rename it to `path` if the block succeeds."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def json_bytes(obj) -> bytes:
    """Canonical JSON: sorted keys, two-space indent, newline at the end (deterministic)."""
    return (json.dumps(obj, indent=2, sort_keys=True, allow_nan=False) + "\n").encode()


def write_json(path, obj) -> None:
    write_bytes_atomic(path, json_bytes(obj))


def read_json(path, *, finite: bool = False) -> dict:
    """A JSON object from `path` (InputError otherwise). finite=True also refuses the NaN
    and Infinity literals Python's parser accepts (files that promise numbers)."""
    path = Path(path)

    def refuse(constant):
        raise InputError(f"{path} holds {constant}, which is not valid JSON")

    try:
        value = json.loads(path.read_text(), parse_constant=refuse if finite else None)
    except FileNotFoundError:
        raise InputError(f"missing file: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path} is not valid JSON: {error}") from None
    if not isinstance(value, dict):
        raise InputError(f"{path} should hold a JSON object, got {type(value).__name__}")
    return value


def sha256_file(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
