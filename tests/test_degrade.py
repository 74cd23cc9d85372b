"""Degraded training views (generate.degrade; docs/conventions.md "Degradations"): the
statistics of the pose noise against what was asked, the photometric pipeline undone
exactly from the recorded parameters, and everything but the train colour and train poses
byte for byte the clean dataset's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfgauge.core import dataset
from nerfgauge.core.camera import Intrinsics
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.core.images import read_exr
from nerfgauge.generate.degrade import (Degradations, Photometric, camera_spread, perturb_poses,
                                        rotation_from_vector, undo_photometric, vignetting_map)
from nerfgauge.generate.pipeline import GenerateConfig


def random_poses(n: int, rng) -> np.ndarray:
    """n camera-to-world matrices [n, 4, 4] with random rotations and centres."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                  2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                  2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1).reshape(n, 3, 3)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = r
    c2w[:, :3, 3] = rng.normal(scale=3.0, size=(n, 3))
    return c2w


def log_rotation(r: np.ndarray) -> np.ndarray:
    """Rotation vectors [n, 3] of rotation matrices [n, 3, 3] (angles below pi)."""
    axis = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=1)
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, np.trace(r, axis1=1, axis2=2) - 1)
    return axis / s[:, None] * angle[:, None]


def test_rotation_from_vector_is_a_rotation_and_inverts_the_log():
    rng = np.random.default_rng(3)
    omega = rng.normal(scale=0.7, size=(200, 3))
    r = rotation_from_vector(omega)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-13)
    np.testing.assert_allclose(log_rotation(r), omega, atol=1e-12)
    np.testing.assert_array_equal(rotation_from_vector(np.zeros((1, 3)))[0], np.eye(3))


@pytest.mark.parametrize("rotation_deg,translation", [(2.0, 0.05), (0.5, 0.0), (10.0, 0.3)])
def test_pose_noise_statistics_match_the_request(rotation_deg, translation):
    """Over n cameras: the mean squared angle estimates sigma^2 (angle^2 = sigma^2/3 chi^2_3,
    variance 2 sigma^4 / 3, so the sample mean has sd sigma^2 sqrt(2 / (3 n))); the axis is
    uniform (each component's mean 0 with sd 1/sqrt(3n), its square's mean 1/3 with sd
    sqrt(4/45 / n)); the offsets' mean squared length estimates (tau s)^2 likewise. All
    within 5 standard deviations; the perturbation is in the camera frame and keeps R a
    rotation; the centre noise is independent of the rotation noise."""
    n = 20000
    rng = np.random.default_rng(11)
    exact = random_poses(n, rng)
    noisy = perturb_poses(exact, Degradations(pose_noise_rotation=rotation_deg, pose_noise_translation=translation), 5)
    delta = np.swapaxes(exact[:, :3, :3], 1, 2) @ noisy[:, :3, :3]  # R^T R' = Exp(omega)
    np.testing.assert_allclose(np.linalg.det(noisy[:, :3, :3]), 1.0, atol=1e-12)
    omega = log_rotation(delta)
    angle2 = np.sum(omega ** 2, axis=1)
    sigma2 = math.radians(rotation_deg) ** 2
    assert abs(angle2.mean() - sigma2) < 5 * sigma2 * math.sqrt(2 / (3 * n))
    axis = omega / np.linalg.norm(omega, axis=1, keepdims=True)
    assert np.all(np.abs(axis.mean(axis=0)) < 5 / math.sqrt(3 * n))
    assert np.all(np.abs((axis ** 2).mean(axis=0) - 1 / 3) < 5 * math.sqrt(4 / 45 / n))
    offsets = noisy[:, :3, 3] - exact[:, :3, 3]
    wanted = (translation * camera_spread(exact)) ** 2
    if translation == 0:
        np.testing.assert_array_equal(offsets, 0.0)
    else:
        assert abs(np.sum(offsets ** 2, axis=1).mean() - wanted) < 5 * wanted * math.sqrt(2 / (3 * n))
        corr = np.corrcoef(offsets[:, 0], omega[:, 0])[0, 1]
        assert abs(corr) < 5 / math.sqrt(n)
    np.testing.assert_array_equal(noisy[:, 3], exact[:, 3])


def test_camera_spread_is_the_rms_distance_from_the_mean():
    c2w = np.tile(np.eye(4), (4, 1, 1))
    c2w[:, :3, 3] = [[1, 0, 0], [-1, 0, 0], [0, 3, 0], [0, -3, 0]]
    assert camera_spread(c2w) == pytest.approx(math.sqrt((1 + 1 + 9 + 9) / 4), rel=1e-15)


def test_draws_are_seeded_per_kind_and_scale_with_the_level():
    """Each kind has its own stream: the pose noise at one level is the same directions scaled
    (a level sweep is monotone per camera); exposure does not move the pose draws; another
    --degrade-seed draws others; None means the dataset seed."""
    exact = random_poses(50, np.random.default_rng(0))
    one = perturb_poses(exact, Degradations(pose_noise_rotation=1.0), 7)
    two = perturb_poses(exact, Degradations(pose_noise_rotation=2.0, exposure_ev=1.0), 7)
    w1 = log_rotation(np.swapaxes(exact[:, :3, :3], 1, 2) @ one[:, :3, :3])
    w2 = log_rotation(np.swapaxes(exact[:, :3, :3], 1, 2) @ two[:, :3, :3])
    np.testing.assert_allclose(w2, 2 * w1, rtol=1e-9, atol=1e-14)
    np.testing.assert_array_equal(perturb_poses(exact, Degradations(pose_noise_rotation=1.0, degrade_seed=7), 99), one)
    assert not np.array_equal(perturb_poses(exact, Degradations(pose_noise_rotation=1.0, degrade_seed=8), 7), one)
    a = Degradations(exposure_ev=0.5).view_photometric(7, 3)
    b = Degradations(exposure_ev=1.0, pose_noise_rotation=3.0).view_photometric(7, 3)
    assert b.exposure_ev == pytest.approx(2 * a.exposure_ev, rel=1e-15) and a.wb_gains == (1.0, 1.0, 1.0)


def test_photometric_draws_follow_the_stated_distributions():
    """Over n views: EV ~ N(0, s_ev^2), log2 of the R and B gains ~ N(0, s_wb^2), G = 1, k
    fixed. Sample mean within 5 sd (s / sqrt n) of 0; sample variance within 5 sd
    (s^2 sqrt(2 / (n - 1))) of s^2; the three independent (|corr| < 5 / sqrt n)."""
    n = 20000
    degradations = Degradations(exposure_ev=0.7, white_balance=0.3, vignetting=0.1)
    draws = [degradations.view_photometric(1, i) for i in range(n)]
    ev = np.array([d.exposure_ev for d in draws])
    wb = np.log2(np.array([d.wb_gains for d in draws]))
    assert np.all(wb[:, 1] == 0) and all(d.vignetting == 0.1 for d in draws)
    for values, sigma in ((ev, 0.7), (wb[:, 0], 0.3), (wb[:, 2], 0.3)):
        assert abs(values.mean()) < 5 * sigma / math.sqrt(n)
        assert abs(values.var(ddof=1) - sigma ** 2) < 5 * sigma ** 2 * math.sqrt(2 / (n - 1))
    corr = np.corrcoef(np.stack([ev, wb[:, 0], wb[:, 2]]))
    assert np.all(np.abs(corr[np.triu_indices(3, 1)]) < 5 / math.sqrt(n))


def test_vignetting_map_is_one_at_the_centre_and_one_minus_k_at_the_corners():
    """Pixel centres at +-(w/2 - 1/2, h/2 - 1/2) from (cx, cy) = (w/2, h/2): r^2 there is
    ((w-1)^2 + (h-1)^2) / (w^2 + h^2)."""
    intr = Intrinsics.from_fov(6, 4, 40.0)
    v = vignetting_map(intr, 0.4)
    r2_corner = ((6 - 1) ** 2 + (4 - 1) ** 2) / (6 ** 2 + 4 ** 2)
    for row, col in ((0, 0), (0, 5), (3, 0), (3, 5)):
        assert v[row, col] == pytest.approx(1 - 0.4 * r2_corner, rel=1e-15)
    assert v.max() < 1 and v.min() > 0.6
    np.testing.assert_allclose(v, v[::-1, ::-1], rtol=0, atol=1e-15)  # symmetric about the centre


@pytest.mark.parametrize("field,value", [("pose_noise_rotation", -0.5), ("pose_noise_translation", float("nan")),
                                         ("exposure_ev", float("inf")), ("white_balance", -1e-3),
                                         ("vignetting", 1.0), ("vignetting", -0.1), ("degrade_seed", -1),
                                         ("exposure_ev", "1"), ("vignetting", True), ("pose_noise_rotation", 90.0)])
def test_bad_degradations_are_input_errors(field, value):
    with pytest.raises(InputError, match="--" + field.replace("_", "-")):
        GenerateConfig(**{field: value}).validate()


def test_recipe_of_a_clean_dataset_is_unchanged():
    """The degradation fields enter config.json only when set: older datasets keep their hash."""
    clean = GenerateConfig().to_json()
    assert not set(clean) & {"pose_noise_rotation", "exposure_ev", "white_balance", "vignetting", "degrade_seed"}
    assert GenerateConfig(vignetting=0.2, degrade_seed=0).to_json()["degrade_seed"] == 0


# --- on rendered datasets ---------------------------------------------------------------------

SETTINGS = dict(views=5, val_views=1, test_views=2, width=32, height=24, spp=4, seed=3)
ALL = dict(pose_noise_rotation=2.0, pose_noise_translation=0.05, exposure_ev=0.5, white_balance=0.2,
           vignetting=0.3, degrade_seed=12)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory, make_dataset):
    root = tmp_path_factory.mktemp("degrade")
    return {"clean": make_dataset(root / "clean", **SETTINGS),
            "all": make_dataset(root / "all", **SETTINGS, **ALL),
            "exposure": make_dataset(root / "exposure", **SETTINGS, exposure_ev=1.0, pose_noise_rotation=1.0)}


def test_everything_but_train_colour_and_poses_is_the_clean_dataset_byte_for_byte(datasets):
    clean, degraded = datasets["clean"], datasets["all"]
    for split in ("val", "test"):
        assert read_json(degraded / f"transforms_{split}.json") == read_json(clean / f"transforms_{split}.json")
    for stem in dataset.Dataset(clean).frames("val") + dataset.Dataset(clean).frames("test"):
        for rel in dataset.frame_files(stem).values():
            assert (degraded / rel).read_bytes() == (clean / rel).read_bytes(), rel
    for stem in dataset.Dataset(clean).frames("train"):
        for kind, rel in dataset.frame_files(stem).items():
            if kind not in ("png", "exr", "noise"):
                assert (degraded / rel).read_bytes() == (clean / rel).read_bytes(), rel
    for mesh in (clean / "meshes").iterdir():
        assert (degraded / "meshes" / mesh.name).read_bytes() == mesh.read_bytes()


def test_undoing_the_recorded_pipeline_recovers_the_clean_linear_render(datasets):
    """degraded = fl32(clean * f) with f the recorded factors, so degraded / f is clean to
    float32 rounding: relative error at most 2^-24 (2^-23 allowed); alpha untouched."""
    clean, degraded = datasets["clean"], datasets["all"]
    ds = dataset.Dataset(degraded)
    intr = ds.intrinsics("train")
    frames = read_json(degraded / "transforms_train.json")["frames"]
    changed = 0
    for frame, stem in zip(frames, ds.frames("train")):
        p = frame["photometric"]
        assert p["wb_gains"][1] == 1.0 and p["vignetting_k"] == 0.3
        assert p["gain"] == pytest.approx(2.0 ** p["exposure_ev"], rel=1e-15)
        photometric = Photometric(p["exposure_ev"], tuple(p["wb_gains"]), p["vignetting_k"])
        exr = dataset.frame_files(stem)["exr"]
        ours, theirs = read_exr(degraded / exr)[0]["RGBA"], read_exr(clean / exr)[0]["RGBA"]
        recovered = undo_photometric(ours, photometric, intr)
        np.testing.assert_allclose(recovered, theirs, rtol=2 ** -23, atol=0)
        np.testing.assert_array_equal(ours[..., 3], theirs[..., 3])
        changed += not np.array_equal(ours, theirs)
    assert changed == len(frames)


def test_noise_json_describes_the_stored_image(datasets):
    """Exposure alone scales both passes by 2^EV: the linear variance by 4^EV, so the linear
    noise PSNR drops by exactly 20 log10(2^EV) dB (float rounding of the passes aside)."""
    clean, degraded = datasets["clean"], datasets["exposure"]
    frames = read_json(degraded / "transforms_train.json")["frames"]
    for frame, stem in zip(frames, dataset.Dataset(clean).frames("train")):
        rel = dataset.frame_files(stem)["noise"]
        before, after = read_json(clean / rel), read_json(degraded / rel)
        shift = 20 * math.log10(frame["photometric"]["gain"])
        assert after["noise_psnr"]["linear"] == pytest.approx(before["noise_psnr"]["linear"] - shift, abs=1e-6)
        assert after["spp"] == before["spp"]


def test_train_transforms_hold_the_perturbed_poses_and_the_exact_ones_beside_them(datasets):
    clean, degraded = datasets["clean"], datasets["all"]
    exact = dataset.Dataset(clean).c2w("train")
    wanted = perturb_poses(exact, Degradations(**ALL), SETTINGS["seed"])
    ours = dataset.Dataset(degraded)
    np.testing.assert_allclose(ours.c2w("train"), wanted, rtol=0, atol=1e-12)  # the reader sees the noisy poses
    synthetic = read_json(degraded / "transforms_train.json")["frames"]
    np.testing.assert_array_equal([f["exact_transform_matrix"] for f in synthetic], exact)
    nerfstudio = {f["file_path"]: f for f in read_json(degraded / "transforms.json")["frames"]}
    clean_ns = {f["file_path"]: f for f in read_json(clean / "transforms.json")["frames"]}
    for k, stem in enumerate(ours.frames("train")):
        frame = nerfstudio[stem + ".png"]
        np.testing.assert_array_equal(frame["transform_matrix"], synthetic[k]["transform_matrix"])
        np.testing.assert_array_equal(frame["exact_transform_matrix"], exact[k])
        assert frame["photometric"] == synthetic[k]["photometric"]
    for stem in ours.frames("val") + ours.frames("test"):
        assert nerfstudio[stem + ".png"] == clean_ns[stem + ".png"]
    scene = read_json(degraded / "scene.json")["degradations"]
    assert scene["seed_used"] == 12 and scene["pose_noise_rotation"] == 2.0
    assert scene["spread"] == pytest.approx(camera_spread(exact), rel=1e-12)
    config = read_json(degraded / "config.json")["config"]
    assert {key: config[key] for key in ALL} == ALL


def test_colmap_export_holds_the_perturbed_train_poses(datasets):
    pycolmap = pytest.importorskip("pycolmap")
    degraded = datasets["all"]
    ds = dataset.Dataset(degraded)
    model = pycolmap.Reconstruction(degraded / "sparse" / "0")
    noisy = ds.c2w("train")
    for k in range(len(noisy)):
        np.testing.assert_allclose(model.images[k + 1].projection_center(), noisy[k, :3, 3], rtol=0, atol=1e-9)
    exact = np.array([f["exact_transform_matrix"] for f in read_json(degraded / "transforms_train.json")["frames"]])
    assert np.abs(noisy[:, :3, 3] - exact[:, :3, 3]).max() > 1e-6  # the export did not take the exact ones


def test_cli_flags_reach_the_config(tmp_path, capsys):
    import argparse

    from nerfgauge.generate import options

    parser = options.add_generate_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--pose-noise-rotation", "1.5", "--pose-noise-translation", "0.1", "--exposure-ev",
                              "0.25", "--white-balance", "0.1", "--vignetting", "0.2", "--degrade-seed", "4"])
    config = GenerateConfig(**options.generate_fields(args))
    assert config.degradations() == Degradations(1.5, 0.1, 0.25, 0.1, 0.2, 4)


def test_ground_truth_geometry_uses_the_exact_poses(datasets):
    """Depth maps were rendered from the exact poses, so visibility and co-visibility pair
    them with those (Dataset.exact_cameras): the held-out pixels of every test view, and the
    COLMAP export's surface points (mesh samples some train view sees), are the clean
    dataset's exactly."""
    pycolmap = pytest.importorskip("pycolmap")
    from nerfgauge.eval.covisibility import held_out_pixels, reference_depths

    clean, degraded = dataset.Dataset(datasets["clean"]), dataset.Dataset(datasets["all"])
    np.testing.assert_array_equal(degraded.exact_cameras("train").c2w, clean.c2w("train"))
    assert not np.array_equal(degraded.c2w("train"), clean.c2w("train"))
    assert degraded.exact_cameras("test") is degraded.cameras("test")
    for index in range(len(clean.frames("test"))):
        masks = []
        for ds in (clean, degraded):
            pixels = held_out_pixels(ds, "test", index, reference_depths(ds), ds.mask("test", index),
                                     ds.depth("test", index, kind="distance"))
            masks.append((pixels.covisible, pixels.resolved))
        np.testing.assert_array_equal(masks[0][0], masks[1][0])
        np.testing.assert_array_equal(masks[0][1], masks[1][1])
    xyz = [np.array(sorted(p.xyz.tolist() for p in pycolmap.Reconstruction(ds.root / "sparse" / "0").points3D.values()))
           for ds in (clean, degraded)]
    np.testing.assert_array_equal(xyz[0], xyz[1])


def test_the_api_takes_the_degradations(tmp_path):
    import nerfgauge

    out = nerfgauge.generate_dataset("primitives", tmp_path / "api", views=3, val_views=0, test_views=1, width=16,
                                     height=16, spp=2, vignetting=0.25, degrade_seed=9)
    scene = read_json(out / "scene.json")["degradations"]
    assert scene["vignetting"] == 0.25 and scene["seed_used"] == 9
    frames = read_json(out / "transforms_train.json")["frames"]
    assert all(f["photometric"]["vignetting_k"] == 0.25 and "exact_transform_matrix" not in f for f in frames)
    with pytest.raises(InputError, match="--vignetting"):
        nerfgauge.generate_dataset("primitives", tmp_path / "bad", views=3, vignetting=-0.5)
    assert not (tmp_path / "bad").exists()


def test_degraded_dataset_is_the_same_bytes_with_two_workers(datasets, tmp_path):
    """Each view's draws depend on (seed, index) only: rendering on two worker processes
    gives the same files, so the same manifest.json (which hashes every file)."""
    from nerfgauge.generate.pipeline import generate

    out = tmp_path / "workers"
    generate(GenerateConfig(scene="primitives", **SETTINGS, **ALL), out, workers=2, progress=False)
    assert (out / "manifest.json").read_bytes() == (datasets["all"] / "manifest.json").read_bytes()
