"""`nerfgauge evaluate`: perfect scores on the ground truth, a hand-computed PSNR for a
corrupted frame, every kind of bad input (exit 2, frame named), metrics.json and error maps."""

import json
import math
import shutil

import numpy as np
import pytest
from nerfgauge.eval.error_maps import COLOUR_CMAP
from nerfgauge.eval.metrics import METRIC_NAMES, PSNR_CAP_DB, opacity_iou
from nerfgauge.eval.uncertainty import EVALUATE_SEED, bootstrap_ci
from PIL import Image

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.images import read_exr, read_png, write_exr, write_png

TOP_KEYS = {"schema", "scene", "split", "background", "depth_kind", "mean", "std", "ci95", "count", "notes", "frames", "timing",
            "noise", "psnr_objects", "empty_views", "tool", "kind",
            "protocol", "evaluation_protocol", "protocol_background", "lpips_net", "ground_truth"}  # eval.protocols; foreign ground truth


@pytest.fixture(scope="module")
def ds(tmp_path_factory, make_dataset):
    """primitives, 4 train / 1 val / 3 test views at 24x24, 4 spp."""
    return make_dataset(tmp_path_factory.mktemp("evaluate") / "primitives", views=4, val_views=1,
                        test_views=3, width=24, height=24)


@pytest.fixture(scope="module")
def test_split(ds):
    return dataset.open_dataset(ds).cameras("test")


def strict_json(text):
    def refuse(constant):
        raise ValueError(f"{constant} in metrics.json")

    return json.loads(text, parse_constant=refuse)


def run(capsys, *argv):
    code = main(["evaluate", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def flat_png_copy(ds, stems, folder):
    """The ground-truth PNGs copied flat into `folder` (another method's layout)."""
    folder.mkdir()
    for stem in stems:
        shutil.copy(ds / (stem + ".png"), folder / (stem.split("/")[1] + ".png"))
    return folder


# --- scores -------------------------------------------------------------------------------


@pytest.mark.parametrize("depth_kind", ["distance", "z"])
def test_ground_truth_scores_perfectly(ds, test_split, tmp_path, capsys, depth_kind):
    # The dataset folder itself is a nested prediction: PNG colour, _distance / _zdepth depth.
    out = tmp_path / "metrics.json"
    code, printed, _ = run(capsys, ds, "--pred", ds, "--out", out, "--depth-kind", depth_kind)
    assert code == 0
    doc = strict_json(out.read_text())
    assert set(doc) == TOP_KEYS and doc["schema"] == 1 and doc["scene"] == "primitives"
    assert doc["ci95"]["psnr"] == [PSNR_CAP_DB, PSNR_CAP_DB] and doc["ci95"]["lpips"] is None  # all equal; none defined
    assert doc["depth_kind"] == depth_kind and doc["split"] == "test" and doc["background"] == "white"
    assert [f["name"] for f in doc["frames"]] == list(test_split.stems)
    assert doc["mean"]["psnr"] == PSNR_CAP_DB  # identical images: MSE floored, PSNR capped
    assert doc["mean"]["ssim"] == 1.0  # identical inputs give identical numerator and denominator
    assert doc["mean"]["depth_absrel"] == 0.0 and doc["mean"]["depth_delta1"] == 1.0
    assert doc["mean"]["depth_absrel_resolved"] == 0.0 and doc["mean"]["psnr_covisible"] == PSNR_CAP_DB
    # LPIPS-Alex needs 31 px: at 24 px it is n/a, whether or not its weights are installed
    # at 24 px every covered pixel lies within a pixel of an edge: no interior to score
    assert all(doc["count"][m] == 3 for m in METRIC_NAMES if m not in ("lpips", "psnr_interior"))
    assert doc["count"]["lpips"] == 0 and doc["mean"]["psnr_edges"] == PSNR_CAP_DB
    # the ground truth's own outline: its alpha read back is the truth's, to the bit
    assert doc["mean"]["psnr_outline"] == PSNR_CAP_DB
    assert doc["mean"]["outline_alpha_bias"] == 0.0 and doc["mean"]["outline_alpha_rmse"] == 0.0
    assert doc["mean"]["lpips"] is None and doc["notes"]["lpips"].startswith("n/a")
    # Opacity from the PNG's alpha (coverage) against the pixel-centre mask: not always 1.
    opened = dataset.open_dataset(ds)
    expected = np.mean([opacity_iou(opened.rgba_of(s, test_split.intrinsics)[..., 3],
                                    opened.mask_of(s, test_split.intrinsics)) for s in test_split.stems])
    assert doc["mean"]["opacity_iou"] == pytest.approx(expected, abs=1e-12)
    assert "psnr" in printed and "100.0000" in printed


def test_flat_exr_renders_score_within_8bit_rounding(ds, test_split, tmp_path, capsys):
    # The renderer's own linear premultiplied EXRs, flat: un-premultiplied, sRGB-encoded and
    # composited they must match the 8-bit PNG up to its rounding. Colour and alpha are each
    # off by <= 0.5/255, so the composite c*a + b*(1 - a) is off by <= 0.5/255 * (a + |c - b|)
    # <= 1/255 per value: PSNR >= 20 log10(255) = 48.13 dB.
    folder = tmp_path / "exr"
    folder.mkdir()
    for stem in test_split.stems:
        shutil.copy(ds / (stem + ".exr"), folder / (stem.split("/")[1] + ".exr"))
    assert run(capsys, ds, "--pred", folder, "--background", "black")[0] == 0
    doc = strict_json((folder / "metrics.json").read_text())
    assert min(f["psnr"] for f in doc["frames"]) >= 20 * math.log10(255)
    assert doc["count"]["depth_rmse"] == 0 and doc["mean"]["depth_rmse"] is None


def test_corrupted_frame_psnr_matches_hand_computation(ds, test_split, tmp_path, capsys):
    folder = flat_png_copy(ds, test_split.stems, tmp_path / "pred")
    (folder / "timing.json").write_text('{"ms_per_frame": 12.5}')
    image = np.asarray(Image.open(folder / "r_001.png")).copy()
    image[4:10, 6:14] = (0, 0, 0, 255)  # an opaque black block
    write_png(folder / "r_001.png", image)
    assert run(capsys, ds, "--pred", folder)[0] == 0
    doc = strict_json((folder / "metrics.json").read_text())

    gt = read_png(ds / "test/r_001.png").astype(np.float64)  # straight alpha in [0, 1]
    on_white = gt[..., :3] * gt[..., 3:] + (1.0 - gt[..., 3:])  # [H, W, 3]
    mse = np.sum(on_white[4:10, 6:14] ** 2) / on_white.size  # the block is 0, the rest exact
    psnr = {f["name"]: f["psnr"] for f in doc["frames"]}
    # float64 sums of a few hundred terms: agreement to ~1e-12 relative.
    assert psnr["test/r_001"] == pytest.approx(-10 * math.log10(mse), rel=1e-9)
    assert psnr["test/r_000"] == psnr["test/r_002"] == PSNR_CAP_DB
    assert doc["mean"]["psnr"] == pytest.approx((2 * PSNR_CAP_DB + psnr["test/r_001"]) / 3, rel=1e-12)
    assert doc["std"]["psnr"] > 0 and doc["timing"]["ms_per_frame"] == 12.5
    # eval.uncertainty: the bootstrap over the 3 views, Generator seeded 0 (EVALUATE_SEED)
    values = [psnr[f"test/r_00{i}"] for i in range(3)]
    expected = bootstrap_ci(values, np.random.default_rng(EVALUATE_SEED)).to_json()
    assert doc["ci95"]["psnr"] == pytest.approx(expected, rel=1e-12)
    assert doc["ci95"]["psnr"][0] < doc["mean"]["psnr"] < doc["ci95"]["psnr"][1] == PSNR_CAP_DB
    assert doc["timing"]["evaluate_seconds"] > 0

    maps = folder / "error_maps"
    assert sorted(p.name for p in maps.iterdir() if not p.name.startswith(".")) == ["r_000_colour.png", "r_001_colour.png",
                                                                             "r_002_colour.png"]
    import matplotlib

    zero = np.round(np.asarray(matplotlib.colormaps[COLOUR_CMAP](0.0)[:3]) * 255).astype(np.uint8)
    error_map = np.asarray(Image.open(maps / "r_001_colour.png"))  # [H, W, 3]
    block = np.zeros(error_map.shape[:2], bool)
    block[4:10, 6:14] = True
    changed = np.any(error_map != zero, axis=-1)
    # Outside the block the error is exactly 0; inside it is 0 only where the ground truth
    # composited to black already (never on the white background).
    assert not changed[~block].any() and changed[block].sum() >= np.sum(np.any(on_white[block] > 0.01, axis=-1))
    assert not np.any(np.asarray(Image.open(maps / "r_000_colour.png")) != zero)


def test_depth_error_map_written_beside_out(ds, tmp_path, capsys):
    out = tmp_path / "reports" / "m.json"
    assert run(capsys, ds, "--pred", ds, "--out", out)[0] == 0
    assert (out.parent / "error_maps" / "r_000_depth.png").is_file()


# --- bad input: exit 2, one line naming the frame or key, nothing written -----------------


def resize(folder):
    Image.open(folder / "r_001.png").resize((12, 12)).save(folder / "r_001.png")


def nan_exr(folder):
    rgba = np.full((24, 24, 4), 0.5, np.float32)
    rgba[3, 5, 1] = np.nan
    (folder / "r_001.png").unlink()
    write_exr(folder / "r_001.exr", {"RGBA": rgba})


def inf_opacity(folder):
    alpha = np.ones((24, 24))
    alpha[0, 0] = np.inf
    np.save(folder / "r_001_opacity.npy", alpha)


def nan_depth_on_hit(ds):
    def mutate(folder):
        opened = dataset.open_dataset(ds)
        depth = opened.depth_of("test/r_001", opened.cameras("test").intrinsics)
        depth[np.unravel_index(np.argmax(depth), depth.shape)] = np.nan  # the largest depth is a hit
        np.save(folder / "r_001_depth.npy", depth)
    return mutate


def twice(folder):
    (folder / "test").mkdir()
    shutil.copy(folder / "r_001.png", folder / "test" / "r_001.png")


def z_header(ds):
    def mutate(folder):
        shutil.copy(ds / "test/r_001_distance.exr", folder / "r_001_depth.exr")  # header: ray_distance
    return mutate


CASES = {
    "size": (resize, [], ["test/r_001", "12x12", "24x24"]),
    "missing": (lambda f: (f / "r_002.png").unlink(), [], ["test/r_002"]),
    "extra": (lambda f: shutil.copy(f / "r_000.png", f / "r_007.png"), [], ["r_007.png"]),
    "extra_aux": (lambda f: np.save(f / "r_009_depth.npy", np.ones((24, 24))), [], ["r_009_depth.npy"]),
    "nan_colour": (nan_exr, [], ["test/r_001", "1 NaN"]),
    "inf_opacity": (inf_opacity, [], ["test/r_001", "1 inf"]),
    "nan_depth": ("nan_depth", [], ["test/r_001", "NaN"]),
    "twice": (twice, [], ["test/r_001"]),
    "depth_kind": ("z_header", ["--depth-kind", "z"], ["test/r_001", "ray_distance"]),
    "bad_timing": (lambda f: (f / "timing.json").write_text('{"ms": NaN}'), [], ["timing.json", "NaN"]),
}


@pytest.mark.parametrize("case", CASES)
def test_bad_prediction_exits_2_naming_it(ds, test_split, tmp_path, capsys, case):
    mutate, extra_args, needles = CASES[case]
    mutate = {"nan_depth": nan_depth_on_hit(ds), "z_header": z_header(ds)}.get(mutate, mutate)
    folder = flat_png_copy(ds, test_split.stems, tmp_path / "pred")
    mutate(folder)
    code, _, err = run(capsys, ds, "--pred", folder, *extra_args)
    assert code == 2 and err.startswith("nerfgauge evaluate: error:") and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    assert not (folder / "metrics.json").exists() and not (folder / "error_maps").exists()


def test_incomplete_dataset_exits_2(ds, test_split, tmp_path, capsys):
    copy = tmp_path / "unfinished"
    shutil.copytree(ds, copy)
    (copy / "manifest.json").unlink()
    code, _, err = run(capsys, copy, "--pred", ds, "--out", tmp_path / "m.json")
    assert code == 2 and "manifest.json" in err and str(copy) in err
    assert not (tmp_path / "m.json").exists()


def test_unknown_split_exits_2(ds, tmp_path, capsys):
    code, _, err = run(capsys, ds, "--pred", ds, "--split", "holdout", "--out", tmp_path / "m.json")
    assert code == 2 and "'holdout'" in err


def test_exr_colour_conversion_matches_png_path(ds, test_split, tmp_path):
    # RGB (no alpha) EXR: linear values become sRGB; the reader must give what the PNG holds.
    from nerfgauge.eval.predictions import read_colour

    channels, _ = read_exr(ds / "test/r_000.exr")
    rgba = channels["RGBA"]
    write_exr(tmp_path / "r_000.exr", {"R": rgba[..., 0], "G": rgba[..., 1], "B": rgba[..., 2], "A": rgba[..., 3]})
    rgb, alpha = read_colour(tmp_path / "r_000.exr", test_split.intrinsics)
    png = read_png(ds / "test/r_000.png")
    # 8-bit rounding of the PNG: <= 0.5/255, plus float32 noise.
    assert np.abs(alpha - png[..., 3]).max() <= 0.5 / 255 + 1e-6
    # The PNG was encoded from the same premultiplied values, so straight colour differs by
    # its rounding only; where alpha is tiny, straight colour is ill-conditioned (premultiplied
    # float32 noise divided by alpha), so compare where alpha > 0.5 (noise at most doubled).
    covered = png[..., 3] > 0.5
    assert np.abs(rgb - png[..., :3])[covered].max() <= 0.5 / 255 + 1e-6
