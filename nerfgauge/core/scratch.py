"""Scratch folders inside a command's own target: removed when the command ends and, after
a kill, by the next command that makes one there.

A command that works in a temporary folder before it writes its results (`sfm`: the staged
images, the feature database, COLMAP's models; `lpips install`: pip's download) keeps that
folder inside its own target, never in TMPDIR: TMPDIR is shared with the user's other
programs, and a folder left there by `kill -9` is never cleaned by anyone.

`scratch_folder(TARGET, NAME)` makes `TARGET/.NAME-XXXXXXXX.scratch` and holds an advisory
lock (`fcntl.flock`) on a file inside it while the block runs. The kernel drops that lock
when the process ends, however it ends; so the next `scratch_folder` in TARGET removes
every `.NAME-*.scratch` folder whose lock it can take (its maker is gone), and leaves the
folders of commands still running. A folder is made under another name (`.NAME-*.new`) and
renamed once its lock is held, so a folder without a lock is never one in use; a `.new`
folder left by a kill in between is removed once it is older than STALE_NEW_SECONDS.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import tempfile
import time
from pathlib import Path

from nerfgauge.core import owned

SUFFIX = ".scratch"
NEW_SUFFIX = ".new"
LOCK_NAME = ".lock"
STALE_NEW_SECONDS = 3600.0  # a folder is renamed from .new within microseconds of its creation


def _lock(folder: Path, blocking: bool):
    """An fd holding the flock of `folder`'s lock file, or None when another process holds it."""
    fd = owned.open_lock(folder / LOCK_NAME)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except OSError as error:
        os.close(fd)
        if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            return None
        raise
    return fd


def remove_stale_scratch(parent, name: str) -> int:
    """Remove the `.NAME-*.scratch` folders in `parent` whose makers have ended (module
    docstring). Returns how many were removed."""
    parent = Path(parent)
    removed = 0
    if not parent.is_dir():
        return 0
    for entry in sorted(parent.glob(f".{name}-*{SUFFIX}")):
        if entry.is_symlink() or not entry.is_dir():
            continue  # not one we made: never followed, never deleted
        try:
            fd = _lock(entry, blocking=False)
        except FileNotFoundError:  # removed meanwhile by another cleaner
            continue
        if fd is None:
            continue  # its command is running
        try:
            with contextlib.suppress(FileNotFoundError):  # another cleaner got there first
                owned.remove_tree(entry)
        finally:
            os.close(fd)
        removed += 1
    now = time.time()
    for entry in parent.glob(f".{name}-*{NEW_SUFFIX}"):
        with contextlib.suppress(OSError):
            if not entry.is_symlink() and entry.is_dir() and now - entry.stat().st_mtime > STALE_NEW_SECONDS:
                owned.remove_tree(entry)
                removed += 1
    return removed


@contextlib.contextmanager
def scratch_folder(parent, name: str):
    """A fresh folder `parent/.NAME-XXXXXXXX.scratch` for the block (yields its Path),
    removed afterwards; stale ones of NAME in `parent` are removed first. `parent` is made
    if missing."""
    parent = owned.make_folder(parent)
    remove_stale_scratch(parent, name)
    new = Path(tempfile.mkdtemp(prefix=f".{name}-", suffix=NEW_SUFFIX, dir=parent))
    fd = _lock(new, blocking=True)  # a fresh folder: nobody else can hold it
    folder = new.with_name(new.name[: -len(NEW_SUFFIX)] + SUFFIX)
    try:
        owned.rename(new, folder)
        yield folder
    finally:
        try:
            owned.remove_tree(folder if folder.exists() else new)
        finally:
            os.close(fd)
