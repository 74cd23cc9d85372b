"""`nerfgauge methods install METHOD [--env DIR]`: build a spec's environment from its install
lines (nerfgauge.methods.external: an argument list each, {env} and {python} replaced, run
without a shell), into DIR or where the method looks for it (external.environment_folder).

An environment we build holds ENVIRONMENT_RECORD, written twice: "building" before the first
line runs and "complete" (with the lines, and the sha256 of each file they name inside the
spec's folder: a constraints file) after the last, so a build that was cut short is never
taken for a complete one. Installing again:
- complete, from the same lines and files: nothing to do;
- ours but incomplete, or built from other lines: emptied and built again;
- a folder that is not empty and holds no record (the user's own environment): refused
  untouched (point the method at it with $NERFGAUGE_ENV_<NAME> instead).
The folder's write lock (core.folders.folder_lock) keeps two installs apart. After the last
line, the spec's commands must be in the environment's bin folder.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, sha256_file, write_json
from nerfgauge.core.folders import LOCK, folder_lock
from nerfgauge.methods.external import (DROPPED_VARIABLES, ENVIRONMENT_RECORD, ExternalMethod, environment_folder,
                                        environment_variable, fill)


def _record(spec) -> dict:
    return {"tool": "nerfgauge", "environment": spec.environment or spec.name,
            "install": [list(argv) for argv in spec.install], "files": _named_files(spec)}


def _named_files(spec) -> dict:
    """{argument: sha256} of each file an install line names inside the spec's folder
    ({spec_folder}/...): its content is part of what the environment is built from."""
    folder = spec.folder.resolve()
    named = {}
    for argv in spec.install:
        for arg in argv:
            if "{spec_folder}" in arg:
                path = Path(fill(arg, {"spec_folder": str(folder), "env": "", "python": ""}))
                if not path.is_file():
                    raise InputError(f"method {spec.name}: its install lines name {path}, which is not a file")
                named[arg] = sha256_file(path)
    return named


def _state(folder: Path, wanted: dict) -> str:
    """"new", "complete" or "rebuild"; InputError for a folder that is not ours."""
    if folder.is_symlink():
        raise InputError(f"environment folder {folder} is a symbolic link; give the real path")
    if folder.exists() and not folder.is_dir():
        raise InputError(f"environment folder {folder} exists and is not a folder")
    if not folder.is_dir() or not [p for p in folder.iterdir() if p.name != LOCK]:
        return "new"
    path = folder / ENVIRONMENT_RECORD
    if not path.is_file() or path.is_symlink():
        raise InputError(f"{folder} is not empty and was not built by `nerfgauge methods install` (no "
                         f"{ENVIRONMENT_RECORD}); choose another --env, or use it as it is by pointing the method "
                         "at it")
    record = read_json(path)
    if record.get("state") == "complete" and {k: record.get(k) for k in wanted} == wanted:
        return "complete"
    return "rebuild"


def _empty(folder: Path) -> None:
    """Everything in an environment we built but the lock we hold and the record (already
    saying "building", so a deletion cut short leaves a folder still known as ours)."""
    for entry in folder.iterdir():
        if entry.name not in (LOCK, ENVIRONMENT_RECORD):
            remove = owned.remove_tree if entry.is_dir() and not entry.is_symlink() else owned.remove_file
            remove(entry)  # a venv's links go as links


def _command_environment() -> dict:
    """Ours, without what would make the new environment's interpreter see our packages."""
    return {key: value for key, value in os.environ.items() if key not in (*DROPPED_VARIABLES, "VIRTUAL_ENV")}


def install_environment(method: ExternalMethod, folder=None, *, log=None) -> tuple[Path, bool]:
    """Build `method`'s environment in `folder` (default: where the method looks for it).
    Returns (its folder, whether anything was built). The lines' output goes to `log`
    (default: this process's stdout and stderr)."""
    spec = method.spec
    if isinstance(spec.install, str):
        told = f": {spec.install}" if spec.install else ""
        raise InputError(f"method {spec.name} has no install lines nerfgauge can run (its spec's install is text"
                         f"{told})")
    folder = Path(os.path.expanduser(str(folder))) if folder is not None else environment_folder(spec)
    folder = folder.absolute()
    wanted = _record(spec)
    if _state(folder, wanted) == "complete":
        return folder, False
    with folder_lock(folder, check_links=False):  # a venv holds links (bin/python)
        if _state(folder, wanted) == "complete":  # another install finished while we waited
            return folder, False
        write_json(folder / ENVIRONMENT_RECORD, {**wanted, "state": "building"})
        _empty(folder)
        values = {"env": str(folder), "python": sys.executable, "spec_folder": str(spec.folder.resolve())}
        for index, template in enumerate(spec.install, 1):
            argv = [fill(arg, values) for arg in template]
            print(f"nerfgauge methods install {spec.name} ({index}/{len(spec.install)}): {shlex.join(argv)}",
                  file=log or sys.stdout, flush=True)
            try:
                status = subprocess.run(argv, stdin=subprocess.DEVNULL, env=_command_environment(),
                                        stdout=log, stderr=subprocess.STDOUT if log is not None else None).returncode
            except OSError as error:
                raise InputError(f"installing {spec.name}: cannot start {argv[0]}: {error.strerror or error}; "
                                 f"{folder} is incomplete (run the install again)") from None
            if status != 0:
                raise InputError(f"installing {spec.name}: line {index} of {len(spec.install)} "
                                 f"({shlex.join(argv)[:160]}) exited with status {status}; {folder} is incomplete "
                                 "(run the install again)")
        missing = [argv[0] for argv in (spec.train.argv, spec.render.argv)
                   if "/" not in argv[0] and "{" not in argv[0] and not (folder / "bin" / argv[0]).is_file()]
        if missing:
            raise InputError(f"installing {spec.name}: the install lines ran, but {folder / 'bin'} holds no "
                             f"{missing[0]}; {folder} is incomplete")
        write_json(folder / ENVIRONMENT_RECORD, {**wanted, "state": "complete"})
    return folder, True


def where_it_looks(method: ExternalMethod, folder: Path) -> str:
    """A note when `folder` is not where the method looks for its environment, saying how to
    point it there; empty otherwise."""
    spec = method.spec
    looks = environment_folder(spec)
    if looks is not None and Path(looks).absolute() == folder:
        return ""
    if spec.environment is None:
        return f"note: method {spec.name} runs from {looks} (its spec's environment.bin), not from {folder}"
    return f"note: method {spec.name} looks in {looks}; set {environment_variable(spec.environment)}={folder} to use this one"
