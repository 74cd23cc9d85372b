"""`nerfgauge evaluate DATASET --poses POSES.json`: a method's optimised train poses scored
against the dataset's exact ones (the maths in eval.poses).

POSES.json is transforms-style: {"frames": [{"file_path": ..., "transform_matrix": 4x4}]},
camera-to-world in the dataset's OpenGL axes (+X right, +Y up, looks along -Z), one frame
per train view, matched by file_path ("./train/r_000", "train/r_000.png" and "r_000.png"
all name train/r_000: the extension and a leading "./" are dropped, a bare name is looked
up in the train split). Frames of other splits are refused; missing train views are
listed and at least 3 must be there (a similarity needs three centres).

The exact train poses are each train frame's "exact_transform_matrix" of
transforms_train.json (a dataset with --pose-noise-*), else its transform_matrix (the
poses are exact). The document (kind "pose-errors") holds per camera the rotation error
(degrees) and translation error after the Sim(3) alignment and as given, the summary
(eval.poses.pose_errors: ATE, RPE, stats), the alignment as (s, Q, t), as 4x4 matrices
both ways, and the dataset's TEST cameras carried into the method's world by the inverse
alignment (eval.poses.to_method_world: the test-time alignment of BARF and nerfstudio's
camera-optimiser evaluation), so the method can render the held-out views where its own
world has them. "input_noise" scores the dataset's own (perturbed) train poses the same
way: what the method started from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfgauge.core import validate
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json
from nerfgauge.eval import poses

KIND = "pose-errors"
MIN_CAMERAS = 3
# Camera centres farther than this from their world's origin are refused: the squared
# distances that the spread, the ATE and the unaligned errors sum overflow float64 (1.8e308)
# near 1e154 (poses scaled by 1e200 were a LinAlgError traceback). The alignment itself
# works at any scale (eval.poses.umeyama).
MAX_CENTRE = 1e150


def exact_train_poses(ds: Dataset) -> tuple[tuple, np.ndarray, np.ndarray]:
    """(stems, exact c2w [n, 4, 4], the transforms' (maybe perturbed) c2w [n, 4, 4]) of the train split."""
    cameras = ds.cameras("train")
    if not cameras.stems:
        raise InputError(f"dataset {ds.root} has no train views to score poses against")
    return cameras.stems, ds.exact_cameras("train").c2w.copy(), cameras.c2w.copy()


def _stem(file_path, train: tuple, where: str) -> str:
    rel = validate.relative_path(file_path, where)
    stem = rel.rsplit(".", 1)[0] if "." in rel.rsplit("/", 1)[-1] else rel
    if "/" not in stem:
        stem = f"train/{stem}"
    if stem not in train:
        raise InputError(f"{where}: {file_path!r} is not a train view of the dataset (train views: "
                         f"{train[0]} ... {train[-1]})")
    return stem


def read_method_poses(path, train: tuple) -> dict:
    """{stem: c2w [4, 4]} of POSES.json (module docstring); InputError naming the frame otherwise."""
    meta = read_json(path, finite=True)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames):
        raise InputError(f"{path}: 'frames' must be a list of objects with file_path and transform_matrix")
    out = {}
    for k, frame in enumerate(frames):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise InputError(f"{path}: frame {k} needs file_path and transform_matrix")
        stem = _stem(frame["file_path"], train, f"{path}: frame {k}")
        if stem in out:
            raise InputError(f"{path}: {stem} is listed twice")
        # a method's own frame: any scale (alignment refuses what it cannot align)
        out[stem] = validate.pose(frame["transform_matrix"], stem, str(path), position_limit=None)
        _check_centre(out[stem], f"{path}: {stem}")
    return out


def _check_centre(c2w: np.ndarray, where: str) -> None:
    distance = float(np.abs(c2w[:3, 3]).max())
    if distance > MAX_CENTRE:
        raise InputError(f"{where}: camera centre {c2w[:3, 3].tolist()} is beyond {MAX_CENTRE:g} of the origin "
                         "(squared distances overflow float64); scale the poses down")


def _per_camera(stems, errors: dict, raw: dict) -> list:
    return [{"name": stem, "rotation_error_degrees": float(errors["rotation_degrees"][k]),
             "translation_error": float(errors["translation"][k]),
             "rotation_error_degrees_unaligned": float(raw["rotation_degrees"][k]),
             "translation_error_unaligned": float(raw["translation"][k])} for k, stem in enumerate(stems)]


def score_pose_arrays(stems, exact: np.ndarray, estimated: np.ndarray) -> dict:
    """The scores of estimated [n, 4, 4] against exact [n, 4, 4] (module docstring)."""
    summary, (scale, rotation, translation) = poses.pose_errors(exact, estimated)
    aligned = poses.per_camera_errors(exact, estimated)
    raw = poses.per_camera_errors(exact, estimated, align=False)
    forward = poses.sim3_matrix(scale, rotation, translation)
    summary["alignment"] |= {"matrix": forward.tolist(), "inverse": np.linalg.inv(forward).tolist(),
                             "maps": "x_exact = s Q x_method + t (matrix); inverse: exact world -> method world"}
    summary["unaligned"] = {"rotation_error_degrees_mean": float(raw["rotation_degrees"].mean()),
                            "translation_error_mean": float(raw["translation"].mean()),
                            "ate_rmse": poses.ate_rmse(raw["translation"])}
    return summary | {"cameras": _per_camera(stems, aligned, raw)}


def score_poses(dataset_root, poses_path) -> dict:
    """The pose-errors document of POSES.json against the dataset's exact train poses."""
    ds = Dataset(dataset_root)
    stems, exact, given = exact_train_poses(ds)
    method = read_method_poses(poses_path, stems)
    present = [k for k, stem in enumerate(stems) if stem in method]
    missing = [stem for stem in stems if stem not in method]
    if len(present) < MIN_CAMERAS:
        raise InputError(f"{poses_path}: {len(present)} train view(s) matched; scoring poses needs at least "
                         f"{MIN_CAMERAS} (a similarity is fitted to the camera centres)")
    names = [stems[k] for k in present]
    estimated = np.stack([method[stem] for stem in names])
    for k in present:
        _check_centre(exact[k], f"dataset {ds.root}: {stems[k]}")
    try:
        document = score_pose_arrays(names, exact[present], estimated)
    except InputError as error:  # centres that leave the alignment undetermined: say whose
        raise InputError(f"{poses_path}: {error}") from None
    scale, rotation, translation = (document["alignment"]["scale"], np.array(document["alignment"]["rotation"]),
                                    np.array(document["alignment"]["translation"]))
    test = ds.cameras("test")
    in_method_world = poses.to_method_world(test.c2w, scale, rotation, translation) if test.stems else np.zeros((0, 4, 4))
    input_noise, _ = poses.pose_errors(exact[present], given[present])
    return {"dataset": str(Path(dataset_root)), "poses": str(poses_path), "split": "train",
            "convention": "OpenGL camera-to-world (+X right, +Y up, looks along -Z), as the dataset's transforms",
            "matched": len(names), "missing": missing, **document,
            "input_noise": {key: input_noise[key] for key in ("rotation_error_degrees", "translation_error", "ate_rmse")},
            "test_time_alignment": {
                "protocol": "the Sim(3) fitted on the train camera centres, inverted, applied to the exact test "
                            "poses (BARF; nerfstudio's camera-optimiser evaluation): render these to score the "
                            "test views in the method's own world",
                "frames": [{"file_path": stem + ".png", "transform_matrix": matrix.tolist()}
                           for stem, matrix in zip(test.stems, in_method_world)]}}


def format_pose_scores(document: dict) -> str:
    rot, trans = document["rotation_error_degrees"], document["translation_error"]
    return (f"poses: {document['matched']} train cameras; after Sim(3) (scale {document['alignment']['scale']:.4g}): "
            f"rotation error mean {rot['mean']:.4f} deg (max {rot['max']:.4f}), translation error mean "
            f"{trans['mean']:.4g} (max {trans['max']:.4g}), ATE {document['ate_rmse']:.4g}; "
            f"the dataset's train poses had ATE {document['input_noise']['ate_rmse']:.4g}, rotation error mean "
            f"{document['input_noise']['rotation_error_degrees']['mean']:.4f} deg")
