"""Single-file outputs at paths the user chose: what may be written there, and what may be replaced.

Folders are claimed with a marker (core.folders); a file a command writes at a path the user
gives (`evaluate --out`, `--ns-eval`, `--nerfbaselines`, `check --junit`, `mesh -o`,
`geometry -o`, `toy-pe --out`'s two files, `check --calibrate --out`) goes through `check_output_file` before any work
is done. The rule, in order:

1. Devices, FIFOs, sockets, folders and symbolic links are refused (`files.check_writable_target`),
   and so are a folder's marker and lock files.
2. The folder that owns the path is the nearest one above it holding a marker. A dataset,
   suite or bench folder is refused whatever the path: single-file outputs never go into
   them (`generate` and `suite` write those, through `claim_folder`).
3. A path where nothing is: written.
4. A file of the same kind nerfgauge wrote (recognised by content, `identify`): replaced.
   Reruns of the same command onto its own output need no flag.
5. A nerfgauge file of another kind (its mark says so), or a file without our mark inside a
   renders, baseline, evaluation or pipeline folder: replaced only with `--overwrite`.
6. Anything else is refused, `--overwrite` or not: a file without our mark outside our
   folders is the user's, and one inside a run folder is the run's (model.pt, config.json ...;
   the run writes no marked files, so its own files never carry a mark).

Refusals are `InputError`s (one line, exit 2) naming the path and what was found there.

Our files say what they are in their content, so a copy or a move keeps it:
- JSON documents: top-level `"tool": "nerfgauge"` and `"kind"` (`stamp`);
- PLY meshes: a header line `comment nerfgauge-kind: mesh`;
- JUnit XML: a comment `<!-- nerfgauge-kind: junit -->` after the XML declaration;
- PNG images: a tEXt chunk with keyword `nerfgauge-kind`;
- TOML (proposed thresholds, `check --calibrate --out`): a first line `# nerfgauge-kind: KIND`.
Only the first MAX_IDENTIFY_BYTES of a file are read to recognise it.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import struct
from pathlib import Path

from nerfgauge.core.errors import InputError
from nerfgauge.core.files import check_writable_target
from nerfgauge.core.folders import LOCK, MARKER, claim_folder, read_marker, recipe_hash

TOOL = "nerfgauge"
TEXT_MARK = "nerfgauge-kind"  # PLY comment, XML comment, PNG tEXt keyword
PNG_KEY = TEXT_MARK
MAX_IDENTIFY_BYTES = 64 << 20  # a metrics.json of thousands of frames is a few MiB
NEVER_INTO = ("dataset", "suite", "bench")  # folder kinds no single-file output is written into
KEEP_OTHERS = ("run",)  # folder kinds whose other files --overwrite never replaces
_MARK = re.compile(rb"nerfgauge-kind: ([A-Za-z0-9_.-]+)")


def stamp(document: dict, kind: str) -> dict:
    """`document` with `"tool": "nerfgauge"` and `"kind": kind` (a JSON output we wrote)."""
    return {**document, "tool": TOOL, "kind": kind}


def ply_mark(ply: bytes, kind: str = "mesh") -> bytes:
    """A PLY file's bytes with `comment nerfgauge-kind: KIND` after its `format` line."""
    if not ply.startswith(b"ply\n"):
        raise ValueError("not a PLY file")
    line_end = ply.index(b"\n", 4) + 1  # end of the "format ..." line
    return ply[:line_end] + f"comment {TEXT_MARK}: {kind}\n".encode() + ply[line_end:]


def xml_mark(xml: bytes, kind: str) -> bytes:
    """XML bytes with `<!-- nerfgauge-kind: KIND -->` after the declaration (or first)."""
    comment = f"<!-- {TEXT_MARK}: {kind} -->\n".encode()
    if xml.startswith(b"<?xml"):
        end = xml.index(b"?>") + 2
        return xml[:end] + b"\n" + comment + xml[end:].lstrip(b"\n")
    return comment + xml


def png_kind_info(kind: str):
    """Pillow PngInfo holding the tEXt chunk `nerfgauge-kind` = kind."""
    from PIL import PngImagePlugin  # Pillow: only when a PNG is marked

    info = PngImagePlugin.PngInfo()
    info.add_text(PNG_KEY, kind)
    return info


def identify(path) -> str | None:
    """The nerfgauge kind a file states in its content (module docstring), or None."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(MAX_IDENTIFY_BYTES + 1)
    except OSError:
        return None
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return _png_kind(head)
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        header = head[:head.find(b"end_header")] if b"end_header" in head else b""
        found = _MARK.search(header)
        return found.group(1).decode() if found and b"comment " + found.group(0) in header else None
    if head.startswith(b"# " + TEXT_MARK.encode() + b": "):  # TOML (thresholds): the first line says so
        found = _MARK.match(head[2:head.find(b"\n") if b"\n" in head else 200])
        return found.group(1).decode() if found else None
    if head.lstrip().startswith(b"<"):
        found = _MARK.search(head[:512])
        return found.group(1).decode() if found and b"<!-- " + found.group(0) in head[:512] else None
    if head.lstrip().startswith(b"{") and len(head) <= MAX_IDENTIFY_BYTES:
        try:
            document = json.loads(head.decode())
        except (ValueError, RecursionError):
            return None
        kind = document.get("kind") if isinstance(document, dict) and document.get("tool") == TOOL else None
        return kind if isinstance(kind, str) and kind else None
    return None


def _png_kind(data: bytes) -> str | None:
    at = 8
    while at + 8 <= len(data):
        length, chunk = struct.unpack(">I4s", data[at:at + 8])
        if chunk in (b"IDAT", b"IEND"):
            return None
        body = data[at + 8:at + 8 + length]
        if chunk == b"tEXt" and body.startswith(PNG_KEY.encode() + b"\0"):
            return body[len(PNG_KEY) + 1:].decode("latin-1") or None
        at += 12 + length
    return None


def owning_folder(path) -> tuple[Path, str] | None:
    """(folder, kind) of the nearest folder above `path` holding a nerfgauge marker, or None.
    A marker that cannot be read counts as kind "unknown" (and is not written into)."""
    folder = Path(os.path.realpath(Path(path).absolute().parent))  # "..", symlinked folders resolved
    for candidate in (folder, *folder.parents):
        if (candidate / MARKER).is_file():
            try:
                marker = read_marker(candidate)
            except InputError:
                marker = None
            return candidate, (marker or {}).get("kind", "unknown")
    return None


def check_output_file(path, kind: str, *, overwrite: bool = False, flag: str = "--overwrite") -> Path:
    """`path` if a command writing a `kind` file may write there (the rule in the module
    docstring); an InputError naming what is there otherwise. Call before the work.

    flag: how the command spells its overwrite option, named in the refusal (None: the
    command has none)."""
    path = check_writable_target(path)
    if path.name in (MARKER, LOCK):
        raise InputError(f"refusing to write {path}: it is the {'ownership marker' if path.name == MARKER else 'lock'} "
                         "of a nerfgauge folder")
    owner = owning_folder(path)
    exists = path.is_file()
    if owner is not None and owner[1] not in ("run", "renders", "baseline", "evaluation", "pipeline"):
        folder, folder_kind = owner
        where = f"{folder_kind} folder {folder}"
        if exists:
            relative = Path(os.path.realpath(path)).relative_to(folder)
            raise InputError(f"refusing to write {path}: it is another {folder_kind}'s {relative} ({where}); "
                             f"this command never writes into a nerfgauge {folder_kind}")
        raise InputError(f"refusing to write {path}: it is inside the nerfgauge {where}, which this command "
                         "never writes into; choose a path outside it")
    if not exists:
        return path
    found = identify(path)
    if found == kind:
        return path  # our own output of this kind: a rerun replaces it
    how = f"pass {flag} to replace it" if flag else "delete it first if it should go"
    if found is not None:  # a nerfgauge output of another kind
        if overwrite:
            return path
        raise InputError(f"refusing to replace {path}: it is a nerfgauge {found} file, not a {kind} file; {how}")
    if owner is not None and owner[1] in KEEP_OTHERS:  # a run's own files: model.pt, config.json, ...
        raise InputError(f"refusing to replace {path}: it is one of its own files in the {owner[1]} folder {owner[0]}, "
                         f"not a {kind} file; choose another path")
    if owner is not None:
        if overwrite:
            return path
        raise InputError(f"refusing to replace {path}: it is a file of the nerfgauge {owner[1]} folder {owner[0]}, "
                         f"not a {kind} file; {how}")
    raise InputError(f"refusing to replace {path}: it is a file nerfgauge did not write (no nerfgauge {kind} mark in it); "
                     "choose another path (overwriting replaces only nerfgauge's own files)")


def claim_output_file(out: Path, recipe: dict, kind: str, overwrite: bool = False):
    """Refuse a target that is not new nor a `kind` file nerfgauge wrote
    (core.outputs.check_output_file; overwrite: also another nerfgauge kind); claim a parent
    folder this command creates as an "evaluation" folder (marker and lock). For commands
    that write one file (`mesh`, `geometry`)."""
    check_output_file(out, kind, overwrite=overwrite)
    if out.parent.exists():
        return contextlib.nullcontext()
    return claim_folder(out.parent, "evaluation", recipe_hash(recipe))
