"""Splits that test extrapolation (issue 35, item 6): held-out sectors, test views at other
distances, sparse view lists, the evaluator's interpolation/extrapolation gap, and
training our NeRF on a sparse list."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.generate import holdout
from nerfgauge.generate.pipeline import GenerateConfig, plan

SMALL = dict(scene="primitives", views=24, val_views=4, test_views=6, width=32, height=32, spp=4)


def azimuth(c2w, centre):
    d = c2w[:, :3, 3] - centre
    return np.degrees(np.arctan2(d[:, 1], d[:, 0]))


def elevation(c2w, centre):
    d = c2w[:, :3, 3] - centre
    return np.degrees(np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1)))


def centre_of(the_plan):
    return (the_plan.scene.aabb[0] + the_plan.scene.aabb[1]) / 2


@pytest.mark.parametrize("sampling", ["fibonacci", "random"])
@pytest.mark.parametrize("sector", ["azimuth:0:60", "azimuth:330:390", "azimuth:-30:30"])
def test_azimuth_sector_holds_out_test_views(sector, sampling):
    the_plan = plan(GenerateConfig(**SMALL, sampling=sampling, holdout=sector))
    lo, hi = (float(x) for x in sector.split(":")[1:])
    centre = centre_of(the_plan)
    inside = lambda az: np.mod(az - lo, 360) <= hi - lo  # noqa: E731
    for split in ("train", "val"):
        assert not inside(azimuth(the_plan.poses[split], centre)).any(), split
    assert [len(the_plan.poses[s]) for s in ("train", "val", "test")] == [24, 4, 6]
    frames = the_plan.extrapolation["frames"]
    test_az = azimuth(the_plan.poses["test"], centre)
    groups = [f["group"] for f in frames]
    assert groups == ["extrapolation"] * 3 + ["interpolation"] * 3  # ceil(6/2) in the sector, the rest outside
    assert inside(test_az[:3]).all() and not inside(test_az[3:]).any()
    assert [f["name"] for f in frames] == the_plan.stems["test"]
    # every camera at the layout's radius, in its elevation band, looking at the centre
    for split in ("train", "val", "test"):
        c2w = the_plan.poses[split]
        assert np.allclose(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1), the_plan.radius, rtol=1e-12)
        assert ((elevation(c2w, centre) >= 10 - 1e-9) & (elevation(c2w, centre) <= 75 + 1e-9)).all()
        forward = -c2w[:, :3, 2]
        to_centre = centre - c2w[:, :3, 3]
        assert np.allclose(np.cross(forward, to_centre), 0, atol=1e-9)


def test_elevation_sector_and_sphere_layout():
    the_plan = plan(GenerateConfig(**SMALL, holdout="elevation:60:90"))
    centre = centre_of(the_plan)
    assert (elevation(the_plan.poses["train"], centre) < 60).all()
    assert (elevation(the_plan.poses["test"][:3], centre) >= 60 - 1e-9).all()
    # a sector inside the band leaves two pieces, above and below it
    the_plan = plan(GenerateConfig(**(SMALL | {"views": 40}), layout="sphere", holdout="elevation:-20:20"))
    train = elevation(the_plan.poses["train"], the_plan.scene.aabb.mean(axis=0))
    assert ((train < -20) | (train > 20)).all() and (train < -20).any() and (train > 20).any()


def test_sector_without_train_views_is_one_line_exit_2(capsys, tmp_path):
    out = tmp_path / "ds"
    line = one_line_exit_2(capsys, ["generate", "primitives", "--out", out, "--views", "4", "--res", "32",
                                    "--holdout", "elevation:0:90"], "--holdout elevation:0:90 leaves no training view")
    assert "10..75" in line and not out.exists()
    with pytest.raises(InputError, match="no camera direction"):
        plan(GenerateConfig(**SMALL, holdout="elevation:80:90"))  # the band 10..75 never reaches it
    for bad in ("azimuth:60:0", "tilt:0:10", "azimuth:0:360", "elevation:-100:0", "azimuth:0"):
        with pytest.raises(InputError, match="--holdout"):
            plan(GenerateConfig(**SMALL, holdout=bad))
    with pytest.raises(InputError, match="hemisphere or sphere"):
        plan(GenerateConfig(**SMALL, layout="orbit", holdout="azimuth:0:60"))


def test_test_scales_put_views_at_radius_over_scale():
    the_plan = plan(GenerateConfig(**SMALL, test_scales=(0.5, 1, 2)))
    centre, n = centre_of(the_plan), SMALL["test_views"]
    test = the_plan.poses["test"]
    assert len(test) == 3 * n
    frames = the_plan.extrapolation["frames"]
    assert [f["scale"] for f in frames] == [1.0] * n + [0.5] * n + [2.0] * n
    distance = np.linalg.norm(test[:, :3, 3] - centre, axis=1)
    expected = np.array([the_plan.radius / f["scale"] for f in frames])
    assert np.allclose(distance, expected, rtol=1e-12)
    # without them, the layout's cameras are untouched (the options draw from their own generator)
    base = plan(GenerateConfig(**SMALL))
    for split in ("train", "val"):
        assert np.array_equal(base.poses[split], the_plan.poses[split])
    assert np.array_equal(base.poses["test"], test[:n])
    assert base.extrapolation is None and "test_scales" not in base.config.to_json()
    with pytest.raises(InputError, match="inside the scene's AABB"):
        plan(GenerateConfig(**SMALL, test_scales=(1, 8)))
    with pytest.raises(InputError, match="--test-scales"):
        plan(GenerateConfig(**SMALL, test_scales=(0, 1)))


def test_holdout_and_scales_compose():
    the_plan = plan(GenerateConfig(**SMALL, holdout="azimuth:0:90", test_scales=(2,)))
    frames = the_plan.extrapolation["frames"]
    assert [(f["group"], f["in_sector"], f["scale"]) for f in frames] == (
        [("extrapolation", True, 1.0)] * 3 + [("interpolation", False, 1.0)] * 3 + [("extrapolation", False, 2.0)] * 6)
    az = azimuth(the_plan.poses["test"][6:], centre_of(the_plan))
    assert not (np.mod(az, 360) <= 90).any()  # the scaled views come from the train region


def test_farthest_point_order_is_greedy_and_nested():
    rng = np.random.default_rng(7)
    points = rng.normal(size=(40, 3))
    order = holdout.farthest_point_order(points, 24)
    assert order[0] == int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))
    assert len(set(order)) == 24
    for k in range(1, 24):  # each pick is the farthest from those before it
        gaps = np.min(np.linalg.norm(points[:, None] - points[order[:k]][None], axis=2), axis=1)
        assert gaps[order[k]] == pytest.approx(gaps.max(), abs=0)
    c2w = np.tile(np.eye(4), (40, 1, 1))
    c2w[:, :3, 3] = points
    document = holdout.sparse_views(c2w, [f"train/r_{i:03d}" for i in range(40)])
    assert list(document["counts"]) == ["3", "6", "9", "12", "24"]
    for small, large in zip(("3", "6", "9", "12"), ("6", "9", "12", "24")):
        assert document["counts"][large][:int(small)] == document["counts"][small]
    assert list(holdout.sparse_views(c2w[:7], [str(i) for i in range(7)])["counts"]) == ["3", "6"]


@pytest.fixture(scope="module")
def holdout_dataset(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("holdout") / "ds", views=12, val_views=1, test_views=4,
                        holdout="azimuth:0:90", test_scales=(2,))


def test_dataset_records_split_and_sparse_lists(holdout_dataset):
    ds = Dataset(holdout_dataset)  # the manifest lists (and hashes) sparse_views.json
    assert "sparse_views.json" in ds.manifest_files
    record = ds.scene["extrapolation"]
    assert record["holdout"] == {"axis": "azimuth", "min_degrees": 0.0, "max_degrees": 90.0}
    assert record["test_scales"] == [1.0, 2.0]
    assert [f["name"] for f in record["frames"]] == list(ds.cameras("test").stems)
    config = json.loads((holdout_dataset / "config.json").read_text())["config"]
    assert config["holdout"] == "azimuth:0:90" and config["test_scales"] == [2.0]  # as asked; scale 1 is implied
    sparse = json.loads((holdout_dataset / "sparse_views.json").read_text())
    assert sorted(sparse["counts"], key=int) == ["3", "6", "9", "12"]
    assert sparse["counts"]["3"] == holdout.farthest_point_order(ds.cameras("train").c2w[:, :3, 3], 3)


def test_evaluator_reports_the_gap(holdout_dataset, tmp_path):
    """Predictions: the ground truth composited on white and rounded to 8 bits, with an
    error of k levels on every value of every extrapolation frame. Their PSNR is then
    20 log10(255 / k) up to the rounding, the others' at least that of half a level; the
    evaluator must group the frames as scene.json says and subtract the group means."""
    from nerfgauge.core.images import read_png, write_png
    from nerfgauge.eval.evaluate import evaluate

    ds = Dataset(holdout_dataset)
    group = {f["name"]: f for f in ds.scene["extrapolation"]["frames"]}
    pred = tmp_path / "pred"
    (pred / "test").mkdir(parents=True)
    k = 8
    for stem in ds.cameras("test").stems:
        rgba = read_png(holdout_dataset / f"{stem}.png").astype(np.float64)  # [0, 1]
        rgb = np.round(255 * (rgba[..., :3] * rgba[..., 3:] + 1 - rgba[..., 3:]))  # on white, as scored
        if group[stem]["group"] == "extrapolation":
            rgb = np.where(rgb >= 128, rgb - k, rgb + k)  # |error| = k on every value, no clipping
        write_png(pred / f"{stem}.png", rgb.astype(np.uint8))
    document = evaluate(holdout_dataset, pred, held_out=False)
    gap = document["extrapolation"]
    psnr = {f["name"]: f["psnr"] for f in document["frames"]}
    extra = [psnr[s] for s, f in group.items() if f["group"] == "extrapolation"]
    inter = [psnr[s] for s, f in group.items() if f["group"] == "interpolation"]
    assert gap["counts"] == {"interpolation": 2, "extrapolation": 6}
    # the scored truth is composited in float: partly covered pixels round by up to half a level,
    # so every error lies in [k - 0.5, k + 0.5] levels, and rounding alone gives at least 54 dB
    low, high = 20 * math.log10(255 / (k + 0.5)), 20 * math.log10(255 / (k - 0.5))
    assert all(low - 1e-9 <= v <= high + 1e-9 for v in extra), extra
    assert all(v >= 20 * math.log10(255 / 0.5) - 1e-9 for v in inter), inter
    assert gap["overall"]["psnr"]["gap"] == pytest.approx(np.mean(inter) - np.mean(extra), abs=1e-9)
    assert gap["sector"]["count"] == 2 and gap["scales"]["2"]["count"] == 4
    sector = [psnr[s] for s, f in group.items() if f["in_sector"]]
    assert gap["sector"]["psnr"]["extrapolation"] == pytest.approx(np.mean(sector), abs=1e-9)
    assert gap["sector"]["psnr"]["gap"] >= 20 * math.log10(255 / 0.5) - high - 1e-9
    from nerfgauge.eval.evaluate import format_means

    assert "extrapolation gap (overall)" in format_means(document)


def test_train_on_a_sparse_list(holdout_dataset, tmp_path):
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.data import sparse_train_views
    from nerfgauge.nerf.train import prepare_run

    config = TrainConfig(dataset=str(holdout_dataset), steps=2, sparse=3, threads=1)
    _, _, _, train_rays, _, _, recipe, _ = prepare_run(config)
    assert train_rays.n_views == 3 and train_rays.origins.shape[0] == 3 * 32 * 32
    assert recipe["sparse"] == 3
    assert "sparse" not in TrainConfig(dataset="x").to_json()  # older runs keep their recipe
    assert sparse_train_views(holdout_dataset, 6) == json.loads(
        (holdout_dataset / "sparse_views.json").read_text())["counts"]["6"]
    with pytest.raises(InputError, match="no list of 24 views"):
        sparse_train_views(holdout_dataset, 24)


def test_suites_take_the_options():
    """A suite's [dataset] passes the new GenerateConfig fields through (and [train] sparse);
    bad values are the suite file's one-line errors."""
    from nerfgauge.orchestrate.suite.definition import parse_suite

    data = {"name": "ext", "version": 1,
            "dataset": {"width": 16, "height": 16, "views": 12, "val_views": 1, "test_views": 2, "spp": 4,
                        "holdout": "azimuth:0:60", "test_scales": [0.5, 1, 2], "transients": 2,
                        "transient_fraction": 0.25},
            "train": {"steps": 10, "sparse": 6},
            "protocol": {"split": "test", "background": "white", "depth_kind": "distance"},
            "scenes": [{"scene": "primitives", "seed": 1}]}
    suite = parse_suite(data, "ext.toml")
    the_plan = plan(suite.generate_config(suite.scenes[0]))
    assert [f["scale"] for f in the_plan.extrapolation["frames"]] == [1.0] * 2 + [0.5] * 2 + [2.0] * 2
    assert len(the_plan.transients) == 2 and all(len(t.views) == 3 for t in the_plan.transients)
    bad = data | {"dataset": data["dataset"] | {"holdout": "azimuth:9"}}
    with pytest.raises(InputError, match=r"ext.toml scenes\[0\]: --holdout"):
        parse_suite(bad, "ext.toml")
