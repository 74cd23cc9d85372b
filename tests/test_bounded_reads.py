"""Reads that are bounded, structure that is checked, one camera validator: the third
hostile round (issue 47), grouped by fault class.

- TestSizeBeforeRead: every file's size comes from the file system (fstat on the opened
  descriptor) before it is read: against the manifest for our datasets, against a stated
  cap elsewhere (JSON, COLMAP text, an image's cap from its header); hashing streams.
- TestDecompressionBombs: an image header declaring a huge size, in every reader (ours and
  foreign, ground truth and predictions, PNG, JPEG and EXR), is one line before decoding;
  Pillow is opened in one place only, which turns its bomb warning and error into one line.
- TestColmapStructure: a COLMAP text model whose line structure is off is one line naming
  the line; pycolmap is the oracle (what it reads we read the same, what it refuses we refuse).
- TestPerFrameCameras: nerfstudio's per-frame camera keys are honoured or refused, never ignored.
- TestEmptySplit: a split with nothing to score is one line, exit 2.
- TestForeignIntrinsics: foreign cameras get the checks ours get, by the same function.

Every refusal is judged whole: exit 2, exactly one stderr line, and nothing in the case's
folder (dataset, predictions, output target) created, deleted or changed.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from fuzzing import exr_bytes, exr_with_data_window, png_declaring, rehash_manifest, run_cli, snapshot, \
    snapshot_changes
from PIL import Image
from test_foreign_ground_truth import synthetic_copy  # a NeRF-synthetic folder: camera_angle_x, no manifest

from nerfgauge.core import colmap_text, dataset, images, validate
from nerfgauge.core.distortion import Distortion
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import sha256_file

REPO = Path(__file__).resolve().parents[1]
GIB = 1 << 30


@pytest.fixture(scope="module")
def ours(tmp_path_factory, make_dataset):
    """The issue's dataset: primitives, 8 train / 1 val / 3 test views at 32x32."""
    return make_dataset(tmp_path_factory.mktemp("gt") / "ds", views=8, val_views=1, test_views=3,
                        width=32, height=32)


@pytest.fixture
def case(tmp_path, ours):
    """A folder holding a copy of the dataset (ds/) and of its test PNGs as predictions (p/)."""
    shutil.copytree(ours, tmp_path / "ds")
    (tmp_path / "p").mkdir()
    for png in sorted((ours / "test").glob("r_[0-9][0-9][0-9].png")):
        shutil.copy(png, tmp_path / "p" / png.name)
    return tmp_path


def refused(folder: Path, argv, *fragments) -> str:
    """`nerfgauge ARGV` run in `folder`: exit 2, one stderr line holding every fragment,
    nothing under `folder` changed. Returns the line."""
    before = snapshot([folder])
    outcome = run_cli(argv, folder)
    changes = snapshot_changes(before, snapshot([folder]))
    assert outcome.escaped is None, outcome.escaped
    lines = outcome.stderr.strip().splitlines()
    assert outcome.code == 2 and len(lines) == 1, (outcome.code, outcome.stderr)
    assert lines[0].startswith(f"nerfgauge {argv[0]}: error: "), lines[0]
    assert all(fragment in lines[0] for fragment in fragments), lines[0]
    assert changes == [], changes
    return lines[0]


def evaluate_refused(folder: Path, data: str, *fragments, pred: str = "p", extra=()) -> str:
    return refused(folder, ["evaluate", data, "--pred", pred, "--out", "m.json", *extra], *fragments)


def nerfstudio_copy(ours: Path, out: Path, edit=None) -> Path:
    """A nerfstudio folder: our transforms.json (edited by `edit(meta)`) and the images."""
    shutil.copytree(ours, out, ignore=shutil.ignore_patterns("manifest.json", ".nerfgauge*", "transforms_*.json",
                                                             "sparse", "images"))
    meta = json.loads((ours / "transforms.json").read_text())
    if edit is not None:
        edit(meta)
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def colmap_copy(ours: Path, out: Path) -> Path:
    """The dataset's own COLMAP export (sparse/0/*.txt and images/, the train views)."""
    out.mkdir(parents=True)
    shutil.copytree(ours / "sparse", out / "sparse")
    shutil.copytree(ours / "images", out / "images")
    return out


def jpeg_declaring(width: int, height: int) -> bytes:
    """A JPEG whose frame header (SOF0, 3 components) declares width x height, and nothing else."""
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, height, width, 3) + bytes.fromhex("012200021101031101")
    return b"\xff\xd8" + sof + b"\xff\xd9"


def sparse_file(path: Path, size: int) -> None:
    """Grow `path` to `size` bytes without writing them (a hole: no disk, no time)."""
    os.truncate(path, size)


# --------------------------------------------------------------------------------------------


class TestSizeBeforeRead:
    # `nerfgauge ARGV` as a child process: its exit code, stderr, and peak resident memory
    # (getrusage's ru_maxrss, KiB on Linux: what /usr/bin/time -f %M reports).
    PEAK_SCRIPT = ("import json, resource, subprocess, sys\n"
                   "run = subprocess.run([sys.executable, '-m', 'nerfgauge.cli'] + sys.argv[1:], stderr=subprocess.PIPE,"
                   " text=True)\n"
                   "print(json.dumps({'code': run.returncode, 'stderr': run.stderr,"
                   " 'peak_kib': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))\n")

    def run_measured(self, folder, *argv) -> dict:
        result = subprocess.run([sys.executable, "-c", self.PEAK_SCRIPT, *argv], cwd=folder, capture_output=True,
                                text=True, timeout=600, check=True)
        return json.loads(result.stdout.strip().splitlines()[-1])

    @pytest.mark.slow
    def test_the_issues_2_gib_file_is_refused_on_its_size_in_little_memory(self, case):
        """`truncate -s 2G d01/test/r_001.png` (the manifest says 1005 bytes): refused from
        fstat, unread. Was 2.4 GB of memory; now the refusal's peak is within 32 MiB of the
        same command refused before any image is read (a missing prediction folder), both
        measured with getrusage in fresh processes."""
        target = case / "ds" / "test" / "r_001.png"
        listed = dataset.read_manifest(case / "ds")["test/r_001.png"].size
        baseline = self.run_measured(case, "evaluate", "ds", "--pred", "missing", "--out", "m.json")
        sparse_file(target, 2 * GIB)
        refusal = self.run_measured(case, "evaluate", "ds", "--pred", "p", "--out", "m.json")
        lines = refusal["stderr"].strip().splitlines()
        assert refusal["code"] == 2 and len(lines) == 1, refusal["stderr"]
        assert f"(2147483648 bytes, manifest says {listed})" in lines[0]
        peak, before_any = refusal["peak_kib"] / 1024, baseline["peak_kib"] / 1024
        print(f"peak {peak:.0f} MiB refusing a 2 GiB file; {before_any:.0f} MiB refusing before any image is read")
        assert peak - before_any < 32, (peak, before_any)
        assert not (case / "m.json").exists()

    @pytest.mark.parametrize("rel", ["test/r_001.png", "test/r_001_distance.exr", "test/r_001_mask.png",
                                     "transforms_test.json", "scene.json", "test/r_001_noise.json"])
    def test_any_file_of_ours_past_its_manifest_size_is_refused_unread(self, case, rel):
        sparse_file(case / "ds" / rel, 10 * GIB)  # 10 GiB: 10 GB of memory if it were read
        evaluate_refused(case, "ds", rel, "changed since the manifest was written (10737418240 bytes")

    def test_a_schema_1_manifest_without_sizes_still_bounds_an_image_by_its_header(self, case):
        """Schema 1 records no sizes: the cap an image's header implies applies (32x32 RGBA:
        4 x 4,128 bytes + 16 MiB)."""
        manifest = json.loads((case / "ds" / "manifest.json").read_text())
        sparse_file(case / "ds" / "test" / "r_001.png", 2 * GIB)
        manifest = {"schema": 1, "files": {rel: entry["sha256"] for rel, entry in manifest["files"].items()}}
        (case / "ds" / "manifest.json").write_text(json.dumps(manifest))
        evaluate_refused(case, "ds", "r_001.png", "more than a 32x32 PNG can hold", "16 MiB")

    @pytest.mark.parametrize("kind", ["image", "transforms", "colmap-text", "prediction-png", "prediction-exr",
                                      "prediction-jpeg"])
    def test_files_without_a_manifest_are_bounded_by_a_stated_cap(self, case, ours, kind):
        """Foreign ground truth and predictions: 2 GiB behind a valid head, refused from fstat."""
        data, pred = "blender", "p"
        synthetic_copy(ours, case / "blender")
        if kind == "image":  # a valid 32x32 PNG, then a hole: its header caps it at 16 MiB
            target, fragments = case / "blender" / "test" / "r_001.png", ("more than a 32x32 PNG can hold",)
        elif kind == "transforms":
            target, fragments = case / "blender" / "transforms_test.json", ("above the limit of 64 MiB",)
        elif kind == "colmap-text":
            data = "colmap"
            colmap_copy(ours, case / "colmap")
            target, fragments = case / "colmap" / "sparse" / "0" / "images.txt", ("above the limit of 256 MiB",)
        else:
            suffix = kind.split("-")[1].replace("jpeg", "jpg")
            pred = "q"
            (case / "q").mkdir()
            rgba = np.zeros((32, 32, 4), np.float32)
            for k in range(3):
                name = case / "q" / f"r_{k:03d}.{suffix}"
                if suffix == "exr":
                    name.write_bytes(exr_bytes({"R": rgba[..., 0], "G": rgba[..., 1], "B": rgba[..., 2]}))
                else:
                    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(name)
            target = case / "q" / f"r_001.{suffix}"
            fragments = (f"more than a 32x32 {'EXR' if suffix == 'exr' else 'JPEG' if suffix == 'jpg' else 'PNG'}",)
        sparse_file(target, 2 * GIB)
        evaluate_refused(case, data, target.name, *fragments, pred=pred)

    @pytest.mark.slow
    def test_a_fifo_in_place_of_a_file_is_refused_without_waiting_for_a_writer(self, case):
        """open() on a FIFO blocks until a writer comes; the readers open without blocking
        and refuse what is not a regular file (a subprocess, so a regression times out)."""
        target = case / "ds" / "test" / "r_001.png"
        target.unlink()
        os.mkfifo(target)
        result = subprocess.run([sys.executable, "-m", "nerfgauge.cli", "evaluate", "ds", "--pred", "p", "--out",
                                 "m.json"], cwd=case, capture_output=True, text=True, timeout=300)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1, result.stderr
        assert "not a regular file" in lines[0] and "r_001.png" in lines[0]

    def test_verify_manifest_compares_sizes_before_hashing(self, case, monkeypatch):
        hashed = []
        monkeypatch.setattr(dataset, "sha256_file", lambda path: hashed.append(Path(path).as_posix()) or sha256_file(path))
        sparse_file(case / "ds" / "test" / "r_001.png", 2 * GIB)
        assert dataset.verify_manifest(case / "ds") == ["test/r_001.png"]
        assert not [path for path in hashed if path.endswith("/test/r_001.png")]
        assert [path for path in hashed if path.endswith("/test/r_000.png")]

    def test_a_header_behind_large_metadata_is_still_found(self, tmp_path):
        """The header is read in growing steps (4 KiB, 16 KiB, ...): a JPEG whose frame header
        follows 260 KB of EXIF segments reads as Pillow reads it; past 16 MiB it is refused."""
        import io
        buffer = io.BytesIO()
        pixels = np.random.default_rng(0).integers(0, 256, (20, 30, 3), np.uint8)
        Image.fromarray(pixels).save(buffer, "JPEG", quality=95)
        data = buffer.getvalue()
        segment = b"\xff\xe1" + struct.pack(">H", 65000) + b"\0" * 64998
        path = tmp_path / "exif.jpg"
        path.write_bytes(data[:2] + segment * 4 + data[2:])
        assert images.image_header(path) == images.ImageHeader("JPEG", 30, 20, 3, 1800)
        np.testing.assert_array_equal(images.read_jpeg(path), np.asarray(Image.open(io.BytesIO(data))) / np.float32(255))
        path.write_bytes(data[:2] + segment * 260 + data[2:])
        with pytest.raises(InputError, match="no image header within its first 16 MiB"):
            images.image_header(path)

    def test_hashing_streams(self, tmp_path):
        """sha256_file holds one 1 MiB block at a time, not the file (traced by tracemalloc)."""
        path = tmp_path / "big"
        path.write_bytes(b"\0")
        sparse_file(path, 64 << 20)
        tracemalloc.start()
        try:
            digest = sha256_file(path)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        import hashlib
        assert digest == hashlib.sha256(b"\0" * (64 << 20)).hexdigest()
        assert peak < 4 << 20, peak


# --------------------------------------------------------------------------------------------


class TestDecompressionBombs:
    @pytest.mark.parametrize("side", [60000, 10000])
    @pytest.mark.parametrize("layout", ["nerf-synthetic-png", "nerf-synthetic-jpeg", "colmap-png", "colmap-jpeg"])
    def test_a_foreign_header_declaring_a_huge_image_is_one_line(self, case, ours, layout, side):
        """The issue's 60000 x 60000 (a DecompressionBombError traceback) and 10000 x 10000
        (Pillow's warning: two more stderr lines), refused from the header alone."""
        fmt, kind = layout.rsplit("-", 1)
        bomb = png_declaring(side, side) if kind == "png" else jpeg_declaring(side, side)
        if fmt == "colmap":
            folder = colmap_copy(ours, case / "foreign")
            target = folder / "images" / f"r_002.{kind.replace('jpeg', 'jpg')}"
            if kind == "jpeg":
                (folder / "images" / "r_002.png").unlink()
                text = (folder / "sparse" / "0" / "images.txt").read_text().replace("r_002.png", "r_002.jpg")
                (folder / "sparse" / "0" / "images.txt").write_text(text)
        else:
            folder = synthetic_copy(ours, case / "foreign")
            target = folder / "test" / f"r_001.{kind.replace('jpeg', 'jpg')}"
            if kind == "jpeg":
                (folder / "test" / "r_001.png").unlink()
        target.write_bytes(bomb)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            evaluate_refused(case, "foreign", target.name, f"header says {side}x{side} pixels",
                             "refused before decoding")
        assert not [w for w in caught if issubclass(w.category, Image.DecompressionBombWarning)]

    def test_the_10000_pixel_warning_case_prints_one_line_from_the_command(self, case, ours):
        """The warning case end to end in a fresh process (pytest would swallow a warning)."""
        folder = synthetic_copy(ours, case / "foreign")
        (folder / "test" / "r_001.png").write_bytes(png_declaring(10000, 10000))
        result = subprocess.run([sys.executable, "-m", "nerfgauge.cli", "evaluate", "foreign", "--pred", "p",
                                 "--out", "m.json"], cwd=case, capture_output=True, text=True, timeout=300)
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
        assert "header says 10000x10000" in result.stderr

    @pytest.mark.parametrize("kind", ["png", "jpg", "exr", "ours-exr"])
    def test_predictions_and_our_exr_declaring_a_huge_image_are_one_line(self, case, kind):
        if kind == "ours-exr":  # ground-truth depth of ours, manifest rehashed to match
            target = case / "ds" / "test" / "r_001_distance.exr"
            target.write_bytes(exr_with_data_window(exr_bytes({"Z": np.zeros((8, 8), np.float32)}), 60000, 60000))
            rehash_manifest(case / "ds")
        elif kind == "jpg":  # JPEG predictions: a plain folder of them (the "folder" format)
            for png in sorted((case / "p").glob("*.png")):
                Image.open(png).convert("RGB").save(png.with_suffix(".jpg"))
                png.unlink()
            target = case / "p" / "r_001.jpg"
            target.write_bytes(jpeg_declaring(60000, 60000))
        else:
            target = case / "p" / f"r_001.{kind}"
            (case / "p" / "r_001.png").unlink()
            target.write_bytes(png_declaring(60000, 60000) if kind == "png" else
                               exr_with_data_window(exr_bytes({"R": np.zeros((8, 8), np.float32)}), 60000, 60000))
        evaluate_refused(case, "ds", "r_001", "header says 60000x60000 pixels")

    def test_open_pillow_turns_the_bomb_warning_and_error_into_one_line(self):
        """Pillow itself warns at 10000 x 10000 and raises at 60000 x 60000 (checked, so this
        test can fail); the one opener turns both into InputError. Textures go through it."""
        from nerfgauge.scenes.assets import read_image

        for side, pillow_says in ((10000, Image.DecompressionBombWarning), (60000, Image.DecompressionBombError)):
            data = png_declaring(side, side)
            with warnings.catch_warnings():
                warnings.simplefilter("error", Image.DecompressionBombWarning)
                with pytest.raises(pillow_says):
                    import io
                    Image.open(io.BytesIO(data))
            with pytest.raises(InputError, match="decompression bomb") as error:
                images.open_pillow(data, f"x{side}.png")
            assert "\n" not in str(error.value)
            with pytest.raises(InputError, match=f"cannot read texture t.png: .*{side * side} pixels"):
                read_image(Path("t.png"), data)

    def test_image_open_occurs_only_in_core_images(self):
        """Lint: no Image.open (nor a Pillow plugin's own constructor, which skips the bomb
        check) in the package outside nerfgauge/core/images.py's open_pillow."""
        pattern = re.compile(r"\bImage\.open\(|ImageFile\(|\bImagePlugin\.\w+ImageFile\b")
        found = []
        for folder in ("nerfgauge", "eval", "nerf", "generate", "scenes"):
            for path in sorted((REPO / folder).rglob("*.py")):
                if path == REPO / "nerfgauge" / "core" / "images.py":
                    continue
                for number, line in enumerate(path.read_text().splitlines(), start=1):
                    if pattern.search(line.split("#")[0]):
                        found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()}")
        assert found == [], found
        source = (REPO / "nerfgauge" / "core" / "images.py").read_text()
        assert len(pattern.findall(re.sub(r'"""[\s\S]*?"""|#[^\n]*', "", source))) == 1  # open_pillow's call


# --------------------------------------------------------------------------------------------


def pycolmap_verdict(folder: Path):
    """pycolmap's reading of the text model in `folder` (its .txt files alone: pycolmap
    prefers the .bin files our export writes beside them): the Reconstruction, or the
    refusal's text."""
    pycolmap = pytest.importorskip("pycolmap")
    with tempfile.TemporaryDirectory() as text_only:
        for name in ("cameras.txt", "images.txt", "points3D.txt"):
            shutil.copy(folder / name, text_only)
        try:
            return pycolmap.Reconstruction(text_only)
        except Exception as error:  # pycolmap raises ValueError, IndexError, RuntimeError
            return f"{type(error).__name__}: {error}"


def image_lines(text: str) -> list:
    return [line for line in text.split("\n") if line and not line.startswith("#")]


def _rewrite(folder: Path, name: str, text: str) -> None:
    (folder / "sparse" / "0" / name).write_text(text)


def _read(folder: Path, name: str) -> str:
    return (folder / "sparse" / "0" / name).read_text()


def with_observations(folder: Path) -> None:
    """Give image 1 two 2D points, one seeing 3D point 1 (and its track saying so), and
    image 2 one, seeing nothing: a model with the cross references to check."""
    lines = _read(folder, "images.txt").split("\n")
    first = next(i for i, line in enumerate(lines) if line.startswith("1 "))
    second = next(i for i, line in enumerate(lines) if line.startswith("2 "))
    lines[first + 1], lines[second + 1] = "3.5 4.5 1 10.25 11.5 -1", "7.0 8.0 -1"
    _rewrite(folder, "images.txt", "\n".join(lines))
    points = [line + (" 1 0" if line.startswith("1 ") else "") for line in _read(folder, "points3D.txt").split("\n")]
    _rewrite(folder, "points3D.txt", "\n".join(points))


def _break(folder: Path, damage: str) -> str:
    """Apply one kind of damage to the model; returns the fragment our refusal must name."""
    images_text, points_text = _read(folder, "images.txt"), _read(folder, "points3D.txt")
    heads = image_lines(images_text)
    head = [line for line in heads if line.startswith("1 ")][0]  # image 1: two 2D points (with_observations)
    bare = [line for line in heads if line.startswith("3 ")][0]  # image 3: an empty POINTS2D line
    if damage == "issue-no-empty-lines":  # grep -v '^$': images 1 and 2 keep theirs, image 4 is read as 3's
        _rewrite(folder, "images.txt", "\n".join(line for line in images_text.split("\n") if line) + "\n")
        return "images.txt line 10: expected the POINTS2D line of image 3"
    if damage == "last-image-without-points":
        _rewrite(folder, "images.txt", images_text.rstrip("\n") + "\n")
        return "has no POINTS2D line (the file ends"
    if damage == "comment-as-points":
        _rewrite(folder, "images.txt", images_text.replace(bare + "\n\n", bare + "\n# points\n", 1))
        return "got a comment"
    if damage == "points-not-triples":
        _rewrite(folder, "images.txt", images_text.replace(bare + "\n\n", bare + "\n1.0 2.0\n", 1))
        return "got 2 fields"
    if damage == "image-id-twice":
        _rewrite(folder, "images.txt", images_text + head.replace("r_000.png", "r_extra.png") + "\n\n")
        return "image id 1 is given twice"
    if damage == "image-name-twice":
        _rewrite(folder, "images.txt", images_text + "99" + head[1:] + "\n\n")
        return "image r_000.png is listed twice"
    if damage == "camera-id-twice":
        _rewrite(folder, "cameras.txt", _read(folder, "cameras.txt") + "1 PINHOLE 32 32 40 40 16 16\n")
        return "camera 1 is given twice"
    if damage == "camera-missing":
        _rewrite(folder, "images.txt", images_text.replace(head, " ".join(head.split()[:8] + ["7"] + head.split()[9:]), 1))
        return "names camera 7"
    if damage == "point-id-twice":
        first = image_lines(points_text)[0]
        _rewrite(folder, "points3D.txt", points_text + first + "\n")
        return f"3D point {first.split()[0]} is given twice"
    if damage == "points2d-name-a-missing-3d-point":
        _rewrite(folder, "images.txt", images_text.replace(bare + "\n\n", bare + "\n1.0 2.0 999999\n", 1))
        return "name 3D point 999999"
    if damage == "track-names-a-missing-image":
        _rewrite(folder, "points3D.txt", points_text.rstrip("\n") + " 42 0\n")
        return "is seen by image 42"
    if damage == "track-names-a-missing-2d-point":
        _rewrite(folder, "points3D.txt", points_text.rstrip("\n") + " 1 5\n")
        return "is 2D point 5 of image 1, which has 2"
    if damage == "track-of-odd-length":
        _rewrite(folder, "points3D.txt", points_text.rstrip("\n") + " 1\n")
        return "has a track of 1 numbers"
    raise AssertionError(damage)


# damage pycolmap refuses too (the rest it reads wrongly or leniently: see colmap_text's docstring)
PYCOLMAP_REFUSES = {"image-id-twice", "camera-id-twice", "camera-missing", "point-id-twice", "points-not-triples",
                    "track-names-a-missing-image", "track-names-a-missing-2d-point"}
DAMAGE = sorted(PYCOLMAP_REFUSES | {"issue-no-empty-lines", "last-image-without-points", "comment-as-points",
                                    "image-name-twice", "points2d-name-a-missing-3d-point", "track-of-odd-length"})


class TestColmapStructure:
    def test_the_issues_images_txt_without_its_empty_lines_is_refused_naming_the_line(self, case, ours):
        """Read before as every second image (4 of 8, exit 0); pycolmap reads it so too."""
        folder = colmap_copy(ours, case / "col")
        text = _read(folder, "images.txt")
        _rewrite(folder, "images.txt", "\n".join(line for line in text.split("\n") if line) + "\n")
        verdict = pycolmap_verdict(folder / "sparse" / "0")
        assert not isinstance(verdict, str) and verdict.num_images() == 4  # the silent wrong result we refuse
        line = evaluate_refused(case, "col", "images.txt line 6", "POINTS2D line of image 1", "got 10 fields")
        assert re.search(r"'2 [-0-9.]+ ", line), line  # shows the image line found in its place

    @pytest.mark.parametrize("damage", DAMAGE)
    def test_a_damaged_model_is_one_line_naming_its_line(self, case, ours, damage):
        folder = colmap_copy(ours, case / "col")
        with_observations(folder)
        fragment = _break(folder, damage)
        verdict = pycolmap_verdict(folder / "sparse" / "0")
        assert isinstance(verdict, str) == (damage in PYCOLMAP_REFUSES), verdict  # what pycolmap says, pinned
        line = evaluate_refused(case, "col", fragment)
        assert re.search(r"\.txt line \d+", line), line

    @pytest.mark.parametrize("variant", ["as-exported", "with-observations", "ids-out-of-order", "blank-lines"])
    def test_a_model_pycolmap_reads_reads_the_same_here(self, case, ours, variant):
        folder = colmap_copy(ours, case / "col")
        if variant != "as-exported":
            with_observations(folder)
        text = _read(folder, "images.txt")
        if variant == "ids-out-of-order":  # COLMAP writes its images in any order
            comments = "\n".join(line for line in text.split("\n") if line.startswith("#"))
            records = re.findall(r"^(\d+ .*)\n(.*)$", text, re.M)  # (image line, POINTS2D line)
            assert len(records) == 8, records
            _rewrite(folder, "images.txt", comments + "\n" + "".join(f"{h}\n{p}\n" for h, p in reversed(records)))
        if variant == "blank-lines":  # blank lines where a record may start are skipped, as COLMAP does
            _rewrite(folder, "images.txt", text.replace("\n\n", "\n\n\n\n"))
        reference = pycolmap_verdict(folder / "sparse" / "0")
        assert not isinstance(reference, str), reference
        ds = dataset.Dataset(folder)
        by_name = {image.name: image for image in reference.images.values()}
        stems = [stem for split in ds.splits for stem in ds.frames(split)]
        assert sorted(f"images/{name}"[:-4] for name in by_name) == sorted(stems)
        for split in ds.splits:
            for stem, c2w in zip(ds.frames(split), ds.c2w(split)):
                pose = by_name[stem.removeprefix("images/") + ".png"].cam_from_world()
                w2c_cv = np.vstack([pose.matrix(), [0, 0, 0, 1]])
                np.testing.assert_allclose(c2w, np.linalg.inv(w2c_cv) @ np.diag([1.0, -1, -1, 1]), atol=1e-9)
        theirs = np.array(sorted(point.xyz.tolist() for point in reference.points3D.values()))
        np.testing.assert_allclose(np.array(sorted(ds.foreign.points.tolist())), theirs, atol=1e-12)
        camera = next(iter(reference.cameras.values()))
        intrinsics = ds.intrinsics("train")
        assert (intrinsics.width, intrinsics.height) == (camera.width, camera.height)
        np.testing.assert_allclose([intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy], camera.params)

    @pytest.mark.parametrize("model, params", [
        ("SIMPLE_RADIAL", [40.0, 16.2, 15.7, -0.08]),
        ("RADIAL", [40.0, 16.2, 15.7, -0.08, 0.01]),
        ("OPENCV", [40.0, 41.0, 16.2, 15.7, -0.08, 0.01, 0.002, -0.001]),
        ("FULL_OPENCV", [40.0, 41.0, 16.2, 15.7, -0.08, 0.01, 0.002, -0.001, 0.003, 0.0, 0.0, 0.0]),
        ("OPENCV_FISHEYE", [30.0, 31.0, 16.2, 15.7, 0.05, -0.01, 0.002, -0.0005]),
    ])
    def test_distorted_cameras_project_as_pycolmap_projects(self, case, ours, model, params):
        """A distorted COLMAP camera is honoured: the split's Distortion and intrinsics map
        camera points to the pixels pycolmap's Camera.img_from_cam gives (float32 there)."""
        pycolmap = pytest.importorskip("pycolmap")
        folder = colmap_copy(ours, case / "col")
        _rewrite(folder, "cameras.txt", f"1 {model} 32 32 {' '.join(repr(p) for p in params)}\n")
        ds = dataset.Dataset(folder)
        cameras = ds.cameras("train")
        assert cameras.distortion is not None and cameras.distortion.model == (
            "fisheye" if model == "OPENCV_FISHEYE" else "opencv")
        rng = np.random.default_rng(0)
        points = np.concatenate([rng.uniform(-0.4, 0.4, (50, 2)), np.ones((50, 1))], axis=1) * rng.uniform(1, 3, (50, 1))
        theirs = pycolmap.Camera(model=model, width=32, height=32, params=params).img_from_cam(points)
        xd, yd = cameras.distortion.distort(points[:, 0] / points[:, 2], points[:, 1] / points[:, 2])
        i = cameras.intrinsics
        np.testing.assert_allclose(np.stack([i.fx * xd + i.cx, i.fy * yd + i.cy], axis=1), theirs, atol=2e-4)

    def test_a_line_longer_than_the_line_cap_is_refused_before_it_is_split(self, case, ours):
        """A POINTS2D line of 17 MiB (each number would become a Python object)."""
        folder = colmap_copy(ours, case / "col")
        text = _read(folder, "images.txt")
        head = [line for line in image_lines(text) if line.startswith("1 ")][0]
        _rewrite(folder, "images.txt", text.replace(head + "\n\n", head + "\n" + "1 1 -1 " * ((17 << 20) // 7) + "\n", 1))
        evaluate_refused(case, "col", "images.txt line 6", "lines of at most 16 MiB")

    def test_full_opencv_with_a_rational_term_is_refused_naming_it(self, case, ours):
        folder = colmap_copy(ours, case / "col")
        _rewrite(folder, "cameras.txt", "1 FULL_OPENCV 32 32 40 40 16 16 0 0 0 0 0 0.1 0 0\n")
        evaluate_refused(case, "col", "cameras.txt line 1", "k4=0.1")


# --------------------------------------------------------------------------------------------


def _frames(meta: dict, prefix: str) -> list:
    return [frame for frame in meta["frames"] if frame["file_path"].startswith(prefix)]


class TestPerFrameCameras:
    def test_per_frame_distortion_is_honoured_when_a_split_shares_it(self, case, ours):
        def edit(meta):
            for frame in _frames(meta, "test/"):
                frame.update(k1=0.05, p2=0.001)
        ds = dataset.Dataset(nerfstudio_copy(ours, case / "ns", edit))
        assert ds.cameras("test").distortion == Distortion("opencv", k1=0.05, p2=0.001)
        assert ds.cameras("train").distortion is None

    def test_per_frame_intrinsics_alone_are_honoured(self, case, ours):
        reference = dataset.Dataset(ours).intrinsics("test")

        def edit(meta):
            keys = {key: meta.pop(key) for key in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
            for frame in meta["frames"]:
                frame.update(keys)
        assert dataset.Dataset(nerfstudio_copy(ours, case / "ns", edit)).intrinsics("test") == reference

    @pytest.mark.parametrize("key, value", [("k1", 0.05), ("fl_x", 50.0), ("cx", 17.0), ("p2", 0.001),
                                            ("camera_model", "OPENCV_FISHEYE"), ("k4", 0.01)])
    def test_a_frame_whose_camera_differs_from_its_splits_is_refused_naming_the_key(self, case, ours, key, value):
        """Was ignored for the distortion keys (scored as a pinhole, exit 0)."""
        def edit(meta):
            meta["camera_model"] = "OPENCV_FISHEYE" if key == "k4" else meta["camera_model"]
            _frames(meta, "test/r_001")[0][key] = value
        nerfstudio_copy(ours, case / "ns", edit)
        evaluate_refused(case, "ns", f"frame test/r_001 has {key}={value!r}", "one camera per split")

    @pytest.mark.parametrize("edit, fragment", [
        (lambda meta: meta.update(camera_model="PINHOLE", k1=0.1), "k1=0.1 under camera_model PINHOLE"),
        (lambda meta: (meta.pop("camera_model"), meta.update(k2=0.1)), "k2=0.1 under camera_model (none given)"),
        (lambda meta: meta.update(fisheye_crop_radius=10.0), "fisheye_crop_radius is not read"),
        (lambda meta: meta.update(camera_model="EQUIRECTANGULAR"), "camera_model must be PINHOLE, OPENCV"),
        (lambda meta: meta.update(k1=-2.0), "folds the 32x32 image"),
    ])
    def test_camera_keys_that_would_be_ignored_are_refused(self, case, ours, edit, fragment):
        nerfstudio_copy(ours, case / "ns", edit)
        evaluate_refused(case, "ns", fragment)

    def test_our_own_transforms_get_the_same_per_frame_rule(self, case):
        meta = json.loads((case / "ds" / "transforms_test.json").read_text())
        meta["frames"][2]["k1"] = 0.05
        (case / "ds" / "transforms_test.json").write_text(json.dumps(meta))
        rehash_manifest(case / "ds")
        evaluate_refused(case, "ds", "transforms_test.json: frame 2 has k1=0.05")


# --------------------------------------------------------------------------------------------


class TestEmptySplit:
    @pytest.mark.parametrize("layout", ["ours", "nerf-synthetic", "nerfstudio", "missing-split"])
    def test_a_split_with_no_frames_is_not_a_success(self, case, ours, layout):
        """Was scored as a success with no frames (exit 0, means of nothing)."""
        data, split = "ds", "test"
        if layout == "ours":
            meta = json.loads((case / "ds" / "transforms_test.json").read_text())
            (case / "ds" / "transforms_test.json").write_text(json.dumps({**meta, "frames": []}))
            rehash_manifest(case / "ds")
        elif layout == "nerf-synthetic":
            data = "blender"
            synthetic_copy(ours, case / "blender")
            meta = json.loads((case / "blender" / "transforms_test.json").read_text())
            (case / "blender" / "transforms_test.json").write_text(json.dumps({**meta, "frames": []}))
        elif layout == "nerfstudio":
            data = "ns"
            nerfstudio_copy(ours, case / "ns", lambda meta: meta.update(test_filenames=[]))
        else:  # a split the folder does not have at all
            data, split = "blender", "val"
            synthetic_copy(ours, case / "blender")
            (case / "blender" / "transforms_val.json").unlink()
        evaluate_refused(case, data, f"split {split} of", "has no frames", extra=("--split", split))


# --------------------------------------------------------------------------------------------


class TestForeignIntrinsics:
    """One validator (nerfgauge.core.validate.camera) for ours and every foreign format: the
    same hostile camera is refused with the same reason, whichever file states it."""

    def _ours(self, case, values):
        meta = json.loads((case / "ds" / "transforms_test.json").read_text())
        meta.update(values)
        (case / "ds" / "transforms_test.json").write_text(json.dumps(meta))
        rehash_manifest(case / "ds")
        return "ds"

    def _nerfstudio(self, case, ours, values):
        nerfstudio_copy(ours, case / "ns", lambda meta: meta.update(values))
        return "ns"

    def _colmap(self, case, ours, values):
        folder = colmap_copy(ours, case / "col")
        merged = {"w": 32, "h": 32, "fl_x": 40.0, "fl_y": 40.0, "cx": 16.0, "cy": 16.0} | values
        _rewrite(folder, "cameras.txt", "1 PINHOLE {w} {h} {fl_x!r} {fl_y!r} {cx!r} {cy!r}\n".format(**merged))
        return "col"

    @pytest.mark.parametrize("values, reason", [
        ({"fl_y": 1e-300}, "focal lengths off the axis"),
        ({"w": 100000}, "w = 100000 is outside 1..8192"),
        ({"cx": 1e6}, "focal lengths off the axis"),
        ({"fl_x": -40.0}, "focal lengths must be > 0"),
    ])
    def test_a_hostile_camera_is_refused_alike_in_every_format(self, case, ours, values, reason):
        lines = []
        for name, make in (("ours", lambda: self._ours(case, {**values, "camera_angle_x": 0.7})),
                           ("nerfstudio", lambda: self._nerfstudio(case, ours, values)),
                           ("colmap", lambda: self._colmap(case, ours, values))):
            lines.append(evaluate_refused(case, make(), reason))
        assert len(lines) == 3

    def test_camera_angle_x_near_pi_is_refused_as_ours_would_be(self, case, ours):
        """Was accepted for NeRF-synthetic: its focal length came from the angle unchecked."""
        synthetic_copy(ours, case / "blender")
        meta = json.loads((case / "blender" / "transforms_test.json").read_text())
        (case / "blender" / "transforms_test.json").write_text(json.dumps({**meta, "camera_angle_x": 3.14159}))
        evaluate_refused(case, "blender", "transforms_test.json", "focal lengths off the axis")

    def test_our_camera_angle_x_must_agree_with_fl_x_as_foreign_ones_must(self, case):
        angle = 2 * math.atan(16 / 40.0)  # fl_x 40 at w 32; the dataset's fl_x differs
        self._ours(case, {"camera_angle_x": angle})
        evaluate_refused(case, "ds", "camera_angle_x", "means fl_x 40")

    def test_a_colmap_camera_that_folds_its_image_is_refused(self, case, ours):
        folder = colmap_copy(ours, case / "col")
        _rewrite(folder, "cameras.txt", "1 OPENCV 32 32 20 20 16 16 -0.9 0 0 0\n")
        evaluate_refused(case, "col", "cameras.txt line 1", "folds the 32x32 image")


def test_validate_camera_names_the_key_and_both_frames():
    frames = [{"fl_x": 10.0}, {"fl_x": 10.0}, {"fl_x": 11.0}]
    meta = {"w": 8, "h": 8, "fl_y": 10.0, "cx": 4.0, "cy": 4.0}
    with pytest.raises(InputError, match=r"t.json: frame c has fl_x=11.0 but frame a has 10.0"):
        validate.camera(meta, frames, "t.json", ["a", "b", "c"])
    intrinsics, distortion = validate.camera(meta, frames[:2], "t.json")
    assert (intrinsics.fx, distortion) == (10.0, None)
    assert colmap_text.MAX_TEXT_BYTES == 256 << 20 and images.IMAGE_METADATA_BYTES == 16 << 20
