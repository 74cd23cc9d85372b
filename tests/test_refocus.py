"""Synthetic-aperture refocusing (`nerfgauge baseline --method refocus`): shift and add over
the light-field camera grid obeys the thin-lens model the ground truth is rendered with."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.camera import Intrinsics, ThinLens
from nerfgauge.core.images import linear_to_srgb, read_png, srgb_to_linear
from nerfgauge.methods.baselines import LightField
from test_thinlens import blur_radius_px, second_moment


@pytest.fixture(scope="module")
def lens_lightfield(tmp_path_factory, make_dataset):
    """primitives on a 3x3 light-field grid, 2 off-grid test views through a thin lens, 16 px."""
    return make_dataset(tmp_path_factory.mktemp("refocus") / "lightfield", layout="lightfield", views=9,
                        val_views=1, test_views=2, width=16, height=16, spp=4, aperture=0.1, focus_distance=4.5)


def test_aperture_zero_at_a_grid_camera_is_that_camera_image(lens_lightfield):
    """With aperture 0 every lens ray is the grid camera's own pixel ray, and the focus point
    of each pixel projects back onto that pixel's centre, whatever the focus distance."""
    field = LightField(lens_lightfield)
    for node in (0, 4, 8):
        for focus in (2.0, 4.5, 9.0):
            refocused = field.refocus(field.c2w[node], ThinLens(0.0, focus))
            stored = field.images[node].astype(np.float64) / 255.0
            covered = stored[..., 3] > 0
            np.testing.assert_allclose(refocused[..., 3], stored[..., 3], atol=1e-9)
            np.testing.assert_allclose(refocused[covered, :3], stored[covered, :3], atol=1e-9)


def synthetic_dot_field(depth: float, side: int = 32, nodes: int = 21, half_span: float = 0.5) -> LightField:
    """A light field of a single small bright dot at distance `depth` in front of a dense
    nodes x nodes grid of cameras on the plane y = 0 facing +Y (the generator's light-field
    pose), spanning [-half_span, half_span] in x and z. Each image is the dot's exact
    projection, drawn as a Gaussian of sigma 0.7 px in light, stored as 8-bit sRGB (as the
    dataset stores it)."""
    field = object.__new__(LightField)
    field.origin = np.array([-half_span, 0.0, -half_span])
    field.axes = np.eye(3)[[0, 2, 1]]  # s = +X, t = +Z, view = +Y
    field.spacing = np.array([2 * half_span / (nodes - 1)] * 2)
    field.rows = field.cols = nodes
    field.focal_distance = depth
    field.intrinsics = Intrinsics.from_fov(side, side, 40.0)
    rotation = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    t_index, s_index = np.divmod(np.arange(nodes * nodes), nodes)
    field.c2w = np.repeat(np.eye(4)[None], nodes * nodes, axis=0)
    field.c2w[:, :3, :3] = rotation
    field.c2w[:, :3, 3] = field.origin + np.stack([s_index, np.zeros_like(s_index), t_index], 1) * field.spacing[0]
    dot = np.array([0.0, depth, 0.0])
    centre = field.project(np.arange(nodes * nodes), np.repeat(dot[None], nodes * nodes, 0))  # [K, 2] (col, row)
    rows, cols = np.mgrid[0:side, 0:side]
    glow = np.exp(-((cols[None] - centre[:, 0, None, None]) ** 2 + (rows[None] - centre[:, 1, None, None]) ** 2)
                  / (2 * 0.7**2))
    field.images = np.zeros((nodes * nodes, side, side, 4), np.uint8)
    field.images[..., :3] = np.round(255 * linear_to_srgb(glow))[..., None]
    field.images[..., 3] = 255
    return field


@pytest.mark.parametrize("aperture,focus,depth", [(0.3, 2.0, 4.0), (0.5, 2.0, 4.0), (0.45, 3.0, 1.8)])
def test_refocused_off_focus_point_blurs_into_the_thin_lens_circle(aperture, focus, depth):
    """Shift and add focused at D moves the dot's copy seen from grid offset b by
    f_px b (1/d - 1/D) pixels; over the aperture disc |b| <= A the copies fill a disc of
    radius f_px A |1/d - 1/D| = blur_radius_px (tests/test_thinlens.py), the thin lens's
    circle of confusion. Measured as there: r = sqrt(2 (M - M0)), M0 the sharp image's
    second moment. The camera grid is a sampling of the aperture: the bilinear weights in
    (s, t) add the variance of a tent of one grid spacing h (h^2 / 6 per axis), i.e.
    (r h / A)^2 / 3 px^2, and reading views at fractional pixels adds at most 1/6 px^2 per
    axis; at h = A / 10 or less and r > 2 px both stay below 2 % of r, inside the 4 % + 0.15 px
    tolerance (which also covers 256 lens samples' residual error). Moments add for light,
    not for its sRGB code: both images are decoded first (the lens averages light)."""
    field = synthetic_dot_field(depth)
    centre_camera = field.c2w[(field.rows * field.cols) // 2]  # the grid's middle node
    sharp = srgb_to_linear(field.refocus(centre_camera, ThinLens(0.0, depth))[..., 0])
    blurred = srgb_to_linear(field.refocus(centre_camera, ThinLens(aperture, focus), samples=256, seed=0)[..., 0])
    expected = blur_radius_px(aperture, focus, depth, field.intrinsics.fx)
    assert 2.0 < expected < 7.0
    measured = math.sqrt(2 * (second_moment(blurred) - second_moment(sharp)))
    assert abs(measured - expected) < 0.04 * expected + 0.15, (measured, expected)


def test_refocused_point_in_the_focus_plane_stays_sharp():
    field = synthetic_dot_field(3.0)
    centre_camera = field.c2w[(field.rows * field.cols) // 2]
    sharp, in_focus, off_focus = (srgb_to_linear(field.refocus(centre_camera, lens, samples=64)[..., 0])
                                  for lens in (ThinLens(0.0, 3.0), ThinLens(0.5, 3.0), ThinLens(0.5, 2.0)))
    # only the bilinear resampling of the views (<= 1/6 px^2 per axis) may widen it
    assert second_moment(in_focus) - second_moment(sharp) < 2 * (1 / 6) + 0.05
    assert second_moment(off_focus) - second_moment(sharp) > 4.0


def test_the_lens_moves_light_and_neither_makes_nor_loses_it():
    """Shift and add averages light, as the thin lens does: the blurred dot's light (its
    decoded pixel values summed) is the sharp dot's. Bilinear reads and the mean over the
    lens both keep a sum away from the border (the disc's radius is 3.3 px, its centre the
    32 px image's); what is left is the 8-bit sRGB quantisation of the views (glow under
    1.5e-4 rounds to 0: well under 1% of a glow summing to 2 pi 0.7^2 = 3.1), inside the 2%
    allowed. A mean of sRGB codes keeps a fraction of the light: the code is concave in it."""
    field = synthetic_dot_field(4.0)
    centre_camera = field.c2w[(field.rows * field.cols) // 2]
    sharp = srgb_to_linear(field.refocus(centre_camera, ThinLens(0.0, 4.0))[..., 0]).sum()
    blurred = srgb_to_linear(field.refocus(centre_camera, ThinLens(0.3, 2.0), samples=256, seed=0)[..., 0]).sum()
    assert blur_radius_px(0.3, 2.0, 4.0, field.intrinsics.fx) == pytest.approx(3.3, abs=0.1)
    assert sharp == pytest.approx(2 * math.pi * 0.7 ** 2, rel=0.01)
    assert blurred == pytest.approx(sharp, rel=0.02)


def test_refocus_baseline_writes_every_test_frame_and_evaluates(lens_lightfield, tmp_path, capsys):
    out = tmp_path / "refocus"
    assert main(["baseline", str(lens_lightfield), "--method", "refocus", "--out", str(out)]) == 0
    assert main(["evaluate", str(lens_lightfield), "--pred", str(out)]) == 0
    capsys.readouterr()
    test = dataset.open_dataset(lens_lightfield).cameras("test")
    for stem in test.stems:
        assert read_png(out / (stem + ".png")).shape == (16, 16, 4)
    metrics = json.loads((out / "metrics.json").read_text())
    assert [frame["name"] for frame in metrics["frames"]] == list(test.stems)
    assert all(frame["lens"]["aperture_radius"] == 0.1 for frame in metrics["frames"])  # scored against the lens truth


def test_refocus_on_a_dataset_that_is_not_a_camera_array_is_one_line(tiny_dataset, tmp_path, capsys):
    one_line_exit_2(capsys, ["baseline", tiny_dataset, "--method", "refocus", "--out", tmp_path / "r"],
                    "not a camera array", "refocusing")


def test_report_rows_and_aperture_table(lens_lightfield, tmp_path, capsys):
    """The report's defocus pieces: an image row per method and PSNR/SSIM against aperture."""
    from nerfgauge.eval.report import aperture_table, focus_rows

    out = tmp_path / "refocus"
    assert main(["baseline", str(lens_lightfield), "--method", "refocus", "--out", str(out)]) == 0
    assert main(["evaluate", str(lens_lightfield), "--pred", str(out)]) == 0
    capsys.readouterr()
    document = json.loads((out / "metrics.json").read_text())
    table = aperture_table({"refocus": {0.1: document}, "nerf": {}}, [0.1])
    assert table[0] == ["method", "PSNR dB A=0.1", "SSIM A=0.1"]
    assert table[1] == ["refocus", f"{document['mean']['psnr']:.2f}", f"{document['mean']['ssim']:.4f}"]
    assert table[2] == ["nerf", "–", "–"]
    focus_rows({0.1: lens_lightfield}, {"refocus": {0.1: out}}, "test/r_000", tmp_path / "rows.png")
    image = read_png(tmp_path / "rows.png")
    assert image.shape[0] > image.shape[1]  # two rows (truth, refocus), one column


def test_refocus_any_lens_overrides_the_frames(lens_lightfield, tmp_path):
    """write_baseline(lens=...) refocuses every frame at that aperture and focus: aperture 0
    at the light field's focal plane is the quadrilinear light field (the same 16 samples)."""
    from nerfgauge.methods.baselines import write_baseline

    focal = LightField(lens_lightfield).focal_distance
    timing = write_baseline(lens_lightfield, "refocus", tmp_path / "r0", lens=ThinLens(0.0, focal), samples=8)
    write_baseline(lens_lightfield, "lightfield-quadrilinear", tmp_path / "quad")
    assert timing["lens"]["aperture_radius"] == 0.0 and timing["lens_samples"] == 8
    for stem in dataset.open_dataset(lens_lightfield).cameras("test").stems:
        # the same sums up to float rounding, which may tip a uint8 step
        np.testing.assert_allclose(read_png(tmp_path / "r0" / (stem + ".png")),
                                   read_png(tmp_path / "quad" / (stem + ".png")), atol=1.01 / 255)
