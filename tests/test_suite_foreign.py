"""Suites with folder entries: ground truth nerfgauge did not write (a NeRF-synthetic folder:
camera_angle_x only, extension-less file_path, PNG and JPEG images) beside a procedural scene.
`suite generate` records the folder's identity instead of rendering it; `suite evaluate`,
`suite report` and read_results check it; what it cannot give is unavailable, not an error."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest
from PIL import Image

from nerfgauge.cli import main
from nerfgauge.core.files import read_json
from nerfgauge.core.images import read_png
from nerfgauge.orchestrate.suite.definition import SUITE_MANIFEST, files_sha256, load_suite
from suite_toml import suite_toml
from test_suite import one_line_error, run

LEGO = {"id": "lego", "folder": "gt/lego"}
PRIMITIVES = {"scene": "primitives", "seed": 0}


def suite(procedural: bool, scenes=None) -> str:
    """A 16x16 suite holding the foreign folder gt/lego (after the procedural scene when asked)."""
    return suite_toml("tiny-fg", {"width": 16, "height": 16, "views": 4, "val_views": 1, "test_views": 2, "spp": 2},
                      {"steps": 10}, scenes if scenes is not None else ([PRIMITIVES] if procedural else []) + [LEGO],
                      protocol={"baselines": ["nearest", "lightfield-nearest"]})


def synthetic_copy(ours, out):
    """A NeRF-synthetic folder from one of our datasets: transforms_<split>.json with
    camera_angle_x and extension-less file_path only; test images PNG, the others JPEG."""
    for split in ("train", "val", "test"):
        meta = json.loads((ours / f"transforms_{split}.json").read_text())
        (out / split).mkdir(parents=True)
        frames = []
        for frame in meta["frames"]:
            stem = frame["file_path"].removeprefix("./")
            if split == "test":
                shutil.copy(ours / (stem + ".png"), out / (stem + ".png"))
            else:
                rgba = read_png(ours / (stem + ".png"))
                rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
                Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(out / (stem + ".jpg"), quality=95)
            frames.append({"file_path": "./" + stem, "transform_matrix": frame["transform_matrix"]})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": meta["camera_angle_x"],
                                                                 "frames": frames}))
    return out


@pytest.fixture(scope="module")
def lego_source(tmp_path_factory, make_dataset):
    """Our dataset the foreign folder is made from (16x16, 4 train / 1 val / 2 test)."""
    return make_dataset(tmp_path_factory.mktemp("src") / "lego", views=4, val_views=1, test_views=2,
                        width=16, height=16, spp=2)


def make_suite(root, lego_source, procedural=True):
    """root/tiny-fg.toml and root/gt/lego (the folder entry, relative to the .toml)."""
    synthetic_copy(lego_source, root / "gt" / "lego")
    toml = root / "tiny-fg.toml"
    toml.write_text(suite(procedural))
    return toml


def own_images(suite_dir, lego, out):
    """Predictions in our naming (<id>/test/r_00k.png): each entry's own test PNGs, and the
    procedural scene's own ray-distance EXRs (so the depth columns exist)."""
    for entry_id, root in (("primitives", suite_dir / "datasets" / "primitives"), ("lego", lego)):
        if not root.is_dir():
            continue
        (out / entry_id / "test").mkdir(parents=True)
        for path in sorted((root / "test").glob("r_???*")):
            if path.name.endswith((".png", "_distance.exr")) and not path.name.endswith(("_mask.png", "_instance.png")):
                shutil.copy(path, out / entry_id / "test" / path.name)
    return out


@pytest.fixture(scope="module")
def generated(tmp_path_factory, lego_source):
    root = tmp_path_factory.mktemp("fg")
    toml = make_suite(root, lego_source)
    out = root / "suite"
    assert main(["suite", "generate", str(toml), "--out", str(out)]) == 0
    return toml, out, root / "gt" / "lego"


def test_folder_entry_is_recorded_not_rendered(generated):
    toml, out, lego = generated
    suite = load_suite(toml)
    # the definition holds the folder as written: the suite's hash does not depend on where it lives
    assert suite.definition()["scenes"][1] == {"id": "lego", "folder": "gt/lego"}
    assert suite.definition()["scenes"][0] == {"id": "primitives", "scene": "primitives", "seed": 0,
                                               "dataset": suite.scenes[0].dataset}
    manifest = read_json(out / SUITE_MANIFEST)
    record = manifest["datasets"]["lego"]
    assert "manifest_sha256" not in record and record["format"] == "nerf-synthetic"
    on_disk = {p.relative_to(lego).as_posix() for p in lego.rglob("*") if p.is_file()}
    assert set(record["files"]) == on_disk  # the transforms and every frame's image (PNG and JPEG)
    for rel, digest in record["files"].items():
        assert digest == hashlib.sha256((lego / rel).read_bytes()).hexdigest()
    assert record["ground_truth_sha256"] == files_sha256(record["files"])
    assert "no ground-truth depth" in record["unavailable"]["depth"]
    assert "manifest_sha256" in manifest["datasets"]["primitives"]
    assert not (out / "datasets" / "lego").exists()


def test_folder_entry_scores_and_leaderboard_shows_depth_unavailable(generated, tmp_path, capsys):
    toml, out, lego = generated
    pred = own_images(out, lego, tmp_path / "pred")
    code, _, err = run(capsys, "suite", "evaluate", toml, out, "--method", "mirror", "--pred", pred)
    assert code == 0, err
    result = read_json(out / "results" / "mirror" / "result.json")
    manifest = read_json(out / SUITE_MANIFEST)
    assert result["datasets"]["lego"]["ground_truth_sha256"] == manifest["datasets"]["lego"]["ground_truth_sha256"]
    assert result["datasets"]["primitives"]["manifest_sha256"] == manifest["datasets"]["primitives"]["manifest_sha256"]
    metrics = read_json(out / result["datasets"]["lego"]["metrics"])
    assert metrics["mean"]["psnr"] == 100.0 and metrics["mean"]["ssim"] == pytest.approx(1.0)  # its own PNGs
    assert metrics["mean"]["depth_absrel"] is None
    read = metrics["ground_truth"]["files"]  # what evaluate read and hashed: the recorded files
    assert {"transforms_test.json", "test/r_000.png", "test/r_001.png"} <= set(read)
    assert all(manifest["datasets"]["lego"]["files"][rel] == digest for rel, digest in read.items())

    code, _, err = run(capsys, "suite", "report", out)
    assert code == 0, err
    board = read_json(out / "leaderboard.json")
    assert board["scenes"] == ["primitives", "lego"]
    lego_values = board["methods"]["mirror"]["scenes"]["lego"]["values"]
    assert lego_values["psnr"] == 100.0
    assert "depth_absrel" in board["columns"]  # defined on the procedural scene
    assert lego_values["depth_absrel"] is None and lego_values["opacity_iou"] is None
    assert board["methods"]["mirror"]["scenes"]["primitives"]["values"]["depth_absrel"] is not None
    assert board["methods"]["mirror"]["scenes_scored"]["depth_absrel"] == 1
    assert "no ground-truth depth" in board["unavailable"]["lego"]["depth_absrel"]
    text = (out / "leaderboard.md").read_text()
    section = text.split("## lego", 1)[1].split("\n## ", 1)[0]
    depth_col = [c.strip() for c in section.splitlines()[2].split("|")].index("depth AbsRel ↓")
    mirror_row = next(line for line in section.splitlines() if line.startswith("| mirror"))
    assert [c.strip() for c in mirror_row.split("|")][depth_col] == "–"
    assert "Unavailable on this ground truth" in section and "no ground-truth depth" in section
    assert "no ground-truth depth" in (out / "leaderboard.html").read_text()


def test_changed_folder_is_refused_with_one_line(tmp_path, lego_source, capsys):
    toml = make_suite(tmp_path, lego_source, procedural=False)
    out = tmp_path / "suite"
    code, _, err = run(capsys, "suite", "generate", toml, "--out", out)
    assert code == 0, err
    recorded = read_json(out / SUITE_MANIFEST)["datasets"]["lego"]["ground_truth_sha256"]
    lego = tmp_path / "gt" / "lego"
    pred = own_images(out, lego, tmp_path / "pred")
    code, _, err = run(capsys, "suite", "evaluate", toml, out, "--method", "mirror", "--pred", pred)
    assert code == 0, err
    # one test image edited after suite generate (same size, one pixel)
    png = lego / "test" / "r_001.png"
    image = np.asarray(Image.open(png)).copy()
    image[0, 0, 0] ^= 1
    Image.fromarray(image).save(png)
    code, _, err = run(capsys, "suite", "evaluate", toml, out, "--method", "other", "--pred", pred)
    one_line_error(code, err, "changed since suite generate", recorded, "test/r_001.png")
    now = err.split("its files hash to ", 1)[1].split(",", 1)[0]
    assert len(now) == 64 and now != recorded
    assert not (out / "results" / "other").exists()
    code, _, err = run(capsys, "suite", "report", out)  # read_results checks the folder the same way
    one_line_error(code, err, "changed since suite generate", recorded, now)
    assert not (out / "leaderboard.json").exists()
    code, _, err = run(capsys, "suite", "generate", toml, "--out", out)  # not re-recorded silently
    one_line_error(code, err, "changed since suite generate", recorded, now, "--overwrite")
    code, _, err = run(capsys, "suite", "generate", toml, "--out", out, "--overwrite")
    assert code == 0, err
    assert read_json(out / SUITE_MANIFEST)["datasets"]["lego"]["ground_truth_sha256"] == now
    code, _, err = run(capsys, "suite", "evaluate", toml, out, "--method", "other", "--pred", pred)
    assert code == 0, err


@pytest.mark.parametrize("entry, words", [
    ('id = "x"\nfolder = "gt/nowhere"', ("scenes[0]", "not found")),
    ('folder = "gt/lego"\nseed = 0', ("scenes[0]", "unknown field 'seed'")),
    ('folder = "ours"', ("scenes[0]", "is a nerfgauge dataset")),
    ('folder = ""', ("scenes[0]", "folder must be a path")),
])
def test_bad_folder_entries_are_one_line(tmp_path, lego_source, capsys, entry, words):
    shutil.copytree(lego_source, tmp_path / "ours")
    (tmp_path / "gt" / "lego").mkdir(parents=True)
    toml = tmp_path / "bad.toml"
    toml.write_text(suite(False, scenes=[]) + "\n[[scenes]]\n" + entry + "\n")
    code, _, err = run(capsys, "suite", "generate", toml, "--out", tmp_path / "out")
    one_line_error(code, err, *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_suite_run_skips_methods_a_folder_cannot_serve_with_the_reason(tmp_path, lego_source, capsys):
    toml = make_suite(tmp_path, lego_source)
    out = tmp_path / "suite"
    code, _, err = run(capsys, "suite", "run", toml, "--out", out)
    assert code == 0, err
    board = read_json(out / "leaderboard.json")
    assert set(board["methods"]["compact-nerf"]["scenes"]) == {"primitives"}
    assert "manifest" in board["methods"]["compact-nerf"]["skipped"]["lego"]
    assert "bounds" in board["methods"]["nearest"]["skipped"]["lego"]
    section = (out / "leaderboard.md").read_text().split("## lego", 1)[1].split("\n## ", 1)[0]
    assert "| nearest | n/a: needs the scene's bounds" in section


def test_nerfstudio_folder_entry(tmp_path, lego_source, capsys):
    """A nerfstudio folder (transforms.json, paths with extensions) as a folder entry."""
    folder = tmp_path / "gt" / "lego"
    shutil.copytree(lego_source, folder, ignore=shutil.ignore_patterns("*.exr", "*_mask.png", "*_instance.png",
                                                                       "*.json", ".nerfgauge*", "meshes", "sparse"))
    shutil.copy(lego_source / "transforms.json", folder / "transforms.json")
    toml = tmp_path / "tiny-fg.toml"
    toml.write_text(suite(False))
    out = tmp_path / "suite"
    code, _, err = run(capsys, "suite", "generate", toml, "--out", out)
    assert code == 0, err
    record = read_json(out / SUITE_MANIFEST)["datasets"]["lego"]
    assert record["format"] == "nerfstudio" and "transforms.json" in record["files"]
    pred = own_images(out, folder, tmp_path / "pred")
    code, _, err = run(capsys, "suite", "evaluate", toml, out, "--method", "mirror", "--pred", pred)
    assert code == 0, err
    code, _, err = run(capsys, "suite", "report", out)
    assert code == 0, err
    values = read_json(out / "leaderboard.json")["methods"]["mirror"]["scenes"]["lego"]["values"]
    assert values["psnr"] == 100.0 and values["depth_absrel"] is None
