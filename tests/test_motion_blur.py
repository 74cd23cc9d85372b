"""`generate --motion-blur` (issue 35, item 3): a train view's colour integrates the camera's
motion over each row's exposure (K sub-frames; a rolling shutter gives every row its own
times); its transform and ground truth are the sharp mid-frame pose's.

Tolerances come from the views' own noise estimates (docs/conventions.md, "Noise"): two
independent estimates M1, M2 of one image differ by E[(M1 - M2)^2] = Var(M1) + Var(M2).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.generate import motion

SPP = 8


@pytest.fixture(scope="module")
def loaded(mi, tmp_path_factory):
    from nerfgauge.generate.mitsuba_scene import write_meshes
    from nerfgauge.generate.pipeline import GenerateConfig, plan
    from nerfgauge.generate.workers import load_mitsuba_scene

    the_plan = plan(GenerateConfig(scene="primitives", views=2, val_views=0, test_views=1, width=32, height=32,
                                   spp=SPP, variant=mi.variant().split("_")[0]))
    out = tmp_path_factory.mktemp("motion")
    write_meshes(the_plan.scene, out / "meshes")
    return load_mitsuba_scene(out, the_plan)[1], the_plan


def linear_variance(images) -> float:
    """The stored image's estimated variance (mean over pixels and RGB), from its passes."""
    return 10 ** (-images.noise["noise_psnr"]["linear"] / 10)


def render_moving(mi, loaded, spec: str, seed: int = 5):
    scene, the_plan = loaded
    blur = motion.MotionBlur.parse(spec)
    path = motion.view_path(the_plan.poses["train"][0], blur, the_plan.scene.aabb, 0, 0)
    images, count = motion.render_motion_view(mi, scene, path, blur, the_plan.intrinsics, SPP, seed,
                                              aabb=the_plan.scene.aabb)
    return images, count, path, blur


@pytest.mark.parametrize("spec", ["0", "travel=0,exposure=0.5,readout=0.5"])
def test_a_still_camera_gives_the_sharp_render_within_its_noise(mi, loaded, spec):
    """Global shutter: one sub-frame, the sharp render itself (same seed, bit for bit).
    Rolling shutter: every sample's ray made from the row's pose (the ray map), which for a
    still camera is the sharp camera again: equal to the sharp render of another seed within
    the two images' noise."""
    from nerfgauge.generate.render import render_view

    scene, the_plan = loaded
    still, count, _, blur = render_moving(mi, loaded, spec)
    assert count == 1
    sharp = render_view(mi, scene, the_plan.poses["train"][0], the_plan.intrinsics, SPP, 5)
    if blur.readout == 0:
        assert np.array_equal(still.rgba, sharp.rgba)
    other = render_view(mi, scene, the_plan.poses["train"][0], the_plan.intrinsics, SPP, 77)
    difference = np.mean((still.rgba[..., :3].astype(np.float64) - other.rgba[..., :3]) ** 2)
    expected = linear_variance(still) + linear_variance(other)
    assert difference <= 2 * expected, (difference, expected)  # E = expected; 2x for the estimates' own scatter
    assert np.array_equal(still.distance, sharp.distance) and np.array_equal(still.hit, sharp.hit)


def test_a_moving_view_is_the_mean_of_its_sub_frame_renders(mi, loaded):
    from nerfgauge.generate.render import render_passes, render_view

    scene, the_plan = loaded
    images, count, path, blur = render_moving(mi, loaded, "travel=0.12,rotation=3,exposure=0.8")
    assert count > 1
    times = motion.subframe_times(blur, count, the_plan.intrinsics.height)
    assert np.allclose(times, times[:1])  # a global shutter: every row the same times
    subframes = []
    for k in range(count):
        a, b = render_passes(mi, scene, path.pose(times[0, k]), the_plan.intrinsics, SPP, motion.subframe_seed(5, k))
        subframes.append((a.total + b.total) / (a.spp + b.spp))
    mean = np.mean(subframes, axis=0)[..., :4]
    assert np.abs(images.rgba - mean).max() <= 1e-6  # float32 rounding of the same sums
    # the sharp mid-frame pose is the ground truth recorded, and the blur is visible
    sharp = render_view(mi, scene, path.c2w_mid, the_plan.intrinsics, SPP, 5)
    assert np.array_equal(images.distance, sharp.distance) and np.array_equal(images.normals, sharp.normals)
    blurred = np.mean((images.rgba[..., :3].astype(np.float64) - sharp.rgba[..., :3]) ** 2)
    assert blurred > 3 * (linear_variance(images) + linear_variance(sharp)), blurred  # noise alone: E = 1x
    # pose(1/2) is the recorded pose; the path's ends are the layout pose moved as stated
    assert np.allclose(path.pose(0.5), path.c2w_mid, atol=1e-15)
    moved = path.pose(1.0)[:3, 3] - path.pose(0.0)[:3, 3]
    diagonal = np.linalg.norm(np.subtract(*the_plan.scene.aabb[::-1]))
    assert np.isclose(np.linalg.norm(moved), 0.12 * diagonal)


def test_a_rolling_shutter_exposes_each_row_at_its_own_times(mi, loaded):
    """Row i of a rolling-shutter image is row i of the global-shutter integral over row i's
    own window (K sub-frames at t[i, :]), within both images' noise; the global shutter's
    row (the window about mid-frame) is further off at the first and last rows that see the
    objects."""
    from nerfgauge.generate.render import render_passes

    scene, the_plan = loaded
    spec = "travel=0.15,rotation=3,exposure=0.4,readout=0.6"
    images, count, path, blur = render_moving(mi, loaded, spec)
    height = the_plan.intrinsics.height
    times = motion.subframe_times(blur, count, height)
    covered = np.flatnonzero(images.hit.mean(axis=1) > 0.25)  # rows that see the objects
    rows = [covered[0], covered[len(covered) // 2], covered[-1]]
    assert rows[2] - rows[0] > height // 3
    own, centred = [], []  # row i through its own window; through the window about mid-frame
    variance = 0.0
    for row in rows:
        for reference, store in ((times[row], own), (times[row] - times[row].mean() + 0.5, centred)):
            a_total = b_total = 0.0
            n = 0
            parts = []
            for k, t in enumerate(reference):
                a, b = render_passes(mi, scene, path.pose(t), the_plan.intrinsics, SPP, motion.subframe_seed(99, k))
                a_total, b_total, n = a_total + a.mean, b_total + b.mean, n + 1
                parts.append(((a.total + b.total) / (a.spp + b.spp))[row, :, :3])
            store.append(np.mean(parts, axis=0))
            if store is own:  # the reference's own noise, from its passes (the mean of K of each)
                variance += np.mean((a_total / n - b_total / n)[row, :, :3] ** 2) / 4 / len(rows)
    got = images.rgba[rows][..., :3].astype(np.float64)
    error_own = np.mean((got - np.stack(own)) ** 2)
    rolling_variance = linear_variance(images)
    assert error_own <= 3 * (rolling_variance + variance), (error_own, rolling_variance, variance)
    error_centred = np.mean((got[[0, 2]] - np.stack(centred)[[0, 2]]) ** 2)
    assert error_centred > 3 * error_own, (error_centred, error_own)


@pytest.mark.parametrize("text, expected", [
    ("-0.1", "from 0 to 10"), ("travel=0.1,rotation=-2", "from 0 to 360"), ("travel=0.1,exposure=0", "(0, 1]"),
    ("travel=0.1,exposure=0.7,readout=0.5", "longer than the camera's path"), ("travel=0.1,readout=-0.1", ">= 0"),
    ("fast", "--motion-blur: must be"), ("travel=0.1,speed=2", "--motion-blur: must be"), ("rotation=2", "travel is required"),
    ("travel=nan", "finite"),
])
def test_bad_motion_blur_is_one_line_exit_2_and_writes_nothing(capsys, tmp_path, text, expected):
    with pytest.raises(InputError):
        motion.MotionBlur.parse(text)
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "d", "--views", "2", "--motion-blur", text],
                    expected)
    assert not (tmp_path / "d").exists()


def test_motion_blur_with_spp_auto_is_refused(capsys, tmp_path):
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "d", "--views", "2", "--motion-blur", "0.1",
                             "--spp", "auto", "--noise-psnr", "30"], "--spp auto")


def test_a_generated_dataset_records_the_path_and_the_sharp_ground_truth(mi, make_dataset, tmp_path):
    from nerfgauge.generate.mitsuba_scene import scene_dict
    from nerfgauge.generate.render import render_geometry
    from nerfgauge.scenes import make_scene

    root = make_dataset(tmp_path / "moving", views=2, val_views=0, test_views=1, motion_blur="travel=0.05,readout=0.3,exposure=0.5")
    ds = Dataset(root)
    train = json.loads((root / "transforms_train.json").read_text())
    scene = mi.load_dict(scene_dict(mi, make_scene("primitives", 0), {p.stem: p for p in (root / "meshes").glob("*.ply")},
                                    8), optimize=False)
    for index, frame in enumerate(train["frames"]):
        entry = frame["motion"]
        assert entry["readout"] == 0.3 and entry["exposure"] == 0.5 and entry["subframes"] >= 1
        start, end = np.array(entry["start"]), np.array(entry["end"])
        mid = np.array(frame["transform_matrix"])
        assert np.allclose((start[:3, 3] + end[:3, 3]) / 2, mid[:3, 3], atol=1e-12)
        distance = render_geometry(mi, scene, mid, ds.intrinsics("train"))[0]
        assert np.array_equal(ds.depth("train", index), distance)
    assert "motion" not in json.loads((root / "transforms_test.json").read_text())["frames"][0]
    assert json.loads((root / "scene.json").read_text())["camera"]["motion_blur"]["readout"] == 0.3


def test_a_still_rolling_shutter_through_a_distortion_is_the_distorted_render(mi, loaded):
    """The rolling shutter's ray map undistorts each sample itself: with a still camera it
    must give the distorted camera's render (generate.distorted's film map) within noise."""
    from nerfgauge.core.distortion import Distortion
    from nerfgauge.generate.render import render_view

    scene, the_plan = loaded
    spp = 32  # the distortion's bias must stand out of the noise
    distortion = Distortion.parse("opencv:-0.3,0.05,0.003,-0.002")
    from nerfgauge.core.camera import look_at

    blur = motion.MotionBlur.parse("travel=0,exposure=0.5,readout=0.5")
    centre = (np.asarray(the_plan.scene.aabb[0]) + np.asarray(the_plan.scene.aabb[1])) / 2
    eye = the_plan.poses["train"][1][:3, 3]
    c2w = look_at(centre + 0.5 * (eye - centre), centre)  # close: the objects reach where the distortion is large
    path = motion.view_path(c2w, blur, the_plan.scene.aabb, 0, 1)
    rolling, _ = motion.render_motion_view(mi, scene, path, blur, the_plan.intrinsics, spp, 5,
                                           aabb=the_plan.scene.aabb, distortion=distortion)
    distorted = render_view(mi, scene, c2w, the_plan.intrinsics, spp, 77, distortion=distortion)
    pinhole = render_view(mi, scene, c2w, the_plan.intrinsics, spp, 77)
    expected = linear_variance(rolling) + linear_variance(distorted)
    difference = np.mean((rolling.rgba[..., :3].astype(np.float64) - distorted.rgba[..., :3]) ** 2)
    assert difference <= 2 * expected, (difference, expected)
    off = np.mean((rolling.rgba[..., :3].astype(np.float64) - pinhole.rgba[..., :3]) ** 2)
    assert off > 3 * (linear_variance(rolling) + linear_variance(pinhole)), off  # noise alone: E = 1x
    assert np.array_equal(rolling.distance, distorted.distance)
