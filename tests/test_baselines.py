"""Baselines: the nearest view on a hemisphere dataset, the two-plane light field on a
light-field dataset (against a per-ray reference loop), scored by `nerfgauge evaluate`."""

import json
import math

import numpy as np
import pytest
from nerfgauge.methods.baselines import (
    LightField,
    pose_distance,
    render_lightfield,
    render_nearest,
)
from nerfgauge.eval.metrics import METRIC_NAMES

from nerfgauge.cli import main
from nerfgauge.core import dataset
from nerfgauge.core.camera import look_at, pixel_rays
from nerfgauge.core.images import linear_to_srgb, read_png, srgb_to_linear


@pytest.fixture(scope="module")
def lightfield_ds(tmp_path_factory, make_dataset):
    """primitives on a 4x4 light-field grid, 4 off-grid test views, 24x24 px, 8 spp."""
    return make_dataset(tmp_path_factory.mktemp("baselines") / "lightfield", layout="lightfield", views=16,
                        val_views=1, test_views=4, width=24, height=24, spp=8)


@pytest.fixture(scope="module")
def hemisphere_ds(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("baselines") / "hemisphere", views=6, val_views=1,
                        test_views=3, width=24, height=24)


def baseline_scores(root, method, out, capsys, split="test"):
    """Run `nerfgauge baseline` then `nerfgauge evaluate`; returns metrics.json."""
    assert main(["baseline", str(root), "--method", method, "--out", str(out), "--split", split]) == 0
    assert main(["evaluate", str(root), "--pred", str(out), "--split", split]) == 0
    capsys.readouterr()
    return json.loads((out / "metrics.json").read_text())


# --- the per-ray reference (test oracle) ------------------------------------------------


def reference_quadrilinear(root, c2w, row, col):
    """One pixel of the quadrilinear light field, written out ray by ray from scene.json."""
    plane = dataset.open_dataset(root).scene["camera"]["lightfield"]
    origin, s_axis, t_axis, view = (np.array(plane[k]) for k in ("camera_plane_origin", "s_axis", "t_axis", "view_axis"))
    ds_, dt_ = plane["spacing"]
    rows, cols = plane["grid"]
    train = dataset.open_dataset(root).cameras("train")
    k = train.intrinsics
    origins, directions = pixel_rays(c2w, k)
    o, d = origins[row, col], directions[row, col]
    on_cameras = o + d * ((origin - o) @ view) / (d @ view)
    focal = o + d * ((origin + plane["focal_plane_distance"] * view - o) @ view) / (d @ view)
    s, t = (on_cameras - origin) @ s_axis / ds_, (on_cameras - origin) @ t_axis / dt_
    i0, j0 = min(max(int(math.floor(t)), 0), rows - 2), min(max(int(math.floor(s)), 0), cols - 2)
    total = np.zeros(4)
    for i in (i0, i0 + 1):
        for j in (j0, j0 + 1):
            w_st = (1 - abs(s - j)) * (1 - abs(t - i))
            centre = origin + j * ds_ * s_axis + i * dt_ * t_axis
            (index,) = [n for n, pose in enumerate(train.c2w) if np.allclose(pose[:3, 3], centre, atol=1e-9)]
            pose = train.c2w[index]
            x, y, z = pose[:3, :3].T @ (focal - centre)
            u, v = k.fx * x / -z + k.cx - 0.5, k.cy - k.fy * y / -z - 0.5  # continuous pixel index
            image = read_png(root / (train.stems[index] + ".png")).astype(np.float64)
            # Cell corner clamped into the image, fraction clamped to [0, 1]: edge pixels beyond.
            c0, r0 = min(max(int(math.floor(u)), 0), k.width - 2), min(max(int(math.floor(v)), 0), k.height - 2)
            fc, fr = min(max(u - c0, 0.0), 1.0), min(max(v - r0, 0.0), 1.0)
            for r, w_r in ((r0, 1 - fr), (r0 + 1, fr)):
                for c, w_c in ((c0, 1 - fc), (c0 + 1, fc)):
                    p = image[r, c]  # straight sRGB in [0, 1], decoded to light before it is mixed
                    total += w_st * w_r * w_c * np.array([*(srgb_to_linear(p[:3]) * p[3]), p[3]])
    return total  # premultiplied RGBA, colour in linear light


def test_vectorised_light_field_matches_reference_loop(lightfield_ds):
    field = LightField(lightfield_ds)
    test = dataset.open_dataset(lightfield_ds).cameras("test")
    rendered = field.render(test.c2w[0], "quadrilinear")  # straight alpha [H, W, 4], sRGB colour
    for row, col in [(0, 0), (5, 17), (12, 12), (11, 9), (23, 23), (18, 2)]:
        expected = np.clip(reference_quadrilinear(lightfield_ds, test.c2w[0], row, col), 0, 1)
        alpha = expected[3]
        straight = linear_to_srgb(expected[:3] / alpha) if alpha > 0 else np.zeros(3)
        # Same arithmetic in another order: float64 rounding, ~1e-15, plus the clip to [0, 1].
        np.testing.assert_allclose(rendered[row, col], [*straight, alpha], atol=1e-9)


# --- scores ---------------------------------------------------------------------------------


def test_quadrilinear_beats_nearest_on_held_out_positions(lightfield_ds, tmp_path, capsys):
    scores = {m: baseline_scores(lightfield_ds, m, tmp_path / m, capsys)
              for m in ("lightfield-nearest", "lightfield-quadrilinear")}
    nearest, quad = (scores[m]["mean"] for m in ("lightfield-nearest", "lightfield-quadrilinear"))
    assert quad["psnr"] > nearest["psnr"] and quad["ssim"] > nearest["ssim"]
    assert scores["lightfield-quadrilinear"]["count"]["psnr"] == 4
    timing = scores["lightfield-quadrilinear"]["timing"]
    assert timing["method"] == "lightfield-quadrilinear" and timing["ms_per_frame"] > 0


@pytest.mark.parametrize("mode", ["nearest", "quadrilinear"])
def test_light_field_reproduces_training_views(lightfield_ds, mode):
    # At a grid node the (s, t) weights are 1 and 0, and a pixel's focal point projects back
    # onto its own pixel centre: every sample weight is 1 or 0 up to float64 rounding
    # (~1e-15), far from the 0.5/255 that could change an 8-bit value.
    train = dataset.open_dataset(lightfield_ds).cameras("train")
    for stem, image in render_lightfield(lightfield_ds, "train", mode).items():
        expected = np.round(dataset.open_dataset(lightfield_ds).rgba_of(stem, train.intrinsics) * 255).astype(np.uint8)
        np.testing.assert_array_equal(image, expected, err_msg=stem)


def test_nearest_view_on_hemisphere_scores_every_test_view(hemisphere_ds, tmp_path, capsys):
    doc = baseline_scores(hemisphere_ds, "nearest", tmp_path / "nearest", capsys)
    stems = dataset.open_dataset(hemisphere_ds).cameras("test").stems
    assert sorted(p.name for p in (tmp_path / "nearest" / "test").iterdir()) == [f"{s[5:]}.png" for s in stems]
    assert [f["name"] for f in doc["frames"]] == list(stems)
    assert all(math.isfinite(doc["mean"][m]) for m in ("psnr", "ssim", "opacity_iou"))
    assert all(doc["mean"][m] is None and doc["count"][m] == 0 for m in METRIC_NAMES if m.startswith("depth"))
    assert doc["mean"]["psnr"] < 40  # another pose's image is no copy of the test view


def test_nearest_view_of_a_training_pose_is_itself(hemisphere_ds):
    train = dataset.open_dataset(hemisphere_ds).cameras("train")
    for stem, image in render_nearest(hemisphere_ds, "train").items():
        expected = np.round(dataset.open_dataset(hemisphere_ds).rgba_of(stem, train.intrinsics) * 255).astype(np.uint8)
        np.testing.assert_array_equal(image, expected, err_msg=stem)


def test_pose_distance_combines_offset_and_angle():
    base = look_at([0, -2, 0], [0, 0, 0])
    moved = look_at([1, -2, 0], [1, 0, 0])  # 1 to the side, same direction
    turned = look_at([0, -2, 0], [0, -4, 0])  # same place, looking the other way
    side = look_at([0, -2, 0], [1, -2, 0])  # same place, turned by 90 degrees
    d = pose_distance(base[None], np.stack([base, moved, turned, side]), scale=2.0)[0]
    # Exact up to float64 rounding of unit vectors (~1e-16).
    np.testing.assert_allclose(d, [0.0, 0.5, 2.0, 1.0], atol=1e-12)


# --- bad input --------------------------------------------------------------------------------


def test_lightfield_on_hemisphere_dataset_exits_2(hemisphere_ds, tmp_path, capsys):
    code = main(["baseline", str(hemisphere_ds), "--method", "lightfield-quadrilinear", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "--layout lightfield" in err and "'hemisphere'" in err
    assert not (tmp_path / "o").exists()
