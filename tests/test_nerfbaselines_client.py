"""NerfBaselines itself as the client: its Blender loader reads our datasets, and its results
tooling reads the results.json that `evaluate --nerfbaselines` writes (scored under
`--protocol nerfbaselines`, their "nerf" protocol).

nerfbaselines is not a dependency (its requirements pull opencv, tensorboard and a numpy
below 2): where it is installed (`pip install --no-deps nerfbaselines`), these run; else
they are skipped, saying so.
"""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.images import read_png, write_png

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(importlib.util.find_spec("nerfbaselines") is None,
                                 reason="nerfbaselines is not installed (pip install --no-deps nerfbaselines)")]


@pytest.fixture(scope="module")
def ds(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("nb") / "primitives", views=4, val_views=1, test_views=2,
                        width=40, height=40)


def test_their_blender_loader_reads_our_dataset(ds):
    from nerfbaselines.datasets.blender import load_blender_dataset

    theirs = load_blender_dataset(str(ds), "test")
    ours = dataset.Dataset(ds)
    intr = ours.intrinsics("test")
    assert [str(p) for p in theirs["image_paths"]] == [str(ds / (s + ".png")) for s in ours.frames("test")]
    cams = theirs["cameras"]
    np.testing.assert_array_equal(cams.image_sizes[0], [intr.width, intr.height])
    np.testing.assert_allclose(cams.intrinsics[0], [intr.fx, intr.fy, intr.cx, intr.cy], rtol=1e-6)
    # their poses are OpenCV (y, z flipped) [3, 4]; ours OpenGL [4, 4]
    expected = ours.c2w("test")[:, :3, :4] @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(cams.poses, expected, atol=1e-6)
    assert theirs["metadata"]["background_color"].tolist() == [255, 255, 255]


def test_their_blender_loader_reads_a_degraded_dataset_with_the_perturbed_train_poses(tmp_path, make_dataset):
    """The extra train-frame keys (exact_transform_matrix, photometric) are passed over: their
    loader reads the train split and gets the perturbed poses the transforms hold."""
    from nerfbaselines.datasets.blender import load_blender_dataset

    ds = make_dataset(tmp_path / "degraded", views=4, val_views=1, test_views=2, width=24, height=24,
                      pose_noise_rotation=2.0, pose_noise_translation=0.05, exposure_ev=0.5, vignetting=0.2)
    theirs = load_blender_dataset(str(ds), "train")
    ours = dataset.Dataset(ds)
    expected = ours.c2w("train")[:, :3, :4] @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(theirs["cameras"].poses, expected, atol=1e-6)
    exact = np.array([f["exact_transform_matrix"] for f in json.loads((ds / "transforms_train.json").read_text())["frames"]])
    assert np.abs(exact[:, :3, 3] - ours.c2w("train")[:, :3, 3]).max() > 1e-6


def test_their_results_tooling_reads_our_results_json(ds, tmp_path, capsys):
    from nerfbaselines import io as nb_io
    from nerfbaselines import results as nb_results

    pred = tmp_path / "pred"
    (pred / "test").mkdir(parents=True)
    for k, stem in enumerate(dataset.open_dataset(ds).cameras("test").stems):
        image = np.round(read_png(ds / (stem + ".png")) * 255).astype(np.uint8)
        image[4 + k: 9 + k, :, :3] = 60
        write_png(pred / (stem + ".png"), image)
    out = tmp_path / "results.json"
    assert main(["evaluate", str(ds), "--pred", str(pred), "--out", str(tmp_path / "m.json"),
                 "--protocol", "nerfbaselines", "--nerfbaselines", str(out)]) == 0
    capsys.readouterr()
    results = json.loads(out.read_text())
    assert results["evaluation_protocol"] == "nerf"
    assert nb_results._is_scene_results(results)
    lists = nb_results.load_metrics_from_results(results)
    ours = json.loads((tmp_path / "m.json").read_text())
    np.testing.assert_allclose(lists["psnr"], [f["psnr"] for f in ours["frames"]], rtol=1e-6)
    assert nb_io.get_metrics_hash(lists) == results["metrics_sha256"]
    assert results["metrics"]["psnr"] == pytest.approx(np.mean(lists["psnr"]), abs=1e-5)
    assert "lpips_vgg" in results["metrics_raw"] or "lpips_vgg" not in ours["mean"] or ours["mean"]["lpips"] is None
    # their results tooling files it under dataset "nerfgauge", scene "primitives", our method
    listed = nb_results._list_dataset_results(tmp_path, dataset="nerfgauge")
    assert [(data["dataset"], data["render_dataset_metadata"]["scene"], data["nb_info"]["method"])
            for _, data in listed] == [("nerfgauge", "primitives", "pred")]


@pytest.mark.parametrize("split", ["train", "test"])
def test_their_load_dataset_reads_our_dataset_by_its_path(ds, split):
    """As `nerfbaselines train --data PATH` does: `load_dataset(PATH, split)` with no loader
    named. Our nb-info.json names their nerfstudio loader (both it and their colmap loader
    would claim the folder otherwise); every frame of the split, with our cameras."""
    from nerfbaselines.datasets import load_dataset

    theirs = load_dataset(str(ds), split, features=frozenset({"color"}), load_features=False)
    ours = dataset.Dataset(ds)
    intr = ours.intrinsics(split)
    assert [str(p) for p in theirs["image_paths"]] == [str(ds / (s + ".png")) for s in ours.frames(split)]
    cams = theirs["cameras"]
    np.testing.assert_array_equal(cams.image_sizes, [[intr.width, intr.height]] * len(ours.frames(split)))
    np.testing.assert_allclose(cams.intrinsics, [[intr.fx, intr.fy, intr.cx, intr.cy]] * len(ours.frames(split)),
                               rtol=1e-6)
    expected = ours.c2w(split)[:, :3, :4] @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(cams.poses, expected, atol=1e-5)
    assert theirs["metadata"]["background_color"].tolist() == [255, 255, 255]
    assert theirs["metadata"]["evaluation_protocol"] == "nerf"


def test_their_load_dataset_reads_a_non_square_dataset(tmp_path, make_dataset):
    """Their Blender loader assumes square images centred at w/2 (it would put cy at w/2);
    the nerfstudio loader that nb-info.json names reads our intrinsics as written."""
    from nerfbaselines.datasets import load_dataset

    ds = make_dataset(tmp_path / "wide", views=4, val_views=1, test_views=2, width=40, height=24)
    theirs = load_dataset(str(ds), "test", features=frozenset({"color"}), load_features=False)
    intr = dataset.Dataset(ds).intrinsics("test")
    np.testing.assert_allclose(theirs["cameras"].intrinsics[0], [intr.fx, intr.fy, 20.0, 12.0], rtol=1e-6)
    np.testing.assert_array_equal(theirs["cameras"].image_sizes[0], [40, 24])
