"""The pixel's footprint (issue 34, item 1): training rays through any point of a pixel and
box-filtered renders, checked against rays built independently from shifted intrinsics."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerfgauge.core.camera import Intrinsics, SplitCameras, look_at, pixel_rays
from nerfgauge.nerf.data import jittered_direction, pixel_footprints
from nerfgauge.nerf.frames import box_frame, pixel_offsets


def _camera(seed: int):
    rng = np.random.default_rng(seed)
    eye = rng.normal(size=3) * 3
    intrinsics = Intrinsics(width=13, height=9, fx=11.0, fy=12.5, cx=6.1, cy=4.7)
    return look_at(eye, rng.normal(size=3) * 0.3), intrinsics


def _shifted_rays(c2w, intrinsics, offset):
    """Rays through (column + 0.5 + ox, row + 0.5 + oy): the pinhole's rays with the
    principal point moved by -offset (an independent route to the same rays)."""
    moved = replace(intrinsics, cx=intrinsics.cx - offset[0], cy=intrinsics.cy - offset[1])
    return pixel_rays(c2w, moved)[1].reshape(-1, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_jittered_ray_is_the_ray_through_that_point_of_the_pixel(seed):
    c2w, intrinsics = _camera(seed)
    _, directions = pixel_rays(c2w, intrinsics)
    footprint = torch.from_numpy(pixel_footprints(directions, c2w))
    centre = torch.from_numpy(directions.reshape(-1, 3))
    rng = np.random.default_rng(seed)
    for offset in rng.uniform(-0.5, 0.5, size=(4, 2)):
        got = jittered_direction(centre.float(), footprint, torch.tensor(offset, dtype=torch.float32).expand(len(centre), 2))
        expected = _shifted_rays(c2w, intrinsics, offset)
        # float32 footprint and directions: a few ulps of a unit vector
        assert np.abs(got.numpy() - expected).max() < 2e-6
        assert np.allclose(np.linalg.norm(got.numpy(), axis=1), 1, atol=1e-6)


def test_pixel_offsets_are_the_midpoint_rule():
    for n in (1, 2, 3, 5):
        offsets = pixel_offsets(n)
        assert offsets.shape == (n * n, 2) and np.allclose(offsets.mean(axis=0), 0, atol=1e-15)
        assert np.all(np.abs(offsets) < 0.5) and len({tuple(o) for o in offsets}) == n * n
        # the cells' centres: spaced 1/n, so the rule integrates a linear function over the pixel exactly
        assert np.allclose(np.sort(np.unique(offsets[:, 0])), (np.arange(n) + 0.5) / n - 0.5)
    assert np.array_equal(pixel_offsets(1), [[0.0, 0.0]])


class EdgeField:
    """A stand-in model: colour by which side of a plane through the origin a ray points to
    (a sharp edge in the image), opacity 1, depth the ray's x component (so the centre ray
    can be told from the others)."""

    def render(self, origins, directions):
        side = (directions @ torch.tensor([0.6, 0.0, 0.8]) > 0).float()
        rgb = torch.stack([side, 1 - side, 0.5 * torch.ones_like(side)], dim=-1)
        return SimpleNamespace(rgb=rgb, opacity=torch.ones_like(side), depth=directions[:, 0])


@pytest.mark.parametrize("per_axis", [1, 2, 3])
def test_a_box_frame_averages_the_rays_through_the_grid_of_points(per_axis):
    c2w, intrinsics = _camera(5)
    cameras = SplitCameras("test", ("a",), np.stack([c2w]), intrinsics)
    rgb, opacity, depth = box_frame(EdgeField(), cameras, 0, per_axis, None, 1, torch.device("cpu"))
    field = EdgeField()
    # opaque rays: the pixel is the sRGB of the rays' mean linear value (the ground truth's
    # box filter, in linear light), by numpy's transfer functions
    from nerfgauge.core.images import linear_to_srgb, srgb_to_linear

    ray_colours = [field.render(None, torch.from_numpy(_shifted_rays(c2w, intrinsics, offset)).float()).rgb.numpy()
                   for offset in pixel_offsets(per_axis)]
    expected = linear_to_srgb(np.mean([srgb_to_linear(colour.astype(np.float64)) for colour in ray_colours], axis=0))
    assert np.allclose(rgb.numpy(), expected, atol=1e-5)
    assert torch.all(opacity == 1)
    centre = pixel_rays(c2w, intrinsics)[1].reshape(-1, 3)[:, 0]
    assert np.allclose(depth.numpy(), centre, atol=1e-6)  # depth of the centre rays, as the ground truth's
    # the edge crosses the image: a mixed pixel exists once there is more than one ray
    mixed = (rgb[:, 0] > 0) & (rgb[:, 0] < 1)
    assert bool(mixed.any()) == (per_axis > 1)


def test_pixel_sample_offsets_are_the_box_renders_points_or_one_uniform_point():
    """2 x 2 and 3 x 3: every pixel's rays go through the centres of its k x k cells, in the
    order the box render averages them (nerf.frames.pixel_offsets, checked against the
    midpoint rule by its own test), with no draw from the generator; 1: a uniform point."""
    from nerfgauge.nerf.train import pixel_sample_offsets

    generator = torch.Generator().manual_seed(0)
    n_pixels = 500
    for per_pixel in (4, 9):
        k = int(round(per_pixel ** 0.5))
        state = generator.get_state()
        offsets = pixel_sample_offsets(n_pixels, per_pixel, generator).view(per_pixel, n_pixels, 2)
        assert torch.equal(generator.get_state(), state)
        centres = (torch.arange(k, dtype=torch.float32) + 0.5) / k - 0.5
        y, x = torch.meshgrid(centres, centres, indexing="ij")  # ray r: cell (r % k, r // k), x fastest
        expected = torch.stack([x.reshape(-1), y.reshape(-1)], dim=-1)  # [per_pixel, 2]
        assert torch.allclose(offsets, expected[:, None, :].expand(per_pixel, n_pixels, 2), rtol=0, atol=1e-7)
    uniform = pixel_sample_offsets(20_000, 1, generator)
    assert uniform.shape == (20_000, 2) and bool(((uniform >= -0.5) & (uniform < 0.5)).all())
    # U[-0.5, 0.5): mean 0 and variance 1/12, within 4 standard errors
    assert torch.allclose(uniform.double().mean(dim=0), torch.zeros(2, dtype=torch.float64), atol=4 * (1 / 12 / 20_000) ** 0.5)
    assert torch.allclose(uniform.double().var(dim=0), torch.full((2,), 1 / 12, dtype=torch.float64), atol=0.003)


@pytest.mark.parametrize("per_axis", [2, 3])
def test_an_edges_only_frame_is_the_box_on_the_centre_renders_edges_and_the_centre_elsewhere(per_axis):
    from nerfgauge.core.pixel_edges import ALPHA_ROUNDING, edge_mask
    from nerfgauge.nerf.frames import rgba_png

    c2w, intrinsics = _camera(5)
    cameras = SplitCameras("test", ("a",), np.stack([c2w]), intrinsics)
    device = torch.device("cpu")
    centre = box_frame(EdgeField(), cameras, 0, 1, None, 1, device)
    box = box_frame(EdgeField(), cameras, 0, per_axis, None, 1, device)
    rgb, opacity, depth = box_frame(EdgeField(), cameras, 0, per_axis, None, 1, device, edges_only=True,
                                    sub_rays="edge-pixels")  # the default, "changes": tests/test_render_sub_rays.py
    straight = rgba_png(centre[0].numpy(), centre[1].numpy(), intrinsics.height, intrinsics.width) / 255.0
    edges = edge_mask(straight, alpha_rounding=ALPHA_ROUNDING).reshape(-1)
    assert 0 < edges.sum() < edges.size  # the plane's edge crosses the image, and not everywhere
    assert torch.equal(rgb[torch.from_numpy(edges)], box[0][torch.from_numpy(edges)])
    assert torch.equal(rgb[torch.from_numpy(~edges)], centre[0][torch.from_numpy(~edges)])
    assert torch.equal(depth, centre[2]) and torch.all(opacity == 1)
    # a frame with no edge pixel at all is its centre render
    flat = SimpleNamespace(render=lambda o, d: SimpleNamespace(rgb=torch.full((len(d), 3), 0.3), opacity=torch.ones(len(d)),
                                                               depth=d[:, 0]))
    for sub_rays in ("edge-pixels", "changes"):
        assert all(torch.equal(a, b) for a, b in zip(box_frame(flat, cameras, 0, per_axis, None, 1, device, True, sub_rays),
                                                     box_frame(flat, cameras, 0, 1, None, 1, device)))


@pytest.mark.parametrize("per_axis", [2, 3])
def test_the_edges_filter_spends_the_box_renders_rays_on_edge_pixels_and_the_centre_ray_on_the_rest(per_axis):
    from nerfgauge.nerf.data import RayBatch
    from nerfgauge.nerf.train import _edge_rays

    c2w, intrinsics = _camera(3)
    origins, directions = pixel_rays(c2w, intrinsics)
    n = intrinsics.width * intrinsics.height
    is_edge = torch.arange(n) % 3 == 0
    rays = RayBatch(torch.from_numpy(origins.reshape(-1, 3)).float(), torch.from_numpy(directions.reshape(-1, 3)).float(),
                    torch.zeros((n, 4)), 1, torch.from_numpy(pixel_footprints(directions, c2w)), is_edge)
    index = torch.randperm(n, generator=torch.Generator().manual_seed(0))[:50]
    per_pixel = per_axis ** 2
    (ray_o, ray_d), split = _edge_rays(rays, index, rays.origins[index], rays.directions[index], per_pixel,
                                       torch.Generator().manual_seed(1), torch.device("cpu"))
    n_edge = int(is_edge[index].sum())
    assert 0 < n_edge < 50 and ray_d.shape == (50 - n_edge + per_pixel * n_edge, 3)
    # a plain pixel's one ray is its centre ray
    assert torch.equal(ray_d[:50 - n_edge], rays.directions[index][~is_edge[index]])
    # an edge pixel's rays: block r holds, for every edge pixel in batch order, its ray through
    # the centre of cell r (pixel_sample_offsets' placement is checked above, the ray through
    # a point against shifted intrinsics)
    from nerfgauge.nerf.train import pixel_sample_offsets

    edge_pixels = index[is_edge[index]]
    offsets = pixel_sample_offsets(n_edge, per_pixel, torch.Generator().manual_seed(1))
    expected = jittered_direction(rays.directions[edge_pixels].repeat(per_pixel, 1),
                                  rays.footprint[edge_pixels].repeat(per_pixel, 1, 1), offsets)
    assert torch.equal(ray_d[50 - n_edge:], expected)
    assert torch.equal(ray_o[50 - n_edge:], rays.origins[edge_pixels].repeat(per_pixel, 1))
    # pixel values: the plain pixels' rays as they are, each edge pixel the mean of its rays
    # (a grey opaque ray's linear value is its own: the mean in linear light, by hand)
    generator = torch.Generator().manual_seed(2)
    grey = torch.rand(len(ray_d), generator=generator, dtype=torch.float64) * 0.8 + 0.2
    opacity = torch.rand(len(ray_d), generator=generator, dtype=torch.float64) * 0.9 + 0.1
    rgb, alpha = split.gather(grey[:, None].expand(-1, 3) * opacity[:, None], opacity)
    plain = ~is_edge[index]
    assert torch.equal(alpha[plain], opacity[:50 - n_edge]) and torch.equal(rgb[plain, 0], (grey * opacity)[:50 - n_edge])
    linear = torch.where(grey <= 0.04045, grey / 12.92, ((grey + 0.055) / 1.055) ** 2.4) * opacity
    mean_alpha = opacity[50 - n_edge:].view(per_pixel, n_edge).mean(dim=0)
    mean_linear = linear[50 - n_edge:].view(per_pixel, n_edge).mean(dim=0) / mean_alpha
    expected = (1.055 * mean_linear ** (1 / 2.4) - 0.055) * mean_alpha  # grey >= 0.2: every mean is on the power branch
    assert torch.allclose(alpha[~plain], mean_alpha) and torch.allclose(rgb[~plain, 0], expected)


@pytest.mark.parametrize("pixel_filter", ["box", "jitter", "edges"])
def test_training_through_the_pixels_footprint_runs_and_renders_box_filtered(tiny_dataset, tmp_path, pixel_filter):
    import json

    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.render_views import render_split
    from nerfgauge.nerf.train import train

    run = tmp_path / "run"
    train(TrainConfig(dataset=str(tiny_dataset), steps=4, pixel_filter=pixel_filter, threads=1), run, progress=False)
    assert json.loads((run / "config.json").read_text())["pixel_filter"] == pixel_filter
    timing = render_split(run, "test", progress=False)
    if pixel_filter == "edges" and json.loads((run / "config.json").read_text())["render_filter"] == "centre":
        assert timing["pixel_samples"] == 1  # chosen on the val views (the next tests)
    else:  # the box filter's 2 x 2 rays for a run trained through the footprint
        assert timing["pixel_samples"] == 2 and timing.get("edges_only", False) == (pixel_filter == "edges")


@pytest.mark.parametrize("fields, edge_share, expected_filter", [
    ({"budget_seconds": 60.0}, None, "centre"),
    ({"steps": 100}, 0.2, "edges"),
    ({"steps": 100}, 1 / 3, "edges"),
    ({"budget_seconds": 60.0}, 0.34, "centre"),
    ({"budget_seconds": 60.0, "pixel_filter": "box"}, 0.1, "box"),
    ({"steps": 100, "pixel_filter": "jitter"}, 0.1, "jitter"),
    ({"steps": 100, "pixel_filter": "centre"}, 0.1, "centre"),
])
def test_the_pixel_filter_and_its_batch(fields, edge_share, expected_filter):
    """As set; else edges while at most a third of the training pixels are edge pixels (the
    extra rays at most double a step's), centre beyond or when the share is unknown; a box
    run's automatic batch holds TRAIN_PIXEL_SAMPLES times the rays a step (as many pixels as
    one ray a pixel)."""
    from nerfgauge.nerf.config import BATCH_RAYS, TRAIN_PIXEL_SAMPLES, TrainConfig, resolve

    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w = np.stack([look_at(np.array([3.0, 0.0, 1.0]), np.zeros(3)), look_at(np.array([0.0, 3.0, 1.0]), np.zeros(3))])
    config, reasons = resolve(TrainConfig(dataset="unused", **fields), None, aabb, c2w, 100.0, 64, 0.5, edge_share)
    assert config.pixel_filter == expected_filter and reasons["pixel_filter"]
    if "pixel_filter" not in fields and edge_share is not None:
        assert f"{100 * edge_share:.1f}%" in reasons["pixel_filter"]  # the reason states the measured share
    assert config.batch_rays == BATCH_RAYS[config.parametrisation] * TRAIN_PIXEL_SAMPLES[expected_filter]


def test_a_run_states_its_training_images_edge_share_and_drops_what_centre_rays_do_not_need(tiny_dataset, tmp_path):
    import json

    from nerfgauge.core.dataset import open_dataset
    from nerfgauge.core.pixel_edges import edge_mask
    from nerfgauge.nerf.config import TrainConfig
    from nerfgauge.nerf.train import prepare_run

    ds = open_dataset(tiny_dataset)
    cameras = ds.cameras("train")
    share = np.mean([edge_mask(ds.rgba_of(stem, cameras.intrinsics).astype(np.float64)).mean() for stem in cameras.stems])
    config, reasons, _, rays, *_ = prepare_run(TrainConfig(dataset=str(tiny_dataset), steps=1))
    assert f"{100 * share:.1f}%" in reasons["pixel_filter"]
    assert config.pixel_filter == ("edges" if share <= 1 / 3 else "centre")
    assert (rays.edges is None) == (config.pixel_filter != "edges")
    config, _, _, rays, *_ = prepare_run(TrainConfig(dataset=str(tiny_dataset), steps=1, pixel_filter="centre"))
    assert rays.footprint is None and rays.edges is None


def test_a_batch_without_edge_pixels_is_its_centre_rays():
    """An empty scene has no edge pixel at all: the edges filter then trains on centre rays."""
    from nerfgauge.nerf.data import RayBatch
    from nerfgauge.nerf.train import _edge_rays

    c2w, intrinsics = _camera(4)
    origins, directions = pixel_rays(c2w, intrinsics)
    n = intrinsics.width * intrinsics.height
    rays = RayBatch(torch.from_numpy(origins.reshape(-1, 3)).float(), torch.from_numpy(directions.reshape(-1, 3)).float(),
                    torch.zeros((n, 4)), 1, torch.from_numpy(pixel_footprints(directions, c2w)),
                    torch.zeros(n, dtype=torch.bool))
    index = torch.arange(0, n, 7)
    (ray_o, ray_d), split = _edge_rays(rays, index, rays.origins[index], rays.directions[index], 4,
                                       torch.Generator().manual_seed(0), torch.device("cpu"))
    assert torch.equal(ray_d, rays.directions[index]) and torch.equal(ray_o, rays.origins[index])
    opacity = torch.rand(len(index))
    premultiplied = torch.rand(len(index), 3) * opacity[:, None]
    gathered_rgb, gathered_opacity = split.gather(premultiplied, opacity)
    assert torch.equal(gathered_rgb, premultiplied) and torch.equal(gathered_opacity, opacity)


@pytest.mark.parametrize("kind, share, expected", [
    ("bounded", 0.2, "edges"), ("bounded", 0.5, "centre"), ("forward", 0.2, "centre"), ("contracted", 0.1, "centre"),
    (None, 0.1, "centre"), ("bounded", None, "centre"),
])
def test_the_automatic_filter_is_edges_only_in_bounded_space_with_few_edges(kind, share, expected):
    from nerfgauge.nerf.config import TrainConfig, pixel_filter_for

    chosen, reason = pixel_filter_for(TrainConfig(dataset="d", steps=1), share, kind)
    assert chosen == expected and reason
    assert pixel_filter_for(TrainConfig(dataset="d", steps=1, pixel_filter="edges"), 0.9, "forward")[0] == "edges"


def _closest_to_origin(origins, directions):
    """Each ray's point closest to the origin [n, 3] (unit directions [n, 3])."""
    return origins - (origins * directions).sum(dim=-1, keepdim=True) * directions


class _FrameModel:
    """A stand-in model for whole frames: two colours either side of a plane through the
    origin, by the point of each ray closest to it, so the edge crosses the middle of every
    view of a camera looking at the origin; opacity 1."""

    def render(self, origins, directions):
        closest = _closest_to_origin(origins, directions)
        side = (closest @ torch.tensor([0.6, 0.0, 0.8]) > 0).float()
        rgb = torch.stack([side, 1 - side, 0.5 * torch.ones_like(side)], dim=-1)
        return SimpleNamespace(rgb=rgb, opacity=torch.ones_like(side), depth=directions[:, 0])

    def eval(self):
        return self

    def train(self):
        return self


@pytest.mark.parametrize("truth", ["edges", "centre", "edges-3x3", "edges-4x4"])
def test_an_edges_run_keeps_the_render_filter_that_scores_higher_on_its_val_views(tiny_dataset, truth):
    """Targets made by one of the renders: that render scores exactly and is kept."""
    from nerfgauge.core.dataset import open_dataset
    from nerfgauge.nerf.config import RENDER_FILTERS, TrainConfig
    from nerfgauge.nerf.data import RayBatch
    from nerfgauge.nerf.train import choose_render_filter

    ds = open_dataset(tiny_dataset)
    split = "val" if ds.cameras("val").stems else "test"
    cameras = ds.cameras(split)
    device = torch.device("cpu")
    n_views = min(2, len(cameras.stems))

    def render(per_axis):
        return [box_frame(_FrameModel(), cameras, i, per_axis, None, 1, device, per_axis > 1) for i in range(n_views)]

    frames = render(RENDER_FILTERS[truth])
    rgba = torch.cat([torch.cat([rgb, opacity[:, None]], dim=1) for rgb, opacity, _ in frames])
    for name, per_axis in RENDER_FILTERS.items():  # each other render differs somewhere
        if name != truth:
            assert all(not torch.equal(a[0], b[0]) for a, b in zip(frames, render(per_axis)))
    val = RayBatch(torch.zeros((len(rgba), 3)), torch.zeros((len(rgba), 3)), rgba, len(frames))
    config, reason, chosen_psnr = choose_render_filter(_FrameModel(), TrainConfig(dataset=str(tiny_dataset), steps=1,
                                                                     pixel_filter="edges"), cameras, val, device)
    assert config.render_filter == truth and "dB" in reason
    # the chosen render reproduces its targets exactly: val_psnr's error floor, 1e-10, is 100 dB
    assert chosen_psnr == pytest.approx(100.0)


class _RippleModel(_FrameModel):
    """A faint ripple across every view: colour 0.5 + 0.03 sin(2 pi u / period) of u, the
    coordinate of each ray's point closest to the origin along a fixed axis, with a period of
    about 3 pixels, so neighbouring centres differ by 0 to about 0.06 and a point between them
    is not their interpolation; opacity 1."""

    def __init__(self, period: float):
        self.period = period

    def render(self, origins, directions):
        closest = _closest_to_origin(origins, directions)
        u = closest @ torch.tensor([0.6, 0.0, 0.8])
        value = 0.5 + 0.03 * torch.sin(2 * np.pi * u / self.period)
        rgb = value[:, None] * torch.tensor([1.0, 0.9, 0.8])
        return SimpleNamespace(rgb=rgb, opacity=torch.ones_like(value), depth=directions[:, 0])


@pytest.mark.parametrize("truth_step", [0.04, 0.02, 0.01])
def test_an_edges_run_keeps_the_smaller_change_step_only_while_it_pays_on_its_val_views(tiny_dataset, truth_step):
    """Targets rendered 3 x 3 at one of the change steps: the choice walks down from the default
    and stops at that step, which scores exactly (a smaller one moves away from the targets,
    a larger one interpolates what they rendered)."""
    from nerfgauge.core.dataset import open_dataset
    from nerfgauge.nerf.config import CHANGE_STEP, RENDER_CHANGE_STEPS, TrainConfig
    from nerfgauge.nerf.data import RayBatch
    from nerfgauge.nerf.train import choose_render_filter

    ds = open_dataset(tiny_dataset)
    split = "val" if ds.cameras("val").stems else "test"
    cameras = ds.cameras(split)
    device = torch.device("cpu")
    n_views = min(2, len(cameras.stems))
    origins, directions = cameras.rays(0)  # the ripple's period: 3 pixels at the middle of view 0
    middle = [torch.from_numpy(part[cameras.intrinsics.height // 2, cameras.intrinsics.width // 2 + k]).float()
              for part in (origins, directions) for k in (0, 1)]
    points = [_closest_to_origin(o[None], d[None])[0] for o, d in ((middle[0], middle[2]), (middle[1], middle[3]))]
    model = _RippleModel(3 * float(torch.linalg.vector_norm(points[1] - points[0])))

    def render(step):
        return [box_frame(model, cameras, i, 3, None, 1, device, True, change_step=step) for i in range(n_views)]

    frames = render(truth_step)
    rgba = torch.cat([torch.cat([rgb, opacity[:, None]], dim=1) for rgb, opacity, _ in frames])
    for step in RENDER_CHANGE_STEPS:  # each other step renders differently
        if step != truth_step:
            assert all(not torch.equal(a[0], b[0]) for a, b in zip(frames, render(step)))
    val = RayBatch(torch.zeros((len(rgba), 3)), torch.zeros((len(rgba), 3)), rgba, len(frames))
    config, reason, chosen_psnr = choose_render_filter(model, TrainConfig(dataset=str(tiny_dataset), steps=1,
                                                                          pixel_filter="edges"), cameras, val, device)
    assert config.render_filter == "edges-3x3" and "change step" in reason
    assert config.render_change_step == (None if truth_step == CHANGE_STEP else truth_step)
    assert chosen_psnr == pytest.approx(100.0)
    # the rays the choice weighs: one a pixel through centres, and a changes render's beyond it
    from nerfgauge.nerf.trials import val_psnr
    rays = {}
    val_psnr(model, cameras, val, device, {"centre": (1, False), "fine": (3, True, 0.01), "all": (3, False)}, rays)
    assert rays["centre"] == 1.0 and 1.0 < rays["fine"] < rays["all"] == 9.0


@pytest.mark.parametrize("scores, expected", [
    # (val PSNR, rays a pixel) at 0.02 and 0.01 after 40 dB at 1.5 rays for the default
    ({0.02: (40.30, 1.60), 0.01: (40.45, 2.00)}, 0.02),  # 0.30 >= 0.1 (log2 1.07 = 0.09); 0.15 < log2 1.25 = 0.32
    ({0.02: (40.20, 3.00), 0.01: (45.00, 3.10)}, 0.04),  # twice the rays need 1 dB: the walk stops at once
    ({0.02: (40.05, 1.50), 0.01: (41.00, 1.50)}, 0.04),  # free rays still need 0.1 dB
    ({0.02: (40.30, 1.60), 0.01: (40.70, 1.70)}, 0.01),  # 0.40 >= max(0.1, log2 1.0625 = 0.087)
])
def test_a_smaller_change_step_must_pay_for_its_rays(monkeypatch, scores, expected):
    """The walk's arithmetic, on scripted val scores: each halving is kept while it gains
    0.1 dB and 1 dB per doubling of the frame's rays over the last step kept."""
    import nerfgauge.nerf.train as train_module

    def scripted(model, cameras, val_rays, device, filters, rays=None):
        (per_axis, edges_only, step), = filters.values()
        assert per_axis == 3 and edges_only
        rays["step"] = scores[step][1]
        return {"step": scores[step][0]}

    monkeypatch.setattr(train_module, "val_psnr", scripted)
    step, psnr, tried = train_module.choose_change_step(None, None, None, None, 3, 40.0, 1.5)
    assert step == expected and psnr == (40.0 if expected == 0.04 else scores[expected][0]) and "dB" in tried


@pytest.mark.parametrize("scores, expected", [
    # (val PSNR, rays a pixel) of each filter at the default change step
    ({"centre": (34.0, 1.0), "edges": (44.7, 1.2), "edges-3x3": (47.05, 1.4), "edges-4x4": (47.38, 2.03)},
     "edges-3x3"),  # the fresh 600-s model: 4 x 4 gains 0.33 for 1.45x the rays, which needs 0.54
    ({"centre": (34.0, 1.0), "edges": (44.7, 1.2), "edges-3x3": (47.05, 1.4), "edges-4x4": (47.70, 2.03)},
     "edges-4x4"),  # 0.65 >= 0.54
    ({"centre": (58.3, 1.0), "edges": (57.0, 1.1), "edges-3x3": (57.5, 1.2), "edges-4x4": (58.35, 1.3)},
     "centre"),  # a field that cannot resolve a pixel (bench hard's tiny): 4 x 4's 0.05 dB needs 0.38
    ({"centre": (40.0, 1.0), "edges": (39.0, 1.1), "edges-3x3": (41.0, 1.3), "edges-4x4": (41.05, 1.3)},
     "edges-3x3"),  # each against the last kept (centre, then 3 x 3); free rays still need 0.1 dB
])
def test_a_costlier_render_filter_must_pay_for_its_rays(monkeypatch, scores, expected):
    """The filter walk's arithmetic, on scripted val scores: cheapest first, each filter kept
    when it gains 0.1 dB and 1 dB per doubling of the frame's rays over the last one kept; the
    change step's walk then starts from the chosen filter's score (scripted to gain nothing)."""
    import nerfgauge.nerf.train as train_module
    from nerfgauge.nerf.config import TrainConfig

    def scripted(model, cameras, val_rays, device, filters, rays=None):
        if set(filters) == {"step"}:  # the change step's walk: no gain
            rays["step"] = 9.0
            return {"step": 0.0}
        rays.update({name: scores[name][1] for name in filters})
        return {name: scores[name][0] for name in filters}

    monkeypatch.setattr(train_module, "val_psnr", scripted)
    val = SimpleNamespace(n_views=4)
    config, reason, psnr = train_module.choose_render_filter(None, TrainConfig(dataset="d", steps=1, pixel_filter="edges"),
                                                             SimpleNamespace(split="val"), val, None)
    assert config.render_filter == expected and psnr == scores[expected][0]
    assert reason.startswith(f"{expected}: on 4 val views") and "rays a pixel" in reason


def test_an_edges_run_states_its_render_s_val_psnr_as_the_render_gives_it(tiny_dataset, tmp_path, capsys):
    """`nerfgauge train`'s last line gives an `edges` run's val PSNR through its render beside the
    log's (pixel centres): the figure `nerfgauge render RUN --split val` gives on white, to within
    the 8-bit PNGs' rounding (each composited channel off by at most 1/255, so the RMS error moves
    by at most that much) and the line's two decimals."""
    import json
    import re
    from pathlib import Path

    from nerfgauge.cli import main
    from nerfgauge.core.dataset import open_dataset
    from nerfgauge.core.images import read_png

    run = tmp_path / "run"
    assert main(["train", str(tiny_dataset), "--out", str(run), "--steps", "6", "--pixel-filter", "edges",
                 "--threads", "1", "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    stated = re.search(r"\(([0-9.]+) dB through its render, ([a-z0-9-]+)\)", line)
    assert stated, line
    saved = json.loads((run / "config.json").read_text())
    assert stated.group(2) == saved["render_filter"]
    assert main(["render", str(run), "--split", "val", "--out", str(tmp_path / "r"), "--quiet"]) == 0
    ds = open_dataset(tiny_dataset)
    cameras = ds.cameras("val")
    errors = []
    for stem in cameras.stems:
        truth = ds.rgba_of(stem, cameras.intrinsics).astype(np.float64)
        rendered = read_png(tmp_path / "r" / "val" / f"{Path(stem).name}.png")
        on_white = [image[..., :3] * image[..., 3:] + 1 - image[..., 3:] for image in (truth, rendered)]
        errors.append(float(((on_white[1].clip(0, 1) - on_white[0]) ** 2).mean()))
    rms = float(np.sqrt(np.mean(errors)))
    low, high = -20 * np.log10(rms + 1 / 255), -20 * np.log10(max(rms - 1 / 255, 1e-12))
    assert low - 0.005 <= float(stated.group(1)) <= high + 0.005, (stated.group(1), low, high)


def test_an_edges_run_renders_by_its_chosen_filter(tiny_dataset, tmp_path):
    import json

    from nerfgauge.nerf.checkpoint import load_checked, save_atomic
    from nerfgauge.nerf.config import RENDER_FILTERS, TrainConfig
    from nerfgauge.nerf.render_views import render_split
    from nerfgauge.nerf.train import train

    run = tmp_path / "run"
    train(TrainConfig(dataset=str(tiny_dataset), steps=4, pixel_filter="edges", threads=1), run, progress=False)
    saved = json.loads((run / "config.json").read_text())
    assert saved["render_filter"] in RENDER_FILTERS and saved["auto_reasons"]["render_filter"]
    payload = load_checked(run / "model.pt")
    for chosen, samples in RENDER_FILTERS.items():
        payload["config"]["render_filter"] = chosen
        save_atomic(payload, run / "model.pt")
        timing = render_split(run, "test", tmp_path / chosen, progress=False)
        assert timing["pixel_samples"] == samples and timing.get("edges_only", False) == (samples > 1)


def test_the_refined_grid_is_one_stage_past_the_final_one_within_the_cap_and_only_for_automatic_resolutions():
    """refined_resolution: final x STAGE_RATIO, rounded, at most MAX_AUTO_RESOLUTION and never
    below the final grid; resolution_at's stage after the ladder is it. refine_grid_for: as
    set; else on only for a compact `edges` run whose resolution is automatic and not at the
    cap, set by the pixel footprint (not the texture, the cap or the user), and its reason
    names the grids."""
    from nerfgauge.nerf.config import MAX_AUTO_RESOLUTION, TrainConfig, refine_grid_for, refined_resolution
    from nerfgauge.nerf.schedule import STAGE_RATIO, Schedule

    assert refined_resolution(109) == round(109 * STAGE_RATIO) == 173
    assert refined_resolution(200) == MAX_AUTO_RESOLUTION and refined_resolution(MAX_AUTO_RESOLUTION) == MAX_AUTO_RESOLUTION
    config = TrainConfig("d", budget_seconds=600.0, pixel_filter="edges", start_resolution=27, final_resolution=109)
    schedule = Schedule.for_run(config, grid=True, refined_resolution=refined_resolution(109))
    assert [schedule.resolution_at(stage) for stage in (0, schedule.stages, schedule.stages + 1)] == [27, 109, 173]
    on, why = refine_grid_for(config, "footprint")
    assert on is True and "109 -> 173 voxels" in why
    assert refine_grid_for(config, None)[0] is False  # the user's resolution is kept
    assert refine_grid_for(config, "texture")[0] is False  # finer than the pixels already
    assert refine_grid_for(config, "cap")[0] is False
    assert refine_grid_for(replace(config, pixel_filter="centre"), "footprint")[0] is False
    assert refine_grid_for(replace(config, model="vanilla"), "footprint")[0] is False
    assert refine_grid_for(replace(config, final_resolution=MAX_AUTO_RESOLUTION), "footprint")[0] is False
    assert refine_grid_for(replace(config, refine_grid=False), "footprint") == (False, "set on the command line")
    assert refine_grid_for(replace(config, pixel_filter="centre", refine_grid=True), None)[0] is True


def test_a_refining_run_grows_its_grid_at_half_the_steps_states_it_renders_and_resumes(tiny_dataset, tmp_path,
                                                                                      monkeypatch):
    """With the bars lowered as below, a 12-step run with --refine-grid on decides at step 6
    and trains the refined grid (16 -> 25 voxels) from step 7: the log, model.pt and
    config.json say so, the model renders, a resumed run keeps the grid, and a run stopped
    before the decision and resumed grows at the same step as the uninterrupted one."""
    import json

    import nerfgauge.nerf.schedule as schedule_module
    import nerfgauge.nerf.train as train_module
    from nerfgauge.nerf.checkpoint import load_checked
    from nerfgauge.nerf.config import TrainConfig, refined_resolution
    from nerfgauge.nerf.render_views import render_split

    monkeypatch.setattr(schedule_module, "MIN_STAGE_STEPS", 1)
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_MIN_STEPS", 2)
    finer = refined_resolution(16)
    assert finer == 25
    config = TrainConfig(dataset=str(tiny_dataset), steps=12, pixel_filter="edges", start_resolution=16,
                         final_resolution=16, refine_grid=True, eval_every_seconds=1e-9, threads=1)

    def trained(folder, steps, resume=False):
        train_module.train(replace(config, steps=steps), folder, resume=resume, progress=False)
        log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        saved = json.loads((folder / "config.json").read_text())
        return log, load_checked(folder / "model.pt")["resolution"], saved

    log, resolution, saved = trained(tmp_path / "run", 12)
    # decided before step 6, grown in step 7's iteration (log points come before their step)
    assert [entry["resolution"] for entry in log] == [16] * 8 + [finer] * 5
    assert {entry["final_resolution"] for entry in log if entry["step"] >= 7} == {finer}
    assert resolution == finer and saved["final_resolution"] == 16 and saved["refine_grid"] is True
    assert saved["auto_reasons"]["refine_grid"].startswith(f"16 -> {finer} voxels from step 6")
    render_split(tmp_path / "run", "test", tmp_path / "frames", progress=False)
    frames = sorted((tmp_path / "frames" / "test").glob("r_*.png"))
    assert frames and len(frames) == len(list((tiny_dataset / "test").glob("r_???.png")))
    log, resolution, _ = trained(tmp_path / "run", 16, resume=True)
    assert resolution == finer and {entry["resolution"] for entry in log if entry["step"] >= 12} == {finer}
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_AT", 0.9)
    log, resolution, saved = trained(tmp_path / "paused", 4)
    assert resolution == 16 and saved["auto_reasons"]["refine_grid"].startswith("kept 16 voxels: the run ended before")
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_AT", 0.5)
    log, resolution, _ = trained(tmp_path / "paused", 12, resume=True)
    assert resolution == finer and [entry["resolution"] for entry in log][-5:] == [finer] * 5
    # without the flag an explicit resolution is kept (the end-to-end test below runs so)
    assert json.loads((tmp_path / "run" / "config.json").read_text())["recipe"]["refine_grid"] is True


def test_a_run_switches_its_edge_pixels_to_finer_points_states_it_and_resumes_with_them(tiny_dataset, tmp_path,
                                                                                      monkeypatch):
    """With the stages' and the finer points' bars lowered (1 and 2 steps: the final grid
    from step 4), a 12-step `edges` run trains its edge pixels through 2 x 2 points to step 6
    (half the steps), 3 x 3 to step 9 (three quarters) and 4 x 4 after: the log and
    config.json say so. The decisions are in checkpoint.pt's loop state: a resumed run keeps
    them, yes or no, and one resumed from before them decides at the same steps as the
    uninterrupted run."""
    import json

    import nerfgauge.nerf.schedule as schedule_module
    import nerfgauge.nerf.train as train_module
    from nerfgauge.nerf.config import TrainConfig

    monkeypatch.setattr(schedule_module, "MIN_STAGE_STEPS", 1)
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_MIN_STEPS", 2)
    config = TrainConfig(dataset=str(tiny_dataset), steps=12, pixel_filter="edges", start_resolution=16,
                         final_resolution=16, eval_every_seconds=1e-9, threads=1)

    def trained(folder, steps, resume=False):
        train_module.train(replace(config, steps=steps), folder, resume=resume, progress=False)
        log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        loop = torch.load(folder / "checkpoint.pt", weights_only=True)["loop"]
        return log, loop, json.loads((folder / "config.json").read_text())["auto_reasons"]["edge_points"]

    log, loop, reason = trained(tmp_path / "run", 12)
    assert [entry["step"] for entry in log] == list(range(13))  # a point before every step and after the last
    assert [entry["edge_points"] for entry in log] == [2] * 7 + [3] * 3 + [4] * 3  # a step's point comes before it
    assert reason.startswith("2 x 2 to step 6, then 3 x 3") and "then 4 x 4 from step 9" in reason
    assert (loop["edge_points"], loop["edge_points_step"], loop["finer_points_step"]) == (4, 6, 9)
    log, loop, _ = trained(tmp_path / "run", 16, resume=True)
    assert {entry["edge_points"] for entry in log if entry["step"] >= 12} == {4}
    assert (loop["edge_points"], loop["edge_points_step"], loop["finer_points_step"]) == (4, 6, 9)
    log, loop, reason = trained(tmp_path / "early", 4)  # at the final grid from step 3: never 2 steps there
    assert {entry["edge_points"] for entry in log} == {2} and reason.startswith("2 x 2 throughout")
    assert loop["edge_points_step"] == 2  # decided at half the run (no: 0 steps at the final grid)
    log, loop, reason = trained(tmp_path / "early", 12, resume=True)
    assert {entry["edge_points"] for entry in log} == {2} and loop["edge_points_step"] == 2  # no second decision
    assert reason.startswith("2 x 2 throughout: at 50% of the budget (step 2) the final grid had trained fewer")
    # a run stopped before its decision (the bar moved past its end) and resumed decides as
    # the uninterrupted run did
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_AT", 0.9)
    log, loop, reason = trained(tmp_path / "paused", 4)
    assert loop["edge_points_step"] == 0
    assert reason.startswith("2 x 2 throughout: the run ended before 90% of its budget")
    monkeypatch.setattr(schedule_module, "FINE_EDGE_POINTS_AT", 0.5)
    log, loop, _ = trained(tmp_path / "paused", 12, resume=True)
    assert (loop["edge_points"], loop["edge_points_step"], loop["finer_points_step"]) == (4, 6, 9)


def test_refine_grid_keeps_older_recipes_and_is_refused_where_it_cannot_apply(tiny_dataset, tmp_path, capsys):
    """No `refine_grid` key in config.json unless on (older runs keep their recipe); a
    non-bool, or on with the vanilla model, is one line and exit 2, nothing written."""
    from cli_errors import one_line_exit_2

    from nerfgauge.core.errors import InputError
    from nerfgauge.nerf.config import TrainConfig

    assert "refine_grid" not in TrainConfig(dataset="d", steps=1).to_json()
    assert "refine_grid" not in TrainConfig(dataset="d", steps=1, refine_grid=False).to_json()
    assert TrainConfig(dataset="d", steps=1, refine_grid=True).to_json()["refine_grid"] is True
    for bad in ({"refine_grid": "yes"}, {"refine_grid": 1}, {"refine_grid": True, "model": "vanilla"}):
        with pytest.raises(InputError, match="refine-grid"):
            TrainConfig(dataset="d", steps=1, **bad).validate()
    one_line_exit_2(capsys, ["train", tiny_dataset, "--out", tmp_path / "v", "--steps", "2", "--quiet",
                             "--model", "vanilla", "--refine-grid", "on"], "--refine-grid on", "compact")
    one_line_exit_2(capsys, ["train", tiny_dataset, "--out", tmp_path / "b", "--steps", "2", "--quiet",
                             "--refine-grid", "maybe"], "--refine-grid")
    assert not (tmp_path / "v").exists() and not (tmp_path / "b").exists()
