"""`nerfgauge render` through a frame's thin lens: the model integrates the aperture with
stratified, seeded lens samples (nerf/render_views.py).

The fast tests use an analytic "model" with the trained model's public interface
(render(origins, directions) -> rgb premultiplied, opacity, depth): a textured plane facing
the camera, so what the lens does is known exactly. A slow test runs the real thing.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from cli_errors import one_line_exit_2
from nerfgauge.cli import main
from nerfgauge.core.camera import Intrinsics, ThinLens
from nerfgauge.core.dataset import SplitCameras
from nerfgauge.core.images import read_exr_single, read_png
from nerfgauge.nerf.models import RadianceModel
from nerfgauge.nerf.render_views import _render_into
from test_thinlens import blur_radius_px, second_moment

SIDE = 32


class TexturedPlane(RadianceModel):
    """Opaque plane z = -depth in world space (the test cameras sit at the origin looking
    down -Z); its colour at (x, y) is texture(x, y) [n] -> [n] grey. Nothing else."""

    def __init__(self, depth: float, texture):
        super().__init__()
        self.depth, self.texture = depth, texture

    def to(self, device):
        return self

    def eval(self):
        return self

    def render(self, origins, directions):
        t = (-self.depth - origins[:, 2]) / directions[:, 2]  # [n]
        hit = origins + t[:, None] * directions
        grey = self.texture(hit[:, 0].double(), hit[:, 1].double()).float()
        return SimpleNamespace(rgb=grey[:, None].expand(-1, 3).contiguous(), opacity=torch.ones_like(t), depth=t)


def cameras(lens, count: int = 1) -> SplitCameras:
    c2w = np.repeat(np.eye(4)[None], count, axis=0)
    return SplitCameras("test", tuple(f"test/r_{i:03d}" for i in range(count)), c2w,
                        Intrinsics.from_fov(SIDE, SIDE, 40.0), () if lens is None else (lens,) * count)


def render(tmp_path, name, model, lens, samples=16, seed=0):
    """Render through _render_into (the frame loop of `nerfgauge render`). Returns
    (grey [H, W] float from the PNG, depth [H, W], timing)."""
    out = tmp_path / name
    settings = None if lens is None else {"aperture_samples": samples, "lens_seed": seed}
    timing = _render_into(out, model, SimpleNamespace(model="analytic"), cameras(lens), "test", torch.device("cpu"),
                          1, None, False, settings)
    png = read_png(out / "test" / "r_000.png")
    depth = read_exr_single(out / "test" / "r_000_depth.exr")
    return png[..., 0].astype(np.float64), depth, timing, out


def checker(x, y):
    return 0.1 + 0.8 * ((torch.floor(x * 6) + torch.floor(y * 6)) % 2)


def test_aperture_zero_renders_the_pinhole_files_bit_for_bit(tmp_path):
    model = TexturedPlane(2.0, checker)
    *_, pinhole = render(tmp_path, "pinhole", model, None)
    *_, zero = render(tmp_path, "zero", model, ThinLens(0.0, 2.0))
    for name in ("r_000.png", "r_000_depth.exr"):
        assert (pinhole / "test" / name).read_bytes() == (zero / "test" / name).read_bytes()


def test_plane_at_the_focus_distance_renders_sharp(tmp_path):
    """Every lens ray of a pixel meets the plane in focus at the pixel's pinhole point, so
    a plane there has the pinhole image (to float32 rounding of the ray maths); the same
    plane seen with the focus elsewhere is blurred. Depth is the pinhole ray's."""
    model = TexturedPlane(2.0, checker)
    pinhole, pinhole_depth, *_ = render(tmp_path, "pinhole", model, None)
    sharp, sharp_depth, timing, _ = render(tmp_path, "sharp", model, ThinLens(0.4, 2.0))
    blurred, *_ = render(tmp_path, "blurred", model, ThinLens(0.4, 1.0))
    assert np.abs(sharp - pinhole).max() <= 1 / 255  # one uint8 step at most, at checker edges
    assert np.abs(blurred - pinhole).mean() > 0.05
    assert np.array_equal(sharp_depth, pinhole_depth)
    assert timing["lens_frames"] == 1 and timing["aperture_samples"] == 16 and timing["ms_per_lens_frame"] > 0


@pytest.mark.parametrize("aperture,focus,depth", [(0.3, 2.0, 4.0), (0.5, 2.0, 4.0), (0.4, 3.0, 1.8)])
def test_off_focus_dot_blurs_into_the_circle_of_confusion(tmp_path, aperture, focus, depth):
    """A small bright Gaussian dot on a black plane at depth d, focus at D: the render
    spreads it into the thin-lens disc of radius blur_radius_px (derived in
    tests/test_thinlens.py), measured as r = sqrt(2 (M - M0)) from second moments.
    Tolerance 4 % + 0.15 px: 256 stratified lens samples and the uint8 PNG."""
    sigma = 0.02 * depth  # ~1 px on the image

    def dot(x, y):
        return torch.exp(-(x**2 + y**2) / (2 * sigma**2))

    model = TexturedPlane(depth, dot)
    sharp, *_ = render(tmp_path, "sharp", model, None)
    blurred, *_ = render(tmp_path, "blurred", model, ThinLens(aperture, focus), samples=256)
    expected = blur_radius_px(aperture, focus, depth, Intrinsics.from_fov(SIDE, SIDE, 40.0).fx)
    measured = math.sqrt(2 * (second_moment(blurred) - second_moment(sharp)))
    assert abs(measured - expected) < 0.04 * expected + 0.15, (measured, expected)


def test_lens_samples_are_seeded(tmp_path):
    model = TexturedPlane(3.0, checker)
    a, *_ = render(tmp_path, "a", model, ThinLens(0.3, 2.0), samples=4, seed=1)
    b, *_ = render(tmp_path, "b", model, ThinLens(0.3, 2.0), samples=4, seed=1)
    c, *_ = render(tmp_path, "c", model, ThinLens(0.3, 2.0), samples=4, seed=2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.mark.parametrize("flag,value", [("--aperture-samples", "0"), ("--lens-seed", "-1")])
def test_render_refuses_bad_lens_settings_in_one_line(capsys, tmp_path, flag, value):
    one_line_exit_2(capsys, ["render", tmp_path, flag, value], flag)


@pytest.mark.slow
def test_trained_model_renders_lens_views_of_another_dataset(make_dataset, tmp_path, capsys):
    """Train on a pinhole dataset, render the same test cameras of a lens dataset of the
    same scene (--dataset), score against its thin-lens truth."""
    pinhole = make_dataset(tmp_path / "pinhole", views=8, test_views=2, width=24, height=24)
    lens = make_dataset(tmp_path / "lens", views=8, test_views=2, width=24, height=24, aperture=0.2,
                        focus_distance=4.0)
    run = tmp_path / "run"
    assert main(["train", str(pinhole), "--out", str(run), "--steps", "60", "--quiet"]) == 0
    # another dataset (another manifest) needs the explicit flag
    one_line_exit_2(capsys, ["render", run, "--dataset", lens, "--out", tmp_path / "r", "--quiet"], "--other-dataset")
    assert main(["render", str(run), "--dataset", str(lens), "--other-dataset", "--out", str(tmp_path / "r"),
                 "--aperture-samples", "4", "--quiet"]) == 0
    timing = json.loads((tmp_path / "r" / "timing.json").read_text())
    assert timing["lens_frames"] == 2 and timing["aperture_samples"] == 4
    assert main(["evaluate", str(lens), "--pred", str(tmp_path / "r")]) == 0
    other = make_dataset(tmp_path / "other", scene="tiny", views=4, test_views=1, width=16, height=16)
    capsys.readouterr()
    one_line_exit_2(capsys, ["render", run, "--dataset", other, "--other-dataset", "--out", tmp_path / "r2"],
                    "--dataset", "shows scene")
