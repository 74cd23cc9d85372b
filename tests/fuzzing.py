"""Shared helpers of the hostile-input suite (RELIABILITY.md): run a command in-process and judge
what it did, snapshot a tree to prove nothing outside the target folder was touched, and
build hostile files (PNG/EXR/JPEG bytes, pickles that would run code).

The verdict on one command (`judge`) is the spec's, not today's behaviour:
- exit 0 with finite outputs (every number in JSON, EXR and .pt outputs finite), or
- exit 2 with exactly one stderr line `nerfgauge <cmd>: error: ...`;
- never a traceback, never another exit code (3 is reserved for training that diverges
  on valid input), never a file touched outside the command's own output folder.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import struct
import sys
import tempfile
import traceback
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# --------------------------------------------------------------------------------------
# running a command


@dataclass
class Outcome:
    argv: list
    code: int | None  # None: an exception escaped main()
    stdout: str
    stderr: str
    escaped: str | None = None  # "Type: message" of an exception that escaped main()

    def line(self) -> str:
        return "nerfgauge " + " ".join(str(a) for a in self.argv)


@contextlib.contextmanager
def _captured_fd2():
    """Capture file descriptor 2 as well as sys.stderr: Mitsuba and OpenEXR write to the
    descriptor directly, and a stray C-level warning is a stderr line too."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        text = io.StringIO()
        try:
            with contextlib.redirect_stderr(text):
                yield text
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text.write(sink.read().decode(errors="replace"))


def run_cli(argv, cwd) -> Outcome:
    """`nerfgauge.cli.main(argv)` in this process, from folder `cwd` (so a relative path
    the command writes lands inside the snapshotted tree). SystemExit counts as its code."""
    from nerfgauge.cli import main

    argv = [str(a) for a in argv]
    out = io.StringIO()
    code, escaped = None, None
    previous = os.getcwd()
    os.chdir(cwd)
    try:
        with _captured_fd2() as err, contextlib.redirect_stdout(out):
            try:
                code = main(argv)
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
            except Exception as error:  # the finding: a traceback reached the user
                frames = traceback.extract_tb(error.__traceback__)
                where = f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else "?"
                escaped = f"{type(error).__name__} at {where}: {str(error).splitlines()[0][:200] if str(error) else ''}"
    finally:
        os.chdir(previous)
    return Outcome(argv, code, out.getvalue(), err.getvalue(), escaped)


# --------------------------------------------------------------------------------------
# snapshots: nothing outside the target folder changes


def snapshot(roots, exclude=()) -> dict:
    """{path: (kind, size, mtime_ns)} of everything under `roots` (symlinks not followed),
    except the folders in `exclude` and what is below them."""
    excluded = {os.path.abspath(p) for p in exclude}
    seen = {}
    for root in roots:
        root = os.path.abspath(root)
        for folder, dirs, files in os.walk(root, followlinks=False):
            dirs[:] = [d for d in dirs if os.path.join(folder, d) not in excluded]
            for name in dirs + files:
                path = os.path.join(folder, name)
                if path in excluded:
                    continue
                info = os.lstat(path)
                kind = "link" if os.path.islink(path) else "dir" if os.path.isdir(path) else "file"
                seen[path] = (kind, info.st_size if kind != "dir" else 0, info.st_mtime_ns if kind != "dir" else 0)
    return seen


def snapshot_changes(before: dict, after: dict) -> list[str]:
    changes = [f"created {p}" for p in sorted(after.keys() - before.keys())]
    changes += [f"deleted {p}" for p in sorted(before.keys() - after.keys())]
    changes += [f"changed {p}" for p in sorted(before.keys() & after.keys()) if before[p] != after[p]]
    return changes


# --------------------------------------------------------------------------------------
# finite outputs


def _refuse_constant(constant):
    raise ValueError(f"holds {constant}")


def nonfinite_outputs(folder) -> list[str]:
    """Files under `folder` holding NaN or inf: JSON (NaN/Infinity literals), EXR pixels,
    .npy arrays and floating tensors of .pt files (loaded with weights_only=True)."""
    problems = []
    folder = Path(folder)
    if not folder.exists():
        return problems
    paths = [folder] if folder.is_file() else sorted(p for p in folder.rglob("*") if p.is_file() and not p.is_symlink())
    for path in paths:
        try:
            if path.suffix in (".json", ".jsonl"):
                for text in path.read_text().splitlines() if path.suffix == ".jsonl" else [path.read_text()]:
                    if text.strip():
                        json.loads(text, parse_constant=_refuse_constant)
            elif path.suffix == ".exr":
                from nerfgauge.core.images import read_exr

                channels, _ = read_exr(path)
                if not all(np.isfinite(c).all() for c in channels.values()):
                    problems.append(f"{path} holds NaN or inf pixels")
            elif path.suffix == ".npy":
                if not np.isfinite(np.load(path, allow_pickle=False)).all():
                    problems.append(f"{path} holds NaN or inf")
            elif path.suffix == ".pt":
                problems += [f"{path}: {p}" for p in _nonfinite_tensors(path)]
        except Exception as error:  # an output we cannot read back is a finding too
            problems.append(f"{path} unreadable: {type(error).__name__}: {str(error).splitlines()[0][:120] if str(error) else ''}")
    return problems


def _nonfinite_tensors(path) -> list[str]:
    import torch

    payload = torch.load(path, map_location="cpu", weights_only=True)
    bad = []

    def walk(value, where):
        if isinstance(value, torch.Tensor):
            if value.is_floating_point() and not torch.isfinite(value).all():
                bad.append(f"{where} holds NaN or inf")
        elif isinstance(value, dict):
            for key, item in value.items():
                walk(item, f"{where}.{key}")
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                walk(item, f"{where}[{i}]")
        elif isinstance(value, float) and not np.isfinite(value):
            bad.append(f"{where} = {value}")

    walk(payload, "")
    return bad


# --------------------------------------------------------------------------------------
# the verdict

REFUSE, ANY = "refuse", "any"  # what a mutation must cause: exit 2, or exit 0 or 2


@dataclass
class Case:
    """One command on one mutated input, and everything needed to judge it."""

    command: str  # subcommand, for the stderr prefix
    argv: list
    cwd: Path  # the case's own folder (snapshotted)
    out: Path  # the command's own output folder (excluded from the snapshot)
    what: str  # the mutation, in words
    expect: str = ANY
    shared: tuple = ()  # read-only fixtures the command may read (snapshotted too)
    canary: Path | None = None  # must not exist afterwards (code run by a pickle)
    outcome: Outcome | None = field(default=None, init=False)


def judge(case: Case) -> list[str]:
    """Run `case` and return what went wrong (empty: it behaved as the spec says)."""
    roots = [case.cwd, *case.shared]
    before = snapshot(roots, exclude=[case.out])
    outcome = case.outcome = run_cli(case.argv, case.cwd)
    problems = []
    if outcome.escaped is not None:
        problems.append(f"traceback: {outcome.escaped}")
    elif outcome.code not in (0, 2):
        problems.append(f"exit {outcome.code} (only 0 or 2 allowed); stderr {outcome.stderr.strip()[-300:]!r}")
    elif outcome.code == 2:
        lines = [line for line in outcome.stderr.splitlines() if line.strip()]
        prefix = re.compile(rf"^nerfgauge {re.escape(case.command)}: error: \S")
        if len(lines) != 1 or not prefix.match(lines[0]):
            problems.append(f"exit 2 but stderr is not one '{case.command}: error:' line: {outcome.stderr.strip()[-400:]!r}")
    else:
        if case.expect == REFUSE:
            problems.append("exit 0: accepted an input that must be refused")
        problems += nonfinite_outputs(case.out)
    problems += [f"outside the output folder: {c}" for c in snapshot_changes(before, snapshot(roots, exclude=[case.out]))][:5]
    if case.canary is not None and case.canary.exists():
        problems.append(f"loading ran code: {case.canary} exists")
    return problems


def assert_judged(case: Case) -> None:
    problems = judge(case)
    assert not problems, (f"{case.what}: {'; '.join(problems)}\n  reproduce: cd {case.cwd} && "
                          f"{case.outcome.line()}")


# --------------------------------------------------------------------------------------
# datasets: copy, rewrite, keep the manifest consistent


def copy_tree(source, target) -> Path:
    import shutil

    shutil.copytree(source, target, symlinks=True)
    return Path(target)


def rehash_manifest(root) -> None:
    """Rewrite manifest.json for the files it lists that still exist, so a mutated file
    passes the manifest check and reaches the reader behind it."""
    from nerfgauge.core import dataset
    from nerfgauge.core.files import read_json

    root = Path(root)
    listed = read_json(root / dataset.MANIFEST).get("files", {})
    dataset.write_manifest(root, [rel for rel in listed if (root / rel).is_file()])


def write_raw(path, data: bytes) -> None:
    """Replace a file's bytes in place (no atomic dance: this is the attacker's write)."""
    path = Path(path)
    if path.is_symlink():
        path.unlink()
    path.write_bytes(data)


# --------------------------------------------------------------------------------------
# hostile image bytes


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_declaring(width: int, height: int, payload: bytes = b"") -> bytes:
    """A PNG whose IHDR (valid CRC) declares width x height RGBA8 but whose IDAT holds
    only `payload` compressed: a small file promising a huge image."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(payload))
            + _png_chunk(b"IEND", b""))


def image_bytes(array: np.ndarray, fmt: str) -> bytes:
    """A valid image file of `fmt` ("PNG", "JPEG", ...) holding the uint8 array."""
    from PIL import Image

    buffer = io.BytesIO()
    image = Image.fromarray(array)
    if fmt == "JPEG" and image.mode == "RGBA":
        image = image.convert("RGB")
    image.save(buffer, format=fmt)
    return buffer.getvalue()


def exr_bytes(channels: dict, header: dict | None = None) -> bytes:
    import OpenEXR

    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "x.exr")
        merged = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage} | (header or {})
        with OpenEXR.File(merged, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as exr:
            exr.write(path)
        return Path(path).read_bytes()


def exr_with_data_window(data: bytes, width: int, height: int) -> bytes:
    """The EXR `data` with its dataWindow (and displayWindow) attribute rewritten to
    (0, 0)-(width-1, height-1): a small file declaring a huge image."""
    out = bytearray(data)
    for name in (b"dataWindow\x00", b"displayWindow\x00"):
        at = out.find(name + b"box2i\x00")
        if at < 0:
            continue
        start = at + len(name) + len(b"box2i\x00") + 4  # after the attribute's size field
        out[start:start + 16] = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    return bytes(out)


# --------------------------------------------------------------------------------------
# pickles that would run code


class _Payload:
    """Unpickling this calls open(canary, "w"): it creates a file. A loader that runs
    pickled code is caught by the canary existing afterwards."""

    def __init__(self, canary):
        self.canary = str(canary)

    def __reduce__(self):
        return (open, (self.canary, "w"))


def code_running_checkpoint(canary, *, legacy: bool = False) -> bytes:
    """torch.save of a dict that looks like a nerfgauge model with a payload inside."""
    import pickle

    import torch

    obj = {"format": "nerfgauge-model", "version": 1, "model": _Payload(canary)}
    if legacy:
        return pickle.dumps(obj, protocol=2)
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


# --------------------------------------------------------------------------------------
# fresh cases from the run's fuzz seed (tests/conftest.py prints it)


def fuzz_seed() -> int:
    """The run's fuzz seed: tests/conftest.py sets $NERFGAUGE_FUZZ_SEED before any test
    module is imported (from --fuzz-seed, the environment, or a fresh random one)."""
    return int(os.environ["NERFGAUGE_FUZZ_SEED"])


def fresh_twin(test, max_examples: int | None = None):
    """A twin of the hypothesis test `test` (written `@given(data=st.data())`) that draws
    new cases from the run's fuzz seed instead of the fixed derandomized ones: same body,
    same parametrization, settings with derandomize off and `@seed(fuzz_seed())`. Bind it
    to a module-level `test_..._fresh` name; the original keeps the fixed regression cases."""
    import types

    import pytest
    from hypothesis import given, seed, settings
    from hypothesis import strategies as st

    inner = test.hypothesis.inner_test
    body = types.FunctionType(inner.__code__, inner.__globals__, f"{inner.__name__}_fresh", inner.__defaults__,
                              inner.__closure__)
    body.__qualname__, body.__module__ = f"{inner.__qualname__}_fresh", inner.__module__
    fixed = test._hypothesis_internal_use_settings
    fresh = settings(fixed, derandomize=False, database=None,
                     max_examples=fixed.max_examples if max_examples is None else max_examples)
    twin = seed(fuzz_seed())(fresh(given(data=st.data())(body)))
    twin.pytestmark = [*getattr(test, "pytestmark", []), pytest.mark.fuzz_fresh]
    return twin
