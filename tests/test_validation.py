"""Hostile or hand-edited datasets: each defect gives one InputError line (exit 2 at the CLI).

Every test copies the session's tiny dataset before editing it. After an edit that is not
itself about the manifest, `vouch` rewrites manifest.json, so the check under test (not the
manifest's) is the one that fires.
"""

from __future__ import annotations

import io
import json
import math
import shutil
import struct
import zlib

import numpy as np
import pytest
from cli_errors import one_line_exit_2
from PIL import Image, PngImagePlugin

from nerfgauge.cli import main
from nerfgauge.core import dataset, validate
from nerfgauge.core.camera import look_at
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import read_exr, read_png, write_exr


@pytest.fixture
def ds_root(tiny_dataset, tmp_path):
    """A private copy of the tiny dataset, and beside it predictions equal to its test PNGs."""
    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    pred = tmp_path / "pred" / "test"
    pred.mkdir(parents=True)
    for png in (root / "test").glob("r_???.png"):
        shutil.copy(png, pred / png.name)
    return root


def vouch(root):
    """Rewrite manifest.json for the files it lists (accepting a deliberate edit)."""
    dataset.write_manifest(root, dataset.read_manifest(root))


def edit_json(path, change):
    document = json.loads(path.read_text())
    change(document)
    path.write_text(json.dumps(document))


def one_line(capsys, argv, *expected):
    return one_line_exit_2(capsys, argv, *expected)


def evaluate_fails(capsys, root, *expected):
    return one_line(capsys, ["evaluate", str(root), "--pred", str(root.parent / "pred"),
                             "--out", str(root.parent / "metrics.json")], *expected)


def train_fails(capsys, root, *expected):
    err = one_line(capsys, ["train", str(root), "--out", str(root.parent / "run"), "--steps", "5", "--quiet"], *expected)
    assert not (root.parent / "run").exists()
    return err


def test_the_untouched_copy_evaluates(ds_root, capsys):
    # The baseline for every test below: the same copy, unedited, scores (exit 0).
    assert main(["evaluate", str(ds_root), "--pred", str(ds_root.parent / "pred"),
                 "--out", str(ds_root.parent / "metrics.json")]) == 0


# --- confined paths ----------------------------------------------------------------------


@pytest.mark.parametrize("file_path, expected", [("../elsewhere/r_000", "'..'"), ("./test/../../x/r_000", "'..'"),
                                                 ("/tmp/elsewhere/r_000", "absolute path")])
def test_frame_paths_that_leave_the_dataset_are_refused(ds_root, capsys, file_path, expected):
    outside = ds_root.parent / "elsewhere"
    outside.mkdir()
    shutil.copy(ds_root / "test/r_000.png", outside / "r_000.png")  # a readable file waits there
    edit_json(ds_root / "transforms_test.json", lambda m: m["frames"][0].update(file_path=file_path))
    vouch(ds_root)
    err = evaluate_fails(capsys, ds_root, "transforms_test.json", "frame 0", expected)
    assert file_path in err


@pytest.mark.parametrize("linked", ["test/r_000.png", "test"])
def test_a_symlink_out_of_the_dataset_is_refused(ds_root, capsys, linked):
    outside = ds_root.parent / "outside"
    shutil.move(ds_root / linked, outside)  # same bytes: the manifest alone would pass them
    (ds_root / linked).symlink_to(outside)
    evaluate_fails(capsys, ds_root, "frame test/r_000", "test/r_000.png", "outside the dataset")


def test_a_symlink_within_the_dataset_is_followed(ds_root):
    shutil.move(ds_root / "test/r_000.png", ds_root / "kept.png")
    (ds_root / "test/r_000.png").symlink_to("../kept.png")
    image = Dataset(ds_root).image("test", 0)
    assert np.array_equal(image, read_png(ds_root / "kept.png"))


def test_a_dataset_file_symlinked_out_is_refused(ds_root):
    moved = ds_root.parent / "scene.json"
    shutil.move(ds_root / "scene.json", moved)
    (ds_root / "scene.json").symlink_to(moved)
    with pytest.raises(InputError, match="scene.json resolves to .* outside the dataset"):
        Dataset(ds_root)


def test_relative_path_rules():
    assert validate.relative_path("./test//r_000", "x") == "test/r_000"
    for bad in ["", ".", "/abs", "a/../b", "..", "a\\b", 3, None]:
        with pytest.raises(InputError):
            validate.relative_path(bad, "x")


# --- poses -------------------------------------------------------------------------------


def _scaled(m):
    m[0][0] *= 1.1


def _sheared(m):
    m[0][1] += 0.2


def _mirrored(m):
    for row in range(3):
        m[row][0] = -m[row][0]


def _bottom_row(m):
    m[3] = [1, 2, 3, 0]


def _nan(m):
    m[1][3] = float("nan")


@pytest.mark.parametrize("change, expected", [(_scaled, "not a rigid"), (_sheared, "not a rigid"),
                                              (_mirrored, "det R = -1"), (_bottom_row, "bottom row"),
                                              (_nan, "NaN or inf")])
def test_non_rigid_poses_are_refused_naming_the_frame(ds_root, capsys, change, expected):
    edit_json(ds_root / "transforms_train.json", lambda m: change(m["frames"][2]["transform_matrix"]))
    vouch(ds_root)
    train_fails(capsys, ds_root, "transforms_train.json", expected, "train/r_002")


@pytest.mark.parametrize("row, col, expected", [(2, 2, "not a rigid"), (0, 1, "not a rigid"),
                                                 (2, 3, "beyond the"), (0, 3, "beyond the")])
@pytest.mark.parametrize("value", [1e308, -1e12])
def test_huge_pose_entries_are_refused_before_any_arithmetic_overflows(row, col, expected, value):
    # R^T R of a 1e308 entry overflows; a camera 1e12 units out casts to float32 as nonsense
    pose = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    pose[row, col] = value
    with np.errstate(all="raise"), pytest.raises(InputError, match=expected):
        validate.pose(pose.tolist(), "f", "w")
    pose[row, col] = 1e9 if col == 3 else pose[row, col]  # the limit itself is a place
    if col == 3:
        validate.pose(pose.tolist(), "f", "w")


def test_pose_tolerance_is_1e_4():
    pose = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert np.array_equal(validate.pose(pose.tolist(), "f", "w"), pose)
    nudged = pose.copy()
    nudged[:3, :3] *= 1 + 2e-5  # R^T R - I = 4e-5 on the diagonal, det = 1 + 6e-5: within 1e-4
    validate.pose(nudged.tolist(), "f", "w")
    nudged[:3, :3] *= 1 + 1e-4  # now 2.4e-4 off
    with pytest.raises(InputError, match="not a rigid"):
        validate.pose(nudged.tolist(), "f", "w")
    for bad in ["x", [[1, 2, 3]], [["1", 0, 0, 0]] * 4, np.eye(3).tolist()]:
        with pytest.raises(InputError, match="4x4"):
            validate.pose(bad, "f", "w")


# --- intrinsics and bounds ---------------------------------------------------------------


@pytest.mark.parametrize("field, value, expected", [
    ("fl_x", float("nan"), "fl_x must be a finite number"), ("fl_y", 0.0, "focal lengths must be > 0"),
    ("fl_x", -5.0, "focal lengths must be > 0"), ("cx", float("inf"), "cx must be a finite number"),
    ("cy", "16", "cy must be a finite number"), ("w", 32.5, "whole number"), ("h", True, "whole number"),
    ("w", 0, "outside 1..8192"), ("w", 100000, "outside 1..8192")])
def test_bad_intrinsics_are_refused(ds_root, capsys, field, value, expected):
    edit_json(ds_root / "transforms_train.json", lambda m: m.update({field: value}))
    vouch(ds_root)
    train_fails(capsys, ds_root, "transforms_train.json", expected)


def test_huge_width_and_height_fail_before_any_allocation(ds_root, capsys):
    # w = h = 100000 asked for 74.5 GiB of rays; now the transforms are refused on open.
    edit_json(ds_root / "transforms_test.json", lambda m: m.update(w=100000, h=100000))
    vouch(ds_root)
    evaluate_fails(capsys, ds_root, "w = 100000 is outside 1..8192")


def test_image_size_must_match_the_transforms(ds_root):
    # camera_angle_x follows w, so the transforms agree with themselves (validate.camera)
    edit_json(ds_root / "transforms_test.json",
              lambda m: m.update(w=40, cx=20.0, camera_angle_x=2 * math.atan(20.0 / m["fl_x"])))
    vouch(ds_root)
    with pytest.raises(InputError, match="test/r_000.png is 32x32, but the transforms say 40x32"):
        Dataset(ds_root).image("test", 0)
    with pytest.raises(InputError, match="test/r_000_distance.exr is 32x32, but the transforms say 40x32"):
        Dataset(ds_root).depth("test", 0)


@pytest.mark.parametrize("bounds, expected", [
    ([[0, 0, 0], [1, float("nan"), 1]], "holds NaN"), ("x", "bounds must be"), ([["x", 0, 0], [1, 1, 1]], "bounds must be"),
    ([[0, 0, 0], [1, 1]], "bounds must be"), ([[0, 0, 0], [1, 0, 1]], "min < max on every axis, not on y"),
    ([[0, 0, 2], [1, 1, 1]], "not on z")])
def test_bad_bounds_are_refused(ds_root, capsys, bounds, expected):
    edit_json(ds_root / "scene.json", lambda m: m.update(bounds=bounds))
    vouch(ds_root)
    train_fails(capsys, ds_root, "scene.json", expected)


@pytest.mark.parametrize("needs, expected", [
    ("fast", "needs must be an object"), ({"finest_texture_period": "x"}, "finite number"),
    ({"finest_texture_period": -0.1}, "must be > 0"), ({"view_dependent": "yes"}, "true or false")])
def test_bad_needs_are_refused(ds_root, capsys, needs, expected):
    edit_json(ds_root / "scene.json", lambda m: m.update(needs=needs))
    vouch(ds_root)
    train_fails(capsys, ds_root, "scene.json", "needs", expected)


# --- image signatures and sizes ----------------------------------------------------------


def test_jpeg_bytes_in_a_png_are_refused(ds_root, capsys):
    buffer = io.BytesIO()
    Image.open(ds_root / "test/r_000.png").convert("RGB").save(buffer, format="JPEG")
    (ds_root / "test/r_000.png").write_bytes(buffer.getvalue())
    vouch(ds_root)
    evaluate_fails(capsys, ds_root, "test/r_000.png: holds JPEG data, but its extension says PNG")


def test_png_bytes_in_an_exr_are_refused(ds_root):
    shutil.copy(ds_root / "test/r_001_mask.png", ds_root / "test/r_001_distance.exr")
    vouch(ds_root)
    with pytest.raises(InputError, match="r_001_distance.exr: holds PNG data, but its extension says EXR"):
        Dataset(ds_root).depth("test", 1)


def png_claiming(width: int, height: int) -> bytes:
    """A 1x1 gray PNG whose IHDR (CRC fixed) claims width x height: a decompression bomb's header."""
    buffer = io.BytesIO()
    Image.new("L", (1, 1)).save(buffer, format="PNG")
    data = bytearray(buffer.getvalue())
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


@pytest.fixture
def no_decoding(monkeypatch):
    """Make any PNG pixel decoding fail loudly, to show a refusal came from the header."""
    def refuse(self):
        raise AssertionError("pixels were decoded")

    monkeypatch.setattr(PngImagePlugin.PngImageFile, "load", refuse)


@pytest.mark.filterwarnings("error")  # Pillow's DecompressionBombWarning included
@pytest.mark.parametrize("side", [20000, 12000, 8193])
def test_oversized_png_is_refused_from_its_header(tmp_path, no_decoding, side):
    path = tmp_path / "bomb.png"
    path.write_bytes(png_claiming(side, side))
    with pytest.raises(InputError) as error:
        read_png(path)
    assert "bomb.png" in str(error.value) and "8192 pixels on a side" in str(error.value)
    assert "\n" not in str(error.value)


def test_the_no_decoding_guard_bites(tmp_path, no_decoding):
    path = tmp_path / "ok.png"
    path.write_bytes(png_claiming(8192, 1))  # within the limit: reaches the decoder
    with pytest.raises(AssertionError, match="decoded"):
        read_png(path)


def test_oversized_png_in_a_dataset_fails_the_evaluation(ds_root, capsys):
    (ds_root / "test/r_000.png").write_bytes(png_claiming(20000, 20000))
    vouch(ds_root)
    evaluate_fails(capsys, ds_root, "frame test/r_000", "r_000.png", "8192 pixels on a side")


def test_oversized_exr_is_refused_from_its_header(tmp_path):
    path = tmp_path / "wide.exr"
    write_exr(path, {"Z": np.zeros((1, 8193), np.float32)})
    with pytest.raises(InputError, match="wide.exr: header says 8193x1 pixels"):
        read_exr(path)
    write_exr(path, {"Z": np.zeros((1, 8192), np.float32)})
    assert read_exr(path)[0]["Z"].shape == (1, 8192)


def test_garbage_after_a_valid_signature(tmp_path):
    for name, magic in validate.MAGIC.items():
        path = tmp_path / ("junk" + name)
        path.write_bytes(magic + b"\0" * 40)
        with pytest.raises(InputError, match="junk"):
            (read_png if name == ".png" else read_exr)(path)


# --- manifest ----------------------------------------------------------------------------


def test_new_manifests_record_sizes(tiny_dataset):
    manifest = json.loads((tiny_dataset / "manifest.json").read_text())
    assert manifest["schema"] == 2 and manifest["files"]
    for rel, entry in manifest["files"].items():
        assert entry["bytes"] == (tiny_dataset / rel).stat().st_size


@pytest.mark.parametrize("content, expected", [
    (None, "is not valid JSON"), (b'{"schema": 3, "files": {}}', "schema 3"),
    (b'{"schema": 2, "files": []}', "files of type list"),
    (b'{"schema": 2, "files": {"scene.json": "00"}}', "entry 'scene.json' is malformed"),
    (b'{"schema": 1, "files": {"scene.json": "zz"}}', "entry 'scene.json' is malformed"),
    (b'{"schema": 2, "files": {"../x": {"sha256": "' + b"0" * 64 + b'", "bytes": 1}}}', "'..'")])
def test_garbled_manifest_is_one_line(ds_root, capsys, content, expected):
    path = ds_root / "manifest.json"
    path.write_bytes(path.read_bytes()[:20] if content is None else content)
    evaluate_fails(capsys, ds_root, "manifest.json", expected)


def test_changed_file_is_named(ds_root, tiny_dataset, capsys):
    path = ds_root / "test/r_001_mask.png"
    data = bytearray(path.read_bytes())
    data[-5] ^= 1  # same size, other bytes: the IEND chunk's name, after the pixels
    path.write_bytes(bytes(data))
    evaluate_fails(capsys, ds_root, "test/r_001_mask.png changed since the manifest was written (sha256 differs)")
    unverified = Dataset(ds_root, verify_hashes=False).mask("test", 1)  # only the hash would have seen it
    assert np.array_equal(unverified, Dataset(tiny_dataset).mask("test", 1))
    path.write_bytes(bytes(data) + b"\0")
    with pytest.raises(InputError, match=r"r_001_mask.png changed since the manifest was written \(\d+ bytes"):
        Dataset(ds_root, verify_hashes=False).mask("test", 1)  # sizes are checked even without the hash


def test_edited_transforms_are_caught_by_the_manifest(ds_root, capsys):
    edit_json(ds_root / "transforms_test.json", lambda m: m["frames"].pop())
    evaluate_fails(capsys, ds_root, "transforms_test.json changed since the manifest was written")


def test_files_outside_the_manifest_are_not_read(ds_root):
    manifest = json.loads((ds_root / "manifest.json").read_text())
    del manifest["files"]["test/r_000_zdepth.exr"]
    (ds_root / "manifest.json").write_text(json.dumps(manifest))
    ds = Dataset(ds_root)
    ds.depth("test", 0, "distance")
    with pytest.raises(InputError, match="r_000_zdepth.exr is not listed in .*manifest.json"):
        ds.depth("test", 0, "z")


def test_schema_1_manifests_are_still_read(ds_root):
    manifest = json.loads((ds_root / "manifest.json").read_text())
    old = {"schema": 1, "files": {rel: entry["sha256"] for rel, entry in manifest["files"].items()}}
    (ds_root / "manifest.json").write_text(json.dumps(old))
    assert dataset.read_manifest(ds_root)["scene.json"].size is None
    ds = Dataset(ds_root)
    assert ds.image("test", 0).shape == (32, 32, 4)
    path = ds_root / "test/r_000.png"
    path.write_bytes(path.read_bytes() + b"\0")  # no size to compare: the hash catches it
    with pytest.raises(InputError, match="r_000.png changed since the manifest was written \\(sha256"):
        ds.image("test", 0)
    assert dataset.verify_manifest(ds_root) == ["test/r_000.png"]


@pytest.mark.parametrize("value", [float("inf"), float("nan"), -1.0])
def test_ground_truth_depth_outside_the_convention_is_refused_naming_the_file(ds_root, value):
    """A ground-truth depth is finite and >= 0 (0 = miss); an inf row reached co-visibility's
    unprojection as points at infinity (exit 3, found by the fresh fuzz cases)."""
    path = ds_root / "test" / "r_000_distance.exr"
    channels, header = read_exr(path)
    depth = channels["Z"].copy()
    depth[3, :] = value
    path.unlink()
    write_exr(path, {"Z": depth}, {"nerfgauge_depth": "ray_distance"})
    vouch(ds_root)
    with np.errstate(all="raise"), pytest.raises(InputError, match="r_000_distance.exr: ground-truth depth holds"):
        Dataset(ds_root).depth("test", 0)
