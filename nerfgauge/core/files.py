"""Files as every stage writes and reads them: atomic writes, canonical JSON, hashes.

Nothing is written through a symbolic link below a folder nerfgauge owns: `atomic_path`
checks its target with `core.owned.check_no_link` (the other writes, deletes and renames
go through core.owned's helpers, which make the same check).

Every write goes to a temporary name in the same folder, is flushed to disk, checked, and
only then renamed into place, so a file that exists is complete: bytes we wrote must all be
on disk (`check_size`), and a file a library wrote must not be empty and, for PNG and EXR,
must read back whole (`nerfgauge.core.complete`), since OpenEXR does not report a failed
final flush on a full disk. A failed check leaves nothing at the target and no temporary.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path

from nerfgauge.core import bounded, complete
from nerfgauge.core.errors import InputError
from nerfgauge.core.owned import check_no_link


def check_writable_target(path) -> Path:
    """`path` if a write may replace it: absent, or a regular file that is not a symlink.

    Renaming onto a device, FIFO, socket, folder or symlink would replace it (as root,
    `--out /dev/full` became a JSON file), so those are refused with one line."""
    path = Path(path)
    if path.is_symlink():
        raise InputError(f"refusing to write {path}: it is a symbolic link")
    if path.exists() and not path.is_file():
        what = "a folder" if path.is_dir() else "not a regular file (a device, FIFO or socket)"
        raise InputError(f"refusing to write {path}: it is {what}")
    return path


@contextlib.contextmanager
def atomic_path(path, verify=None):
    """Yield a temporary sibling of `path`; when the block succeeds, flush it to disk
    (fsync), check it, and rename it to `path`, so a file that exists is complete even
    after a power cut or on a full disk. The temporary is removed if anything fails.
    A symbolic link on the way to `path` below a folder of ours is refused (core.owned).

    verify(tmp, path): the check (raising `complete.IncompleteWrite`); default
    `complete.check_complete` (not empty; PNG and EXR structurally whole)."""
    path = check_no_link(check_writable_target(path))
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        yield tmp
        with open(tmp, "rb") as handle:
            os.fsync(handle.fileno())
        if verify is None:
            complete.check_complete(tmp, shown=path)
        else:
            verify(tmp, path)
        os.replace(tmp, path)
    except OSError as error:
        if error.filename is None:  # write() on a full disk names no file: name the target
            error.filename = str(path)
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path, data: bytes) -> None:
    """Write `data` to `path` atomically; every byte must be on disk before the rename."""
    with atomic_path(path, verify=lambda tmp, shown: complete.check_size(tmp, len(data), shown)) as tmp:
        tmp.write_bytes(data)


def link_or_copy_atomic(source, target) -> None:
    """`target` becomes a hard link to `source` (a byte copy where the file system has
    none), atomically and checked like any write (atomic_path)."""
    with atomic_path(target) as tmp:
        if os.path.lexists(tmp):  # left by an earlier process of this PID: link(2) will not replace it
            tmp.unlink()
        try:
            os.link(source, tmp)
        except OSError:  # another file system, or one without hard links: copy the bytes
            tmp.write_bytes(Path(source).read_bytes())


def json_bytes(obj) -> bytes:
    """Canonical JSON: sorted keys, two-space indent, newline at the end (deterministic)."""
    return (json.dumps(obj, indent=2, sort_keys=True, allow_nan=False) + "\n").encode()


def write_json(path, obj) -> None:
    write_bytes_atomic(path, json_bytes(obj))


def read_json(path, *, finite: bool = False) -> dict:
    """A JSON object from `path` (InputError otherwise). finite=True also refuses the NaN
    and Infinity literals Python's parser accepts (files that promise numbers)."""
    data = bounded.read_bytes(path, bounded.MAX_JSON_BYTES, "JSON file")
    return json_from_bytes(data, path, finite=finite)


def json_from_bytes(data: bytes, path, *, finite: bool = False) -> dict:
    """A JSON object from bytes already read from `path` (named in errors); see read_json."""

    def refuse(constant):
        raise InputError(f"{path} holds {constant}, which is not valid JSON")

    try:
        value = bounded.loads_json(data, path, parse_constant=refuse if finite else None)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path} is not valid JSON: {error}") from None
    if not isinstance(value, dict):
        raise InputError(f"{path} should hold a JSON object, got {type(value).__name__}")
    return value


def sha256_file(path) -> str:
    """sha256 of a regular file, read as a stream of 1 MiB blocks (never whole)."""
    digest = hashlib.sha256()
    with bounded.open_regular(path) as (handle, _):
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
