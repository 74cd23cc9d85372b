"""Hostile inputs against every command (RELIABILITY.md): mutated transforms, scene.json,
manifests, images, checkpoints and meshes, and faults on the output side (devices, FIFOs,
symlinks, read-only folders, a full disk).

Each case runs `nerfgauge.cli.main([...])` in-process on a fresh copy of a tiny base
fixture and is judged by `fuzzing.judge`: exit 0 with finite outputs, or exit 2 with one
stderr line; no traceback, no other exit code, nothing touched outside the output folder.
A mutation that must be refused (NaN intrinsics, a sheared pose, a path out of the
dataset, JPEG bytes in a .png, ...) is marked REFUSE and fails the case if accepted.

Mutations are drawn by hypothesis with derandomize=True (the same cases every run: the
fixed regression cases); each family is parametrized by mutation kind so a failure names
the kind. Each drawn family also has a `..._fresh` twin (at the end of the file) that draws
new cases every run from the run's fuzz seed, printed in pytest's header and summary
(`nerfgauge fuzz seed: N`); NERFGAUGE_FUZZ_SEED=N or --fuzz-seed N reruns those cases. Case counts are in
RELIABILITY.md (`pytest tests/test_fuzz_inputs.py -q` runs them all).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import shutil
import signal
import stat
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fuzzing import (
    ANY,
    REFUSE,
    Case,
    assert_judged,
    code_running_checkpoint,
    copy_tree,
    exr_bytes,
    exr_with_data_window,
    fresh_twin,
    image_bytes,
    png_declaring,
    rehash_manifest,
    run_cli,
    write_raw,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

# Examples per (family, kind, command). Small: the whole file runs in about 1-2 minutes
# on 2 cores; derandomized, so every run tries the same inputs.
FAST = dict(deadline=None, derandomize=True, database=None, phases=(Phase.explicit, Phase.generate),
            suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
N_EVAL, N_TRAIN, N_MESH = 4, 2, 1

NAN, INF = float("nan"), float("inf")
_case_numbers = itertools.count()


# --------------------------------------------------------------------------------------
# base fixtures, built once per module


@pytest.fixture(scope="module")
def base(tmp_path_factory, tiny_dataset):
    """The shared read-only inputs: tiny dataset, a 3-step run, its test renders, a
    valid PNG outside every dataset, and the folder all cases live in."""
    root = tmp_path_factory.mktemp("fuzz")
    shared = root / "shared"
    shared.mkdir()
    run = shared / "run"
    # run-full: the same, saved unpruned (after 3 steps nothing is occupied, so the pruned
    # model.pt holds no float values for the NaN and reshaping cases to reach)
    for argv in (["train", tiny_dataset, "--out", run, "--steps", "3", "--quiet"],
                 ["train", tiny_dataset, "--out", shared / "run-full", "--steps", "3", "--no-prune", "--quiet"],
                 ["render", run, "--out", shared / "pred", "--quiet"]):
        outcome = run_cli(argv, shared)
        assert outcome.code == 0, outcome
    outside = shared / "outside.png"
    shutil.copyfile(tiny_dataset / "test" / "r_000.png", outside)
    cases = root / "cases"
    cases.mkdir()
    return {"dataset": Path(tiny_dataset), "run": run, "run-full": shared / "run-full", "pred": shared / "pred",
            "outside": outside,
            "shared": (Path(tiny_dataset), shared), "cases": cases}


def new_case_folder(base, family: str) -> Path:
    folder = base["cases"] / f"{family}-{next(_case_numbers)}"
    folder.mkdir()
    return folder


def dataset_case(base, family: str, command: str):
    """A fresh folder with a copy of the dataset (and of the predictions for evaluate);
    returns (folder, dataset copy, argv, output folder)."""
    folder = new_case_folder(base, family)
    ds = copy_tree(base["dataset"], folder / "ds")
    if command == "evaluate":
        pred = copy_tree(base["pred"], folder / "pred")
        out = folder / "eval"
        return folder, ds, ["evaluate", ds, "--pred", pred, "--out", out / "metrics.json"], out
    out = folder / "run"
    return folder, ds, ["train", ds, "--out", out, "--steps", "2", "--threads", "1", "--quiet"], out


def transforms_file(command: str, data) -> str:
    """The transforms file the command reads: test for evaluate, train (or val) for train."""
    if command == "evaluate":
        return "transforms_test.json"
    return data.draw(st.sampled_from(["transforms_train.json", "transforms_train.json", "transforms_val.json"]))


# --------------------------------------------------------------------------------------
# transforms_*.json

READ_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
NOT_A_NUMBER = [NAN, INF, -INF, "x", "", None, [], {}, [1.0]]
EXTREME = [1e308, -1e308, 0, -1, 1e-300, 2**70, 20000]


def _frame(meta, data):
    frames = meta["frames"]
    return frames[data.draw(st.integers(0, len(frames) - 1), label="frame")]


def _rigid_part(matrix):
    return np.asarray(matrix, np.float64)[:3, :3]


def mutate_transforms(kind: str, meta: dict, data, folder: Path, ds: Path, outside: Path):
    """Apply one `kind` of mutation to a transforms dict in place; returns (what, expect)."""
    if kind == "delete-key":
        key = data.draw(st.sampled_from(READ_KEYS + ("camera_angle_x", "frames")), label="key")
        meta.pop(key, None)
        return f"key {key} deleted", ANY
    if kind == "key-not-a-number":
        key = data.draw(st.sampled_from(READ_KEYS), label="key")
        meta[key] = data.draw(st.sampled_from(NOT_A_NUMBER), label="value")
        return f"{key} = {meta[key]!r}", REFUSE
    if kind == "key-extreme":
        key = data.draw(st.sampled_from(READ_KEYS), label="key")
        meta[key] = data.draw(st.sampled_from(EXTREME), label="value")
        # w/h must match the images; a focal length or principal point may be odd but finite
        return f"{key} = {meta[key]!r}", REFUSE if key in ("w", "h") else ANY
    if kind == "matrix-entry":
        frame = _frame(meta, data)
        i, j = data.draw(st.integers(0, 3), label="row"), data.draw(st.integers(0, 3), label="col")
        value = data.draw(st.sampled_from([NAN, INF, -INF, "x", None, 1e308]), label="value")
        frame["transform_matrix"][i][j] = value
        # 1e308 anywhere: in R no rotation, in t beyond core.validate.BOUNDS_LIMIT
        return f"{frame['file_path']} transform_matrix[{i}][{j}] = {value!r}", REFUSE
    if kind == "matrix-sheared":
        frame = _frame(meta, data)
        shear = data.draw(st.sampled_from([0.05, 0.3, 1.0, 5.0]), label="shear")
        m = np.asarray(frame["transform_matrix"], np.float64)
        m[:3, :3] = m[:3, :3] @ np.array([[1, shear, 0], [0, 1, 0], [0, 0, 1]])
        frame["transform_matrix"] = m.tolist()
        return f"{frame['file_path']} rotation sheared by {shear}", REFUSE
    if kind == "matrix-scaled":
        frame = _frame(meta, data)
        scale = data.draw(st.sampled_from([0.0, 0.5, 2.0, -1.0, 1e-9]), label="scale")
        m = np.asarray(frame["transform_matrix"], np.float64)
        if scale == -1.0:
            m[:3, 0] *= -1  # a reflection: det -1, columns still unit and orthogonal
        else:
            m[:3, :3] *= scale
        frame["transform_matrix"] = m.tolist()
        return f"{frame['file_path']} rotation scaled by {scale}", REFUSE
    if kind == "bottom-row":
        frame = _frame(meta, data)
        row = data.draw(st.sampled_from([[1, 2, 3, 0], [0, 0, 0, 0], [0, 0, 0, 2], [0, 0, 1, 1]]), label="row")
        frame["transform_matrix"][3] = row
        return f"{frame['file_path']} bottom row {row}", REFUSE
    if kind == "matrix-shape":
        frame = _frame(meta, data)
        m = frame["transform_matrix"]
        shape = data.draw(st.sampled_from(["4x3", "flat16", "empty", "string", "5x4", "ragged"]), label="shape")
        frame["transform_matrix"] = {"4x3": [row[:3] for row in m], "flat16": sum(m, []), "empty": [],
                                     "string": "eye(4)", "5x4": m + [[0, 0, 0, 1]],
                                     "ragged": [m[0], m[1][:2], m[2], m[3]]}[shape]
        return f"{frame['file_path']} transform_matrix {shape}", REFUSE
    if kind == "file-path":
        frame = _frame(meta, data)
        # a real, valid image of the right size waits behind each escaping path
        shutil.copyfile(outside, folder / "x.png")
        target = data.draw(st.sampled_from(["../x", str(folder / "x"), "./test/../../x", "test/r_999",
                                            "", 5, None, "./" + "a" * 300]), label="file_path")
        frame["file_path"] = target
        return f"file_path = {target!r}", REFUSE
    if kind == "frames-not-a-list":
        value = data.draw(st.sampled_from([{}, "x", [1, 2], [{}], None, [{"file_path": "./test/r_000"}]]),
                          label="frames")
        meta["frames"] = value
        return f"frames = {value!r}", REFUSE
    raise AssertionError(kind)


TRANSFORM_KINDS = ("delete-key", "key-not-a-number", "key-extreme", "matrix-entry", "matrix-sheared",
                   "matrix-scaled", "bottom-row", "matrix-shape", "file-path", "frames-not-a-list")


@pytest.mark.parametrize("command", ["evaluate", "train"])
@pytest.mark.parametrize("kind", TRANSFORM_KINDS)
@given(data=st.data())
@settings(max_examples=N_TRAIN, **FAST)
def test_transforms_mutations(base, command, kind, data):
    folder, ds, argv, out = dataset_case(base, "transforms", command)
    name = transforms_file(command, data)
    meta = json.loads((ds / name).read_text())
    what, expect = mutate_transforms(kind, meta, data, folder, ds, base["outside"])
    (ds / name).write_text(json.dumps(meta))
    rehash_manifest(ds)
    assert_judged(Case(command, argv, folder, out, f"{name}: {what}", expect, base["shared"]))


@pytest.mark.parametrize("command", ["evaluate", "train"])
@given(data=st.data())
@settings(max_examples=N_EVAL, **FAST)
def test_transforms_file_bytes(base, command, data):
    """The JSON itself broken: truncated, garbage, not an object, NaN literals at the top."""
    folder, ds, argv, out = dataset_case(base, "transforms-bytes", command)
    name = transforms_file(command, data)
    text = (ds / name).read_bytes()
    kind = data.draw(st.sampled_from(["truncated", "garbage", "list", "empty", "utf16"]), label="kind")
    if kind == "truncated":
        cut = data.draw(st.integers(0, len(text) - 2), label="cut")
        raw = text[:cut]
    else:
        raw = {"garbage": data.draw(st.binary(min_size=1, max_size=64), label="bytes"),
               "list": b"[1, 2, 3]", "empty": b"", "utf16": text.decode().encode("utf-16")}[kind]
    write_raw(ds / name, raw)
    rehash_manifest(ds)
    assert_judged(Case(command, argv, folder, out, f"{name}: {kind} ({len(raw)} bytes)", REFUSE, base["shared"]))


@pytest.mark.parametrize("command", ["evaluate", "train"])
@pytest.mark.parametrize("link", ["image-out-of-dataset", "split-folder-out-of-dataset"])
def test_symlink_out_of_the_dataset_is_refused(base, command, link):
    """A frame (or the whole split folder) that is a symlink leading out of the dataset:
    the manifest matches (rehashed through the link), the path stays the same; still refused."""
    folder, ds, argv, out = dataset_case(base, "symlink", command)
    split = "test" if command == "evaluate" else "train"
    if link == "image-out-of-dataset":
        (ds / split / "r_000.png").unlink()
        (ds / split / "r_000.png").symlink_to(base["outside"])
    else:
        shutil.move(ds / split, folder / f"elsewhere-{split}")
        (ds / split).symlink_to(folder / f"elsewhere-{split}")
    rehash_manifest(ds)
    assert_judged(Case(command, argv, folder, out, f"{split} {link} symlinked", REFUSE, base["shared"]))


# --------------------------------------------------------------------------------------
# scene.json


SCENE_BOUNDS = {
    "nan": ([[NAN, 0, 0], [1, 1, 1]], REFUSE), "inf": ([[-INF, -1, -1], [1, 1, 1]], REFUSE),
    "string": ("x", REFUSE), "strings": ([["x", 0, 0], [1, 1, 1]], REFUSE),
    "min-above-max": ("swap", REFUSE), "flat": ([[0, 0, 0], [0, 0, 0]], REFUSE),
    "wrong-shape": ([[0, 0], [1, 1]], REFUSE), "empty": ([], REFUSE), "huge": ([[-1e308] * 3, [1e308] * 3], ANY),
    "missing": (None, ANY),
}


@pytest.mark.parametrize("command", ["evaluate", "train"])
@given(data=st.data())
@settings(max_examples=8, **FAST)
def test_scene_json_mutations(base, command, data):
    folder, ds, argv, out = dataset_case(base, "scene", command)
    scene = json.loads((ds / "scene.json").read_text())
    kind = data.draw(st.sampled_from(sorted(SCENE_BOUNDS) + ["needs-garbage", "file-garbage", "file-list"]),
                     label="kind")
    expect = ANY
    if kind in SCENE_BOUNDS:
        bounds, expect = SCENE_BOUNDS[kind]
        if bounds is None:
            scene.pop("bounds")
        else:
            scene["bounds"] = scene["bounds"][::-1] if bounds == "swap" else bounds
        raw = json.dumps(scene).encode()
    elif kind == "needs-garbage":
        scene["needs"] = data.draw(st.sampled_from(["x", [], {"view_dependent": "x"}, None]), label="needs")
        raw = json.dumps(scene).encode()
    else:
        raw = b"\x00\xffnot json" if kind == "file-garbage" else b"[]"
        expect = REFUSE
    if command == "evaluate" and kind in SCENE_BOUNDS:
        expect = ANY  # scoring does not need the bounds
    write_raw(ds / "scene.json", raw)
    rehash_manifest(ds)
    assert_judged(Case(command, argv, folder, out, f"scene.json {kind}", expect, base["shared"]))


# --------------------------------------------------------------------------------------
# manifest.json


def _flip_hex(text: str) -> str:
    return ("0" if text[0] != "0" else "1") + text[1:]


def _alter_entry(entry, what: str):
    """A manifest entry with its hash (or size) changed, whatever the entry's format."""
    if isinstance(entry, str):
        return _flip_hex(entry) if what == "hash" else entry
    if isinstance(entry, dict):
        entry = dict(entry)
        for key, value in entry.items():
            if what == "size" and isinstance(value, int):
                entry[key] = value + 1
            elif what == "hash" and isinstance(value, str) and re.fullmatch("[0-9a-f]{64}", value):
                entry[key] = _flip_hex(value)
        return entry
    return entry


MANIFEST_KINDS = ("hash", "size", "extra-entry", "escaping-entry", "entry-removed", "truncated", "garbage",
                  "files-not-a-dict", "deleted", "file-changed", "file-grown")


@pytest.mark.parametrize("command", ["evaluate", "train"])
@pytest.mark.parametrize("kind", MANIFEST_KINDS)
@given(data=st.data())
@settings(max_examples=N_TRAIN, **FAST)
def test_manifest_mutations(base, command, kind, data):
    folder, ds, argv, out = dataset_case(base, "manifest", command)
    path = ds / "manifest.json"
    manifest = json.loads(path.read_text())
    files = manifest["files"]
    # a file the command certainly reads (a dataset is verified as it is read: a file no
    # command reads may differ from the manifest without harm)
    read_split = "test" if command == "evaluate" else "train"
    read = re.compile(rf"^{read_split}/r_\d+(_mask\.png|_distance\.exr)$" if command == "evaluate"
                      else rf"^{read_split}/r_\d+\.png$")
    rel = data.draw(st.sampled_from(sorted(r for r in files if read.match(r) or r == f"transforms_{read_split}.json"
                                           or command == "evaluate" and re.match(r"^test/r_\d+\.png$", r))),
                    label="file")
    expect = REFUSE
    raw = None
    if kind == "hash" or kind == "size":
        altered = _alter_entry(files[rel], kind)
        if altered == files[rel]:
            pytest.skip(f"manifest entries carry no {kind}")
        files[rel] = altered
    elif kind == "extra-entry":  # lists a file that is not there, which no command reads
        files[f"{read_split}/r_999.png"] = files[rel]
        expect = ANY
    elif kind == "escaping-entry":
        shutil.copyfile(ds / rel, folder / "copy")
        files["../copy"] = files[rel]
        expect = REFUSE
    elif kind == "entry-removed":
        del files[rel]
        expect = ANY
    elif kind == "truncated":
        text = path.read_bytes()
        raw = text[:data.draw(st.integers(0, len(text) - 2), label="cut")]
    elif kind == "garbage":
        raw = data.draw(st.binary(min_size=1, max_size=64), label="bytes")
    elif kind == "files-not-a-dict":
        manifest["files"] = data.draw(st.sampled_from(["x", [], None, [rel]]), label="files")
    elif kind == "deleted":
        path.unlink()
    elif kind == "file-changed":  # same size, one byte differs, manifest not updated
        body = bytearray((ds / rel).read_bytes())
        at = data.draw(st.integers(0, len(body) - 1), label="at")
        body[at] ^= 0x01
        write_raw(ds / rel, bytes(body))
    elif kind == "file-grown":
        write_raw(ds / rel, (ds / rel).read_bytes() + b"\x00" * data.draw(st.integers(1, 64), label="n"))
    if kind != "deleted":
        write_raw(path, raw if raw is not None else json.dumps(manifest).encode())
    assert_judged(Case(command, argv, folder, out, f"manifest {kind} ({rel})", expect, base["shared"]))


# --------------------------------------------------------------------------------------
# images: dataset PNG/EXR and predictions


def _valid_png(shape, mode_kind: str) -> bytes:
    rng = np.random.default_rng(len(mode_kind))
    if mode_kind == "gray":
        return image_bytes(rng.integers(0, 256, shape[:2], dtype=np.uint8), "PNG")
    if mode_kind == "rgb":
        return image_bytes(rng.integers(0, 256, shape[:2] + (3,), dtype=np.uint8), "PNG")
    if mode_kind == "16bit":
        from PIL import Image
        import io

        buffer = io.BytesIO()
        Image.fromarray(rng.integers(0, 65536, shape[:2], dtype=np.uint16)).save(buffer, format="PNG")
        return buffer.getvalue()
    raise AssertionError(mode_kind)


def exr_channel_name_span(body: bytes) -> range:
    """The byte offsets of the first channel's name in an EXR file's header (the chlist
    attribute: its name, type, 4-byte size, then each channel's null-terminated name)."""
    marker = b"channels\x00chlist\x00"
    start = body.find(marker)
    if start < 0:
        return range(0)
    first = start + len(marker) + 4
    return range(first, body.index(b"\x00", first))


def mutate_image(kind: str, path: Path, data, is_prediction: bool):
    """Rewrite the image at `path`; returns (what, expect)."""
    body = path.read_bytes()
    png = path.suffix == ".png"
    size = (32, 32)
    if kind == "truncated":
        cut = data.draw(st.integers(0, len(body) - 1), label="cut")
        write_raw(path, body[:cut])
        return f"truncated to {cut} of {len(body)} bytes", REFUSE
    if kind == "header-byte":
        at = data.draw(st.integers(0, 32), label="at")
        flipped = bytearray(body)
        flipped[at] ^= data.draw(st.sampled_from([0x01, 0x80, 0xFF]), label="xor")
        write_raw(path, bytes(flipped))
        # a predicted depth EXR's one channel may have any name (eval/evaluate.py: "EXR: one
        # channel"), so a flip inside that name may leave a valid file: refused or read
        free = exr_channel_name_span(body) if is_prediction and not png else range(0)
        return f"header byte {at} altered", ANY if at in free else REFUSE
    if kind == "random-bytes":
        write_raw(path, data.draw(st.binary(min_size=0, max_size=2048), label="bytes"))
        return "random bytes", REFUSE
    if kind == "wrong-format":
        other = (image_bytes(np.zeros(size + (3,), np.uint8), "JPEG") if png
                 else image_bytes(np.zeros(size + (4,), np.uint8), "PNG"))
        write_raw(path, other)
        return ("JPEG" if png else "PNG") + f" bytes in {path.suffix}", REFUSE
    if kind == "huge-dimensions":
        # EXR stops at 20000 on a side: OpenEXR's binding allocates 65535^2 floats (16 GiB)
        # before it finds the file short, which would hurt the machine, not just the test
        w, h = data.draw(st.sampled_from([(20000, 20000), (1, 2**31 - 1), (2**31 - 1, 1)] +
                                         ([(65535, 65535)] if png else [])), label="dims")
        if png:
            write_raw(path, png_declaring(w, h, b"\x00" * 64))
        else:
            write_raw(path, exr_with_data_window(body, w, h))
        return f"header declares {w}x{h}", REFUSE
    if kind == "wrong-size":
        shape = data.draw(st.sampled_from([(16, 16), (32, 33), (1, 1)]), label="shape")
        if png:
            write_raw(path, image_bytes(np.zeros(shape + (4,), np.uint8), "PNG"))
        else:
            write_raw(path, exr_bytes({"Z": np.ones(shape, np.float32)}))
        return f"valid image of {shape[1]}x{shape[0]}", REFUSE
    if kind == "other-mode":  # a valid image of the right size, another pixel format
        if png:
            mode = data.draw(st.sampled_from(["gray", "rgb", "16bit"]), label="mode")
            write_raw(path, _valid_png(size, mode))
            return f"valid {mode} PNG", ANY
        channels = data.draw(st.sampled_from(["two", "rgb"]), label="channels")
        write_raw(path, exr_bytes({"Z": np.ones(size), "Y": np.ones(size)} if channels == "two"
                                  else {"R": np.ones(size), "G": np.ones(size), "B": np.ones(size)}))
        return f"EXR with {channels} channels", REFUSE
    if kind == "non-finite-pixels":
        value = data.draw(st.sampled_from([NAN, INF, -INF, 3e38]), label="value")
        depth = np.full(size, 2.0, np.float32)
        if is_prediction:  # everywhere, so it surely covers pixels that hit something
            depth[:] = value
        else:
            depth[data.draw(st.integers(0, 31), label="row"), :] = value
        write_raw(path, exr_bytes({"Z": depth}, {"nerfgauge_depth": "ray_distance"}))
        # a predicted NaN fails the evaluation (documented); in ground truth it may be
        # refused or left out of the scores, as long as every score stays finite
        return f"depth {'everywhere' if is_prediction else 'row'} = {value}", REFUSE if is_prediction and not math.isfinite(value) else ANY
    raise AssertionError(kind)


IMAGE_KINDS = ("truncated", "header-byte", "random-bytes", "wrong-format", "huge-dimensions", "wrong-size",
               "other-mode", "non-finite-pixels")
EVALUATE_IMAGES = {"ds-png": ("ds", "test/r_000.png"), "ds-mask": ("ds", "test/r_001_mask.png"),
                   "ds-depth": ("ds", "test/r_000_distance.exr"), "pred-png": ("pred", "test/r_001.png"),
                   "pred-depth": ("pred", "test/r_000_depth.exr")}


@pytest.mark.parametrize("kind", IMAGE_KINDS)
@given(data=st.data())
@settings(max_examples=N_EVAL, **FAST)
def test_image_mutations_evaluate(base, kind, data):
    folder, ds, argv, out = dataset_case(base, "image-eval", "evaluate")
    targets = sorted(t for t in EVALUATE_IMAGES if kind != "non-finite-pixels" or t.endswith("depth"))
    where, rel = EVALUATE_IMAGES[data.draw(st.sampled_from(targets), label="target")]
    path = (ds if where == "ds" else folder / "pred") / rel
    what, expect = mutate_image(kind, path, data, is_prediction=where == "pred")
    if where == "ds":
        rehash_manifest(ds)
    assert_judged(Case("evaluate", argv, folder, out, f"{where}/{rel}: {what}", expect, base["shared"]))


@pytest.mark.parametrize("kind", IMAGE_KINDS[:-1])
@given(data=st.data())
@settings(max_examples=N_TRAIN, **FAST)
def test_image_mutations_train(base, kind, data):
    folder, ds, argv, out = dataset_case(base, "image-train", "train")
    rel = data.draw(st.sampled_from(["train/r_000.png", "train/r_003.png", "val/r_000.png"]), label="target")
    what, expect = mutate_image(kind, ds / rel, data, is_prediction=False)
    rehash_manifest(ds)
    assert_judged(Case("train", argv, folder, out, f"{rel}: {what}", expect, base["shared"]))


# --------------------------------------------------------------------------------------
# checkpoints: model.pt (render) and checkpoint.pt (train --resume)


def checkpoint_case(base, command: str, pruned: bool):
    folder = new_case_folder(base, "checkpoint")
    run = copy_tree(base["run" if pruned else "run-full"], folder / "run")
    if command == "render":
        out = folder / "renders"
        return folder, run, run / "model.pt", ["render", run, "--out", out, "--quiet"], out
    return (folder, run, run / "checkpoint.pt",
            ["train", base["dataset"], "--out", run, "--steps", "5", "--resume", "--threads", "1", "--quiet"], run)


def _tensor_paths(payload, prefix=()):
    """Paths (key tuples) of every tensor in a nested payload."""
    import torch

    for key, value in payload.items():
        if isinstance(value, torch.Tensor):
            yield prefix + (key,)
        elif isinstance(value, dict):
            yield from _tensor_paths(value, prefix + (key,))


def _get(payload, keys):
    for key in keys[:-1]:
        payload = payload[key]
    return payload, keys[-1]


def mutate_checkpoint(kind: str, path: Path, data, canary: Path):
    """Rewrite the .pt at `path`; returns (what, expect)."""
    import io

    import torch

    if kind == "raw-bytes":
        body = path.read_bytes()
        how = data.draw(st.sampled_from(["random", "truncated", "empty", "flipped"]), label="how")
        if how == "random":
            raw = data.draw(st.binary(min_size=1, max_size=4096), label="bytes")
        elif how == "truncated":
            raw = body[:data.draw(st.integers(0, len(body) - 1), label="cut")]
        elif how == "empty":
            raw = b""
        else:
            flipped = bytearray(body)
            at = data.draw(st.integers(0, len(body) - 1), label="at")
            flipped[at] ^= 0xFF
            raw = bytes(flipped)
        write_raw(path, raw)
        return f"{how} bytes", ANY if how == "flipped" else REFUSE
    if kind == "code-payload":
        legacy = data.draw(st.booleans(), label="legacy pickle")
        write_raw(path, code_running_checkpoint(canary, legacy=legacy))
        return f"pickle whose __reduce__ opens a file ({'plain pickle' if legacy else 'torch zip'})", REFUSE
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if kind == "key-deleted":
        key = data.draw(st.sampled_from(sorted(payload)), label="key")
        del payload[key]
        # a key the loader can do without (or find elsewhere) may go; not these two
        what, expect = f"key {key} deleted", REFUSE if key in ("format", "version") else ANY
    elif kind == "config-value":
        config = payload["config"]
        key = data.draw(st.sampled_from(["dataset", "model", "final_resolution", "start_resolution", "threads",
                                         "feature_channels", "step_ratio", "aabb"]), label="key")
        value = data.draw(st.sampled_from(["x", None, -1, NAN, 10**12, "/nonexistent", "../../x", [], 0]),
                          label="value")
        config[key] = value
        what, expect = f"config.{key} = {value!r}", ANY
    elif kind == "wrong-shape":
        keys = data.draw(st.sampled_from(sorted(_tensor_paths(payload))), label="tensor")
        holder, last = _get(payload, keys)
        tensor = holder[last]
        how = data.draw(st.sampled_from(["drop-last", "extra-dim", "scalar", "empty"]), label="how")
        holder[last] = {"drop-last": tensor.flatten()[:-1] if tensor.numel() > 1 else tensor.flatten()[:0],
                        "extra-dim": tensor[None].repeat(2, *([1] * tensor.dim())),
                        "scalar": torch.tensor(1.0), "empty": tensor.flatten()[:0]}[how]
        # refused, or (a shape that broadcasts into the same model) rendered finite
        what, expect = f"{'.'.join(map(str, keys))} reshaped ({how}) from {tuple(tensor.shape)}", ANY
    elif kind == "wrong-dtype":
        keys = data.draw(st.sampled_from(sorted(_tensor_paths(payload))), label="tensor")
        holder, last = _get(payload, keys)
        dtype = data.draw(st.sampled_from([torch.int64, torch.float64, torch.bool, torch.uint8]), label="dtype")
        holder[last] = holder[last].to(dtype)
        what, expect = f"{'.'.join(map(str, keys))} as {dtype}", ANY
    elif kind == "non-finite":
        floating = sorted(k for k in _tensor_paths(payload) if _get(payload, k)[0][k[-1]].is_floating_point()
                          and _get(payload, k)[0][k[-1]].numel())
        keys = data.draw(st.sampled_from(floating), label="tensor")
        holder, last = _get(payload, keys)
        value = data.draw(st.sampled_from([NAN, INF, -INF]), label="value")
        tensor = holder[last].clone()
        tensor.view(-1)[data.draw(st.integers(0, max(tensor.numel() - 1, 0)), label="at")] = value
        holder[last] = tensor
        what, expect = f"{'.'.join(map(str, keys))} holds {value}", ANY
    elif kind == "scalar-value":
        key = data.draw(st.sampled_from(sorted(k for k, v in payload.items() if not isinstance(v, torch.Tensor))),
                        label="key")
        value = data.draw(st.sampled_from(["x", None, -1, NAN, 10**12, [1, 2]]), label="value")
        payload[key] = value
        what, expect = f"{key} = {value!r}", ANY if key not in ("format", "version") else REFUSE
    else:
        raise AssertionError(kind)
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_raw(path, buffer.getvalue())
    return what, expect


CHECKPOINT_KINDS = ("raw-bytes", "code-payload", "key-deleted", "config-value", "wrong-shape", "wrong-dtype",
                    "non-finite", "scalar-value")


@pytest.mark.parametrize("command", ["render", "train"])
@pytest.mark.parametrize("kind", CHECKPOINT_KINDS)
@given(data=st.data())
@settings(max_examples=N_TRAIN + 1, **FAST)
def test_checkpoint_mutations(base, command, kind, data):
    pruned = command == "train" or kind != "non-finite" and data.draw(st.booleans(), label="pruned model.pt")
    folder, run, path, argv, out = checkpoint_case(base, command, pruned)
    canary = folder / "ran-code"
    what, expect = mutate_checkpoint(kind, path, data, canary)
    assert_judged(Case(command, argv, folder, out, f"{path.name}: {what}", expect, base["shared"], canary))


# --------------------------------------------------------------------------------------
# meshes for generate mesh:PATH

BOX_OBJ = "\n".join(["v -0.5 -0.5 -0.5", "v 0.5 -0.5 -0.5", "v 0.5 0.5 -0.5", "v -0.5 0.5 -0.5",
                     "v -0.5 -0.5 0.5", "v 0.5 -0.5 0.5", "v 0.5 0.5 0.5", "v -0.5 0.5 0.5",
                     "f 1 3 2", "f 1 4 3", "f 5 6 7", "f 5 7 8", "f 1 2 6", "f 1 6 5",
                     "f 2 3 7", "f 2 7 6", "f 3 4 8", "f 3 8 7", "f 4 1 5", "f 4 5 8"]) + "\n"


def _obj_with_vertex(value: str) -> str:
    return BOX_OBJ.replace("v 0.5 0.5 0.5", f"v {value} 0.5 0.5", 1)


MESHES = {
    "random-bytes.obj": (None, REFUSE), "random-bytes.ply": (None, REFUSE), "random-bytes.stl": (None, REFUSE),
    "empty.obj": (b"", REFUSE), "nan-vertex.obj": (_obj_with_vertex("nan").encode(), REFUSE),
    "inf-vertex.obj": (_obj_with_vertex("inf").encode(), REFUSE),
    "huge-vertex.obj": (_obj_with_vertex("1e30").encode(), ANY),
    "face-out-of-range.obj": ((BOX_OBJ + "f 1 2 99\n").encode(), ANY),
    "no-faces.obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", REFUSE),
    "degenerate.obj": (b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", REFUSE),
    "ply-declares-1e9.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
                             b"property float x\nproperty float y\nproperty float z\nelement face 1\n"
                             b"property list uchar int vertex_indices\nend_header\n" + b"\x00" * 64, REFUSE),
    "stl-declares-1e9.stl": (b"\x00" * 80 + struct.pack("<I", 10**9) + b"\x00" * 100, REFUSE),
    "folder.obj": ("folder", REFUSE), "missing.obj": ("missing", REFUSE), "box.obj": (BOX_OBJ.encode(), ANY),
}


@pytest.mark.parametrize("name", sorted(MESHES))
@given(data=st.data())
@settings(max_examples=N_MESH, **FAST)
def test_mesh_inputs_to_generate(base, name, data):
    folder = new_case_folder(base, "mesh")
    body, expect = MESHES[name]
    mesh = folder / name
    if body is None:
        mesh.write_bytes(data.draw(st.binary(min_size=1, max_size=512), label="bytes"))
    elif body == "folder":
        mesh.mkdir()
    elif body != "missing":
        mesh.write_bytes(body)
    out = folder / "ds"
    argv = ["generate", f"mesh:{mesh}", "--out", out, "--res", "16", "--views", "2", "--val-views", "0",
            "--test-views", "1", "--spp", "2", "--quiet"]
    assert_judged(Case("generate", argv, folder, out, f"mesh {name}", expect, base["shared"]))


# --------------------------------------------------------------------------------------
# faults on the output side: devices, FIFOs, symlinks, a read-only folder, a full disk


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


class _Alarm:
    """Fail instead of hanging forever on a FIFO opened for writing."""

    def __enter__(self):
        def fire(signum, frame):
            raise TimeoutError("the command blocked (opened a FIFO?)")

        self.previous = signal.signal(signal.SIGALRM, fire)
        signal.alarm(30)

    def __exit__(self, *exc):
        signal.alarm(0)
        signal.signal(signal.SIGALRM, self.previous)


OUTPUT_FAULTS = ("dev-full", "dev-null", "fifo", "symlink-file", "symlink-folder", "read-only-folder")


def _output_target(fault: str, folder: Path, file_target: bool) -> Path:
    """A path for --out that is hostile in the way `fault` says. Devices are made with
    mknod inside the case folder (same numbers as /dev/full and /dev/null), so a command
    that writes beside its target writes into the test's tree, never into /dev.
    For evaluate (file_target) the hostile path is eval/metrics.json: error maps beside it
    stay in eval/, its output folder."""
    victim = folder / "victim"
    victim.mkdir()
    (victim / "keep.json").write_text("{}")
    parent = folder / "eval" if file_target else folder
    parent.mkdir(exist_ok=True)
    target = parent / ("metrics.json" if file_target else "out")
    if fault in ("dev-full", "dev-null"):
        os.mknod(target, 0o666 | stat.S_IFCHR, os.makedev(1, 7 if fault == "dev-full" else 3))
        return target
    if fault == "fifo":
        return _fifo(target)
    if fault == "symlink-file":
        target.symlink_to(victim / "keep.json")
        return target
    if fault == "symlink-folder":
        if file_target:  # evaluate: its error_maps/ folder is a link out of its output folder
            (parent / "error_maps").symlink_to(victim, target_is_directory=True)
            return target
        target.symlink_to(victim, target_is_directory=True)
        return target
    if fault == "read-only-folder":
        ro = folder / "ro"
        ro.mkdir()
        subprocess.run(["chattr", "+i", str(ro)], check=True)
        return ro / "metrics.json" if file_target else ro / "out"
    raise AssertionError(fault)


@pytest.mark.parametrize("command", ["evaluate", "train", "render", "generate"])
@pytest.mark.parametrize("fault", OUTPUT_FAULTS)
def test_hostile_output_targets(base, command, fault):
    """--out at a device, a FIFO, a symlink (to a file or a folder outside) or inside a
    read-only (immutable) folder: exit 2 with one line, the victim untouched."""
    if fault == "read-only-folder" and shutil.which("chattr") is None:
        pytest.skip("chattr not available")
    folder = new_case_folder(base, "output")
    target = _output_target(fault, folder, file_target=command == "evaluate")
    argv = {"evaluate": ["evaluate", base["dataset"], "--pred", base["pred"], "--out", target],
            "train": ["train", base["dataset"], "--out", target, "--steps", "1", "--threads", "1", "--quiet"],
            "render": ["render", base["run"], "--out", target, "--quiet"],
            "generate": ["generate", "primitives", "--out", target, "--res", "16", "--views", "1",
                         "--val-views", "0", "--test-views", "1", "--spp", "1", "--quiet"]}[command]
    # nothing may change anywhere (the command must refuse), except inside evaluate's own
    # eval/ folder; evaluate may even succeed past a linked error_maps/, as long as nothing
    # lands behind the link
    lenient = command == "evaluate" and fault == "symlink-folder"
    out = folder / ("eval" if command == "evaluate" and fault != "read-only-folder" else "nowhere")
    try:
        with _Alarm():
            assert_judged(Case(command, argv, folder, out, f"--out {fault}", ANY if lenient else REFUSE,
                               base["shared"]))
    finally:
        if fault == "read-only-folder":
            subprocess.run(["chattr", "-i", str(folder / "ro")], check=True)


@pytest.mark.slow
def test_full_disk_is_one_line_and_resumable(base, tmp_path):
    """A disk that fills up mid-run (RLIMIT_FSIZE: writes past 3 kB fail with EFBIG): exit
    2 with one line, no traceback; the same command then finishes the dataset."""
    import resource

    out = tmp_path / "ds"
    argv = [sys.executable, "-m", "nerfgauge.cli", "generate", "primitives", "--out", str(out), "--res", "16",
            "--views", "2", "--val-views", "0", "--test-views", "1", "--spp", "1", "--quiet"]

    def small_disk():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of death, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (3000, 3000))

    full = subprocess.run(argv, capture_output=True, text=True, preexec_fn=small_disk, timeout=300)
    lines = [line for line in full.stderr.splitlines() if line.strip()]
    assert full.returncode == 2 and len(lines) == 1 and lines[0].startswith("nerfgauge generate: error: "), \
        f"full disk: exit {full.returncode}, stderr {full.stderr[-600:]!r}\n  reproduce: ulimit -f 3 && {' '.join(argv[2:])}"
    again = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-600:]
    assert (out / "manifest.json").is_file()
    assert not list(out.rglob(".*.tmp*"))


# Cases the drawn examples above once found, kept as fixed examples: hypothesis's draws
# move whenever this file changes, these do not.
def _set(*keys, value=None, how=None):
    def mutate(payload):
        holder, last = _get(payload, keys)
        holder[last] = how(holder[last]) if how is not None else value
    return mutate


KNOWN_CHECKPOINTS = {
    "model.pt node_mask one byte short": ("render", _set("node_mask", "bits", how=lambda t: t[:-1])),
    "model.pt node_mask another shape": ("render", _set("node_mask", "shape", how=lambda s: s[:-1] + [s[-1] + 1])),
    "model.pt config.threads a string": ("render", _set("config", "threads", value="/nonexistent")),
    "checkpoint.pt aabb NaN": ("train", _set("model", "state", "field.aabb",
                                             how=lambda t: t.index_fill(1, __import__("torch").tensor([0]), NAN))),
    "checkpoint.pt generator as int64": ("train", _set("generator", how=lambda t: t.long())),
    "checkpoint.pt config a string": ("train", _set("config", value="x")),
}


@pytest.mark.parametrize("name", sorted(KNOWN_CHECKPOINTS))
def test_known_hostile_checkpoints(base, name):
    import io

    import torch

    command, mutate = KNOWN_CHECKPOINTS[name]
    folder, run, path, argv, out = checkpoint_case(base, command, pruned=True)
    payload = torch.load(path, map_location="cpu", weights_only=True)
    try:
        mutate(payload)
    except KeyError as missing:
        pytest.fail(f"the checkpoint format changed ({missing} is gone): update this case")
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_raw(path, buffer.getvalue())
    assert_judged(Case(command, argv, folder, out, name, ANY, base["shared"]))


# --------------------------------------------------------------------------------------
# fresh cases: every drawn family again, new inputs each run from the printed fuzz seed

test_transforms_mutations_fresh = fresh_twin(test_transforms_mutations)
test_transforms_file_bytes_fresh = fresh_twin(test_transforms_file_bytes)
test_scene_json_mutations_fresh = fresh_twin(test_scene_json_mutations)
test_manifest_mutations_fresh = fresh_twin(test_manifest_mutations)
test_image_mutations_evaluate_fresh = fresh_twin(test_image_mutations_evaluate)
test_image_mutations_train_fresh = fresh_twin(test_image_mutations_train)
test_checkpoint_mutations_fresh = fresh_twin(test_checkpoint_mutations)
test_mesh_inputs_to_generate_fresh = fresh_twin(test_mesh_inputs_to_generate)
