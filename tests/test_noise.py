"""The two-pass Monte Carlo noise estimate (generate.render, docs/conventions.md "Noise").

The maths is checked on synthetic passes with a known variance; the renderer's estimate
against the error of the stored image to a 16x-spp reference of the same views."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest

from nerfgauge.core.errors import InputError
from nerfgauge.generate import render
from nerfgauge.generate.pipeline import GenerateConfig, plan
from nerfgauge.generate.views import view_seed


def rgba_with_noise(rng, sigma, shape=(64, 64)):
    """A premultiplied RGBA image: a fixed mean plus Gaussian noise of std `sigma` in RGB."""
    mean = np.full(shape + (4,), 0.5)
    mean[..., 3] = 1.0
    noisy = mean.copy()
    noisy[..., :3] += rng.normal(0, sigma, shape + (3,))
    return noisy


def test_estimate_recovers_the_variance_of_the_mean_of_two_passes():
    rng = np.random.default_rng(0)
    sigma = 0.01  # each pass's per-pixel std; the mean of two has variance sigma^2 / 2
    a, b = rgba_with_noise(rng, sigma, (256, 256)), rgba_with_noise(rng, sigma, (256, 256))
    noise = render.noise_estimate(a, b, 8, 8)
    expected = 10 * math.log10(1 / (sigma**2 / 2))
    # 196608 squared differences: the relative std of their mean is sqrt(2 / n) = 0.3%, 0.014 dB.
    assert noise["noise_psnr"]["linear"] == pytest.approx(expected, abs=0.06)
    assert noise["spp"] == 16 and noise["passes"] == [8, 8]


def test_unequal_passes_weigh_the_difference_by_their_counts():
    rng = np.random.default_rng(1)
    sigma1 = 0.02  # one sample's std: a pass of n samples has std sigma1 / sqrt(n)
    n_a, n_b = 3, 1
    a = rgba_with_noise(rng, sigma1 / math.sqrt(n_a), (256, 256))
    b = rgba_with_noise(rng, sigma1 / math.sqrt(n_b), (256, 256))
    expected = 10 * math.log10((n_a + n_b) / sigma1**2)  # Var(mean) = sigma1^2 / (n_a + n_b)
    assert render.noise_estimate(a, b, n_a, n_b)["noise_psnr"]["linear"] == pytest.approx(expected, abs=0.06)


def test_identical_passes_cap_at_100_db_and_srgb_uses_the_composited_colour():
    image = rgba_with_noise(np.random.default_rng(2), 0.0)
    noise = render.noise_estimate(image, image.copy(), 2, 2)
    assert noise["noise_psnr"] == {"linear": 100.0, "srgb_white": 100.0, "srgb_black": 100.0}
    # The ceiling is then the PNG's own rounding: 0.5 in sRGB is not a multiple of 1/255.
    srgb = render.as_metrics_see(image, (1, 1, 1))
    rounding = np.mean((np.round(srgb * 255) / 255 - srgb) ** 2)
    assert noise["psnr_ceiling"]["white"] == pytest.approx(10 * math.log10(1 / rounding), abs=1e-6)


def test_transparent_pixels_carry_no_colour_noise_on_either_background():
    rng = np.random.default_rng(3)
    a, b = rgba_with_noise(rng, 0.05), rgba_with_noise(rng, 0.05)
    a[..., 3] = b[..., 3] = 0.0  # nothing covers the pixels: the evaluator sees pure background
    a[..., :3] = np.abs(a[..., :3])
    noise = render.noise_estimate(a, b, 4, 4)
    assert noise["noise_psnr"]["srgb_white"] == noise["noise_psnr"]["srgb_black"] == 100.0
    assert noise["noise_psnr"]["linear"] < 40  # the linear RGB still differs


def test_spp_1_gives_no_estimate_and_says_why():
    image = rgba_with_noise(np.random.default_rng(4), 0.01)
    noise = render.noise_estimate(image, None, 1, 0)
    assert noise["noise_psnr"] is None and noise["psnr_ceiling"] is None
    assert "spp 1" in noise["reason"] and noise["spp"] == 1


@pytest.mark.parametrize("spp", [1, 2, 5, 32, 35, 36, 64, 512, 1000])
def test_passes_split_into_exact_multijitter_chunks(spp):
    chunks = render.sample_chunks(spp)
    assert sum(chunks) == spp and all(render.multijitter_exact(n) for n in chunks)
    assert chunks == sorted(chunks, reverse=True) and len(chunks) <= 3


def test_chunk_seeds_are_distinct_from_every_other_views_seed():
    seeds = {view_seed(0, split, i) for split in ("train", "val", "test") for i in range(1000)}
    chunk_seeds = {render.chunk_seed(s, k) for s in seeds for k in range(1, 4)}
    assert not seeds & chunk_seeds and len(chunk_seeds) == 3 * len(seeds)


def rendered_views(mi, scene_name, res, views):
    """(Mitsuba scene, plan) of `views` test views of a scene at res x res."""
    from nerfgauge.generate.mitsuba_scene import scene_dict, write_meshes

    the_plan = plan(GenerateConfig(scene=scene_name, views=1, val_views=0, test_views=views, width=res, height=res))
    folder = Path(tempfile.mkdtemp(prefix="noise-"))
    paths = write_meshes(the_plan.scene, folder)
    return mi.load_dict(scene_dict(mi, the_plan.scene, paths, 8)), the_plan


@pytest.mark.slow
@pytest.mark.parametrize("scene_name, res, repeats", [("primitives", 64, 4), ("inside", 32, 2)])
def test_estimate_agrees_with_a_16x_spp_reference(mi, scene_name, res, repeats):
    """Pooled over 8 views rendered `repeats` times, each stored view's estimated variance
    against its actual squared error to a 16x-spp render of the same view. The
    reference's own variance is at most 1/16 of the view's, so E[MSE] lies between the
    variance and 17/16 of it: the midpoint is compared. Pooling, because the per-pixel
    squared differences are heavy-tailed (caustics): one 32 px view's estimate scatters by
    about 1 dB, 8 views at 64 px by about 0.4 dB."""
    spp, views = 16, 8
    scene, the_plan = rendered_views(mi, scene_name, res, views)
    estimated = {"linear": 0.0, "srgb_white": 0.0}
    actual = {"linear": 0.0, "srgb_white": 0.0}
    for index, c2w in enumerate(the_plan.poses["test"]):
        reference = render.render_view(mi, scene, c2w, the_plan.intrinsics, 16 * spp, 10_000 + index).rgba
        for repeat in range(repeats):
            view = render.render_view(mi, scene, c2w, the_plan.intrinsics, spp, 100 * repeat + index)
            for key in estimated:
                estimated[key] += 10 ** (-view.noise["noise_psnr"][key] / 10)
            actual["linear"] += np.mean((view.rgba[..., :3].astype(np.float64) - reference[..., :3]) ** 2)
            actual["srgb_white"] += np.mean((render.as_metrics_see(view.rgba, (1, 1, 1))
                                             - render.as_metrics_see(reference, (1, 1, 1))) ** 2)
    for key in estimated:
        gap_db = 10 * math.log10(estimated[key] * (1 + 1 / 32) / actual[key])
        assert abs(gap_db) < 0.5, f"{scene_name} {key}: estimate {gap_db:+.2f} dB off the reference"


def test_spp_1_views_render_without_an_estimate(mi):
    scene, the_plan = rendered_views(mi, "primitives", 16, 1)
    view = render.render_view(mi, scene, the_plan.poses["test"][0], the_plan.intrinsics, 1, 0)
    assert view.noise["noise_psnr"] is None and view.noise["passes"] == [1]


def test_two_passes_are_deterministic_and_their_mean_is_the_stored_image(mi):
    scene, the_plan = rendered_views(mi, "primitives", 16, 1)
    c2w = the_plan.poses["test"][0]
    first = render.render_view(mi, scene, c2w, the_plan.intrinsics, 8, 5)
    again = render.render_view(mi, scene, c2w, the_plan.intrinsics, 8, 5)
    assert np.array_equal(first.rgba, again.rgba) and first.noise == again.noise
    a, b = render.render_passes(mi, scene, c2w, the_plan.intrinsics, 8, 5)
    assert (a.spp, b.spp) == (4, 4)
    np.testing.assert_allclose(first.rgba, (a.mean[..., :4] + b.mean[..., :4]) / 2, atol=1e-6)


@pytest.mark.slow
def test_auto_spp_adds_samples_until_the_target_and_stops_at_the_cap(mi):
    scene, the_plan = rendered_views(mi, "primitives", 16, 1)
    c2w = the_plan.poses["test"][0]
    easy = render.render_view(mi, scene, c2w, the_plan.intrinsics, 0, 1, target=render.NoiseTarget(20.0))
    assert easy.noise["spp"] == 16  # the first round already meets 20 dB
    target = render.NoiseTarget(34.0, start_spp=4, max_spp=512)
    view = render.render_view(mi, scene, c2w, the_plan.intrinsics, 0, 1, target=target)
    worse = min(view.noise["noise_psnr"]["srgb_white"], view.noise["noise_psnr"]["srgb_black"])
    assert view.noise["spp"] > 4 and (worse >= 34.0 or view.noise["spp"] >= 512)
    capped = render.render_view(mi, scene, c2w, the_plan.intrinsics, 0, 1,
                                target=render.NoiseTarget(79.0, start_spp=4, max_spp=24))
    assert capped.noise["spp"] in (23, 24) and capped.noise["passes"][0] == capped.noise["passes"][1] or \
        capped.noise["spp"] == 24


@pytest.mark.parametrize("overrides, message", [
    ({"spp": "auto", "noise_psnr": float("nan")}, "--noise-psnr must be a finite"),
    ({"spp": "auto", "noise_psnr": float("inf")}, "--noise-psnr must be a finite"),
    ({"spp": "auto", "noise_psnr": 80.5}, "--noise-psnr must be a finite"),
    ({"spp": "auto"}, "--spp auto needs --noise-psnr"),
    ({"spp": 1, "noise_psnr": 30.0}, "--spp 1 renders one pass"),
    ({"spp": 16, "noise_psnr": 30.0}, "--noise-psnr is the target of --spp auto"),
])
def test_bad_noise_settings_are_refused_in_one_line(overrides, message):
    with pytest.raises(InputError, match=message) as caught:
        plan(GenerateConfig(**overrides))
    assert "\n" not in str(caught.value)


def test_generated_dataset_states_its_noise_per_frame_and_split(tiny_dataset):
    import json

    from nerfgauge.core.dataset import Dataset

    ds = Dataset(tiny_dataset)
    noise = json.loads((tiny_dataset / "scene.json").read_text())["noise"]
    frames = noise["splits"]["test"]["frames"]
    assert [f["name"] for f in frames] == list(ds.frames("test"))
    for index, frame in enumerate(frames):
        assert ds.noise("test", index)["noise_psnr"] == frame["noise_psnr"]
        assert frame["spp"] == 4 and frame["passes"] == [2, 2]
        assert frame["psnr_ceiling"]["white"] <= frame["noise_psnr"]["srgb_white"]
    mean = np.mean([f["noise_psnr"]["srgb_white"] for f in frames])
    assert noise["splits"]["test"]["noise_psnr"]["srgb_white"] == pytest.approx(mean)

