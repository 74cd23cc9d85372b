"""Image and depth metrics: pure numpy functions, one definition each.

Conventions (docs/conventions.md, "Metrics"):

- Images are float RGB on [0, 1], shape [H, W, 3]. RGBA predictions and ground truth are
  composited onto a background first (`composite`, white by default in the callers).
- PSNR per image, `10 log10(1 / MSE)`, averaged over images by the caller (`summarize`).
  Identical images have MSE 0 and PSNR +inf; the MSE is floored at `MSE_FLOOR` = 1e-10, so
  PSNR is capped at `PSNR_CAP_DB` = 100 dB and every value stays valid JSON.
- SSIM is exactly scikit-image's `structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1.0, channel_axis=-1)`, the convention of
  mip-NeRF's reference (Wang et al. 2004: 11-tap Gaussian window, sigma 1.5, truncate 3.5,
  population covariance, C1 = 0.01^2, C2 = 0.03^2, mean over channels of the mean SSIM map
  with a 5-pixel border cropped). See `ssim` for images smaller than the window.
- Depth metrics on the pixels that hit geometry (the ground-truth mask), on ray distance.

Inputs are checked where they enter, with messages that print what was received. Shape and
range problems raise `InputError` (the predictions may be another method's renders);
NaN or inf raise `NonFiniteError`, whose message names the array and the count but not the
frame: the caller adds the frame name.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError
from nerfgauge.core.pixel_edges import ALPHA_ROUNDING, EDGE_COLOUR_STEP, edge_mask, partial_coverage

# Metric names as they appear in metrics.json's "mean"/"std" tables and in thresholds files.
METRIC_NAMES = (
    "psnr",
    "ssim",
    "psnr_foreground",
    "psnr_covisible",  # eval.covisibility: on the pixels some training view saw (DyCheck's mPSNR)
    "ssim_covisible",  # DyCheck's mSSIM on the same pixels
    "covisible_fraction",  # the share of pixels in that mask
    "psnr_capture_bound",  # what a method exact on those pixels and right on average elsewhere scores
    "depth_absrel",
    "depth_rmse",
    "depth_mae",
    "depth_delta1",
    "depth_bias",  # median signed relative depth error: > 0 when surfaces are drawn behind the true ones
    "depth_absrel_resolved",  # eval.covisibility: on the hit pixels whose depth two train views resolve
    "resolved_fraction",  # the share of hit pixels they are
    "opacity_iou",
    "psnr_edges",  # `edge_pixels`: partial coverage, an instance boundary or a colour step, dilated by 1 px
    "psnr_interior",  # the other pixels the ground truth covers
    "edge_fraction",  # the share of pixels that are edges
    "psnr_outline",  # on the pixels the ground truth covers partly (`outline_pixels`): silhouettes alone
    "outline_alpha_bias",  # mean predicted minus true alpha there: > 0 when outlines are drawn too wide
    "outline_alpha_rmse",  # its root mean square: how far the silhouettes sit from the true ones
    "lpips",  # eval.lpips: LPIPS-Alex v0.1; null (n/a) where its weights are not installed
)

MSE_FLOOR = 1e-10
# The backgrounds predictions and ground truth are composited onto (white by default, as
# NeRF papers score NeRF-synthetic); RGB tuples in [0, 1].
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
PSNR_CAP_DB = 10.0 * math.log10(1.0 / MSE_FLOOR)  # 100 dB: the PSNR of identical images

# Images may exceed [0, 1] by this much: float32 compositing rounds 1 up to 1 + 6e-8.
RANGE_TOLERANCE = 1e-6

SSIM_SIGMA = 1.5
SSIM_WINDOW = 11  # skimage's window for sigma 1.5: 2 * int(3.5 * 1.5 + 0.5) + 1
DELTA1_THRESHOLD = 1.25


class NonFiniteError(InputError):
    """An array holds NaN or inf where a metric needs finite numbers."""


# --- input checks ---------------------------------------------------------------------


def _describe(array) -> str:
    array = np.asarray(array)
    return f"shape {tuple(array.shape)} dtype {array.dtype}"


def _check_finite(values: np.ndarray, name: str) -> None:
    finite = np.isfinite(values)
    if not finite.all():
        n_nan = int(np.isnan(values).sum())
        n_inf = int((~finite).sum()) - n_nan
        raise NonFiniteError(f"{name} has {n_nan} NaN and {n_inf} inf values out of {values.size}")


def _check_range(values: np.ndarray, name: str) -> None:
    if values.size == 0:
        return
    low, high = float(values.min()), float(values.max())
    if low < -RANGE_TOLERANCE or high > 1.0 + RANGE_TOLERANCE:
        raise InputError(f"{name} must lie in [0, 1], got values in [{low:.6g}, {high:.6g}]")


def _image(array, name: str, channels: int) -> np.ndarray:
    """A finite float64 [H, W, channels] image on [0, 1], or an error saying what came in."""
    image = np.asarray(array)
    if image.ndim != 3 or image.shape[2] != channels or image.shape[0] < 1 or image.shape[1] < 1:
        raise InputError(f"{name} must be [H, W, {channels}] with H, W >= 1, got {_describe(image)}")
    if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)
            or image.dtype == np.bool_):
        raise InputError(f"{name} must hold numbers, got {_describe(image)}")
    image = image.astype(np.float64)
    _check_finite(image, name)
    _check_range(image, name)
    return image


def _image_pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    pred = _image(pred, "prediction", 3)
    gt = _image(gt, "ground truth", 3)
    if pred.shape != gt.shape:
        raise InputError(f"prediction {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ in shape")
    return pred, gt


def _plane(array, name: str) -> np.ndarray:
    """A float64 [H, W] array (not yet checked for finiteness)."""
    plane = np.asarray(array)
    if plane.ndim != 2 or not (np.issubdtype(plane.dtype, np.floating) or np.issubdtype(plane.dtype, np.integer)) \
            or plane.shape[0] < 1 or plane.shape[1] < 1:
        raise InputError(f"{name} must be a numeric [H, W] array with H, W >= 1, got {_describe(plane)}")
    return plane.astype(np.float64)


def _mask(array, name: str, shape: tuple[int, ...]) -> np.ndarray:
    mask = np.asarray(array)
    if mask.dtype != np.bool_ or mask.shape != shape:
        raise InputError(f"{name} must be a bool [H, W] array of shape {shape}, got {_describe(mask)}")
    return mask


# --- images ---------------------------------------------------------------------------


def composite(rgba, background) -> np.ndarray:
    """Composite straight-alpha RGBA onto a constant background.

        rgb = c * a + b * (1 - a)

    Args:
        rgba: [H, W, 4] straight (not premultiplied) alpha, every channel in [0, 1].
        background: [3] RGB in [0, 1], e.g. (1, 1, 1) for white.
    Returns:
        [H, W, 3] float64 in [0, 1] (clipped only against rounding).
    """
    image = _image(rgba, "rgba", 4)
    bg = np.asarray(background)
    if bg.shape != (3,) or not np.issubdtype(bg.dtype, np.number):
        raise InputError(f"background must be 3 numbers (RGB), got {_describe(bg)}")
    bg = bg.astype(np.float64)
    _check_finite(bg, "background")
    _check_range(bg, "background")
    alpha = image[..., 3:4]  # [H, W, 1]
    rgb = image[..., :3] * alpha + bg * (1.0 - alpha)  # [H, W, 3]
    return np.clip(rgb, 0.0, 1.0)


def area_average(image, factor: int) -> np.ndarray:
    """Box-filter an image down by an integer factor: each output pixel is the mean of a
    factor x factor block of the values given (a sensor pixel of that size integrates linear
    light: of an sRGB image this mean is the same operator on a prediction and its ground
    truth, which a comparison at a coarser scale needs, not the ground truth a coarser
    render would give).

    Args:
        image: [H, W, C] with H and W divisible by `factor`.
        factor: positive integer.
    Returns:
        [H / factor, W / factor, C] float64.
    """
    values = np.asarray(image, dtype=np.float64)
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise InputError(f"area-average factor must be a positive integer, got {factor!r}")
    if values.ndim != 3 or values.shape[0] % factor or values.shape[1] % factor:
        raise InputError(f"area average by {factor} needs [H, W, C] with H and W divisible by it, got {_describe(values)}")
    height, width, channels = values.shape
    return values.reshape(height // factor, factor, width // factor, factor, channels).mean(axis=(1, 3))


def psnr(pred, gt) -> float:
    """Peak signal-to-noise ratio in dB on [0, 1] images: 10 log10(1 / max(MSE, MSE_FLOOR)).

    MSE is the mean over all H * W * 3 values. Identical images give `PSNR_CAP_DB`
    (100 dB) instead of +inf.

    Args:
        pred: [H, W, 3] prediction in [0, 1]; NaN or inf raise `NonFiniteError`.
        gt: [H, W, 3] ground truth in [0, 1].
    """
    pred, gt = _image_pair(pred, gt)
    mse = float(np.mean((pred - gt) ** 2))
    return 10.0 * math.log10(1.0 / max(mse, MSE_FLOOR))


def psnr_masked(pred, gt, mask) -> Optional[float]:
    """PSNR over the pixels of `mask` only: 10 log10(1 / max(MSE_mask, MSE_FLOOR)).

    On the foreground (pixels where either image shows something): an object covering a
    few pixels barely moves the whole-image PSNR (a view that is 99% background scores
    40 dB with the object missing); restricted to the foreground, the miss is plain. On
    the co-visible pixels (eval.covisibility): DyCheck's mPSNR.

    Args:
        pred, gt: [H, W, 3] in [0, 1], as for `psnr`.
        mask: [H, W] bool, the pixels to score.
    Returns:
        dB, or None when the mask is empty (nothing to score).
    """
    pred, gt = _image_pair(pred, gt)
    mask = _mask(mask, "mask", pred.shape[:2])
    if not mask.any():
        return None
    mse = float(np.mean((pred[mask] - gt[mask]) ** 2))
    return 10.0 * math.log10(1.0 / max(mse, MSE_FLOOR))


def edge_pixels(gt_rgba, ids=None, colour_step: float = EDGE_COLOUR_STEP) -> np.ndarray:
    """The pixels whose box-filtered value depends on where in the pixel a ray goes
    (nerfgauge.core.pixel_edges.edge_mask: partial coverage, a boundary between instance
    ids, or a colour step above `colour_step` between 4-neighbours, dilated by one pixel).

    Args:
        gt_rgba: [H, W, 4] ground truth on [0, 1], straight alpha.
        ids: [H, W] integer instance ids (the centre rays' hit shapes, 0 = none), or None.
    Returns:
        [H, W] bool.
    """
    rgba = _image(gt_rgba, "ground truth", 4)
    if ids is not None:
        ids = np.asarray(ids)
        if ids.shape != rgba.shape[:2] or not np.issubdtype(ids.dtype, np.integer):
            raise InputError(f"instance ids must be an integer array of shape {rgba.shape[:2]}, got {_describe(ids)}")
    return edge_mask(rgba, ids, colour_step)


def outline_pixels(gt_rgba) -> np.ndarray:
    """The pixels an outline crosses: ground-truth alpha strictly between 0 and 1 beyond
    8-bit rounding (nerfgauge.core.pixel_edges.partial_coverage), the part of the edge
    pixels that only a silhouette in the right place, at sub-pixel accuracy, gets right.

    Args:
        gt_rgba: [H, W, 4] ground truth on [0, 1], straight alpha.
    Returns:
        [H, W] bool.
    """
    return partial_coverage(_image(gt_rgba, "ground truth", 4)[..., 3], ALPHA_ROUNDING)


def outline_alpha_error(pred_alpha, gt_alpha, outline) -> dict[str, Optional[float]]:
    """{"bias", "rmse"} of the predicted minus the true alpha on the `outline` pixels; both
    None where there are none. A silhouette drawn d pixels outside the true one, along an
    outline of smooth curvature, raises its pixels' alpha by about d: the bias is the mean
    such shift (> 0: too wide, a halo or a fattened shape; < 0: eroded), the rmse adds how
    unevenly it varies along the outline. The ground truth's alpha carries the renderer's
    sampling noise (at 64-72 spp about 0.01 on these pixels), which bounds the rmse below.

    Args:
        pred_alpha, gt_alpha: [H, W] on [0, 1]; a non-finite prediction raises `NonFiniteError`.
        outline: [H, W] bool (`outline_pixels`).
    """
    alpha = _plane(pred_alpha, "predicted alpha")
    _check_finite(alpha, "predicted alpha")
    _check_range(alpha, "predicted alpha")
    truth = _plane(gt_alpha, "ground-truth alpha")
    _check_finite(truth, "ground-truth alpha")
    _check_range(truth, "ground-truth alpha")
    if truth.shape != alpha.shape:
        raise InputError(f"ground-truth alpha must have shape {alpha.shape}, got {_describe(truth)}")
    outline = _mask(outline, "outline mask", alpha.shape)
    if not outline.any():
        return {"bias": None, "rmse": None}
    error = alpha[outline] - truth[outline]  # [n], float64 (_plane)
    return {"bias": float(error.mean()), "rmse": float(np.sqrt(np.mean(error ** 2)))}


def psnr_capture_bound(gt, seen, ceiling_db: Optional[float]) -> float:
    """The PSNR a prediction scores when it is the noise-free image wherever `seen` and
    the mean ground-truth colour of the unseen pixels everywhere else: the most a method
    can be expected to reach from what the training views show, without guessing content
    none of them saw.

    MSE = (n_seen * 3 * noise_mse + sum over unseen pixels of |gt - their mean|^2) / (H W 3),
    with noise_mse = 10^(-ceiling_db / 10) the ground truth's own noise (its psnr_ceiling;
    None: no estimate, counted as 0). Unseen pixels keep their noise in their spread.

    Args:
        gt: [H, W, 3] ground truth in [0, 1].
        seen: [H, W] bool, the co-visible pixels (eval.covisibility).
        ceiling_db: the frame's psnr_ceiling in dB, or None.
    Returns:
        dB: `ceiling_db` when everything is seen (PSNR_CAP_DB without a noise estimate).
    """
    gt = _image(gt, "gt", 3)
    seen = _mask(seen, "seen", gt.shape[:2])
    unseen = gt[~seen]  # [k, 3]
    spread = float(((unseen - unseen.mean(axis=0)) ** 2).sum()) if unseen.size else 0.0
    noise_mse = 0.0 if ceiling_db is None else 10.0 ** (-ceiling_db / 10.0)
    mse = (int(seen.sum()) * 3 * noise_mse + spread) / gt.size
    return 10.0 * math.log10(1.0 / max(mse, MSE_FLOOR))


def ssim_window(height: int, width: int) -> int:
    """The window side used for an image's border crop: 11, or less for small images.

    scikit-image refuses images smaller than its window (11 for sigma 1.5). For those we
    pass the largest odd `win_size` <= min(H, W). With gaussian_weights skimage still
    filters with the same 11-tap Gaussian (mirror-reflected at the borders); `win_size`
    only sets the border crop, (win_size - 1) // 2 pixels. So a 1x1 image gives
    (2xy + C1) / (x^2 + y^2 + C1) per channel, never an error or NaN.
    """
    side = min(int(height), int(width))
    if side >= SSIM_WINDOW:
        return SSIM_WINDOW
    return side if side % 2 == 1 else side - 1


def ssim(pred, gt) -> float:
    """Mean structural similarity (Wang et al. 2004), the mip-NeRF / scikit-image convention.

        SSIM = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2))

    with Gaussian-weighted local statistics (sigma 1.5, 11 taps), population covariance,
    C1 = (0.01 * 1)^2, C2 = (0.03 * 1)^2, averaged over the map with a (win - 1) // 2
    border cropped and then over channels. Computed in float64. Constant images are
    well defined (C1, C2 > 0): equal constants give 1. Images smaller than 11x11: see
    `ssim_window`.

    Args:
        pred: [H, W, 3] prediction in [0, 1]; NaN or inf raise `NonFiniteError`.
        gt: [H, W, 3] ground truth in [0, 1].
    """
    value, _, _ = _ssim_with_map(pred, gt)
    return value


def ssim_masked(pred, gt, mask) -> Optional[float]:
    """SSIM averaged over the pixels of `mask` (DyCheck's mSSIM on the co-visible pixels):
    the SSIM map of `ssim` (each value from its pixel's Gaussian neighbourhood, which may
    reach outside the mask) averaged over channels and over the masked pixels inside the
    same cropped border. An all-True mask gives `ssim`.

    Args:
        pred, gt: [H, W, 3] in [0, 1], as for `ssim`.
        mask: [H, W] bool, the pixels to score.
    Returns:
        The mean, or None when no masked pixel lies inside the cropped border.
    """
    _, ssim_map, crop = _ssim_with_map(pred, gt)  # [H, W, 3]
    mask = _mask(mask, "mask", ssim_map.shape[:2])
    height, width = mask.shape
    inner = (slice(crop, height - crop), slice(crop, width - crop))
    kept = mask[inner]
    if not kept.any():
        return None
    return float(ssim_map[inner].mean(axis=-1)[kept].mean())


def _ssim_with_map(pred, gt) -> tuple[float, np.ndarray, int]:
    """(mean SSIM, the SSIM map [H, W, 3], the border crop in pixels) of one pair."""
    from skimage.metrics import structural_similarity  # scikit-image: only when SSIM is computed

    pred, gt = _image_pair(pred, gt)
    window = ssim_window(pred.shape[0], pred.shape[1])
    value, ssim_map = structural_similarity(
        pred, gt,
        gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False,
        data_range=1.0, channel_axis=-1, full=True,
        win_size=None if window == SSIM_WINDOW else window,
    )
    return float(value), ssim_map, (window - 1) // 2


# --- depth and opacity ------------------------------------------------------------------


def depth_metrics(pred, gt, mask) -> dict[str, Optional[float]]:
    """Depth errors on the pixels that hit geometry (mask from the ground truth).

    Over the N masked pixels, with p the predicted and g the true depth (ray distance by
    default; both arrays must hold the same kind):

        absrel = mean(|p - g| / g)
        rmse   = sqrt(mean((p - g)^2))
        mae    = mean(|p - g|)
        delta1 = fraction of pixels with p > 0 and max(p / g, g / p) < 1.25
        bias   = median((p - g) / g)

    `bias` is signed: a method that draws every surface a little behind (or in front of)
    the true one has it > 0 (< 0), where absrel cannot tell a systematic offset from noise;
    the median, so a few floaters do not decide it.

    A prediction <= 0 counts as a delta1 failure (the ratio is undefined) and enters the
    other three as it is. Pixels outside the mask are ignored (they may hold anything,
    even NaN). An empty mask gives all four as None, never NaN. Errors too large for
    float64 (|p - g| beyond ~1e154 overflows the RMSE) raise `InputError`, never inf.

    Args:
        pred: [H, W] predicted depth; NaN or inf on a masked pixel raise `NonFiniteError`.
        gt: [H, W] true depth, finite and > 0 on every masked pixel (misses are stored as 0).
        mask: [H, W] bool, True where the ground-truth ray hit geometry.
    Returns:
        {"absrel", "rmse", "mae", "delta1", "bias"}: floats, or all None for an empty mask.
    """
    pred = _plane(pred, "predicted depth")
    gt = _plane(gt, "ground-truth depth")
    if pred.shape != gt.shape:
        raise InputError(f"predicted depth {tuple(pred.shape)} and ground-truth depth {tuple(gt.shape)} differ in shape")
    mask = _mask(mask, "depth mask", gt.shape)
    p, g = pred[mask], gt[mask]  # [N] each
    if p.size == 0:
        return {"absrel": None, "rmse": None, "mae": None, "delta1": None, "bias": None}
    _check_finite(p, "predicted depth (masked pixels)")
    _check_finite(g, "ground-truth depth (masked pixels)")
    if g.min() <= 0:
        raise InputError(f"ground-truth depth must be > 0 on masked pixels, got minimum {g.min():.6g} "
                         f"on {int((g <= 0).sum())} of {g.size} pixels")
    with np.errstate(over="ignore"):  # absurd predictions (|p| ~ 1e154 and up) overflow: refused below
        error = p - g  # [N]
        positive = p > 0  # [N]
        ratio = np.full(p.shape, np.inf)  # [N]; inf marks p <= 0 as a failure
        ratio[positive] = np.maximum(p[positive] / g[positive], g[positive] / p[positive])
        scores = {
            "absrel": float(np.mean(np.abs(error) / g)),
            "rmse": float(np.sqrt(np.mean(error ** 2))),
            "mae": float(np.mean(np.abs(error))),
            "delta1": float(np.mean(ratio < DELTA1_THRESHOLD)),
            "bias": float(np.median(error / g)),
        }
    overflowed = sorted(key for key, value in scores.items() if not math.isfinite(value))
    if overflowed:
        raise InputError(f"depth errors overflow float64 ({', '.join(overflowed)}): predicted depth on masked "
                         f"pixels spans [{p.min():.6g}, {p.max():.6g}], true depth [{g.min():.6g}, {g.max():.6g}]")
    return scores


def opacity_iou(pred_alpha, gt_mask, threshold: float = 0.5) -> Optional[float]:
    """Intersection over union of the predicted silhouette (alpha > threshold) and the mask.

    Args:
        pred_alpha: [H, W] predicted opacity in [0, 1]; NaN or inf raise `NonFiniteError`.
        gt_mask: [H, W] bool, True where the ground-truth ray hit geometry.
        threshold: in [0, 1); a pixel is predicted opaque when alpha > threshold.
    Returns:
        |P & G| / |P | G|; 1.0 when both silhouettes are empty (they agree: a field that
        predicts nothing where nothing is scores perfectly, so an empty scene is scored).
    """
    alpha = _plane(pred_alpha, "predicted alpha")
    _check_finite(alpha, "predicted alpha")
    _check_range(alpha, "predicted alpha")
    gt_mask = _mask(gt_mask, "ground-truth mask", alpha.shape)
    if not (isinstance(threshold, (int, float)) and 0.0 <= threshold < 1.0):
        raise InputError(f"opacity threshold must be in [0, 1), got {threshold!r}")
    predicted = alpha > threshold  # [H, W]
    union = int(np.sum(predicted | gt_mask))
    if union == 0:
        return 1.0
    return int(np.sum(predicted & gt_mask)) / union


# --- aggregation ----------------------------------------------------------------------


def summarize(values) -> tuple[Optional[float], Optional[float]]:
    """Mean and population standard deviation (ddof=0) of per-frame values.

    Frames whose value is None (e.g. depth metrics of a view that hits no geometry) are
    left out: the mean and std are over the defined frames only, and the caller reports
    how many those were (`sum(v is not None for v in values)`). When no frame is defined
    (or the list is empty) both are None. A single defined frame has std 0.0.
    NaN or inf raise `NonFiniteError`: they would make the mean meaningless. Values near
    the float64 limit, whose plain sum would overflow, are summed scaled by a power of two.

    Args:
        values: [n_frames] floats or None.
    Returns:
        (mean, std) as floats, or (None, None).
    """
    defined = [v for v in values if v is not None]
    if not defined:
        return None, None
    try:
        array = np.asarray(defined, dtype=np.float64)  # [n_defined]
    except (TypeError, ValueError):
        raise InputError(f"summarize needs a list of numbers or None, got {defined[:3]!r}...") from None
    if array.ndim != 1:
        raise InputError(f"summarize needs a list of numbers or None, got {_describe(array)}")
    _check_finite(array, "per-frame metric values")
    with np.errstate(over="ignore"):
        mean, std = float(array.mean()), float(array.std(ddof=0))
    if not (math.isfinite(mean) and math.isfinite(std)):
        # The sum overflowed (values near 1e308): the same sums on values scaled by a power
        # of two, which is exact, then scaled back.
        exponent = math.frexp(float(np.abs(array).max()))[1]
        scaled = array * math.ldexp(1.0, -exponent)  # [n_defined], all in (-1, 1)
        mean, std = math.ldexp(float(scaled.mean()), exponent), math.ldexp(float(scaled.std(ddof=0)), exponent)
    return mean, std
