"""Paths inside folders nerfgauge owns: nothing is written, deleted, renamed or made through
a symbolic link below such a folder.

A folder is ours when it holds the marker `.nerfgauge.json` (core.folders). Every write,
delete, rename and folder creation of the code base goes through this module or through
`core.files.atomic_path` (which calls `check_no_link`), and each walks its path component
by component: a symbolic link anywhere below the outermost folder of ours on the path is
refused with one line naming it (InputError, exit 2). Without it a dataset whose images/ is
a link to a user's folder lost that folder's files to a re-export, and a suite whose
results/<method> is a link had the user's result.json overwritten. A link ABOVE our folder
(the user's own layout: a home folder that is a link) is followed as usual, and so is any
path no folder of ours holds (single-file outputs a user names: core.outputs).

The rule for a link as the LAST component: writing or renaming onto it is refused (it
would replace the link, or a careless writer would follow it); deleting it removes the
link itself (`remove_file`, `remove_tree`: never its target), which is what
`--overwrite` of a folder of ours does with a link planted inside.

The checks run while the command holds the folder's write lock (core.folders.folder_lock),
and `refuse_links_inside` refuses a folder holding any link when the lock is taken, so a
link planted between two runs is refused before any work; only another program changing
the folder between a check and the write it guards could slip past (we hold no file
descriptors across the walk).
"""

from __future__ import annotations

import errno
import os
import shutil
import stat
from pathlib import Path

from nerfgauge.core.errors import InputError

MARKER = ".nerfgauge.json"  # the ownership marker of a folder nerfgauge made (core.folders writes it)


def _nodes(path) -> list[str]:
    """Every folder and file the kernel walks to reach `path`, from "/" down to `path`.
    Relative paths start at the working folder (os.getcwd() is already real); a ".." steps
    up from where the path so far really leads (a link's target's parent, as the kernel does)."""
    path = os.fspath(path)
    current = "/" if path.startswith("/") else os.getcwd()
    nodes = ["/"]
    for part in current.split("/"):
        if part:
            nodes.append(os.path.join(nodes[-1], part))
    current = nodes[-1]
    for part in path.split("/"):
        if part in ("", "."):
            continue
        current = os.path.dirname(os.path.realpath(current)) if part == ".." else os.path.join(current, part)
        nodes.append(current)
    return nodes


def holds_marker(folder) -> bool:
    """Whether `folder` holds our marker as a regular file (a linked marker does not count)."""
    try:
        return stat.S_ISREG(os.lstat(os.path.join(folder, MARKER)).st_mode)
    except OSError:
        return False


def _is_link(path) -> bool:
    try:
        return stat.S_ISLNK(os.lstat(path).st_mode)
    except OSError:  # absent (about to be made), or under a file: not a link
        return False


def link_below_owner(path, *, last: bool = True) -> tuple[Path, Path] | None:
    """(link, owner): the first symbolic link on the way to `path` that lies below `owner`,
    the outermost folder of ours on the way; None when there is none. last=False leaves
    the last component out (deleting a link removes the link, not what it points to)."""
    nodes = _nodes(path)
    owner = None
    for index, node in enumerate(nodes):
        if owner is not None and node != owner and not node.startswith(owner.rstrip("/") + "/"):
            owner = None  # a ".." climbed out of our folder: what follows is judged afresh
        if owner is not None and (last or index < len(nodes) - 1) and _is_link(node):
            return Path(node), Path(owner)
        if owner is None and holds_marker(node):
            owner = node
    return None


def check_no_link(path, action: str = "write", *, last: bool = True) -> Path:
    """`path`, unless reaching it passes a symbolic link below a folder of ours (module
    docstring): then an InputError naming the link. action: the verb of the refusal."""
    found = link_below_owner(path, last=last)
    if found is not None:
        link, owner = found
        raise InputError(f"refusing to {action} {path}: {link} is a symbolic link inside the nerfgauge folder "
                         f"{owner}, and nerfgauge never {_past(action)} through a link in its own folders; "
                         "remove the link (or move the real folder in its place)")
    return Path(path)


def _past(action: str) -> str:
    return {"write": "writes", "delete": "deletes", "rename": "renames", "make": "makes folders",
            "lock": "locks", "restore": "restores"}[action]


def refuse_links_inside(folder) -> None:
    """InputError naming the first symbolic link found anywhere inside `folder` (links are
    not followed; subfolders holding their own marker are left to the command that claims
    them). Called when a command takes a folder of ours, so a planted link is refused before
    any work."""
    for parent, subfolders, names in os.walk(folder):  # followlinks=False: links are listed, not entered
        for name in sorted(subfolders + names):
            path = Path(parent) / name
            if _is_link(path):
                raise InputError(f"refusing to use {folder}: {path} is a symbolic link inside this nerfgauge folder, "
                                 "and nerfgauge never writes through a link in its own folders; remove the link "
                                 "(or move the real folder in its place)")
        subfolders[:] = sorted(name for name in subfolders if not holds_marker(Path(parent) / name))


def make_folder(path) -> Path:
    """os.makedirs(path, exist_ok=True), refusing a link on the way below a folder of ours;
    an InputError when a non-folder is where a folder should be."""
    path = check_no_link(path, "make")
    try:
        os.makedirs(path, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{path} exists and is not a folder") from None
    return path


def remove_file(path, *, missing_ok: bool = True) -> bool:
    """Delete the file (or the link itself) at `path`, refusing a link on the way below a
    folder of ours and a folder at `path`. Returns whether something was deleted."""
    path = check_no_link(path, "delete", last=False)
    try:
        os.unlink(path)
    except FileNotFoundError:
        if not missing_ok:
            raise
        return False
    except IsADirectoryError:
        raise InputError(f"refusing to delete {path}: nerfgauge writes a file there, and it is a folder") from None
    except PermissionError:
        if os.path.isdir(path) and not os.path.islink(path):  # Linux unlink(2) of a folder: EISDIR or EPERM
            raise InputError(f"refusing to delete {path}: nerfgauge writes a file there, and it is a folder") from None
        raise
    return True


def remove_tree(path) -> bool:
    """Delete the folder `path` and everything in it (links inside are removed as links,
    never followed: shutil.rmtree's fd-based walk), refusing a link on the way and `path`
    itself being a link. Returns whether there was a folder."""
    path = check_no_link(path, "delete")
    if _is_link(path):
        raise InputError(f"refusing to delete {path}: it is a symbolic link")
    if not os.path.exists(path):
        return False
    shutil.rmtree(path)
    return True


def remove_empty_folder(path) -> bool:
    """Delete the folder `path` if it is empty (rmdir); False when absent or not empty."""
    path = check_no_link(path, "delete")
    try:
        os.rmdir(path)
    except FileNotFoundError:
        return False
    except OSError as error:
        if error.errno in (errno.ENOTEMPTY, errno.EEXIST):
            return False
        raise
    return True


def rename(source, target) -> Path:
    """os.replace(source, target) inside folders of ours: no link on either way, and the
    target is not a link itself (the rename would replace the link, not what it names)."""
    check_no_link(source, "rename")
    target = check_no_link(target, "rename")
    if _is_link(target):
        raise InputError(f"refusing to replace {target}: it is a symbolic link")
    os.replace(source, target)
    return target


def open_append(path):
    """A text handle appending to `path` (created if absent), never through a link: a link
    on the way below a folder of ours is refused, and `path` itself is opened O_NOFOLLOW."""
    path = check_no_link(path, "write")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise InputError(f"refusing to write {path}: it is a symbolic link") from None
        raise
    return os.fdopen(fd, "a")


def open_lock(path) -> int:
    """A read-write descriptor of the lock file `path` (created if absent), never through a link."""
    path = check_no_link(path, "lock")
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise InputError(f"refusing to lock {path}: it is a symbolic link") from None
        raise
