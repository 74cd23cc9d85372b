"""Folders nerfgauge owns: an ownership marker, safe replacement, one writer at a time.

Every folder a command creates (dataset, run, renders, pipeline output, suite, bench)
holds a small marker, `.nerfgauge.json`, naming its kind and the hash of the recipe that
made it. `--overwrite` deletes only a folder that holds a marker of the expected kind;
a folder without one is the user's, and is never deleted, whatever else it holds.

A command that writes into a folder holds an advisory lock on it (`fcntl.flock` on
`.nerfgauge.lock`), so a second process exits with a one-line error naming the holder's
PID instead of interleaving writes; only the lock holder removes stale temporary files.
The lock is released when the process ends, however it ends (the kernel drops flocks).

Taking a folder (`claim_folder`, `folder_lock`) refuses it when it holds a symbolic link
anywhere inside (core.owned.refuse_links_inside): nothing is written through a link inside
our folders, and a link planted between two runs is named before any work. `--overwrite`
deletes such a link as a link (never its target) with the rest of the folder's content.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import fnmatch
import hashlib
import os
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_bytes, read_json, write_json
from nerfgauge.core.owned import MARKER

LOCK = ".nerfgauge.lock"
KINDS = ("dataset", "run", "renders", "baseline", "evaluation", "pipeline", "suite", "bench", "sfm", "cache")
TEMPORARY_GLOB = ".*.tmp*"  # files.atomic_path's temporary names


def recipe_hash(recipe) -> str:
    """sha256 of a recipe's canonical JSON: the identity of what a folder was made from."""
    return hashlib.sha256(json_bytes(recipe)).hexdigest()


def read_marker(folder) -> dict | None:
    """The folder's marker, or None when it has none (or `folder` is not a folder)."""
    path = Path(folder) / MARKER
    if not path.is_file() or path.is_symlink():
        return None
    marker = read_json(path)
    if marker.get("kind") not in KINDS:
        raise InputError(f"{path} names an unknown kind {marker.get('kind')!r}")
    return marker


def write_marker(folder, kind: str, recipe: str | None) -> None:
    if kind not in KINDS:
        raise ValueError(f"unknown folder kind {kind!r}")
    write_json(Path(folder) / MARKER, {"kind": kind, "recipe": recipe, "tool": "nerfgauge"})


def _describe(folder: Path) -> str:
    names = sorted(p.name for p in folder.iterdir())
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return f"{len(names)} entries ({shown})"


def remove_owned(folder, kind: str) -> None:
    """Delete a folder nerfgauge made, of `kind`; refuse anything else.

    Symlinks are never followed: a link as `folder` (or on the way to it, inside a folder
    of ours) is refused, links inside it are removed as links (core.owned.remove_tree)."""
    folder = Path(folder)
    if folder.is_symlink():
        raise InputError(f"refusing to delete {folder}: it is a symbolic link")
    if not folder.exists():
        return
    if not folder.is_dir():
        raise InputError(f"refusing to delete {folder}: it is not a folder")
    marker = read_marker(folder)
    if marker is None:
        raise InputError(f"refusing to delete {folder}: it has no {MARKER}, so nerfgauge did not make it "
                         f"(it holds {_describe(folder)})")
    if marker["kind"] != kind:
        raise InputError(f"refusing to delete {folder}: it holds a nerfgauge {marker['kind']}, not a {kind}")
    owned.remove_tree(folder)


def _check_claimable(folder: Path, kind: str, recipe: str | None, overwrite: bool) -> str:
    """What claiming `folder` would do, without changing anything: "new", "resume" or
    "replace"; an InputError naming what was found when the folder is not ours to use."""
    if folder.is_symlink():
        raise InputError(f"output folder {folder} is a symbolic link; give the real path")
    if folder.exists() and not folder.is_dir():
        raise InputError(f"output path {folder} exists and is not a folder")
    if not folder.is_dir() or not any(not _ours_in_flight(p.name) for p in folder.iterdir()):
        return "new"
    marker = read_marker(folder)
    if marker is None:
        raise InputError(f"output folder {folder} is not empty and was not made by nerfgauge (no {MARKER}; "
                         f"it holds {_describe(folder)}); choose another folder")
    if marker["kind"] != kind:
        raise InputError(f"output folder {folder} holds a nerfgauge {marker['kind']}, not a {kind}; "
                         "choose another folder")
    if marker.get("recipe") == recipe:
        return "resume"
    if not overwrite:
        raise InputError(f"output folder {folder} holds a {kind} of another recipe; pass --overwrite to replace it")
    return "replace"


def _refuse_inside_a_dataset(folder: Path) -> None:
    """No command makes a folder inside a dataset (only `generate` writes there, into the
    dataset folder itself): the nearest folder above `folder` with a marker must not be a
    dataset's (`render RUN --out DATASET/renders` would change that dataset)."""
    for parent in Path(os.path.realpath(folder.absolute())).parents:  # "..", symlinks resolved
        if (parent / MARKER).is_file():
            try:
                kind = (read_marker(parent) or {}).get("kind")
            except InputError:
                kind = None
            if kind == "dataset":
                raise InputError(f"refusing to write into {folder}: it is inside the nerfgauge dataset folder "
                                 f"{parent}, which only `generate` writes; choose a folder outside it")
            return


def _ours_in_flight(name: str) -> bool:
    """The lock, or a marker being written: what a concurrent claimer leaves in a folder
    before it is recognisably ours (seen unlocked, it must not read as the user's)."""
    return name == LOCK or name.startswith(f".{MARKER}.tmp")


def _empty_owned(folder: Path) -> None:
    """Delete everything in a folder we own except the lock we hold; the marker goes last,
    so a deletion cut short leaves a folder that is still recognisably ours."""
    for entry in sorted(folder.iterdir(), key=lambda p: p.name == MARKER):
        if entry.name == LOCK:
            continue
        if entry.is_dir() and not entry.is_symlink():
            owned.remove_tree(entry)
        else:
            owned.remove_file(entry)  # a link planted inside goes as a link, its target untouched


@contextlib.contextmanager
def claim_folder(folder, kind: str, recipe: str | None, *, overwrite: bool = False):
    """Make `folder` ready for a command that writes a `kind` made from `recipe` (a hash),
    and hold its write lock for the block. Yields "new", "resume" or "replaced".

    Checked before anything is written (a folder that is not ours is refused untouched, and
    so is any folder inside a dataset folder), then again under the lock. Stale temporaries of killed writers are removed under the
    lock. Nothing is deleted from a folder without our marker of the same kind; a folder
    kept (resumed) holding a symbolic link anywhere inside is refused (core.owned)."""
    folder = Path(folder)
    _refuse_inside_a_dataset(folder)
    _check_claimable(folder, kind, recipe, overwrite)
    try:
        owned.make_folder(folder)
    except InputError:
        if folder.exists() and not folder.is_dir():
            raise InputError(f"output path {folder} exists and is not a folder") from None
        raise
    with folder_lock(folder, check_links=False):
        state = _check_claimable(folder, kind, recipe, overwrite)
        if state == "replace":
            _empty_owned(folder)
            state = "replaced"
        owned.refuse_links_inside(folder)
        if state != "resume":
            write_marker(folder, kind, recipe)
        remove_temporaries(folder)
        yield state


def adopt_shared_folder(folder, kind: str) -> Path:
    """Make `folder` (absent, empty, or ours of `kind`) a folder of ours that several
    processes use at once without a write lock (a cache: each file in it is written
    atomically on its own). Refused like claim_folder, before anything is written: a link
    as the folder, a folder inside a dataset, a non-empty folder without our marker or of
    another kind. A link inside is not refused here, since no lock makes a check at entry
    hold for the whole run: its user checks each file as it goes (eval.lpips_cache reads
    with O_NOFOLLOW, writes through core.files.atomic_path, which refuses a link, and
    removes a link at one of its names as a link, core.owned.remove_file). Returns the folder."""
    folder = Path(folder)
    _refuse_inside_a_dataset(folder)
    if _check_claimable(folder, kind, None, overwrite=False) == "new":
        owned.make_folder(folder)
        write_marker(folder, kind, None)  # two processes adopting at once write the same marker
    return folder


@contextlib.contextmanager
def folder_lock(folder, *, check_links: bool = True):
    """Hold the folder's advisory write lock for the block; InputError if another process holds it.

    The holder's PID is written into the lock file so the refusal can name it. check_links:
    once locked, refuse the folder if it holds a symbolic link anywhere inside
    (core.owned.refuse_links_inside; claim_folder checks after an --overwrite emptied it)."""
    folder = owned.make_folder(folder)
    fd = owned.open_lock(folder / LOCK)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise InputError(f"{folder} is in use by another nerfgauge process (PID {holder}); "
                             "wait for it to finish or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        if check_links:
            owned.refuse_links_inside(folder)
        yield folder
    finally:
        os.close(fd)  # closing drops the flock; the file stays (removing it would race)


def remove_temporaries(folder) -> int:
    """Delete temporary files a killed writer left in `folder` and its subfolders, except
    subfolders with a marker of their own (their claimer cleans them under their lock).
    Call only while holding `folder_lock(folder)`: another writer's temporaries are live.
    Returns how many were removed."""
    removed = 0
    for parent, subfolders, names in os.walk(folder):
        subfolders[:] = [name for name in subfolders if not (Path(parent) / name / MARKER).is_file()]
        for name in names:
            if fnmatch.fnmatch(name, TEMPORARY_GLOB):
                owned.remove_file(Path(parent) / name)
                removed += 1
    return removed
