"""The Dataset reader's arrays against the conventions its docstring states."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nerfgauge.core import dataset
from nerfgauge.core.camera import pixel_rays
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import premultiplied_to_png_rgba, read_png


@pytest.fixture(scope="module")
def ds(tiny_dataset):
    return Dataset(tiny_dataset)


def test_splits_frames_and_scene(ds, tiny_dataset):
    assert ds.root == tiny_dataset
    assert ds.splits == ("train", "val", "test")  # the fixture has 4 / 1 / 2 views
    assert [len(ds.frames(s)) for s in ds.splits] == [4, 1, 2]
    assert ds.frames("test") == ("test/r_000", "test/r_001")
    scene = json.loads((tiny_dataset / "scene.json").read_text())
    assert ds.scene == scene
    assert ds.bounds.shape == (2, 3) and np.array_equal(ds.bounds, np.array(scene["bounds"]))
    assert (ds.bounds[0] < ds.bounds[1]).all()


def test_intrinsics_and_k(ds):
    intrinsics = ds.intrinsics("test")
    assert (intrinsics.width, intrinsics.height) == (32, 32)
    k = ds.K("test")
    assert k.dtype == np.float64 and k.shape == (3, 3)
    assert np.array_equal(k, [[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]])


def test_c2w_is_rigid_float64(ds):
    for split in ds.splits:
        c2w = ds.c2w(split)
        assert c2w.dtype == np.float64 and c2w.shape == (len(ds.frames(split)), 4, 4)
        rotation = c2w[:, :3, :3]
        assert np.abs(np.swapaxes(rotation, 1, 2) @ rotation - np.eye(3)).max() < 1e-9
        assert np.allclose(np.linalg.det(rotation), 1.0, atol=1e-9)
        assert np.array_equal(c2w[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(c2w), 1)))
    ds.c2w("test")[0, 0, 0] = 99.0  # a copy: the dataset's poses stay as read
    assert ds.c2w("test")[0, 0, 0] != 99.0


def test_images(ds, tiny_dataset):
    for index in range(2):
        image, linear = ds.image("test", index), ds.image_linear("test", index)
        assert image.shape == linear.shape == (32, 32, 4) and image.dtype == linear.dtype == np.float32
        assert 0.0 <= image.min() and image.max() <= 1.0
        assert np.array_equal(image, read_png(tiny_dataset / f"test/r_00{index}.png"))
        # The PNG is the EXR converted (straight alpha, sRGB, 8 bits) by the generator's own function.
        assert np.array_equal(np.round(image * 255).astype(np.uint8), premultiplied_to_png_rgba(linear))
        # Premultiplied: colour vanishes with coverage.
        assert np.all(linear[..., :3][linear[..., 3] == 0] == 0)


def test_depths_mask_and_normals_agree_with_the_cameras(ds):
    intrinsics = ds.intrinsics("test")
    lo, hi = ds.bounds
    for index, c2w in enumerate(ds.c2w("test")):
        distance, z = ds.depth("test", index, "distance"), ds.depth("test", index, kind="z")
        mask, normals = ds.mask("test", index), ds.normals("test", index)
        assert distance.shape == z.shape == mask.shape == (32, 32) and normals.shape == (32, 32, 3)
        assert mask.dtype == bool and distance.dtype == np.float32
        assert mask.any() and not mask.all()
        assert np.array_equal(mask, distance > 0) and np.array_equal(mask, z > 0)
        origins, directions = pixel_rays(c2w, intrinsics)
        cos_to_axis = directions @ -c2w[:3, 2]  # the camera looks along -Z
        assert np.allclose(z, distance * cos_to_axis, rtol=1e-5, atol=0)
        # Hit points (pixel centres, row 0 at the top, +Y up) lie in the scene's bounds.
        points = origins[mask] + directions[mask] * distance[mask][:, None]
        slack = 1e-4 * float(np.linalg.norm(hi - lo))
        assert np.all(points >= lo - slack) and np.all(points <= hi + slack)
        assert np.allclose(np.linalg.norm(normals[mask], axis=-1), 1.0, atol=1e-3)
        assert np.all(normals[~mask] == 0)


def test_reading_by_stem_and_by_index_is_the_same_reader(ds, tiny_dataset):
    """A dataset opened from its path reads what the open one reads, by stem or by index,
    and open_dataset hands an open Dataset back as it is."""
    opened = dataset.open_dataset(tiny_dataset)
    cameras = opened.cameras("test")
    assert cameras.stems == ds.frames("test") and np.array_equal(cameras.c2w, ds.c2w("test"))
    assert cameras.intrinsics == ds.intrinsics("test")
    stem = cameras.stems[1]
    assert np.array_equal(opened.rgba_of(stem, cameras.intrinsics), ds.image("test", 1))
    assert np.array_equal(opened.depth_of(stem, cameras.intrinsics, "z"), ds.depth("test", 1, "z"))
    assert np.array_equal(ds.mask_of(stem, cameras.intrinsics), ds.mask("test", 1))
    assert opened.root == tiny_dataset
    assert dataset.open_dataset(ds) is ds


def test_bad_requests(ds, tmp_path):
    with pytest.raises(InputError, match="unknown split 'dev'"):
        ds.frames("dev")
    with pytest.raises(InputError, match="unknown depth kind 'inverse'"):
        ds.depth("test", 0, kind="inverse")
    with pytest.raises(IndexError):
        ds.image("test", 2)
    with pytest.raises(InputError, match="not found"):
        Dataset(tmp_path / "nowhere")
    (tmp_path / "unfinished").mkdir()
    with pytest.raises(InputError, match="incomplete"):
        Dataset(tmp_path / "unfinished")


# --------------------------------------------------------------------------------------
# duplicate frames (issue 31): refused on open, so every command that reads a dataset refuses them


def with_frames(tiny_dataset, tmp_path, edit) -> "Path":
    """A copy of the tiny dataset whose transforms_<split>.json were changed by
    edit({split: document}), manifest rehashed to vouch for the edit."""
    import shutil

    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root)
    documents = {split: json.loads((root / f"transforms_{split}.json").read_text()) for split in dataset.SPLITS}
    edit(documents)
    for split, document in documents.items():
        (root / f"transforms_{split}.json").write_text(json.dumps(document))
    dataset.write_manifest(root, dataset.read_manifest(root))
    return root


def test_a_frame_listed_twice_in_a_split_is_refused(tiny_dataset, tmp_path):
    root = with_frames(tiny_dataset, tmp_path, lambda d: d["train"]["frames"].append(dict(d["train"]["frames"][1])))
    with pytest.raises(InputError, match=r"frame train/r_001 is listed twice in transforms_train\.json "
                                         r"\(frames 1 and 4\); it would be trained on or scored twice"):
        Dataset(root)


def test_a_test_frame_that_is_also_a_training_frame_is_refused(tiny_dataset, tmp_path):
    def edit(documents):  # "./train/r_000" and "train/r_000" are the same file
        documents["test"]["frames"][1]["file_path"] = "train/r_000"

    root = with_frames(tiny_dataset, tmp_path, edit)
    with pytest.raises(InputError, match=r"frame train/r_000 is listed in transforms_train\.json \(frame 0\) and in "
                                         r"transforms_test\.json \(frame 1\).*makes the scores meaningless"):
        Dataset(root)


@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_every_command_refuses_duplicate_frames_in_one_line(tiny_dataset, tmp_path, capsys, command):
    from cli_errors import one_line_exit_2
    from test_cli_reliability import snapshot

    root = with_frames(tiny_dataset, tmp_path, lambda d: d["val"]["frames"].append(dict(d["test"]["frames"][0])))
    before = snapshot(tmp_path)
    argv = {"train": ["train", root, "--out", tmp_path / "run", "--steps", "1"],
            "evaluate": ["evaluate", root, "--pred", root, "--out", tmp_path / "m.json"]}[command]
    one_line_exit_2(capsys, argv, "test/r_000", "transforms_val.json", "transforms_test.json", "list each frame once")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("fields", [{"fl_y": 1e-300}, {"fl_x": 1e-3}, {"cx": 1e12}, {"cy": -1e9}])
def test_intrinsics_whose_rays_leave_the_pinhole_are_one_line(fields):
    """A focal length or principal point that puts the image's edge more than
    MAX_RAY_TANGENT focal lengths off the axis (rays within 0.06 deg of 90, whose
    directions overflow in float arithmetic: found by a fresh fuzz seed) is refused where
    the transforms are read; a wide but real pinhole (170 deg) is not."""
    from nerfgauge.core import validate
    from nerfgauge.core.errors import InputError

    meta = {"w": 64, "h": 48, "fl_x": 80.0, "fl_y": 80.0, "cx": 32.0, "cy": 24.0}
    with pytest.raises(InputError, match="focal lengths off the axis"):
        validate.intrinsics({**meta, **fields}, "transforms_train.json")
    wide = 32.0 / math.tan(math.radians(85.0))  # 170 deg across the width
    assert validate.intrinsics({**meta, "fl_x": wide, "fl_y": wide}, "t").fx == wide


def test_a_damaged_exr_is_one_error_and_nothing_on_stderr(tmp_path, capfd):
    """OpenEXR's C library prints its own complaints about a damaged file on file
    descriptor 2 (a fresh fuzz seed found them under a command's one-line error): reading
    any EXR with one header byte zeroed either succeeds or raises InputError naming the
    file, and nothing reaches stderr."""
    from nerfgauge.core.errors import InputError
    from nerfgauge.core.images import read_exr, write_exr

    good = tmp_path / "depth.exr"
    write_exr(good, {"Z": np.linspace(0, 1, 32 * 24, dtype=np.float32).reshape(24, 32)})
    data = good.read_bytes()
    refused = 0
    for position in range(8, min(len(data), 400)):
        bad = bytearray(data)
        bad[position] = 0
        path = tmp_path / f"bad-{position}.exr"
        path.write_bytes(bytes(bad))
        try:
            read_exr(path)
        except InputError as error:
            refused += 1
            assert str(path) in str(error) and "\n" not in str(error)
    assert refused > 0
    assert capfd.readouterr().err == ""


def test_ground_truth_depth_must_be_the_formats_z_channel(tmp_path):
    """nerfgauge's ground-truth depth is one channel named "Z" (nerfgauge.core.dataset's
    format); a file whose one channel has another name (a flipped header byte made "Z" "[")
    is refused with one line, while a reader that names no channel takes it."""
    from nerfgauge.core.images import read_exr_single, write_exr

    depth = np.full((4, 5), 2.0, np.float32)
    for name in ("Z", "["):
        write_exr(tmp_path / f"{ord(name)}.exr", {name: depth})
    assert np.array_equal(read_exr_single(tmp_path / "90.exr", name="Z"), depth)
    with pytest.raises(InputError, match=r"should hold the channel 'Z', has '\['"):
        read_exr_single(tmp_path / "91.exr", name="Z")
    assert np.array_equal(read_exr_single(tmp_path / "91.exr"), depth)
