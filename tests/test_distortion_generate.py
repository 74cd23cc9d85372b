"""`generate --distortion` (issue 35, item 4): distorted train views rendered exactly, their
ground truth on the same rays, the files that state the camera (transforms, COLMAP, read
back by pycolmap and nerfstudio), the reader and the NeRF's rays.

Oracles: OpenCV (cv2.undistortPointsIter / cv2.fisheye.undistortPoints) for the pixels'
rays, pycolmap for the exported camera, nerfstudio's own dataparser for transforms.json.
"""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest

from cli_errors import one_line_exit_2
from nerfgauge.core.camera import Intrinsics, pixel_rays
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.distortion import Distortion

cv2 = pytest.importorskip("cv2")

OPENCV_SPEC = "opencv:-0.2,0.03,0.002,-0.001,0.01"  # k3 != 0: COLMAP's FULL_OPENCV
FISHEYE_SPEC = "fisheye:0.05,-0.02,0.004,-0.001"
PIXEL_TOLERANCE = 1e-3  # px (the bound)
# Mitsuba intersects float32 rays: a direction rounded to float32 (relative 6e-8) moves the hit
# along a surface seen at incidence cos > 1e-3 by at most t * 6e-5.
DEPTH_RELATIVE = 1e-4


@pytest.fixture(scope="module")
def opencv_ds(make_dataset, tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("distort") / "opencv", views=3, val_views=1, test_views=1,
                        distortion=OPENCV_SPEC)


@pytest.fixture(scope="module")
def fisheye_ds(make_dataset, tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("distort") / "fisheye", views=2, val_views=0, test_views=1,
                        distortion=FISHEYE_SPEC)


def opencv_rays(c2w: np.ndarray, intrinsics: Intrinsics, distortion: Distortion) -> np.ndarray:
    """World directions [H*W, 3] of the pixel centres, undistorted by OpenCV (not by us)."""
    cols, rows = np.meshgrid(np.arange(intrinsics.width) + 0.5, np.arange(intrinsics.height) + 0.5)
    points = np.stack([cols.ravel(), rows.ravel()], -1).reshape(-1, 1, 2)
    k = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    if distortion.model == "opencv":
        xy = cv2.undistortPointsIter(points, k, distortion.coefficients, None, None, criteria).reshape(-1, 2)
    else:
        xy = cv2.fisheye.undistortPoints(points, k, distortion.coefficients, criteria=criteria).reshape(-1, 2)
    local = np.column_stack([xy[:, 0], -xy[:, 1], -np.ones(len(xy))])  # OpenCV -> OpenGL camera axes
    d = local @ np.asarray(c2w)[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# --- the files -------------------------------------------------------------------------------


def test_transforms_scene_and_config_state_the_train_distortion_only(opencv_ds):
    distortion = Distortion.parse(OPENCV_SPEC)
    train = json.loads((opencv_ds / "transforms_train.json").read_text())
    assert train["camera_model"] == "OPENCV"
    assert [train[k] for k in ("k1", "k2", "p1", "p2", "k3")] == distortion.coefficients.tolist()
    for split in ("val", "test"):
        assert "camera_model" not in json.loads((opencv_ds / f"transforms_{split}.json").read_text())
    scene = json.loads((opencv_ds / "scene.json").read_text())
    assert scene["camera"]["distortion"]["splits"] == ["train"]
    assert Distortion.parse(scene["camera"]["distortion"]["spec"]) == distortion
    assert json.loads((opencv_ds / "config.json").read_text())["config"]["distortion"] == OPENCV_SPEC
    nerfstudio = json.loads((opencv_ds / "transforms.json").read_text())
    assert nerfstudio["camera_model"] == "OPENCV" and "k1" not in nerfstudio  # per frame: val/test are pinhole
    by_split = {frame["file_path"].split("/")[0]: frame for frame in nerfstudio["frames"]}
    assert [by_split["train"][k] for k in ("k1", "k2", "p1", "p2", "k3")] == distortion.coefficients.tolist()
    assert all(by_split["test"][k] == 0 for k in ("k1", "k2", "k3", "p1", "p2"))


def test_the_reader_gives_the_distortion_back_and_the_nerf_trains_on_its_rays(opencv_ds, fisheye_ds):
    from nerfgauge.nerf.data import load_split_rays

    for root, spec in ((opencv_ds, OPENCV_SPEC), (fisheye_ds, FISHEYE_SPEC)):
        ds = Dataset(root)
        assert ds.cameras("train").distortion == Distortion.parse(spec)
        assert ds.cameras("test").distortion is None
        cameras, batch = load_split_rays(ds, "train")
        h, w = cameras.intrinsics.height, cameras.intrinsics.width
        expected = np.concatenate([opencv_rays(c2w, cameras.intrinsics, cameras.distortion) for c2w in cameras.c2w])
        assert np.abs(batch.directions.numpy() - expected).max() < 1e-6  # float32 of the same rays
        pinhole = np.concatenate([pixel_rays(c2w, cameras.intrinsics)[1].reshape(-1, 3) for c2w in cameras.c2w])
        # the distortion matters here: about fx r^3 |k1| ~ 1 px at the corners (r ~ 0.5, k1 = -0.2)
        assert np.abs(pinhole - expected).max() > 0.5 / cameras.intrinsics.fx
        assert batch.rgba.shape == (len(cameras.c2w) * h * w, 4)


def test_nerfgauge_train_runs_on_a_distorted_dataset(opencv_ds, tmp_path):
    from nerfgauge.cli import main

    assert main(["train", str(opencv_ds), "--out", str(tmp_path / "run"), "--steps", "20", "--quiet",
                 "--threads", "1"]) == 0
    assert (tmp_path / "run" / "model.pt").is_file()


# --- exact ground truth of the distorted views ---------------------------------------------


@pytest.mark.parametrize("which", ["opencv", "fisheye"])
def test_distorted_depth_and_mask_are_the_scene_hit_by_opencvs_pixel_rays(mi, opencv_ds, fisheye_ds, which):
    from nerfgauge.generate.mitsuba_scene import scene_dict
    from nerfgauge.generate.render import cast_rays
    from nerfgauge.scenes import make_scene

    root = opencv_ds if which == "opencv" else fisheye_ds
    ds = Dataset(root)
    scene = mi.load_dict(scene_dict(mi, make_scene("primitives", 0), {p.stem: p for p in (root / "meshes").glob("*.ply")},
                                    8), optimize=False)
    for split in ("train", "test"):
        cameras = ds.cameras(split)
        for index, c2w in enumerate(cameras.c2w):
            if cameras.distortion is None:
                directions = pixel_rays(c2w, cameras.intrinsics)[1].reshape(-1, 3)
            else:
                directions = opencv_rays(c2w, cameras.intrinsics, cameras.distortion)
            origins = np.broadcast_to(c2w[:3, 3], directions.shape)
            distance, _, hit = cast_rays(mi, scene, np.ascontiguousarray(origins), directions)
            stored = ds.depth(split, index).ravel().astype(np.float64)
            mask = ds.mask(split, index).ravel()
            assert np.mean(mask != hit) <= 2 / mask.size, f"{split} {index}: masks differ"  # grazing rays only
            both = mask & hit
            assert np.all(np.abs(stored[both] - distance[both]) <= DEPTH_RELATIVE * distance[both])


def subpixel_coverage(mi, scene, c2w, intrinsics: Intrinsics, distortion: Distortion, n: int) -> np.ndarray:
    """Share of an n x n grid of sub-pixel positions per pixel whose ray (undistorted by
    OpenCV) hits geometry. [H, W]."""
    steps = (np.arange(n) + 0.5) / n
    cols = (np.arange(intrinsics.width)[:, None] + steps[None, :]).ravel()
    rows = (np.arange(intrinsics.height)[:, None] + steps[None, :]).ravel()
    u, v = np.meshgrid(cols, rows)
    k = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    xy = cv2.undistortPointsIter(np.stack([u.ravel(), v.ravel()], -1).reshape(-1, 1, 2), k, distortion.coefficients,
                                 None, None, criteria).reshape(-1, 2)
    d = np.column_stack([xy[:, 0], -xy[:, 1], -np.ones(len(xy))]) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    from nerfgauge.generate.render import cast_rays

    _, _, hit = cast_rays(mi, scene, np.ascontiguousarray(np.broadcast_to(c2w[:3, 3], d.shape)), d)
    grid = hit.reshape(intrinsics.height, n, intrinsics.width, n)
    return grid.mean(axis=(1, 3))


@pytest.fixture(scope="module")
def loaded_primitives(mi, tmp_path_factory):
    from nerfgauge.generate.mitsuba_scene import write_meshes
    from nerfgauge.generate.pipeline import GenerateConfig, plan
    from nerfgauge.generate.workers import load_mitsuba_scene

    the_plan = plan(GenerateConfig(scene="primitives", views=2, val_views=0, test_views=1, width=32, height=32,
                                   spp=4, variant=mi.variant().split("_")[0]))
    out = tmp_path_factory.mktemp("distorted-render")
    write_meshes(the_plan.scene, out / "meshes")
    return load_mitsuba_scene(out, the_plan)[1], the_plan


def test_rendered_coverage_is_the_distorted_pixels_coverage(mi, loaded_primitives):
    """Alpha is the share of a pixel's area whose rays hit geometry; for a distorted camera
    that area is the pixel of the distorted grid, whose rays OpenCV gives. On the pixels an
    edge crosses (in the distorted or the pinhole image) the rendered alpha must match a
    16 x 16 sub-pixel estimate within the Monte Carlo bound, and the pinhole image's alpha
    must miss it by more than twice that bound (the test tells the two cameras apart). The
    camera is moved to half its distance so that the objects' edges reach where the
    distortion is large."""
    from nerfgauge.core.camera import look_at
    from nerfgauge.generate.render import render_chunk

    scene, the_plan = loaded_primitives
    distortion = Distortion.parse("opencv:-0.3,0.05,0.003,-0.002")
    centre = (np.asarray(the_plan.scene.aabb[0]) + np.asarray(the_plan.scene.aabb[1])) / 2
    eye = the_plan.poses["train"][0][:3, 3]
    c2w, intrinsics = look_at(centre + 0.5 * (eye - centre), centre), the_plan.intrinsics
    spp, n = 64, 16
    expected = subpixel_coverage(mi, scene, c2w, intrinsics, distortion, n)
    expected_pinhole = subpixel_coverage(mi, scene, c2w, intrinsics, Distortion("opencv", p1=1e-13), n)
    distorted = render_chunk(mi, scene, None, c2w, intrinsics, spp, 3, distortion=distortion)[..., 3]
    pinhole = render_chunk(mi, scene, None, c2w, intrinsics, spp, 3)[..., 3]
    edge = (expected > 0) & (expected < 1)
    pixels = edge | ((expected_pinhole > 0) & (expected_pinhole < 1))
    assert pixels.sum() > 50
    # per pixel, E|alpha - c| <= the sd of a mean of spp Bernoulli(c) draws (independent
    # sampling; multijitter is tighter) plus the sub-pixel grid's own error on a pixel an edge
    # crosses (at most one row or column of n sub-cells, 1 / n)
    bound = np.mean((np.sqrt(expected * (1 - expected) / spp) + edge / n)[pixels])
    error = np.mean(np.abs(distorted - expected)[pixels])
    assert error <= bound, (error, bound)
    assert np.mean(np.abs(pinhole - expected)[pixels]) > 2 * bound


def test_a_negligible_distortion_renders_the_pinhole_image(mi, loaded_primitives):
    """The distorted path changes nothing but the film positions: with a distortion far below
    float32's resolution, llvm gives the pinhole image bit for bit (the same samples in the
    same order); scalar_rgb's per-sample loop is the same estimator as mi.render, so the two
    agree within their Monte Carlo noise (estimated from a second seed of each)."""
    from nerfgauge.generate.render import render_chunk

    scene, the_plan = loaded_primitives
    tiny = Distortion("opencv", p1=1e-13)
    c2w, intrinsics = the_plan.poses["train"][1], the_plan.intrinsics
    if not mi.variant().startswith("scalar"):
        pinhole = render_chunk(mi, scene, None, c2w, intrinsics, 16, 11)
        assert np.array_equal(render_chunk(mi, scene, None, c2w, intrinsics, 16, 11, distortion=tiny), pinhole)
        return
    spp = 16
    loop = [render_chunk(mi, scene, None, c2w, intrinsics, spp, seed, distortion=tiny) for seed in (1, 2)]
    film = [render_chunk(mi, scene, None, c2w, intrinsics, spp, seed) for seed in (1, 2)]
    # E[(A1 - A2)^2] = 2 Var(A): the variance of each image from its two seeds
    variance = np.mean((loop[0] - loop[1]) ** 2) / 2 + np.mean((film[0] - film[1]) ** 2) / 2
    assert np.mean((loop[0] - film[0]) ** 2) <= 2 * variance + 1e-12


# --- COLMAP and nerfstudio read the camera ---------------------------------------------------


@pytest.mark.parametrize("which, model", [("opencv", "FULL_OPENCV"), ("fisheye", "OPENCV_FISHEYE")])
def test_pycolmap_reads_the_exported_camera_and_projects_like_us(opencv_ds, fisheye_ds, which, model):
    pycolmap = pytest.importorskip("pycolmap")
    root = opencv_ds if which == "opencv" else fisheye_ds
    cameras = Dataset(root).cameras("train")
    for text in (True, False):
        folder = root / "sparse" / "0"
        if not text:  # the binary model alone
            import shutil
            import tempfile

            copy = tempfile.mkdtemp()
            for name in ("cameras.bin", "images.bin", "points3D.bin"):
                shutil.copyfile(folder / name, f"{copy}/{name}")
            folder = copy
        reconstruction = pycolmap.Reconstruction(folder)
        camera = reconstruction.cameras[1]
        assert camera.model.name == model
        i = cameras.intrinsics
        d = cameras.distortion
        expected = ([i.fx, i.fy, i.cx, i.cy, d.k1, d.k2, d.p1, d.p2, d.k3, 0, 0, 0] if model == "FULL_OPENCV"
                    else [i.fx, i.fy, i.cx, i.cy, d.k1, d.k2, d.k3, d.k4])
        assert np.array_equal(np.asarray(camera.params), np.asarray(expected, np.float64))
        # our pixel-centre rays, in COLMAP's camera axes, project onto the pixel centres
        for image in reconstruction.images.values():
            c2w = cameras.c2w[cameras.stems.index("train/" + image.name[:-4])]
            _, directions = cameras.rays(cameras.stems.index("train/" + image.name[:-4]))
            local = directions.reshape(-1, 3) @ c2w[:3, :3]  # OpenGL camera axes
            pixels = camera.img_from_cam(np.column_stack([local[:, 0], -local[:, 1], -local[:, 2]]))
            cols, rows = np.meshgrid(np.arange(i.width) + 0.5, np.arange(i.height) + 0.5)
            assert np.abs(pixels - np.column_stack([cols.ravel(), rows.ravel()])).max() < PIXEL_TOLERANCE


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("nerfstudio") is None, reason="nerfstudio is not installed (tox.ini)")
@pytest.mark.parametrize("which", ["opencv", "fisheye"])
def test_nerfstudios_dataparser_reads_the_camera_model(opencv_ds, fisheye_ds, which):
    try:
        from nerfstudio.cameras.cameras import CameraType
        from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    except ImportError as error:
        pytest.skip(f"nerfstudio's dataparser is not importable ({error})")
    root = opencv_ds if which == "opencv" else fisheye_ds
    d = Dataset(root).cameras("train").distortion
    config = NerfstudioDataParserConfig(data=root, downscale_factor=1, orientation_method="none",
                                        center_method="none", auto_scale_poses=False, load_3D_points=False)
    outputs = config.setup().get_dataparser_outputs(split="train")
    cameras = outputs.cameras
    expected = CameraType.PERSPECTIVE if which == "opencv" else CameraType.FISHEYE
    assert (cameras.camera_type == expected.value).all()
    # nerfstudio's order: k1 k2 k3 k4 p1 p2, float32
    params = np.array([d.k1, d.k2, d.k3, d.k4, d.p1, d.p2], np.float32)
    assert np.array_equal(cameras.distortion_params.numpy(), np.broadcast_to(params, cameras.distortion_params.shape))
    assert len(outputs.image_filenames) >= 1
    if which == "opencv":
        test = config.setup().get_dataparser_outputs(split="test")
        assert not test.cameras.distortion_params.numpy().any()  # the pinhole views


# --- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize("flags, expected", [
    (["--distortion", "opencv:-0.5,0,0,0", "--fov", "90"], "folds"),
    (["--distortion", "fisheye:0,0,0,0", "--fov", "170"], "90 degrees"),
    (["--distortion", "opencv:0.1,0.2"], "opencv:K1,K2,P1,P2[,K3]"),
    (["--distortion", "brown:0.1,0,0,0"], "--distortion"),
    (["--distortion", "opencv:nan,0,0,0"], "finite"),
])
def test_bad_distortion_is_one_line_exit_2_and_writes_nothing(capsys, tmp_path, flags, expected):
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "d", "--views", "2", *flags], expected)
    assert not (tmp_path / "d").exists()


def test_fold_radius_is_where_the_derivative_vanishes():
    """k1 < 0 alone: d/dr r (1 + k1 r^2) = 1 + 3 k1 r^2 = 0 at r = sqrt(-1 / (3 k1))."""
    for k1 in (-0.1, -0.5, -2.0):
        assert math.isclose(Distortion("opencv", k1=k1).first_fold(), math.sqrt(-1 / (3 * k1)), rel_tol=1e-12)
    assert Distortion("opencv", k1=0.3, k2=0.1).first_fold() == math.inf


def test_a_distorted_rolling_shutter_dataset_is_byte_identical_when_made_again(make_dataset, tmp_path):
    """The distorted and the rolling-shutter paths map sample positions in numpy between
    Dr.Jit kernels: the same recipe twice gives the same bytes (every file's sha256 in the
    manifest)."""
    settings = dict(views=2, val_views=0, test_views=1, distortion="fisheye:0.02,-0.01,0,0",
                    motion_blur="travel=0.03,rotation=1,exposure=0.5,readout=0.5")
    a = json.loads((make_dataset(tmp_path / "a", **settings) / "manifest.json").read_text())
    b = json.loads((make_dataset(tmp_path / "b", **settings) / "manifest.json").read_text())
    assert a == b


def test_sfm_points_with_a_distortion_are_refused_before_anything_is_written(capsys, tmp_path):
    pytest.importorskip("pycolmap")
    one_line_exit_2(capsys, ["generate", "primitives", "--out", tmp_path / "d", "--views", "2", "--points", "sfm",
                             "--distortion", "opencv:-0.1,0,0,0"], "PINHOLE")
    assert not (tmp_path / "d").exists()
