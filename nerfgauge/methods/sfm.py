"""Structure from motion, scored against the exact poses: `nerfgauge sfm DS --out DIR`.

pycolmap extracts SIFT features from the dataset's train images, matches them exhaustively
and runs COLMAP's incremental mapping from scratch (no poses given; the camera is the
dataset's PINHOLE intrinsics as a prior, refined by bundle adjustment unless
--fix-intrinsics). The largest reconstruction is then compared with the exact cameras:

- alignment: the similarity (scale s, rotation R, translation t) that maps the recovered
  camera centres onto the exact ones in the least-squares sense (Umeyama 1991, closed form);
- registered: fraction of the train images in the reconstruction;
- rotation error (degrees): angle of R_gt^T (R R_est), camera-to-world rotations, per
  registered image (mean, median, max);
- translation error: |c_gt - (s R c_est + t)| per registered image, in scene units and as a
  fraction of the camera spread (RMS distance of the exact train centres from their mean);
- ATE: root mean square of those translation errors (the absolute trajectory error as the
  field computes it after a Sim(3) alignment, e.g. evo's APE on translations);
- RPE: relative pose error over every pair of registered images (our views are no
  trajectory, so "consecutive" frames mean nothing): the rotation angle (degrees) and
  translation distance (scene units, after the alignment's scale) between the exact and the
  recovered relative pose, root mean square over pairs;
- reprojection error: COLMAP's mean over observations (pixels);
- points: the recovered points, aligned, against the ground-truth meshes (distance to the
  surface, generate/points.py: mean, 90th percentile, in scene units).

Why not evo: the alignment and the errors above are a dozen lines of numpy, while evo brings
pandas, seaborn and ROS bag readers into an evaluation harness that otherwise needs none of
them; `umeyama` is tested against a known random similarity and against pycolmap's own
estimator (estimate_sim3d) in tests/test_colmap.py.

The output folder (kind "sfm") holds sfm.json ("tool": "nerfgauge", "kind": "sfm"), the
feature database and the reconstruction (sparse/0, COLMAP binary). The folder is claimed
(and locked) first; everything is computed in a scratch folder inside it
(`.sfm-work-*.scratch`, core.scratch: removed at the end, and by the next run after a
kill -9; nothing goes to TMPDIR), then moved into place, sfm.json last. Bad input, too few
matches or no reconstruction leave nothing (a folder that was there before stays, empty).
"""

from __future__ import annotations

import importlib.metadata
import math
import platform
import time
from pathlib import Path

import numpy as np

from nerfgauge.core import arguments, owned
from nerfgauge.core.colmap import GL_TO_CV
from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import link_or_copy_atomic, write_json
from nerfgauge.core.folders import _check_claimable, _empty_owned, claim_folder, recipe_hash
from nerfgauge.core.outputs import stamp
from nerfgauge.core.scratch import scratch_folder
from nerfgauge.eval.poses import pose_errors, rotation_angle_degrees, umeyama  # noqa: F401 (the maths lives in eval.poses)
from nerfgauge.generate import points as points_module
from nerfgauge.generate.export import check_exportable, extract_and_match, require_pycolmap, stage_images

SCHEMA = 1
SCRATCH = "sfm-work"  # OUT/.sfm-work-XXXXXXXX.scratch while it runs (core.scratch)
MIN_REGISTERED = 3  # a similarity needs three non-collinear centres
# COLMAP's mapper wants 100 inliers to start and 30 to register an image: more than the
# ~40 SIFT features of a 128 px view of a synthetic scene hold. These thresholds (recorded in
# sfm.json) let small images reconstruct; --colmap-defaults restores COLMAP's.
SMALL_IMAGE_MAPPER = {"init_min_num_inliers": 30, "abs_pose_min_num_inliers": 15}


def run_sfm(ds, work: Path, fix_intrinsics: bool = False, colmap_defaults: bool = False) -> tuple:
    """Features, matches and incremental mapping in `work`. Returns (the largest
    reconstruction or None, names in train order, timings)."""
    pycolmap = require_pycolmap("nerfgauge sfm")
    cameras = ds.cameras("train")
    owned.make_folder(work / "images")
    names = stage_images(ds, work / "images")
    timings = {}
    start = time.perf_counter()
    extract_and_match(pycolmap, work / "database.db", work / "images", names, cameras.intrinsics)
    timings["features_and_matching"] = time.perf_counter() - start
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    options.random_seed = 0
    if not colmap_defaults:
        for name, value in SMALL_IMAGE_MAPPER.items():
            setattr(options.mapper, name, value)
    if fix_intrinsics:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    owned.make_folder(work / "sparse")
    start = time.perf_counter()
    reconstructions = pycolmap.incremental_mapping(work / "database.db", work / "images", work / "sparse",
                                                   options=options)
    timings["mapping"] = time.perf_counter() - start
    best = max(reconstructions.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)
    return best, names, timings, reconstructions


def score(ds, reconstruction, names) -> dict:
    cameras = ds.cameras("train")
    index_of = {name: k for k, name in enumerate(names)}
    registered = sorted((index_of[reconstruction.images[image_id].name], image_id)
                        for image_id in reconstruction.reg_image_ids())
    if len(registered) < MIN_REGISTERED:
        raise InputError(f"dataset {ds.root}: structure from motion registered {len(registered)} of {len(names)} train "
                         f"images (too few matches); at least {MIN_REGISTERED} are needed to align and score them")
    gt = np.stack([cameras.c2w[k] @ GL_TO_CV for k, _ in registered])
    est = []
    for _, image_id in registered:
        matrix = np.eye(4)
        matrix[:3, :] = reconstruction.images[image_id].cam_from_world().matrix()
        est.append(np.linalg.inv(matrix))
    errors, (scale, rotation, translation) = pose_errors(gt, np.stack(est))
    xyz = np.array([p.xyz for _, p in sorted(reconstruction.points3D.items())], np.float64).reshape(-1, 3)
    aligned = scale * xyz @ rotation.T + translation
    vertices, faces = points_module.read_meshes(ds)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    distance = points_module.distance_to_surface(aligned, vertices, faces, np.random.default_rng([0, 3232, 2]))
    camera = reconstruction.cameras[reconstruction.images[registered[0][1]].camera_id]
    return {
        "train_images": len(names), "registered": len(registered), "registered_fraction": len(registered) / len(names),
        "unregistered": [names[k] for k in range(len(names)) if k not in {k for k, _ in registered}],
        **errors,
        "reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "points": {"count": int(len(xyz)), "distance_to_surface": points_module.distance_summary(distance, diagonal),
                   "diagonal": diagonal},
        "camera": {"model": camera.model_name, "params": [float(p) for p in camera.params],
                   "exact": [cameras.intrinsics.fx, cameras.intrinsics.fy, cameras.intrinsics.cx, cameras.intrinsics.cy]},
    }


def sfm_command(root, out, *, overwrite: bool = False, fix_intrinsics: bool = False,
                colmap_defaults: bool = False) -> dict:
    """Run, score and save (module docstring). Returns the saved document."""
    pycolmap = require_pycolmap("nerfgauge sfm")
    ds = Dataset(root)
    check_exportable(ds)
    out = Path(out)
    recipe = recipe_hash({"dataset": ds.manifest_sha256, "fix_intrinsics": fix_intrinsics,
                          "colmap_defaults": colmap_defaults,
                          "pycolmap": pycolmap.__version__, "schema": SCHEMA})
    _check_claimable(out, "sfm", recipe, overwrite)  # refuse before the work, not after it
    existed = out.exists()
    with claim_folder(out, "sfm", recipe, overwrite=overwrite):  # held for the whole run: one sfm per folder
        try:
            return _sfm_claimed(pycolmap, ds, out, fix_intrinsics, colmap_defaults)
        except BaseException:
            if not (out / "sfm.json").is_file():  # no result here: leave nothing (the lock file of a folder
                _empty_owned(out)                  # that was there before aside)
                if not existed:
                    owned.remove_tree(out)
            raise


def _sfm_claimed(pycolmap, ds, out: Path, fix_intrinsics: bool, colmap_defaults: bool) -> dict:
    """sfm_command's work in the claimed folder `out`: computed in a scratch folder inside it
    (core.scratch: removed at the end, and by the next run after a kill -9; never TMPDIR),
    then the results moved into place, sfm.json last."""
    start = time.perf_counter()
    with scratch_folder(out, SCRATCH) as work:
        best, names, timings, reconstructions = run_sfm(ds, work, fix_intrinsics, colmap_defaults)
        if best is None:
            raise InputError(f"dataset {ds.root}: structure from motion found no reconstruction (too few matches "
                             f"between the {len(names)} train images)")
        result = score(ds, best, names)
        timings["total"] = time.perf_counter() - start
        document = stamp({
            "schema": SCHEMA, "dataset": str(ds.root), "dataset_sha256": ds.manifest_sha256,
            "reconstructions": len(reconstructions), **result, "seconds": timings,
            "options": {"features": "SIFT (pycolmap CPU, defaults)", "matching": "exhaustive",
                        "mapper": "incremental, one thread, seed 0, COLMAP's defaults"
                                  + ("" if colmap_defaults else " but " + ", ".join(
                                      f"{k} = {v}" for k, v in SMALL_IMAGE_MAPPER.items())),
                        "intrinsics": "fixed to the exact PINHOLE" if fix_intrinsics
                        else "exact PINHOLE as the prior, refined by bundle adjustment"},
            "versions": {"pycolmap": pycolmap.__version__, "colmap": str(getattr(pycolmap, "COLMAP_version", "")),
                         "numpy": np.__version__, "python": platform.python_version(),
                         "nerfgauge": importlib.metadata.version("nerfgauge")},
        }, "sfm")
        owned.remove_file(out / "sfm.json")  # an earlier result of this recipe stops looking current
        link_or_copy_atomic(work / "database.db", out / "database.db")
        owned.remove_tree(out / "sparse")
        best.write_binary(str(owned.make_folder(out / "sparse" / "0")))
        write_json(out / "sfm.json", document)
    return document


def format_sfm(document: dict) -> str:
    rot, trans = document["rotation_error_degrees"], document["translation_error"]
    points = document["points"]["distance_to_surface"]
    return (f"registered {document['registered']}/{document['train_images']} "
            f"({100 * document['registered_fraction']:.0f}%), rotation error mean {rot['mean']:.3f} deg "
            f"(max {rot['max']:.3f}), translation error mean {trans['mean']:.4f} "
            f"({100 * document['translation_error_over_spread']['mean']:.2f}% of the camera spread), "
            f"ATE {document['ate_rmse']:.4f}, RPE {document['rpe']['rotation_rmse_degrees'] or 0:.3f} deg / "
            f"{document['rpe']['translation_rmse'] or 0:.4f}, reprojection {document['reprojection_error_px']:.3f} px, "
            f"{document['points']['count']} points: distance to surface mean "
            f"{points['mean'] if points['mean'] is not None else math.nan:.4f} p90 "
            f"{points['p90'] if points['p90'] is not None else math.nan:.4f}; {document['seconds']['total']:.1f} s")


def register(subparsers) -> None:
    parser = subparsers.add_parser("sfm", help="structure from motion (pycolmap) on the train images, scored against "
                                               "the exact poses",
                                   description="Run pycolmap's incremental mapping from scratch on a dataset's train "
                                               "images and score the recovered cameras and points against the exact "
                                               "ones after a Sim(3) alignment. Needs pycolmap.")
    parser.add_argument("dataset", type=arguments.path)
    parser.add_argument("--out", required=True, type=arguments.path,
                        help="output folder (claimed: sfm.json, database.db, sparse/0)")
    parser.add_argument("--fix-intrinsics", action="store_true",
                        help="keep the exact intrinsics fixed in bundle adjustment (default: refine them)")
    parser.add_argument("--colmap-defaults", action="store_true",
                        help="COLMAP's own mapper thresholds (100 inliers to start, 30 to register an image) instead "
                             "of 30 and 15, which small images need")
    parser.add_argument("--overwrite", action="store_true", help="replace an sfm folder of another dataset or options")
    parser.set_defaults(func=run)


def run(args) -> int:
    document = sfm_command(args.dataset, args.out, overwrite=args.overwrite, fix_intrinsics=args.fix_intrinsics,
                           colmap_defaults=args.colmap_defaults)
    print(f"{args.out}: {format_sfm(document)}")
    return 0
