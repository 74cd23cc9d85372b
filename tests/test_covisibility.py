"""Held-out pixels (eval.covisibility): the co-visible ones, scored by psnr_covisible and
ssim_covisible (DyCheck's mPSNR and mSSIM), and the depth-resolved ones, scored by
depth_absrel_resolved."""

import json
import shutil

import numpy as np
import pytest
from nerfgauge.eval.covisibility import (RESOLVED_RELATIVE_DEPTH, RESOLVED_SHIFT_PX, held_out_pixels, holds_out,
                                         parallax_pixels, reference_depths)
from nerfgauge.eval.metrics import PSNR_CAP_DB, psnr, psnr_capture_bound, ssim, ssim_masked
from test_geometry import _visible_sample_by_sample

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.camera import pixel_rays
from nerfgauge.core.images import write_png
from PIL import Image


@pytest.fixture(scope="module")
def ds_root(tmp_path_factory, make_dataset):
    """primitives, 4 train / 1 val / 4 test views at 24x24: few train views, so some test
    pixels show surfaces no train view sees."""
    return make_dataset(tmp_path_factory.mktemp("covisibility") / "primitives", views=4, val_views=1,
                        test_views=4, width=24, height=24)


@pytest.fixture(scope="module")
def ds(ds_root):
    return dataset.Dataset(ds_root)


@pytest.fixture(scope="module")
def held_out(ds):
    depths = reference_depths(ds)
    return {stem: held_out_pixels(ds, "test", index, depths, ds.mask("test", index), ds.depth("test", index))
            for index, stem in enumerate(ds.cameras("test").stems)}


@pytest.fixture(scope="module")
def test_masks(held_out):
    return {stem: pixels.covisible for stem, pixels in held_out.items()}


def test_a_view_sees_everything_it_hits(ds):
    """Each train frame against the train split: its own exact depth confirms every hit
    pixel's back-projected point (the depth test's tolerance holds the pixel centre)."""
    depths = reference_depths(ds)
    for index in range(len(ds.cameras("train").c2w)):
        pixels = held_out_pixels(ds, "train", index, depths, ds.mask("train", index), ds.depth("train", index))
        assert pixels.covisible.all()


def test_mask_matches_the_sample_by_sample_depth_test(ds, test_masks):
    """Hit pixels: the written-out depth test of tests/test_geometry on the back-projected
    points; misses: always co-visible."""
    cameras = ds.cameras("test")
    unseen = 0
    for index, stem in enumerate(cameras.stems):
        distance = ds.depth("test", index).astype(np.float64)
        hit = ds.mask("test", index) & (distance > 0)
        origins, directions = pixel_rays(cameras.c2w[index], cameras.intrinsics)
        points = origins[hit] + directions[hit] * distance[hit][:, None]
        expected = np.ones(hit.shape, bool)
        expected[hit] = _visible_sample_by_sample(points, ds.normals("test", index)[hit].astype(np.float64), ds, "train")
        np.testing.assert_array_equal(test_masks[stem], expected)
        unseen += int((~expected).sum())
    assert unseen > 0  # the fixture must exercise both outcomes


def test_no_mask_for_the_reference_split_itself(ds):
    assert not holds_out(ds, "train") and holds_out(ds, "test") and holds_out(ds, "val")


def test_ssim_masked_is_the_mean_of_the_ssim_map_over_the_mask():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(3)
    gt = rng.random((40, 40, 3))
    pred = np.clip(gt + rng.normal(0, 0.1, gt.shape), 0, 1)
    assert ssim_masked(pred, gt, np.ones((40, 40), bool)) == pytest.approx(ssim(pred, gt), abs=1e-12)
    mask = rng.random((40, 40)) < 0.3
    _, full = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                    data_range=1.0, channel_axis=-1, full=True)
    inner = np.zeros_like(mask)
    inner[5:-5, 5:-5] = True  # skimage's border crop for its 11-tap window
    assert ssim_masked(pred, gt, mask) == pytest.approx(full.mean(axis=-1)[mask & inner].mean(), abs=1e-12)
    border_only = ~inner
    assert ssim_masked(pred, gt, border_only) is None


def test_errors_where_no_train_view_looked_leave_the_covisible_scores_perfect(ds_root, ds, test_masks, tmp_path,
                                                                              capsys):
    """The ground truth as the prediction, with every non-co-visible pixel painted magenta:
    PSNR drops by the painted error, psnr_covisible stays at the cap, covisible_fraction
    is the mask's share."""
    pred = tmp_path / "pred" / "test"
    pred.mkdir(parents=True)
    cameras = ds.cameras("test")
    expected_psnr, expected_bound = [], []
    for stem in cameras.stems:
        gt = np.asarray(Image.open(ds_root / (stem + ".png")).convert("RGBA"))  # [H, W, 4] uint8
        painted = gt.copy()
        painted[~test_masks[stem]] = (255, 0, 255, 255)
        write_png(pred / (stem.split("/")[1] + ".png"), painted)
        on_white = [rgba[..., :3] / 255 * (rgba[..., 3:] / 255) + 1 - rgba[..., 3:] / 255 for rgba in (painted, gt)]
        expected_psnr.append(psnr(*on_white))
        expected_bound.append((on_white[1], test_masks[stem]))  # the bound's ground truth and mask
    out = tmp_path / "metrics.json"
    assert main(["evaluate", str(ds_root), "--pred", str(tmp_path / "pred"), "--out", str(out)]) == 0
    capsys.readouterr()
    doc = json.loads(out.read_text())
    for frame, stem, value, (gt, seen) in zip(doc["frames"], cameras.stems, expected_psnr, expected_bound):
        assert frame["covisible_fraction"] == pytest.approx(test_masks[stem].mean(), abs=1e-12)
        assert frame["psnr_ceiling"] is not None  # the bound charges the ground truth's own noise
        assert frame["psnr_capture_bound"] == pytest.approx(psnr_capture_bound(gt, seen, frame["psnr_ceiling"]),
                                                            abs=1e-5)
        assert frame["psnr_covisible"] == PSNR_CAP_DB  # the co-visible pixels are the ground truth's bytes
        assert frame["psnr"] == pytest.approx(value, abs=1e-5)  # the reader decodes to float32 (6e-8 relative)
    assert doc["mean"]["psnr"] < 40 < doc["mean"]["psnr_covisible"]
    assert "covisible" not in doc["notes"]


def test_scoring_the_train_split_says_why_there_is_no_mask(ds_root, tmp_path, capsys):
    out = tmp_path / "metrics.json"
    pred = tmp_path / "pred"
    shutil.copytree(ds_root / "train", pred / "train", ignore=shutil.ignore_patterns("r_*_*"))  # colour PNGs only
    assert main(["evaluate", str(ds_root), "--pred", str(pred), "--split", "train", "--out", str(out)]) == 0
    capsys.readouterr()
    doc = json.loads(out.read_text())
    assert doc["mean"]["psnr_covisible"] is None and doc["count"]["covisible_fraction"] == 0
    assert doc["count"]["depth_absrel_resolved"] == 0 and doc["count"]["resolved_fraction"] == 0
    assert doc["notes"]["covisible"] == "split train is not held out from train: no co-visibility mask"


def test_capture_bound_is_the_psnr_of_the_oracle_that_guesses_the_unseen_mean():
    """Without a noise estimate the bound is the PSNR of the ground truth with its unseen
    pixels replaced by their mean colour; with one, the seen pixels add its MSE: everything
    seen gives the ceiling itself, and nothing seen gives the unseen spread plus nothing."""
    rng = np.random.default_rng(7)
    gt = rng.uniform(0, 1, (16, 20, 3))
    seen = rng.uniform(size=(16, 20)) < 0.7
    oracle = gt.copy()
    oracle[~seen] = gt[~seen].mean(axis=0)
    assert psnr_capture_bound(gt, seen, None) == pytest.approx(psnr(oracle, gt), abs=1e-9)
    everything = np.ones((16, 20), bool)
    assert psnr_capture_bound(gt, everything, 35.0) == pytest.approx(35.0, abs=1e-9)
    assert psnr_capture_bound(gt, everything, None) == PSNR_CAP_DB
    assert psnr_capture_bound(gt, ~everything, 35.0) == pytest.approx(psnr_capture_bound(gt, ~everything, None), abs=1e-12)
    # the mixture: MSE is the area-weighted sum of the two parts
    noise_mse = 10 ** (-3.5)
    mixed = 10 ** (-psnr_capture_bound(gt, seen, 35.0) / 10)
    assert mixed == pytest.approx(seen.mean() * noise_mse + 10 ** (-psnr(oracle, gt) / 10), rel=1e-9)


# --- depth-resolved pixels ------------------------------------------------------------------


def _widest_angle_by_brute_force(points, seen, centres):
    """The largest angle at each point over every pair of seeing cameras (0 below two)."""
    best = np.zeros(len(points))
    for a in range(len(centres)):
        for b in range(a + 1, len(centres)):
            da = (centres[a] - points) / np.linalg.norm(centres[a] - points, axis=1, keepdims=True)
            db = (centres[b] - points) / np.linalg.norm(centres[b] - points, axis=1, keepdims=True)
            angle = np.arccos(np.clip(np.einsum("ij,ij->i", da, db), -1, 1))
            best = np.where(seen[a] & seen[b], np.maximum(best, angle), best)
    return best


def test_parallax_is_within_half_of_the_widest_pair_and_exact_on_a_line():
    """Two sweeps never overestimate the widest angle and find at least half of it (the
    triangle inequality on the sphere); cameras on a line through nothing, seen by all,
    give the exact widest pair. focal * sin(min(theta, 90 deg)), 0 below two views."""
    rng = np.random.default_rng(11)
    points = rng.normal(size=(500, 3))
    centres = rng.normal(size=(9, 3)) * 4
    seen = rng.random((9, 500)) < 0.5
    focal = 50.0
    widest = _widest_angle_by_brute_force(points, seen, centres)
    got = parallax_pixels(points, seen, centres, focal)
    expected_high = focal * np.sin(np.minimum(widest, np.pi / 2))
    expected_low = focal * np.sin(np.minimum(widest / 2, np.pi / 2))
    assert (got <= expected_high + 1e-9).all() and (got >= expected_low - 1e-9).all()
    assert (got[seen.sum(axis=0) < 2] == 0).all()
    # a row of cameras at x = -2..2 on the line y = 0, z = 10 and a point at the origin:
    # the widest pair is the two ends, angle 2 atan(2 / 10)
    line = np.array([[x, 0.0, 10.0] for x in (0.5, -2.0, 1.0, 2.0, -0.5)])
    value = parallax_pixels(np.zeros((1, 3)), np.ones((5, 1), bool), line, focal)
    assert value[0] == pytest.approx(focal * np.sin(2 * np.arctan(0.2)), rel=1e-12)


def test_resolved_pixels_are_covisible_hits_with_enough_parallax(ds, held_out):
    """A resolved pixel hits, some train view sees its point, and its parallax by the brute
    force pairs reaches the threshold (the sweeps may only miss pairs, never invent one)."""
    from test_geometry import _visible_sample_by_sample

    cameras, train = ds.cameras("test"), ds.cameras("train")
    focal = max(train.intrinsics.fx, train.intrinsics.fy)
    threshold = RESOLVED_SHIFT_PX / RESOLVED_RELATIVE_DEPTH
    resolved_total = 0
    for index, stem in enumerate(cameras.stems):
        pixels = held_out[stem]
        distance = ds.depth("test", index).astype(np.float64)
        hit = ds.mask("test", index) & (distance > 0)
        assert not (pixels.resolved & ~hit).any() and not (pixels.resolved & ~pixels.covisible).any()
        origins, directions = pixel_rays(cameras.c2w[index], cameras.intrinsics)
        points = origins[pixels.resolved] + directions[pixels.resolved] * distance[pixels.resolved][:, None]
        normals = ds.normals("test", index)[pixels.resolved].astype(np.float64)
        seen = np.stack([_visible_sample_by_sample(points, normals, ds, "train", only=view)
                         for view in range(len(train.c2w))])
        widest = _widest_angle_by_brute_force(points, seen, train.c2w[:, :3, 3])
        assert (focal * np.sin(np.minimum(widest, np.pi / 2)) >= threshold - 1e-9).all()
        resolved_total += int(pixels.resolved.sum())
    assert resolved_total > 0


def test_report_overlay_marks_what_no_train_view_saw():
    from nerfgauge.eval.covisibility import HeldOutPixels
    from nerfgauge.eval.report import UNRESOLVED_RGB, UNSEEN_RGB, held_out_overlay

    rng = np.random.default_rng(4)
    gt = rng.random((6, 5, 3))
    hit = rng.random((6, 5)) < 0.7
    covisible = ~hit | (rng.random((6, 5)) < 0.6)
    resolved = hit & covisible & (rng.random((6, 5)) < 0.5)
    out = held_out_overlay(gt, HeldOutPixels(covisible, resolved), hit)
    gray = 0.35 + 0.65 * gt.mean(axis=-1)
    np.testing.assert_array_equal(out[~covisible], np.broadcast_to(UNSEEN_RGB, out[~covisible].shape))
    unresolved = hit & covisible & ~resolved
    np.testing.assert_allclose(out[unresolved], 0.4 * gray[unresolved][:, None] + 0.6 * np.asarray(UNRESOLVED_RGB),
                               rtol=1e-12)
    plain = covisible & ~unresolved  # misses and resolved hits: the gray ground truth
    np.testing.assert_allclose(out[plain], np.repeat(gray[plain][:, None], 3, axis=1), rtol=1e-12)
    assert (~covisible).any() and unresolved.any() and plain.any()


def test_no_held_out_skips_the_pass_and_says_so(ds_root, tmp_path, capsys):
    out = tmp_path / "metrics.json"
    assert main(["evaluate", str(ds_root), "--pred", str(ds_root), "--out", str(out), "--no-held-out"]) == 0
    capsys.readouterr()
    doc = json.loads(out.read_text())
    assert doc["notes"]["covisible"] == "not computed (--no-held-out)"
    for name in ("psnr_covisible", "ssim_covisible", "covisible_fraction", "psnr_capture_bound",
                 "depth_absrel_resolved", "resolved_fraction"):
        assert doc["mean"][name] is None and doc["count"][name] == 0
    assert doc["mean"]["psnr"] == PSNR_CAP_DB  # the rest is scored as usual
    from nerfgauge.api import evaluate
    from nerfgauge.core.errors import InputError

    with pytest.raises(InputError, match="held_out must be True or False, got 'no'"):
        evaluate(ds_root, ds_root, out=tmp_path / "other.json", held_out="no")
