"""Render one view: RGBA and albedo with the path tracer (two independent half passes, so
the view states its own Monte Carlo noise), exact depth, normals and instance ids from
pixel-centre rays.

Depth is not the filtered depth AOV (averaged across edges, measured from a near-clip
shifted origin): every pixel's centre ray from `nerfgauge.core.camera.pixel_rays` is intersected
with the scene, giving the Euclidean ray distance from the camera centre. Instance ids
come from the same rays (not Mitsuba's box-filtered shape_index AOV, which averages ids
across edges), so they agree with the hit mask pixel for pixel.

Noise (docs/conventions.md, "Noise"): the spp samples of a view are rendered as two
passes A and B of spp/2 samples with different seeds; the stored image is their mean M.
A and B are independent and identically distributed, so Var(M) = Var(A) / 2 and
E[(A - B)^2] = 2 Var(A): a quarter of the mean squared difference estimates the mean's
variance without a reference. With spp 1 there is one pass and no estimate.

Determinism (issue 31): on the JIT variants (llvm_*, cuda_*) the colour and albedo are not
made by `mi.render`. Its film adds every sample into its pixel with an atomic scatter-add
(ImageBlock::put, box filter: `dr::scatter_reduce(ReduceOp::Add, ...)`) from all of Dr.Jit's
worker threads at once, so the order in which a pixel's float32 samples are summed, and so
the last bit of the sum, depends on thread scheduling. Measured on `primitives` (llvm_ad_rgb,
2 threads, one process, the same view and seed 8 times, 36 spp): 1 distinct image at 48 px,
2 at 64 px, 4 at 128 px; with `dr.set_thread_count(1)` 1 at 128 px. One differing ulp then
changes the noise JSON, the EXR's sha256 and the manifest. `render_samples` instead evaluates
the same samples (the sampler seeded and laid out as Mitsuba's SamplingIntegrator::render
does, drawn in its order: pixel position, aperture, time; RGB variants draw no wavelength)
into one value per sample and sums each pixel's samples in numpy in a fixed order (float64):
the same image as `mi.render` with the same seed to float32 rounding (relative 6e-7), at
1.0-1.13x its time per view (primitives, 64 px 64 spp and 128 px 72 spp, on a shared 2-core
machine). scalar_rgb keeps `mi.render`: each pixel there belongs to one image block rendered
by one thread with a sampler seeded from the block's number, so it is byte-identical from
run to run; the block size is fixed (mitsuba_scene.SCALAR_BLOCK_SIZE) because Mitsuba would
otherwise shrink the blocks with more threads (8 threads gave other bytes than 1 or 2).
tests/test_determinism.py holds all of this.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.camera import (
    Intrinsics,
    ThinLens,
    pixel_rays,
    to_mitsuba,
    z_depth_from_distance,
)
from nerfgauge.core.errors import InputError
from nerfgauge.core.images import linear_to_srgb, premultiplied_to_png_rgba
from nerfgauge.generate import distorted
from nerfgauge.generate.mitsuba_scene import SCALAR_BLOCK_SIZE

NEAR_CLIP = 1e-3  # scene units; only clips what is closer than this to the camera
SEED_STRIDE = 0x9E3779B9  # odd, ~0.62 * 2^32: sub-pass k of a view renders with seed + k * stride
MSE_FLOOR = 1e-10  # as eval.metrics: a noiseless view (all background) scores 100 dB, not inf
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}  # those `nerfgauge evaluate` offers
AOVS = "albedo:albedo"
# Albedo is box-filtered over the pixel from primary hits only (no light transport): only
# edge pixels vary, so few samples do. Mitsuba's aov integrator wrapped around the path
# tracer doubled the render time (128 px, primitives, llvm); alone at 4 spp it adds ~3%.
MAX_ALBEDO_SPP = 4
ALBEDO_CHUNK = 1 << 16  # the albedo render's chunk number (far beyond any pass's)
MAX_INSTANCES = 65535  # 16-bit ids, 0 = no geometry


@dataclass(frozen=True)
class NoiseTarget:
    """--spp auto: add samples until the view's sRGB noise PSNR (the worse background)
    reaches `noise_psnr` dB, starting from `start_spp` and never beyond `max_spp`."""

    noise_psnr: float
    start_spp: int = 16
    max_spp: int = 4096


@dataclass(frozen=True)
class ViewImages:
    """rgba [H,W,4] linear premultiplied (alpha = coverage); distance, z_depth [H,W]
    (0 where the centre ray misses); normals [H,W,3] world shading normals (0 on
    misses); hit [H,W] bool; instance [H,W] uint16 (0 = miss, k = legend entry k);
    albedo [H,W,3] linear, box-filtered like rgba; passes: ((rgba A [H,W,4], spp A),
    (rgba B, spp B)) or just A with spp 1 (their means, float64)."""

    rgba: np.ndarray
    distance: np.ndarray
    z_depth: np.ndarray
    normals: np.ndarray
    hit: np.ndarray
    instance: Optional[np.ndarray] = None
    albedo: Optional[np.ndarray] = None
    passes: tuple = ()

    @property
    def noise(self) -> dict:
        """noise_estimate of the passes (computed on each call: the writer thread calls it
        once, off the render thread)."""
        (rgba_a, n_a), (rgba_b, n_b) = self.passes if len(self.passes) == 2 else (self.passes[0], (None, 0))
        return noise_estimate(rgba_a, rgba_b, n_a, n_b)


def sensor_dict(mi, c2w: np.ndarray, intrinsics: Intrinsics, spp: int, lens: Optional[ThinLens] = None) -> dict:
    """A Mitsuba perspective sensor for an OpenGL camera-to-world pose; Mitsuba's `thinlens`
    sensor (same pose and field of view) when `lens` has a non-zero aperture. A lens with
    aperture 0 is the pinhole: the same perspective sensor, so the same pixels bit for bit."""
    if abs(intrinsics.fx - intrinsics.fy) > 1e-9 * intrinsics.fx or \
            (intrinsics.cx, intrinsics.cy) != (intrinsics.width / 2, intrinsics.height / 2):
        raise ValueError("Mitsuba's perspective sensor needs square pixels and a centred principal point")
    optics = {"type": "perspective"}
    if lens is not None and not lens.is_pinhole:
        # focus_distance: along the optical axis, as camera.thin_lens_rays has it
        optics = {"type": "thinlens", "aperture_radius": float(lens.aperture_radius),
                  "focus_distance": float(lens.focus_distance)}
    return optics | {
        "fov": intrinsics.fov_x_degrees,
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "far_clip": 1e7,
        "to_world": mi.ScalarTransform4f(to_mitsuba(c2w).tolist()),
        "film": {"type": "hdrfilm", "width": intrinsics.width, "height": intrinsics.height,
                 "rfilter": {"type": "box"}, "pixel_format": "rgba", "component_format": "float32"},
        "sampler": sampler_dict(spp),
    }


def multijitter_exact(spp: int) -> bool:
    """Mitsuba's multijitter uses a = floor(sqrt(spp)) columns and ceil(spp / a) rows and
    rounds the count up to their product (32 -> 35): exact for a^2, a^2 + a, a^2 + 2a."""
    columns = math.isqrt(int(spp))
    return columns * -(-int(spp) // columns) == int(spp)


def sampler_dict(spp: int) -> dict:
    """Multi-jittered samples when Mitsuba can lay `spp` out as a grid exactly; otherwise
    independent samples, so a view never gets a different count than scene.json states."""
    return {"type": "multijitter" if multijitter_exact(spp) else "independent", "sample_count": int(spp)}


def sample_chunks(spp: int) -> list:
    """`spp` as a sum of multijitter-exact counts, largest first (32 -> [30, 2]).

    Stratification matters: at 64 px, 64 multi-jittered samples of `primitives` are 8 dB
    less noisy than 64 independent ones; two passes of 36 are as good as one of 64. So a
    pass whose count multijitter cannot lay out is rendered as an exact grid plus a small
    remainder rather than with independent samples."""
    chunks, left = [], int(spp)
    while left > 0:
        a = math.isqrt(left)
        exact = max(n for n in (a * a, a * a + a, a * a + 2 * a) if n <= left)
        chunks.append(exact)
        left -= exact
    return chunks


def chunk_seed(view_seed: int, chunk: int) -> int:
    """Seed of a view's chunk-th render call; chunk 0 keeps the view's own seed."""
    return (int(view_seed) + chunk * SEED_STRIDE) % (2**32)


def render_chunk(mi, scene, integrator, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                 lens: Optional[ThinLens] = None, distortion=None, ray_map=None) -> np.ndarray:
    """`spp` samples per pixel of one view (through `lens` if given) with `seed`: with
    render_samples on the JIT variants (byte-identical from run to run), with mi.render on
    scalar ones. Returns [H, W, C] float32 whose last channels are the integrator's AOVs (the
    first four RGBA, except from mi.render with the AOV integrator, which gives the AOVs
    only). distortion: a core.distortion.Distortion the pixel grid is seen through (None or
    the identity: the pinhole); its samples go through generate.distorted (the AOVs then
    follow the RGBA on every variant). ray_map: every sample's own world ray (render_samples;
    the pixels' distortion is then the ray map's business)."""
    sensor = mi.load_dict(sensor_dict(mi, c2w, intrinsics, spp, lens))
    if ray_map is not None and mi.variant().startswith("scalar"):
        array = distorted.render_scalar(mi, scene, integrator, sensor, intrinsics, None, int(spp), int(seed), ray_map)
    elif ray_map is not None:
        array = render_samples(mi, scene, integrator, sensor, int(spp), int(seed), ray_map=ray_map)
    elif distortion is not None and not distortion.is_identity and mi.variant().startswith("scalar"):
        array = distorted.render_scalar(mi, scene, integrator, sensor, intrinsics, distortion, int(spp), int(seed))
    elif distortion is not None and not distortion.is_identity:
        array = render_samples(mi, scene, integrator, sensor, int(spp), int(seed), distorted.film_map(distortion, intrinsics))
    elif mi.variant().startswith("scalar"):
        image = mi.render(scene, sensor=sensor, integrator=integrator, spp=int(spp), seed=int(seed))
        array = np.array(image, dtype=np.float32)
    else:
        array = render_samples(mi, scene, integrator, sensor, int(spp), int(seed))
    return array.reshape(intrinsics.height, intrinsics.width, -1)


MAX_WAVE_SAMPLES = 1 << 22  # samples evaluated at once by render_samples (a band of rows per wave)
BAND_SEED_STRIDE = 0x85EBCA6B  # odd: band b > 0 of a render_samples call is seeded seed + b * stride


def band_rows(width: int, spp: int) -> int:
    """Rows of pixels per wave of render_samples: as many as keep a wave within
    MAX_WAVE_SAMPLES samples, at least one. A constant of the image size and spp only (never
    of the machine), so the bands and their seeds, and so the image, are too."""
    return max(1, MAX_WAVE_SAMPLES // (int(width) * int(spp)))


def band_seed(seed: int, band: int) -> int:
    """The sampler seed of band `band`; band 0 keeps `seed`, so an image that fits one wave
    has exactly mi.render's samples."""
    return (int(seed) + int(band) * BAND_SEED_STRIDE) % (2**32)


def render_samples(mi, scene, integrator, sensor, spp: int, seed: int, film_map=None, ray_map=None) -> np.ndarray:
    """mi.render's estimator, summed in a fixed order (the module's "Determinism").

    Each pixel's value is the mean of its `spp` samples, each box-filtered over the pixel's
    area (a uniform position in it, as Mitsuba's box filter puts a sample only into the pixel
    it was drawn in), with the sensor's ray weight; alpha is the share of samples whose ray
    hit something (the integrator's `valid`), as the film's A channel. The sampler is
    Mitsuba's own (multijitter stratifies each pixel's consecutive samples) and draws its
    dimensions in SamplingIntegrator::render_sample's order; ray differentials are scaled by
    1/sqrt(spp) as there. Rows are evaluated in bands of band_rows() (band b seeded
    band_seed(seed, b)), so no wave holds more than MAX_WAVE_SAMPLES samples (x 4 floats and
    the AOVs). film_map: None, or a function of the samples' film positions in pixels
    (u [n], v [n] float64) giving the film positions whose sensor rays they take instead (a
    lens distortion: generate.distorted); the sample order and seeds are unchanged.
    ray_map: None, or a function of the film positions (u [n], v [n] float64, pixels) giving
    each sample's world ray (origins, unit directions [n, 3] float64) in place of the
    sensor's (weight 1, no differentials; a rolling shutter: generate.motion).
    Returns [H, W, 4 + AOVs] float32."""
    import drjit as dr  # drjit: loaded with the Mitsuba variant, only when rendering

    if mi.is_spectral or mi.is_monochromatic:
        raise ValueError(f"render_samples handles the RGB variants nerfgauge uses, not {mi.variant()}")
    integrator = integrator if integrator is not None else scene.integrator()
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    sampler_template = sensor.sampler()
    sampler_template.set_sample_count(int(spp))
    if sampler_template.sample_count() != spp:
        raise ValueError(f"the sampler lays out {sampler_template.sample_count()} samples, not {spp}")
    rows = band_rows(width, spp)
    scale = mi.ScalarVector2f(1.0 / width, 1.0 / height)
    bands = []
    for band, top in enumerate(range(0, height, rows)):
        bottom = min(height, top + rows)
        count = (bottom - top) * width * spp
        sampler = sampler_template.clone()
        sampler.set_samples_per_wavefront(int(spp))
        sampler.seed(dr.opaque(mi.UInt32, band_seed(seed, band)), count)
        pixel = dr.arange(mi.UInt32, count) // dr.opaque(mi.UInt32, spp)
        row = pixel // width
        position = mi.Vector2f(mi.Float(pixel - row * width), mi.Float(row + dr.opaque(mi.UInt32, top)))
        position = position + sampler.next_2d()
        if film_map is not None:
            dr.eval(position)
            u, v = film_map(position.x.numpy().astype(np.float64), position.y.numpy().astype(np.float64))
            position = mi.Vector2f(mi.Float(np.asarray(u, np.float32)), mi.Float(np.asarray(v, np.float32)))
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time = time + sampler.next_1d() * sensor.shutter_open_time()
        wavelength = mi.Float(0.0)  # RGB variants draw no wavelength sample
        if ray_map is not None:
            dr.eval(position)
            origins, directions = ray_map(position.x.numpy().astype(np.float64), position.y.numpy().astype(np.float64))
            ray = mi.RayDifferential3f(mi.Ray3f(
                mi.Point3f(*(mi.Float(np.ascontiguousarray(origins[:, k], np.float32)) for k in range(3))),
                mi.Vector3f(*(mi.Float(np.ascontiguousarray(directions[:, k], np.float32)) for k in range(3)))))
            ray.time = time
            weight = mi.Float(1.0)
        else:
            ray, weight = sensor.sample_ray_differential(time, wavelength, position * scale, aperture)
        if ray.has_differentials:
            ray.scale_differential(1.0 / math.sqrt(spp))
        radiance, valid, aovs = integrator.sample(scene, sampler, ray, sensor.get_medium())
        rgb = mi.unpolarized_spectrum(weight * radiance)
        channels = [rgb[0], rgb[1], rgb[2], dr.select(valid, mi.Float(1.0), mi.Float(0.0))] + list(aovs)
        dr.eval(*channels)
        sums = np.empty(((bottom - top) * width, len(channels)))
        for k, channel in enumerate(channels):
            values = np.broadcast_to(channel.numpy(), (count,))  # a literal (an AOV that is 0) has width 1
            np.sum(values.reshape(-1, spp), axis=1, dtype=np.float64, out=sums[:, k])  # fixed order
        bands.append(sums / spp)
    return np.concatenate(bands).reshape(height, width, -1).astype(np.float32)


def render_rgba(mi, scene, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                lens: Optional[ThinLens] = None) -> np.ndarray:
    """Path-traced linear premultiplied RGBA in one pass (through `lens` if given).
    Returns [H, W, 4] float32."""
    return render_chunk(mi, scene, None, c2w, intrinsics, spp, seed, lens)[..., :4]


class _Pass:
    """A running sample-weighted mean of chunk images ([H, W, C] float64)."""

    def __init__(self):
        self.spp, self.total = 0, None

    def add(self, image: np.ndarray, spp: int) -> None:
        weighted = image.astype(np.float64) * spp
        self.total = weighted if self.total is None else self.total + weighted
        self.spp += spp

    @property
    def mean(self) -> np.ndarray:
        return self.total / self.spp


def aov_integrator(mi):
    """Mitsuba's `aov` integrator alone: the albedo of the first surface each camera
    sample hits, [H, W, 3] (0 where the sample misses)."""
    return mi.load_dict({"type": "aov", "aovs": AOVS, "block_size": SCALAR_BLOCK_SIZE})


def render_albedo(mi, scene, integrator, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                  distortion=None) -> np.ndarray:
    """Linear albedo, box-filtered over the pixel with min(spp, MAX_ALBEDO_SPP) samples
    (through `distortion`'s pixel grid when given). Returns [H, W, 3] float32."""
    count = max(n for n in range(1, min(int(spp), MAX_ALBEDO_SPP) + 1) if multijitter_exact(n))
    return render_chunk(mi, scene, integrator, c2w, intrinsics, count, chunk_seed(seed, ALBEDO_CHUNK),
                        distortion=distortion)[..., -3:]


def render_passes(mi, scene, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                  target: Optional[NoiseTarget] = None, integrator=None, lens: Optional[ThinLens] = None,
                  distortion=None, ray_map=None) -> tuple:
    """Two independent passes of spp/2 samples each (spp 1: pass A only). With a target,
    both passes grow by equal amounts until the noise estimate reaches it or the total
    reaches target.max_spp. Returns (pass A, pass B or None), each with .mean [H, W, 4]
    and .spp. integrator: None for the scene's own; lens: the colour's thin lens (None: pinhole);
    distortion: the pixel grid's lens distortion (None: pinhole); ray_map: render_chunk's."""
    passes, chunk = (_Pass(), _Pass()), 0

    def grow(per_pass: int) -> None:
        nonlocal chunk
        for one in passes:
            for count in sample_chunks(per_pass):
                one.add(render_chunk(mi, scene, integrator, c2w, intrinsics, count, chunk_seed(seed, chunk), lens,
                                         distortion, ray_map), count)
                chunk += 1

    if target is None:
        if spp == 1:
            passes[0].add(render_chunk(mi, scene, integrator, c2w, intrinsics, 1, seed, lens, distortion, ray_map), 1)
            return passes[0], None
        a_spp = spp // 2
        for count in sample_chunks(a_spp):
            passes[0].add(render_chunk(mi, scene, integrator, c2w, intrinsics, count, chunk_seed(seed, chunk), lens,
                                         distortion, ray_map), count)
            chunk += 1
        for count in sample_chunks(spp - a_spp):
            passes[1].add(render_chunk(mi, scene, integrator, c2w, intrinsics, count, chunk_seed(seed, chunk), lens,
                                         distortion, ray_map), count)
            chunk += 1
        return passes
    grow(max(1, min(target.start_spp, target.max_spp) // 2))
    goal = 10 ** (-target.noise_psnr / 10)  # the variance the target allows
    while True:
        total = passes[0].spp + passes[1].spp
        variance = auto_variance(passes[0].mean[..., :4], passes[1].mean[..., :4], passes[0].spp, passes[1].spp)
        if variance <= goal or total + 2 > target.max_spp:  # reached, or no room for one more pair
            return passes
        # Variance falls as 1/spp (at least): ask for what that predicts, 10% over, at
        # least double, within the cap.
        wanted = min(target.max_spp, max(2 * total, math.ceil(1.1 * total * variance / goal)))
        grow(max(1, (wanted - total) // 2))


def mean_of_passes(pass_a: _Pass, pass_b: Optional[_Pass]) -> np.ndarray:
    """The stored image: the sample-weighted mean of both passes. [H, W, C] float32."""
    if pass_b is None:
        return pass_a.mean.astype(np.float32)
    return ((pass_a.total + pass_b.total) / (pass_a.spp + pass_b.spp)).astype(np.float32)


def straight_srgb(rgba_linear: np.ndarray) -> tuple:
    """Linear premultiplied RGBA [H, W, 4] -> (straight-alpha sRGB [H, W, 3], alpha
    [H, W, 1]) as the PNG holds them before 8-bit rounding, float64."""
    alpha = np.clip(rgba_linear[..., 3:4].astype(np.float64), 0.0, 1.0)
    straight = np.divide(rgba_linear[..., :3], alpha, out=np.zeros(rgba_linear.shape[:-1] + (3,)), where=alpha > 0)
    return linear_to_srgb(straight), alpha


def _composite(srgb_alpha: tuple, background) -> np.ndarray:
    """c * a + b * (1 - a), as eval.metrics.composite. Returns [H, W, 3] float64."""
    srgb, alpha = srgb_alpha
    return np.clip(srgb * alpha + np.asarray(background, np.float64) * (1 - alpha), 0.0, 1.0)


def as_metrics_see(rgba_linear: np.ndarray, background) -> np.ndarray:
    """Linear premultiplied RGBA -> the colour `nerfgauge evaluate` scores: straight-alpha
    sRGB (the PNG, before 8-bit rounding) composited onto `background`. [H, W, 4] ->
    [H, W, 3] float64."""
    return _composite(straight_srgb(rgba_linear), background)


def png_straight(rgba_linear: np.ndarray) -> tuple:
    """The stored 8-bit PNG of `rgba_linear` as (straight sRGB [H, W, 3], alpha [H, W, 1])
    on [0, 1], for _composite."""
    png = premultiplied_to_png_rgba(rgba_linear).astype(np.float64) / 255.0
    return png[..., :3], png[..., 3:]


def _variance_of_mean(a: np.ndarray, b: np.ndarray, n_a: int, n_b: int) -> float:
    """Mean over pixels and channels of the estimated variance of the (n_a A + n_b B) /
    (n_a + n_b) mean: E[(A - B)^2] = s2 (1/n_a + 1/n_b), Var = s2 / (n_a + n_b), so the
    factor is n_a n_b / (n_a + n_b)^2 (1/4 for equal passes, where it needs no assumption
    about how variance falls with spp)."""
    factor = n_a * n_b / (n_a + n_b) ** 2
    return float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) * factor)


def psnr_of_variance(variance: float) -> float:
    """10 log10(1 / variance) for a peak of 1, capped at 100 dB like eval.metrics.psnr."""
    return 10.0 * math.log10(1.0 / max(variance, MSE_FLOOR))


def auto_variance(rgba_a, rgba_b, n_a, n_b) -> float:
    """What --spp auto drives down: the larger sRGB variance of the two backgrounds."""
    a, b = straight_srgb(rgba_a), straight_srgb(rgba_b)
    return max(_variance_of_mean(_composite(a, bg), _composite(b, bg), n_a, n_b) for bg in BACKGROUNDS.values())


def noise_estimate(rgba_a: np.ndarray, rgba_b: Optional[np.ndarray], n_a: int, n_b: int) -> dict:
    """The view's noise, from its two passes (linear premultiplied RGBA [H, W, 4] each).

    noise_psnr: {"linear": on the EXR's RGB, "srgb_white"/"srgb_black": on the colour the
    evaluator scores (as_metrics_see), the transfer function applied to each pass before
    differencing}; dB, 10 log10(1 / mean variance of the stored mean). psnr_ceiling:
    {background: the PSNR that the noise-free image would score against the stored PNG,
    from the sRGB variance plus the PNG's own 8-bit rounding error}. spp: samples used.
    With one pass (spp 1) the numbers are None and `reason` says why."""
    mean = rgba_a if rgba_b is None else (n_a * rgba_a.astype(np.float64) + n_b * rgba_b) / (n_a + n_b)
    mean_srgb, png = straight_srgb(mean), png_straight(mean)
    quantisation = {name: float(np.mean((_composite(png, bg) - _composite(mean_srgb, bg)) ** 2))
                    for name, bg in BACKGROUNDS.items()}
    out = {"spp": int(n_a + n_b), "passes": [int(n_a)] + ([int(n_b)] if rgba_b is not None else []),
           "png_quantisation_mse": quantisation}
    if rgba_b is None:
        reason = "spp 1: a single pass, no two independent halves to compare"
        return out | {"noise_psnr": None, "psnr_ceiling": None, "reason": reason}
    variance = {"linear": _variance_of_mean(rgba_a[..., :3], rgba_b[..., :3], n_a, n_b)}
    srgb_a, srgb_b = straight_srgb(rgba_a), straight_srgb(rgba_b)
    for name, bg in BACKGROUNDS.items():
        variance[f"srgb_{name}"] = _variance_of_mean(_composite(srgb_a, bg), _composite(srgb_b, bg), n_a, n_b)
    return out | {"noise_psnr": {key: psnr_of_variance(value) for key, value in variance.items()},
                  "psnr_ceiling": {name: psnr_of_variance(variance[f"srgb_{name}"] + quantisation[name])
                                   for name in BACKGROUNDS}}


def cast_rays(mi, scene, origins: np.ndarray, directions: np.ndarray):
    """Intersect rays with the scene: cast_rays_with_ids without the ids."""
    return cast_rays_with_ids(mi, scene, origins, directions)[:3]


def cast_rays_with_ids(mi, scene, origins: np.ndarray, directions: np.ndarray, shape_ids: tuple = ()):
    """Intersect rays with the scene.

    origins, directions: [N, 3] (directions unit). shape_ids: Mitsuba shape ids in legend
    order. Returns distance [N] (inf on miss), shading normal [N, 3] (0 on miss), hit [N]
    bool, instance [N] uint16 (1 + the hit shape's position in shape_ids, 0 on a miss or a
    shape not listed).
    """
    if mi.variant().startswith("scalar"):
        return _cast_rays_scalar(mi, scene, origins, directions, shape_ids)

    o = mi.Point3f(*(np.ascontiguousarray(origins[:, k], np.float32) for k in range(3)))
    d = mi.Vector3f(*(np.ascontiguousarray(directions[:, k], np.float32) for k in range(3)))
    si = scene.ray_intersect(mi.Ray3f(o, d))
    hit = np.array(si.is_valid(), dtype=bool)
    distance = np.where(hit, np.array(si.t, dtype=np.float64), np.inf)
    normals = np.stack([np.array(si.sh_frame.n[k], dtype=np.float64) for k in range(3)], -1)
    # A ShapePtr is an index into Dr.Jit's instance registry: one read, then a lookup table.
    import drjit as dr  # drjit: only when a view renders

    registry = np.array(dr.reinterpret_array(mi.UInt32, si.shape), dtype=np.int64)
    numbers = {name: number for number, name in enumerate(shape_ids, start=1)}
    table = np.zeros(max([int(registry.max(initial=0))] + [0]) + 1, np.uint16)
    for shape in scene.shapes():
        index = int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape)))[0])
        if index >= len(table):
            continue  # no ray hit it
        table[index] = numbers.get(shape.id(), 0)
    instance = np.where(hit, table[registry], 0).astype(np.uint16)
    return distance, np.where(hit[:, None], normals, 0.0), hit, instance


def _cast_rays_scalar(mi, scene, origins, directions, shape_ids):
    n = len(origins)
    distance, normals, hit = np.full(n, np.inf), np.zeros((n, 3)), np.zeros(n, bool)
    instance = np.zeros(n, np.uint16)
    numbers = {name: number for number, name in enumerate(shape_ids, start=1)}
    for index in range(n):
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*origins[index]), mi.Vector3f(*directions[index])))
        if si.is_valid():
            hit[index], distance[index] = True, si.t
            normals[index] = [si.sh_frame.n[0], si.sh_frame.n[1], si.sh_frame.n[2]]
            instance[index] = numbers.get(si.shape.id(), 0)
    return distance, normals, hit, instance


def render_geometry(mi, scene, c2w, intrinsics: Intrinsics):
    """Exact distance, z-depth, normals and hit mask from pixel-centre rays."""
    return render_geometry_with_ids(mi, scene, c2w, intrinsics)[:4]


def render_geometry_with_ids(mi, scene, c2w, intrinsics: Intrinsics, shape_ids: tuple = (), distortion=None):
    """Exact distance, z-depth, normals, hit mask and instance ids ([H, W] uint16, see
    cast_rays_with_ids) from pixel-centre rays (through `distortion` when given)."""
    origins, directions = pixel_rays(c2w, intrinsics, distortion)
    shape = directions.shape[:2]
    distance, normals, hit, instance = cast_rays_with_ids(mi, scene, origins.reshape(-1, 3), directions.reshape(-1, 3),
                                                 shape_ids)
    distance = np.where(hit, distance, 0.0).reshape(shape)
    z_depth = z_depth_from_distance(distance, directions, c2w)
    return (distance.astype(np.float32), z_depth.astype(np.float32),
            normals.reshape(*shape, 3).astype(np.float32), hit.reshape(shape), instance.reshape(shape))


def instance_legend(scene) -> tuple:
    """Mitsuba shape ids in legend order: every shape sorted by id, so a number names the
    same shape in every view and every run (Mitsuba's own shape order is not promised)."""
    return tuple(sorted(shape.id() for shape in scene.shapes()))


_LOADED = {}  # the last scene's (scene, albedo integrator, legend): one integrator per loaded scene


def _loaded_for(mi, scene) -> tuple:
    """(aov integrator, legend) of `scene`, made once per scene: a new integrator object
    per view would make Dr.Jit compile the render kernel again for every view."""
    if _LOADED.get("scene") is not scene:
        _LOADED.update(scene=scene, integrator=aov_integrator(mi), legend=instance_legend(scene))
    return _LOADED["integrator"], _LOADED["legend"]


def render_view(mi, scene, c2w, intrinsics: Intrinsics, spp: int, seed: int, *,
                target: Optional[NoiseTarget] = None, integrator=None, legend: Optional[tuple] = None,
                lens: Optional[ThinLens] = None, distortion=None) -> ViewImages:
    """Everything one view writes. integrator, legend: aov_integrator(mi) (for albedo) and
    instance_legend(scene); made once per scene when not given. Colour through `lens`
    (None: pinhole); depth, normals, mask, ids and albedo always from the pinhole camera.
    distortion (a core.distortion.Distortion, None: none) moves every pixel's samples and its
    centre ray, so colour, albedo, depth, normals, mask and ids all follow the distorted grid."""
    if spp == "auto" and target is None:
        raise InputError("--spp auto needs a noise target (--noise-psnr)")
    if integrator is None or legend is None:
        integrator, legend = _loaded_for(mi, scene)
    pass_a, pass_b = render_passes(mi, scene, c2w, intrinsics, spp, seed, target, lens=lens, distortion=distortion)
    image = mean_of_passes(pass_a, pass_b)
    albedo = render_albedo(mi, scene, integrator, c2w, intrinsics, pass_a.spp + (pass_b.spp if pass_b else 0), seed,
                           distortion)
    passes = ((pass_a.mean, pass_a.spp),) + (() if pass_b is None else ((pass_b.mean, pass_b.spp),))
    distance, z_depth, normals, hit, instance = render_geometry_with_ids(mi, scene, c2w, intrinsics, legend, distortion)
    return ViewImages(image[..., :4], distance, z_depth, normals, hit, instance, albedo, passes)
