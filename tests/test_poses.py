"""Pose errors (eval.poses) and `nerfgauge evaluate DATASET --poses POSES.json`
(eval.pose_scores): the Umeyama alignment and the ATE checked against evo, an independent
implementation; known similarities and rotations recovered; the test-time alignment
carries exact test poses into the method's world."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nerfgauge.cli import main
from nerfgauge.core.files import read_json
from nerfgauge.eval import poses
from nerfgauge.generate.degrade import rotation_from_vector

from test_degrade import random_poses


def random_similarity(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    return float(rng.uniform(0.3, 3.0)), q, rng.normal(size=3)


def test_umeyama_agrees_with_evo():
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(1)
    for _ in range(5):
        source = rng.normal(size=(40, 3))
        s, q, t = random_similarity(rng)
        target = s * source @ q.T + t + rng.normal(scale=0.1, size=source.shape)
        ours = poses.umeyama(source, target)
        r, tt, c = umeyama_alignment(source.T, target.T, True)
        assert ours[0] == pytest.approx(c, rel=1e-10)
        np.testing.assert_allclose(ours[1], r, atol=1e-10)
        np.testing.assert_allclose(ours[2], tt, atol=1e-10)


def test_ate_agrees_with_evo_ape_after_sim3_alignment():
    """evo: PosePath3D of both, est.align(ref, correct_scale=True), APE on the translation
    part, RMSE statistic; ours: poses.pose_errors' ate_rmse. Same numbers to 1e-9."""
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    rng = np.random.default_rng(2)
    gt = random_poses(30, rng)
    s, q, t = random_similarity(rng)
    est = poses.to_method_world(gt, s, q, t)
    est[:, :3, 3] += rng.normal(scale=0.05, size=(30, 3))
    est[:, :3, :3] = est[:, :3, :3] @ rotation_from_vector(rng.normal(scale=0.01, size=(30, 3)))
    ours, _ = poses.pose_errors(gt, est)
    ref, theirs = PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))
    theirs.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, theirs))
    assert ours["ate_rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    # evo's rotation angle per pose after its alignment equals ours
    ape_rot = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape_rot.process_data((ref, theirs))
    per = poses.per_camera_errors(gt, est)
    np.testing.assert_allclose(np.sort(per["rotation_degrees"]), np.sort(ape_rot.error), atol=1e-7)


def test_a_method_world_moved_by_a_similarity_scores_zero_and_its_test_poses_come_back():
    rng = np.random.default_rng(3)
    gt, gt_test = random_poses(12, rng), random_poses(4, rng)
    s, q, t = random_similarity(rng)
    est = poses.to_method_world(gt, s, q, t)  # the method's world: x_gt = s q x + t
    per = poses.per_camera_errors(gt, est)
    scale, rotation, translation = per["alignment"]
    assert scale == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(rotation, q, atol=1e-12)
    np.testing.assert_allclose(translation, t, atol=1e-11)
    assert per["rotation_degrees"].max() < 1e-6 and per["translation"].max() < 1e-11
    unaligned = poses.per_camera_errors(gt, est, align=False)
    assert unaligned["translation"].max() > 1e-3  # as given, the worlds differ
    test_in_method = poses.to_method_world(gt_test, *per["alignment"])
    np.testing.assert_allclose(poses.align_c2w(test_in_method, *per["alignment"]), gt_test, atol=1e-11)
    np.testing.assert_allclose(test_in_method, poses.to_method_world(gt_test, s, q, t), atol=1e-11)


def test_known_rotation_errors_are_measured():
    """Centres exact, rotations turned by known angles: the alignment is the identity and
    each camera's error is its angle."""
    rng = np.random.default_rng(4)
    gt = random_poses(20, rng)
    angles = rng.uniform(0.1, 20.0, size=20)
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    est = gt.copy()
    est[:, :3, :3] = gt[:, :3, :3] @ rotation_from_vector(axes * np.radians(angles)[:, None])
    per = poses.per_camera_errors(gt, est)
    np.testing.assert_allclose(per["rotation_degrees"], angles, atol=1e-9)
    np.testing.assert_allclose(per["translation"], 0.0, atol=1e-12)


# --- the command ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def noisy(tmp_path_factory, make_dataset):
    return make_dataset(tmp_path_factory.mktemp("poses") / "noisy", views=8, val_views=0, test_views=2, width=16,
                        height=16, spp=2, pose_noise_rotation=3.0, pose_noise_translation=0.05)


def write_poses(path, frames):
    path.write_text(json.dumps({"frames": frames}))
    return path


def test_evaluate_poses_scores_the_datasets_own_noisy_poses_and_the_exact_ones(noisy, tmp_path, capsys):
    frames = read_json(noisy / "transforms_train.json")["frames"]
    exact = np.array([f["exact_transform_matrix"] for f in frames])
    given = write_poses(tmp_path / "given.json", [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]}
                                                  for f in frames])
    assert main(["evaluate", str(noisy), "--poses", str(given)]) == 0
    assert "ATE" in capsys.readouterr().out
    document = read_json(tmp_path / "pose_errors.json")
    assert document["kind"] == "pose-errors" and document["matched"] == 8 and document["missing"] == []
    noisy_c2w = np.array([f["transform_matrix"] for f in frames])
    wanted = poses.rotation_angle_degrees(np.swapaxes(exact[:, :3, :3], 1, 2) @ noisy_c2w[:, :3, :3])
    got = [c["rotation_error_degrees_unaligned"] for c in document["cameras"]]
    np.testing.assert_allclose(got, wanted, atol=1e-9)
    assert document["ate_rmse"] == pytest.approx(document["input_noise"]["ate_rmse"], rel=1e-12)
    assert len(document["test_time_alignment"]["frames"]) == 2
    # the exact poses, by bare names: zero error, an identity alignment
    bare = write_poses(tmp_path / "exact.json", [{"file_path": f["file_path"].rsplit("/", 1)[-1] + ".png",
                                                   "transform_matrix": m.tolist()} for f, m in zip(frames, exact)])
    assert main(["evaluate", str(noisy), "--poses", str(bare), "--poses-out", str(tmp_path / "zero.json")]) == 0
    zero = read_json(tmp_path / "zero.json")
    assert zero["ate_rmse"] < 1e-12 and zero["rotation_error_degrees"]["max"] < 1e-6
    assert zero["alignment"]["scale"] == pytest.approx(1.0, rel=1e-12)
    test = read_json(noisy / "transforms_test.json")["frames"]
    np.testing.assert_allclose([f["transform_matrix"] for f in zero["test_time_alignment"]["frames"]],
                               [f["transform_matrix"] for f in test], atol=1e-12)


@pytest.mark.parametrize("frames,expected", [
    (lambda fs: fs[:2], "needs at least 3"),
    (lambda fs: fs + [{"file_path": "./test/r_000", "transform_matrix": fs[0]["transform_matrix"]}],
     "is not a train view"),
    (lambda fs: fs + fs[:1], "listed twice"),
    (lambda fs: [{"file_path": fs[0]["file_path"], "transform_matrix": [[1, 0, 0, 0]] * 4}] + fs[1:],
     "transform_matrix"),
])
def test_bad_pose_files_are_one_line_and_exit_2(noisy, tmp_path, capsys, frames, expected):
    given = [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]}
             for f in read_json(noisy / "transforms_train.json")["frames"]]
    path = write_poses(tmp_path / "p.json", frames(given))
    assert main(["evaluate", str(noisy), "--poses", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not (tmp_path / "pose_errors.json").exists()


def test_evaluate_without_pred_or_poses_is_refused(noisy, capsys):
    assert main(["evaluate", str(noisy)]) == 2
    assert "--pred" in capsys.readouterr().err


def test_rms_of_the_scored_noise_matches_the_request_loosely(noisy, tmp_path):
    """8 cameras only: the unaligned RMS angle is within the chi(3)-based 3-sigma band of
    3 degrees (angle^2 mean has relative sd sqrt(2 / (3 n)) = 0.29 at n = 8)."""
    frames = read_json(noisy / "transforms_train.json")["frames"]
    write_poses(tmp_path / "given.json", [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]}
                                          for f in frames])
    assert main(["evaluate", str(noisy), "--poses", str(tmp_path / "given.json")]) == 0
    document = read_json(tmp_path / "pose_errors.json")
    ms = np.mean([c["rotation_error_degrees_unaligned"] ** 2 for c in document["cameras"]])
    assert abs(ms / 9.0 - 1) < 3 * math.sqrt(2 / (3 * 8))


def test_poses_out_never_replaces_a_users_file(noisy, tmp_path, capsys):
    frames = read_json(noisy / "transforms_train.json")["frames"]
    given = write_poses(tmp_path / "given.json", [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]}
                                                  for f in frames])
    mine = tmp_path / "pose_errors.json"
    mine.write_text('{"mine": true}')
    assert main(["evaluate", str(noisy), "--poses", str(given)]) == 2
    assert "refusing to replace" in capsys.readouterr().err and mine.read_text() == '{"mine": true}'
    out = tmp_path / "scores.json"
    assert main(["evaluate", str(noisy), "--poses", str(given), "--poses-out", str(out)]) == 0
    assert main(["evaluate", str(noisy), "--poses", str(given), "--poses-out", str(out)]) == 0  # our own: replaced
    assert main(["evaluate", str(noisy), "--poses", str(given), "--poses-out", str(noisy / "x.json")]) == 2
    assert "dataset" in capsys.readouterr().err
