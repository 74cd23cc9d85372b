"""eval.metrics: exact values on hand-computed cases, SSIM against a plain re-implementation."""

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from nerfgauge.eval.metrics import (
    PSNR_CAP_DB,
    NonFiniteError,
    composite,
    depth_metrics,
    opacity_iou,
    psnr,
    ssim,
    ssim_window,
    summarize,
)
from numpy.lib.stride_tricks import sliding_window_view

from nerfgauge.core.errors import InputError

C1, C2 = 0.01 ** 2, 0.03 ** 2  # K1 = 0.01, K2 = 0.03, data range 1


def reference_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. 2004 written out from the formula: the test oracle for `ssim`.

    x, y: [H, W, 3] float64. Gaussian window sigma 1.5 cut at 3.5 sigma (radius 5, 11 taps,
    normalised), images extended by half-sample mirroring (d c b a | a b c d, what
    scipy calls "reflect"), population (co)variances, SSIM map cropped by (win - 1) // 2
    with win = 11, or the largest odd side <= min(H, W) for smaller images, then the mean
    over the map and over channels.
    """
    sigma = 1.5
    radius = int(3.5 * sigma + 0.5)  # 5
    taps = np.arange(-radius, radius + 1)  # [11]
    g = np.exp(-taps ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    weights = np.outer(g, g)  # [11, 11]
    h, w = x.shape[:2]
    side = min(h, w)
    win = 11 if side >= 11 else (side if side % 2 else side - 1)
    cut = (win - 1) // 2

    def local_mean(image):  # [H, W] -> [H, W], weighted mean over each pixel's window
        padded = np.pad(image, radius, mode="symmetric")  # [H + 10, W + 10]
        windows = sliding_window_view(padded, weights.shape)  # [H, W, 11, 11]
        return np.einsum("ijkl,kl->ij", windows, weights)

    means = []
    for c in range(x.shape[2]):
        a, b = x[..., c], y[..., c]
        mu_a, mu_b = local_mean(a), local_mean(b)
        var_a = local_mean(a * a) - mu_a ** 2
        var_b = local_mean(b * b) - mu_b ** 2
        cov = local_mean(a * b) - mu_a * mu_b
        s = ((2 * mu_a * mu_b + C1) * (2 * cov + C2)) / ((mu_a ** 2 + mu_b ** 2 + C1) * (var_a + var_b + C2))
        means.append(s[cut:h - cut, cut:w - cut].mean())
    return float(np.mean(means))


def noisy_pair(rng, shape):
    """A smooth-ish ground truth and a noisy prediction of it, both in [0, 1]."""
    gt = rng.random(shape)
    pred = np.clip(gt + rng.normal(0.0, 0.1, shape), 0.0, 1.0)
    return pred, gt


# --- composite ---------------------------------------------------------------------


def test_composite_blends_straight_alpha_over_background():
    rgba = np.array([[[1.0, 0.0, 0.0, 0.25], [0.2, 0.4, 0.6, 1.0], [0.3, 0.3, 0.3, 0.0]]])  # [1, 3, 4]
    out = composite(rgba, np.array([1.0, 1.0, 1.0]))
    assert out.shape == (1, 3, 3)
    # 0.25 * c + 0.75 * white; all values are exact in binary except 0.2/0.4/0.6 times 1.
    np.testing.assert_allclose(out[0, 0], [1.0, 0.75, 0.75], atol=1e-15)
    np.testing.assert_allclose(out[0, 1], [0.2, 0.4, 0.6], atol=1e-15)
    np.testing.assert_allclose(composite(rgba, np.array([0.0, 0.5, 0.0]))[0, 2], [0.0, 0.5, 0.0], atol=1e-15)


def test_composite_rejects_wrong_shapes_and_ranges():
    with pytest.raises(InputError, match=r"\[H, W, 4\].*\(2, 2, 3\)"):
        composite(np.zeros((2, 2, 3)), np.ones(3))
    with pytest.raises(InputError, match="background"):
        composite(np.zeros((2, 2, 4)), np.ones(4))
    with pytest.raises(InputError, match=r"\[0, 1\].*1\.5"):
        composite(np.full((2, 2, 4), 1.5), np.ones(3))


# --- PSNR --------------------------------------------------------------------------


def test_psnr_of_identical_images_is_the_cap():
    gt = np.random.default_rng(1).random((6, 5, 3))
    assert psnr(gt, gt.copy()) == PSNR_CAP_DB
    assert PSNR_CAP_DB == pytest.approx(100.0, abs=1e-12)
    assert math.isfinite(PSNR_CAP_DB)


def test_psnr_of_a_known_mse():
    rng = np.random.default_rng(2)
    gt = rng.uniform(0.0, 0.9, (8, 7, 3))
    # MSE = 0.1^2 = 0.01 -> 20 dB. (gt + 0.1) - gt differs from 0.1 by a rounding error of
    # ~1e-17, a relative MSE error ~1e-15 and a PSNR error ~4e-15 dB: 1e-9 is far above it.
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)
    # Multiples of 1/8 are exact in binary: MSE is exactly 1/64, PSNR 10 log10(64).
    eighths = rng.integers(0, 7, (4, 4, 3)) / 8.0  # 0 .. 6/8
    assert psnr(eighths + 0.125, eighths) == pytest.approx(10 * math.log10(64), abs=1e-12)
    # One value off by 0.5 in a 4x5x3 image: MSE = 0.25 / 60.
    pred = np.zeros((4, 5, 3))
    pred[2, 3, 1] = 0.5
    assert psnr(pred, np.zeros((4, 5, 3))) == pytest.approx(10 * math.log10(240.0), abs=1e-12)


def test_psnr_below_the_cap_is_not_clipped():
    gt = np.full((3, 3, 3), 0.5)
    # MSE 1e-8 > floor 1e-10: 80 dB, not 100.
    assert psnr(gt + 1e-4, gt) == pytest.approx(80.0, abs=1e-6)


@pytest.mark.parametrize("metric", [psnr, ssim])
@pytest.mark.parametrize("bad, word", [(np.nan, "1 NaN"), (np.inf, "1 inf"), (-np.inf, "1 inf")])
def test_non_finite_prediction_raises(metric, bad, word):
    gt = np.full((12, 12, 3), 0.5)
    pred = gt.copy()
    pred[3, 4, 2] = bad
    with pytest.raises(NonFiniteError, match=f"prediction.*{word}"):
        metric(pred, gt)
    assert issubclass(NonFiniteError, ValueError) and issubclass(NonFiniteError, InputError)


@pytest.mark.parametrize("metric", [psnr, ssim])
def test_image_metrics_check_shapes_and_ranges(metric):
    with pytest.raises(InputError, match=r"\(4, 4, 3\).*\(4, 5, 3\)"):
        metric(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(InputError, match=r"prediction must be \[H, W, 3\].*\(4, 4\)"):
        metric(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(InputError, match=r"\[0, 1\].*255"):
        metric(np.full((4, 4, 3), 255, np.uint8), np.zeros((4, 4, 3)))
    with pytest.raises(InputError, match="H, W >= 1"):
        metric(np.zeros((0, 4, 3)), np.zeros((0, 4, 3)))


# --- SSIM --------------------------------------------------------------------------


def test_ssim_of_identical_images_is_one():
    gt = np.random.default_rng(3).random((16, 13, 3))
    assert abs(ssim(gt, gt.copy()) - 1.0) <= 1e-12


@pytest.mark.parametrize("shape", [(24, 20, 3), (11, 11, 3), (9, 13, 3), (4, 6, 3), (2, 2, 3), (1, 7, 3), (1, 1, 3)])
def test_ssim_matches_the_reference_formula(shape):
    rng = np.random.default_rng(sum(shape))
    pred, gt = noisy_pair(rng, shape)
    expected = reference_ssim(pred, gt)
    # Both are float64 evaluations of the same sums in different orders (~1e-16 each); the
    # worst amplification is dividing a variance's rounding by C2 ~ 1e-3, so ~1e-13. Kept
    # tight on purpose: sample instead of population covariance moves SSIM by only ~2e-6.
    assert ssim(pred, gt) == pytest.approx(expected, abs=1e-9)
    # Not vacuous: the noise (std 0.1) lowers SSIM measurably below 1 even for a 1x1 image,
    # where only the luminance term is left.
    assert expected < 0.999
    other = rng.random(shape)
    assert ssim(other, gt) == pytest.approx(reference_ssim(other, gt), abs=1e-9)


def test_ssim_window_for_small_images():
    assert ssim_window(64, 64) == 11
    assert ssim_window(11, 40) == 11
    assert ssim_window(10, 40) == 9
    assert ssim_window(7, 7) == 7
    assert ssim_window(2, 9) == 1
    assert ssim_window(1, 1) == 1


def test_ssim_of_constant_images_is_the_luminance_term():
    # Constant images have zero local variance: the structure term is C2 / C2 = 1 and
    # SSIM = (2 c d + C1) / (c^2 + d^2 + C1) per channel. The variance of a constant comes
    # out as ~1e-17 rounding, ~1e-14 relative to C2.
    for shape in [(20, 20, 3), (5, 3, 3), (1, 1, 3)]:
        c = np.array([0.3, 0.0, 1.0])
        d = np.array([0.7, 0.0, 0.9])
        pred, gt = np.broadcast_to(d, shape).copy(), np.broadcast_to(c, shape).copy()
        expected = np.mean((2 * c * d + C1) / (c ** 2 + d ** 2 + C1))
        value = ssim(pred, gt)
        assert value == pytest.approx(expected, abs=1e-12)
        assert ssim(np.zeros(shape), np.zeros(shape)) == pytest.approx(1.0, abs=1e-12)


def test_ssim_is_defined_on_every_small_size():
    rng = np.random.default_rng(5)
    for h in range(1, 13):
        for w in (1, 2, 5, 12):
            pred, gt = rng.random((h, w, 3)), rng.random((h, w, 3))
            value = ssim(pred, gt)
            assert math.isfinite(value) and -1.0 <= value <= 1.0, (h, w, value)


def test_ssim_accepts_float32_and_computes_in_float64():
    pred, gt = noisy_pair(np.random.default_rng(6), (16, 16, 3))
    p32, g32 = pred.astype(np.float32), gt.astype(np.float32)
    # Identical to the float64 value of the float32-rounded inputs: nothing is lost inside.
    assert ssim(p32, g32) == pytest.approx(reference_ssim(p32.astype(np.float64), g32.astype(np.float64)), abs=1e-9)


# --- depth -------------------------------------------------------------------------


def test_depth_metrics_on_masked_pixels():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])
    pred = np.array([[1.1, 1.0], [5.0, 7.0]])  # the unmasked 7.0 must not count
    mask = np.array([[True, True], [True, False]])
    out = depth_metrics(pred, gt, mask)
    # errors 0.1, -1, 1; relative 0.1, 0.5, 0.25; ratios 1.1, 2, 1.25 (exactly the bound: fails)
    # rel=1e-12: a mean of three doubles carries a few ulps.
    assert out["absrel"] == pytest.approx(0.85 / 3, rel=1e-12)
    assert out["mae"] == pytest.approx(2.1 / 3, rel=1e-12)
    assert out["rmse"] == pytest.approx(math.sqrt(2.01 / 3), rel=1e-12)
    assert out["delta1"] == pytest.approx(1 / 3, rel=1e-12)
    # signed relative errors 0.1, -0.5, 0.25: the median is the middle one, 0.1
    assert out["bias"] == pytest.approx(0.1, rel=1e-12)
    assert set(out) == {"absrel", "rmse", "mae", "delta1", "bias"}


def test_depth_bias_is_signed_and_ignores_a_few_floaters():
    """Surfaces drawn 2% behind everywhere: bias +0.02 (absrel cannot tell behind from in
    front); 2% in front: -0.02; the same with 10% of the pixels on floaters at 1/10 of the
    depth: the median keeps +0.02 where the mean would be pulled below zero."""
    rng = np.random.default_rng(3)
    gt = rng.uniform(1.0, 5.0, (20, 20))
    mask = np.ones_like(gt, bool)
    assert depth_metrics(gt * 1.02, gt, mask)["bias"] == pytest.approx(0.02, rel=1e-9)
    assert depth_metrics(gt * 0.98, gt, mask)["bias"] == pytest.approx(-0.02, rel=1e-9)
    floaters = gt * 1.02
    floaters.flat[::10] = gt.flat[::10] * 0.1
    assert depth_metrics(floaters, gt, mask)["bias"] == pytest.approx(0.02, rel=1e-9)
    assert np.mean((floaters - gt) / gt) < 0


def test_depth_non_positive_prediction_fails_delta():
    gt = np.array([[2.0, 4.0, 3.0]])
    pred = np.array([[0.0, -1.0, 3.0]])
    out = depth_metrics(pred, gt, np.ones((1, 3), bool))
    assert out["delta1"] == pytest.approx(1 / 3, rel=1e-12)
    assert out["absrel"] == pytest.approx((1.0 + 1.25 + 0.0) / 3, rel=1e-12)
    assert out["mae"] == pytest.approx(7.0 / 3, rel=1e-12)
    assert out["rmse"] == pytest.approx(math.sqrt(29.0 / 3), rel=1e-12)


def test_depth_empty_mask_gives_none_and_unmasked_nan_is_ignored():
    gt = np.zeros((3, 3))
    pred = np.full((3, 3), np.nan)
    assert depth_metrics(pred, gt, np.zeros((3, 3), bool)) == {"absrel": None, "rmse": None, "mae": None, "delta1": None,
                                                                   "bias": None}
    gt[1, 1], pred[1, 1] = 2.0, 2.0
    mask = np.zeros((3, 3), bool)
    mask[1, 1] = True
    assert depth_metrics(pred, gt, mask) == {"absrel": 0.0, "rmse": 0.0, "mae": 0.0, "delta1": 1.0, "bias": 0.0}


def test_depth_input_errors():
    gt, mask = np.ones((2, 2)), np.ones((2, 2), bool)
    with pytest.raises(NonFiniteError, match="predicted depth.*1 NaN"):
        depth_metrics(np.array([[1.0, np.nan], [1.0, 1.0]]), gt, mask)
    with pytest.raises(InputError, match=r"> 0.*1 of 4"):
        depth_metrics(gt, np.array([[1.0, 0.0], [1.0, 1.0]]), mask)
    with pytest.raises(InputError, match="bool"):
        depth_metrics(gt, gt, np.ones((2, 2)))
    with pytest.raises(InputError, match=r"\(2, 3\).*\(2, 2\)"):
        depth_metrics(np.ones((2, 3)), gt, mask)


# --- opacity -----------------------------------------------------------------------


def test_opacity_iou():
    alpha = np.array([[0.9, 0.6], [0.2, 0.5]])
    mask = np.array([[True, False], [True, False]])
    # alpha > 0.5 selects the top row (0.5 itself is not above): 1 shared of 3 in the union.
    assert opacity_iou(alpha, mask) == pytest.approx(1 / 3, rel=1e-15)
    assert opacity_iou(alpha, mask, threshold=0.1) == pytest.approx(0.5, rel=1e-15)
    assert opacity_iou(np.zeros((2, 2)), np.zeros((2, 2), bool)) == 1.0  # both empty: they agree
    assert opacity_iou(np.ones((2, 2)), np.ones((2, 2), bool)) == 1.0
    with pytest.raises(NonFiniteError):
        opacity_iou(np.full((2, 2), np.nan), mask)
    with pytest.raises(InputError, match="threshold"):
        opacity_iou(alpha, mask, threshold=1.0)


# --- summarize ---------------------------------------------------------------------


def test_summarize_population_std():
    mean, std = summarize([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5
    assert std == pytest.approx(math.sqrt(1.25), rel=1e-15)  # ddof=0; ddof=1 would give sqrt(5/3)
    assert summarize([5.0]) == (5.0, 0.0)


def test_summarize_skips_undefined_frames():
    assert summarize([None, 2.0, 4.0]) == (3.0, 1.0)
    assert summarize([None, None]) == (None, None)
    assert summarize([]) == (None, None)
    with pytest.raises(NonFiniteError):
        summarize([1.0, float("nan")])


def test_foreground_psnr_sees_what_the_whole_image_averages_away():
    """A 2x2 object missing from a 100x100 white view: the whole-image MSE is 4/10000 of
    the object's, so whole-image PSNR is 10 log10(10000/4) = 33.98 dB above the
    foreground's; over the 4 foreground pixels the miss (black vs white, MSE 1) is 0 dB."""
    from nerfgauge.eval.metrics import psnr_masked

    gt = np.ones((100, 100, 3))
    gt[10:12, 20:22] = 0.0
    pred = np.ones((100, 100, 3))
    foreground = np.zeros((100, 100), bool)
    foreground[10:12, 20:22] = True
    assert psnr_masked(pred, gt, foreground) == pytest.approx(0.0, abs=1e-12)
    assert psnr(pred, gt) == pytest.approx(10 * np.log10(10000 / 4), rel=1e-12)
    assert psnr_masked(pred, gt, np.zeros((100, 100), bool)) is None
    assert psnr_masked(gt, gt, foreground) == pytest.approx(100.0)


@settings(max_examples=50, deadline=None)
@given(factor=st.integers(1, 4), height=st.integers(1, 5), width=st.integers(1, 5), seed=st.integers(0, 2**31 - 1))
def test_area_average_inverts_pixel_replication_and_keeps_each_block_mean(factor, height, width, seed):
    """Replicating every pixel into a factor x factor block and area-averaging gives the image
    back; any image's block means are what it returns (checked against an explicit loop)."""
    from nerfgauge.eval.metrics import area_average

    rng = np.random.default_rng(seed)
    small = rng.random((height, width, 3))
    assert np.allclose(area_average(np.kron(small, np.ones((factor, factor, 1))), factor), small, atol=1e-15)
    big = rng.random((height * factor, width * factor, 2))
    expected = np.array([[big[i * factor:(i + 1) * factor, j * factor:(j + 1) * factor].mean(axis=(0, 1))
                          for j in range(width)] for i in range(height)])
    assert np.allclose(area_average(big, factor), expected, atol=1e-15)


@pytest.mark.parametrize("shape, factor, message", [
    ((4, 6, 3), 4, "divisible"), ((4, 4), 2, "[H, W, C]"), ((4, 4, 3), 0, "positive integer"),
    ((4, 4, 3), 1.5, "positive integer"), ((4, 4, 3), True, "positive integer")])
def test_area_average_refuses_what_it_cannot_split_into_blocks(shape, factor, message):
    from nerfgauge.eval.metrics import area_average

    with pytest.raises(InputError, match=re.escape(message)):
        area_average(np.zeros(shape), factor)


def _edge_pixels_by_scipy(rgba, ids, step):
    """The same rule built another way: gradients by np.diff, dilation by scipy.ndimage."""
    from scipy import ndimage

    alpha = rgba[..., 3]
    colour = rgba[..., :3] * alpha[..., None]
    seeds = (alpha > 0) & (alpha < 1)
    for axis in (0, 1):
        jump = np.abs(np.diff(colour, axis=axis)).max(axis=-1) > step
        if ids is not None:
            jump |= np.diff(ids, axis=axis) != 0
        pad_before = [(1, 0) if a == axis else (0, 0) for a in range(2)]
        pad_after = [(0, 1) if a == axis else (0, 0) for a in range(2)]
        seeds |= np.pad(jump, pad_before) | np.pad(jump, pad_after)
    return ndimage.binary_dilation(seeds, structure=np.ones((3, 3), bool))


@pytest.mark.parametrize("with_ids", [False, True])
def test_edge_pixels_equal_an_independent_construction(with_ids):
    from nerfgauge.eval.metrics import edge_pixels

    rng = np.random.default_rng(3)
    rgba = np.zeros((40, 50, 4))
    rgba[8:30, 10:40] = [0.2, 0.6, 0.3, 1.0]  # an opaque block
    rgba[8:30, 25:40, 0] += rng.uniform(0, 0.08, size=(22, 15))  # texture below the step threshold
    rgba[15:20, 12:20, :3] = 0.9  # a colour step inside the block
    rgba[29, 10:40, 3] = 0.5  # a partially covered row
    ids = np.where(rgba[..., 3] > 0, 1, 0)
    ids[8:30, 30:40] = 2  # two shapes meeting without a colour step
    got = edge_pixels(rgba, ids if with_ids else None)
    assert np.array_equal(got, _edge_pixels_by_scipy(rgba, ids if with_ids else None, 0.1))
    # what the rule must and must not mark, by construction
    assert not got[23:27, 13:24].any()  # the block's inside, two pixels from every step
    assert got[7:10, 10:40].all() and got[28:31, 10:40].all()  # silhouette rows (and the half-covered row)
    assert got[20, 29:31].all() == with_ids  # the shapes' shared boundary is an edge only by the ids


# --- outline ----------------------------------------------------------------------------


def test_outline_pixels_are_the_partly_covered_ones_beyond_8_bit_rounding():
    from nerfgauge.eval.metrics import outline_pixels

    alpha = np.array([[0.0, 0.4 / 255, 1 / 255, 0.5], [254 / 255, 254.6 / 255, 1.0, 0.999]])
    rgba = np.concatenate([np.full(alpha.shape + (3,), 0.5), alpha[..., None]], -1)
    assert outline_pixels(rgba).tolist() == [[False, False, True, True], [True, False, False, False]]


def test_outline_alpha_error_is_the_silhouettes_shift_in_pixels():
    """A vertical edge at x = 10.5 (the object on the right), exact coverage: column 10 is
    half covered. The prediction moves the edge of row r left by d_r, inside the column
    (|d_r| < 0.5), so that pixel's alpha rises by exactly d_r and no other pixel changes:
    the bias is the mean shift, the RMSE the root mean square of the shifts."""
    from nerfgauge.eval.metrics import outline_alpha_error, outline_pixels

    rng = np.random.default_rng(7)
    height, width = 16, 24
    truth = np.zeros((height, width))
    truth[:, 11:] = 1.0
    truth[:, 10] = 0.5
    shifts = rng.uniform(-0.35, 0.35, size=height) + 0.1  # in (-0.25, 0.45): outward on average
    predicted = truth.copy()
    predicted[:, 10] += shifts
    rgba = np.concatenate([np.full((height, width, 3), 0.3), truth[..., None]], -1)
    outline = outline_pixels(rgba)
    assert outline.sum() == height and outline[:, 10].all()
    got = outline_alpha_error(predicted, truth, outline)
    assert got["bias"] == pytest.approx(shifts.mean(), abs=1e-12)
    assert got["rmse"] == pytest.approx(np.sqrt(np.mean(shifts ** 2)), abs=1e-12)
    assert got["bias"] > 0  # drawn too wide


def test_outline_alpha_error_without_an_outline_is_none_and_bad_input_is_refused():
    from nerfgauge.eval.metrics import NonFiniteError, outline_alpha_error

    plane = np.zeros((4, 5))
    assert outline_alpha_error(plane, plane, np.zeros((4, 5), bool)) == {"bias": None, "rmse": None}
    with pytest.raises(InputError, match="ground-truth alpha must have shape"):
        outline_alpha_error(plane, np.zeros((5, 4)), np.ones((4, 5), bool))
    nan = plane.copy()
    nan[1, 2] = np.nan
    with pytest.raises(NonFiniteError):
        outline_alpha_error(nan, plane, np.ones((4, 5), bool))
    with pytest.raises(InputError, match=r"lie in \[0, 1\]"):
        outline_alpha_error(plane + 2, plane, np.ones((4, 5), bool))
