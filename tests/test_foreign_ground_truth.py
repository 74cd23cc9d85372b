"""Ground truth nerfgauge did not write (nerfgauge/core/foreign_dataset.py): NeRF-synthetic
(PNG and JPEG), nerfstudio and COLMAP text-model folders, built here in the formats' own
conventions from a small generated dataset, scored by `evaluate`; what they cannot give is
reported as unavailable; bad folders are one line, exit 2."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.colmap import quaternion_to_rotation as quaternion_to_matrix
from nerfgauge.core.images import read_png, write_png
from nerfgauge.eval.evaluate import evaluate


@pytest.fixture(scope="module")
def ours(tmp_path_factory, make_dataset):
    """primitives, 8 train / 1 val / 2 test views at 40x40."""
    return make_dataset(tmp_path_factory.mktemp("gt") / "primitives", views=8, val_views=1, test_views=2,
                        width=40, height=40)


@pytest.fixture(scope="module")
def renders(ours, tmp_path_factory):
    """Predictions for the test split in our naming (test/r_00k.png): the ground truth with a stripe."""
    pred = tmp_path_factory.mktemp("renders")
    (pred / "test").mkdir()
    for k, stem in enumerate(dataset.open_dataset(ours).cameras("test").stems):
        image = np.round(read_png(ours / (stem + ".png")) * 255).astype(np.uint8)
        image[5 + 2 * k: 12 + 2 * k, :, :3] = 70
        image[5 + 2 * k: 12 + 2 * k, :, 3] = 255
        write_png(pred / (stem + ".png"), image)
    return pred


def synthetic_copy(ours, out, jpeg=False):
    """transforms_<split>.json with camera_angle_x, extension-less file_path and
    transform_matrix only, and the images (PNG, or JPEG composited onto white)."""
    for split in ("train", "val", "test"):
        meta = json.loads((ours / f"transforms_{split}.json").read_text())
        (out / split).mkdir(parents=True)
        frames = []
        for frame in meta["frames"]:
            stem = frame["file_path"].removeprefix("./")
            if jpeg:
                rgba = read_png(ours / (stem + ".png"))
                rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
                Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(out / (stem + ".jpg"), quality=95)
            else:
                shutil.copy(ours / (stem + ".png"), out / (stem + ".png"))
            frames.append({"file_path": "./" + stem, "transform_matrix": frame["transform_matrix"]})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": meta["camera_angle_x"],
                                                                 "frames": frames}))
    return out


def colmap_copy(ours, out):
    """sparse/0/{cameras,images,points3D}.txt and images/<split>_r_00k.png, every frame of ours."""
    ds = dataset.Dataset(ours)
    intr = ds.intrinsics("train")
    (out / "images").mkdir(parents=True)
    (out / "sparse" / "0").mkdir(parents=True)
    (out / "sparse" / "0" / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        f"1 PINHOLE {intr.width} {intr.height} {intr.fx!r} {intr.fy!r} {intr.cx!r} {intr.cy!r}\n")
    lines, poses = ["# Image list with two lines of data per image:"], {}
    image_id = 1
    for split in ds.splits:
        for stem, c2w_gl in zip(ds.frames(split), ds.c2w(split)):
            name = stem.replace("/", "_") + ".png"
            shutil.copy(ours / (stem + ".png"), out / "images" / name)
            w2c = np.linalg.inv(c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0]))
            q = matrix_to_quaternion(w2c[:3, :3])
            t = w2c[:3, 3]
            lines.append(f"{image_id} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {name}")
            lines.append("")  # no 2D points
            poses["images/" + name[:-4]] = c2w_gl
            image_id += 1
    (out / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")
    (out / "sparse" / "0" / "points3D.txt").write_text("# 3D point list\n1 0.1 0.2 0.3 255 0 0 0.5\n")  # no track: the images have no 2D points
    return out, poses


def matrix_to_quaternion(R):
    """[3, 3] rotation -> (w, x, y, z), w >= 0 (Shepperd's method; a test helper)."""
    trace = np.trace(R)
    if trace > 0:
        s = 2 * np.sqrt(trace + 1)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return q if q[0] >= 0 else -q


def test_nerf_synthetic_png_without_manifest_scores_as_ours(ours, renders, tmp_path):
    folder = synthetic_copy(ours, tmp_path / "blender")
    reference = evaluate(ours, renders, out=tmp_path / "ours.json", held_out=False)
    document = evaluate(folder, renders, out=tmp_path / "theirs.json")
    for metric in ("psnr", "ssim", "psnr_foreground"):
        assert document["mean"][metric] == pytest.approx(reference["mean"][metric], abs=1e-9)
    record = document["ground_truth"]
    assert record["format"] == "nerf-synthetic"
    assert set(record["files"]) == {"transforms_train.json", "transforms_val.json", "transforms_test.json",
                                    "test/r_000.png", "test/r_001.png"}
    assert record["frames"]["test/r_000"] == "test/r_000.png"
    # what the folder cannot give: n/a with the reason, not an error
    assert document["mean"]["depth_absrel"] is None and document["notes"]["depth_absrel"].startswith("unavailable: ")
    assert "no ground-truth depth" in document["notes"]["depth_absrel"]
    assert "hit mask" in document["notes"]["opacity_iou"] and document["noise"]["psnr_ceiling"] is None
    assert "unavailable" in document["notes"]["covisible"]
    assert reference["ground_truth"] == {"format": "nerfgauge", "manifest_sha256": dataset.manifest_sha256(ours)}


def test_nerf_synthetic_jpeg_is_scored(ours, renders, tmp_path, capsys):
    folder = synthetic_copy(ours, tmp_path / "blender-jpeg", jpeg=True)
    assert main(["evaluate", str(folder), "--pred", str(renders), "--out", str(tmp_path / "m.json")]) == 0
    document = json.loads((tmp_path / "m.json").read_text())
    assert document["ground_truth"]["frames"]["test/r_001"] == "test/r_001.jpg"
    assert "test/r_001.jpg" in document["ground_truth"]["files"]
    reference = evaluate(ours, renders, out=tmp_path / "ours.json", held_out=False)
    assert abs(document["mean"]["psnr"] - reference["mean"]["psnr"]) < 1.0  # JPEG at quality 95


def test_colmap_text_model_is_scored_with_its_poses(ours, tmp_path):
    folder, poses = colmap_copy(ours, tmp_path / "colmap")
    ds = dataset.Dataset(folder)
    assert ds.foreign.format == "colmap" and ds.foreign.points.shape == (1, 3)
    stems = sorted(poses)
    assert ds.frames("test") == tuple(stems[::8])  # llffhold 8: every 8th by name
    for split in ("train", "test"):
        for stem, c2w in zip(ds.frames(split), ds.c2w(split)):
            np.testing.assert_allclose(c2w, poses[stem], atol=1e-9)
    pred = tmp_path / "pred"
    pred.mkdir()
    for stem in ds.frames("test"):  # flat, by image name
        shutil.copy(folder / ds.foreign.images[stem], pred / (stem.split("/")[-1] + ".png"))
    document = evaluate(folder, pred, out=tmp_path / "m.json")
    assert document["mean"]["psnr"] == 100.0 and document["ground_truth"]["format"] == "colmap"
    assert {"sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt"} <= set(document["ground_truth"]["files"])
    assert "every 8th" in document["ground_truth"]["split_rule"]


def test_nerfstudio_transforms_json_is_scored(ours, renders, tmp_path):
    folder = tmp_path / "ns"
    shutil.copytree(ours, folder, ignore=shutil.ignore_patterns("*.exr", "*_mask.png", "*_instance.png", "*.json"))
    shutil.copy(ours / "transforms.json", folder / "transforms.json")
    document = evaluate(folder, renders, out=tmp_path / "m.json")
    reference = evaluate(ours, renders, out=tmp_path / "ours.json", held_out=False)
    assert document["ground_truth"]["format"] == "nerfstudio"
    assert document["mean"]["psnr"] == pytest.approx(reference["mean"]["psnr"], abs=1e-9)


def _expect_one_line(capsys, argv, *fragments):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    for fragment in fragments:
        assert fragment in err, err


def test_a_foreign_folder_that_disagrees_with_its_images_is_one_line_exit_2(ours, renders, tmp_path, capsys):
    folder = synthetic_copy(ours, tmp_path / "sizes")
    Image.new("RGBA", (20, 40)).save(folder / "test" / "r_001.png")  # one image of another size
    _expect_one_line(capsys, ["evaluate", str(folder), "--pred", str(renders), "--out", str(tmp_path / "a.json")],
                     "frame test/r_001", "is 20x40", "40x40")
    folder = synthetic_copy(ours, tmp_path / "missing")
    (folder / "test" / "r_000.png").unlink()  # a frame without its image
    _expect_one_line(capsys, ["evaluate", str(folder), "--pred", str(renders), "--out", str(tmp_path / "b.json")],
                     "no image", "test/r_000")
    folder = synthetic_copy(ours, tmp_path / "intrinsics")
    meta = json.loads((folder / "transforms_test.json").read_text())
    meta.update(w=40, h=40, fl_x=10.0, fl_y=10.0, cx=20.0, cy=20.0)  # disagrees with camera_angle_x
    (folder / "transforms_test.json").write_text(json.dumps(meta))
    _expect_one_line(capsys, ["evaluate", str(folder), "--pred", str(renders), "--out", str(tmp_path / "c.json")],
                     "camera_angle_x", "fl_x is 10")
    folder, _ = colmap_copy(ours, tmp_path / "colmap-size")
    text = (folder / "sparse" / "0" / "cameras.txt").read_text().replace("PINHOLE 40 40", "PINHOLE 40 41")
    (folder / "sparse" / "0" / "cameras.txt").write_text(text)
    _expect_one_line(capsys, ["evaluate", str(folder), "--pred", str(renders), "--out", str(tmp_path / "d.json")],
                     "is 40x40, the cameras say 40x41")
    for path in (tmp_path / name for name in ("a.json", "b.json", "c.json", "d.json")):
        assert not path.exists()


def test_our_unfinished_dataset_is_still_refused(ours, tmp_path):
    folder = tmp_path / "unfinished"
    shutil.copytree(ours, folder)
    (folder / "manifest.json").unlink()
    with pytest.raises(Exception, match="incomplete"):
        dataset.Dataset(folder)


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quaternion_to_matrix(q)
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


def test_geometry_of_a_foreign_folder_with_meshes_scores_the_whole_surface(ours, tmp_path, capsys):
    """Meshes but no depth: the visible-surface test is unavailable (said so), the whole surface is scored."""
    folder = synthetic_copy(ours, tmp_path / "blender-meshes")
    shutil.copytree(ours / "meshes", folder / "meshes")
    mesh = sorted((folder / "meshes").glob("*.ply"))[0]
    out = tmp_path / "geometry.json"
    assert main(["geometry", str(folder), "--pred-mesh", str(mesh), "--samples", "2000", "-o", str(out)]) == 0
    document = json.loads(out.read_text())
    assert document["notes"]["visible_surface"].startswith("unavailable: ")
    assert "no ground-truth depth" in capsys.readouterr().out
