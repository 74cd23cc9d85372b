"""Camera pose errors as pure functions: a method's optimised (or recovered) train poses
against the exact ones, after a similarity alignment. numpy only, float64.

Notation: c2w [n, 4, 4] camera-to-world matrices (rotation R_i = c2w[:3, :3], centre
c_i = c2w[:3, 3]); gt the exact poses, est the method's. A similarity (s, Q, t) maps the
method's world to the dataset's: x_gt = s Q x_est + t.

- Alignment (umeyama): argmin over (s, Q, t) of sum_i |c_gt_i - (s Q c_est_i + t)|^2, closed
  form (Umeyama, PAMI 1991): with mu the means, Sigma = (1/n) sum (c_gt - mu_gt)(c_est - mu_est)^T
  = U D V^T, S = diag(1, 1, det(U) det(V)), Q = U S V^T, s = tr(D S) / var_est, t = mu_gt - s Q mu_est.
  The minimiser is unique only when Sigma has rank 2 or more: centres that coincide leave
  s and Q free, centres on one line leave the rotation about that line free, so either set
  of centres coinciding or collinear (within COINCIDENT and COLLINEAR) is an InputError
  naming which and why (`check_alignable`), never an arbitrary alignment. Each set is scaled
  by a power of two before the sums (exact: the results are those of the plain formula), so
  centres anywhere in float64's range do not overflow their squares; s, Q, t are checked
  finite before they are used.
- Aligned pose: R'_i = Q R_est_i, c'_i = s Q c_est_i + t (align_c2w).
- Rotation error (deg): angle(R_gt_i^T R'_i) = atan2(|vee(M - M^T)|, tr M - 1).
- Translation error: |c'_i - c_gt_i| (scene units), also over the spread of the exact
  centres (sqrt(mean |c_gt - mean c_gt|^2)).
- ATE: sqrt(mean_i |c'_i - c_gt_i|^2), the absolute trajectory error after a Sim(3)
  alignment as evo's APE (translation part, --align --correct_scale) computes it.
- RPE over every pair (i, j) (views are no trajectory): angle of the exact against the
  aligned relative rotation, and the distance of the relative translations, RMS over pairs.

Test-time alignment (to_method_world): a method that optimised its poses has drifted into
its own world; to render the held-out views it needs their exact poses in that world,
c2w_method = inverse similarity applied to c2w_gt: R = Q^T R_gt, c = Q^T (c_gt - t) / s. This
is the protocol of BARF and of nerfstudio's camera-optimiser evaluation (the Sim(3) fitted
on the train cameras is applied to the test cameras before rendering; BARF then also
refines each test pose photometrically, which needs the method and is not done here).
"""

from __future__ import annotations

import numpy as np

from nerfgauge.core.errors import InputError


# Degenerate centres (module docstring). COINCIDENT: the centres' RMS spread below this
# fraction of their largest coordinate is float64 rounding of one point (1e-16 relative),
# with room for the rounding of any pose arithmetic before us. COLLINEAR: a spread off the
# best line below this fraction of the spread along it determines the rotation about that
# line only to about this many radians, which is noise, not an alignment.
COINCIDENT = 1e-9
COLLINEAR = 1e-6


def _power_of_two_scale(points: np.ndarray) -> float:
    """2^k near the largest |coordinate| of `points` (1 for all zeros): dividing by it is exact."""
    largest = float(np.abs(points).max()) if points.size else 0.0
    return float(np.ldexp(1.0, np.frexp(largest)[1])) if largest > 0 else 1.0


def principal_spreads(points: np.ndarray) -> np.ndarray:
    """RMS spread of points [n, 3] along their principal axes, largest first. [3]."""
    centred = points - points.mean(axis=0)
    return np.linalg.svd(centred / np.sqrt(len(points)), compute_uv=False)


def check_alignable(points: np.ndarray, name: str, unit: float = 1.0) -> None:
    """InputError (one line, naming `name` and why) when the centres `points` [n, 3] (in
    multiples of `unit`, which the message undoes) leave a similarity fitted to them
    undetermined: fewer than 3, coinciding or on one line (module docstring)."""
    if len(points) < 3:
        raise InputError(f"the {name} camera centres are {len(points)}: fitting a similarity needs 3 that are not "
                         "on one line")
    spreads = principal_spreads(points)
    largest = float(np.abs(points).max())
    if spreads[0] <= COINCIDENT * largest or largest == 0:
        raise InputError(f"the {name} camera centres coincide (spread {spreads[0] * unit:.3g} of coordinates up to "
                         f"{largest * unit:.3g}): a similarity aligning them has no determined scale or rotation")
    if spreads[1] <= COLLINEAR * spreads[0]:
        raise InputError(f"the {name} camera centres lie on one line (spread {spreads[1] * unit:.3g} off it against "
                         f"{spreads[0] * unit:.3g} along it): the rotation about that line of a similarity aligning "
                         "them is not determined")


def umeyama(source: np.ndarray, target: np.ndarray, names: tuple = ("source", "target")
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, Q, t) minimising sum |target - (s Q source + t)|^2 over similarities (module
    docstring). source, target: [n, 3] finite, each set neither coinciding nor on one line
    (InputError naming it by `names` otherwise). Returns (float, [3, 3], [3]), finite."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if not (np.isfinite(source).all() and np.isfinite(target).all()):
        raise InputError(f"the {names[0]} or {names[1]} camera centres are not finite")
    source_unit, target_unit = _power_of_two_scale(source), _power_of_two_scale(target)
    source, target = source / source_unit, target / target_unit  # exact; order-1 coordinates
    check_alignable(source, names[0], source_unit)
    check_alignable(target, names[1], target_unit)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)  # [3]
    xs, xt = source - mu_s, target - mu_t  # [n, 3]
    variance = (xs ** 2).sum() / len(source)
    covariance = xt.T @ xs / len(source)  # [3, 3]
    u, d, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / variance)
    translation = (mu_t - scale * rotation @ mu_s) * target_unit
    scale = scale * target_unit / source_unit
    if not (np.isfinite(scale) and scale > 0 and np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise InputError(f"the similarity aligning the {names[0]} camera centres to the {names[1]} ones is not "
                         f"finite and positive (scale {scale!r}): their scales differ by more than float64 holds")
    return scale, rotation, translation


def rotation_angle_degrees(rotation: np.ndarray) -> np.ndarray:
    """Angle of rotation matrices [..., 3, 3], degrees [...]: atan2(2 sin, 2 cos), precise
    near 0 and 180 degrees, where arccos of the trace is not."""
    trace = np.trace(rotation, axis1=-2, axis2=-1)
    axis = np.stack([rotation[..., 2, 1] - rotation[..., 1, 2], rotation[..., 0, 2] - rotation[..., 2, 0],
                     rotation[..., 1, 0] - rotation[..., 0, 1]], axis=-1)
    return np.degrees(np.arctan2(np.linalg.norm(axis, axis=-1), trace - 1))


def sim3_matrix(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The 4x4 matrix [[s Q, t], [0, 1]] of a similarity. -> [4, 4]."""
    out = np.eye(4)
    out[:3, :3] = scale * np.asarray(rotation, np.float64)
    out[:3, 3] = translation
    return out


def align_c2w(c2w: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Poses moved by the similarity: R' = Q R, c' = s Q c + t (the rotation stays
    orthonormal; the scale acts on positions only). c2w [n, 4, 4] -> [n, 4, 4]."""
    c2w = np.asarray(c2w, np.float64)
    out = c2w.copy()
    out[:, :3, :3] = rotation @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * c2w[:, :3, 3] @ np.asarray(rotation).T + translation
    return out


def to_method_world(c2w_gt: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Exact poses [n, 4, 4] carried into the method's world by the inverse of the
    alignment (s, Q, t) (test-time alignment, module docstring): R = Q^T R_gt,
    c = Q^T (c_gt - t) / s. -> [n, 4, 4]."""
    q = np.asarray(rotation, np.float64)
    return align_c2w(c2w_gt, 1.0 / scale, q.T, -(q.T @ np.asarray(translation, np.float64)) / scale)


def camera_spread(c2w: np.ndarray) -> float:
    """sqrt(mean_i |c_i - mean c|^2) of the centres of c2w [n, 4, 4]."""
    centres = np.asarray(c2w, np.float64)[:, :3, 3]
    return float(np.sqrt(((centres - centres.mean(axis=0)) ** 2).sum(axis=1).mean()))


def per_camera_errors(gt_c2w: np.ndarray, est_c2w: np.ndarray, align: bool = True) -> dict:
    """Per camera: rotation error (degrees) [n] and translation error [n] of est against gt,
    after the Umeyama alignment of the centres (align) or as given. Returns
    {"rotation_degrees", "translation", "alignment": (s, Q, t)}."""
    gt_c2w, est_c2w = np.asarray(gt_c2w, np.float64), np.asarray(est_c2w, np.float64)
    similarity = umeyama(est_c2w[:, :3, 3], gt_c2w[:, :3, 3], ("recovered", "exact")) if align \
        else (1.0, np.eye(3), np.zeros(3))
    aligned = align_c2w(est_c2w, *similarity)
    rotation = rotation_angle_degrees(np.swapaxes(gt_c2w[:, :3, :3], 1, 2) @ aligned[:, :3, :3])
    translation = np.linalg.norm(aligned[:, :3, 3] - gt_c2w[:, :3, 3], axis=1)
    return {"rotation_degrees": rotation, "translation": translation, "alignment": similarity, "aligned": aligned}


def ate_rmse(translation_errors: np.ndarray) -> float:
    """sqrt(mean e_i^2) of per-camera translation errors [n]."""
    return float(np.sqrt(np.mean(np.asarray(translation_errors, np.float64) ** 2)))


PAIR_BLOCK = 1 << 16  # camera pairs of the RPE held at once (~600 B each)


def relative_pose_squares(gt_c2w: np.ndarray, aligned_c2w: np.ndarray) -> tuple[int, float, float]:
    """RPE over every pair (i < j) of n cameras (module docstring): (pairs, sum of squared
    rotation errors in degrees^2, sum of squared translation errors). The pairs are taken
    PAIR_BLOCK / n rows i at a time, so memory does not grow with n^2 (5000 registered
    images: 12.5M pairs, ~7 GB at once). gt_c2w, aligned_c2w: [n, 4, 4]."""
    count = len(gt_c2w)
    gt_r, gt_c = gt_c2w[:, :3, :3], gt_c2w[:, :3, 3]
    est_r, est_c = aligned_c2w[:, :3, :3], aligned_c2w[:, :3, 3]
    pairs, rotation_squares, translation_squares = 0, 0.0, 0.0
    rows = max(1, PAIR_BLOCK // max(1, count))
    for start in range(0, count, rows):
        i, j = np.nonzero(np.arange(start, min(start + rows, count))[:, None] < np.arange(count)[None, :])
        i += start  # [p] and [p]: the pairs i < j of these rows
        gt_rel_r = np.transpose(gt_r[i], (0, 2, 1)) @ gt_r[j]
        est_rel_r = np.transpose(est_r[i], (0, 2, 1)) @ est_r[j]
        rotation = rotation_angle_degrees(np.transpose(gt_rel_r, (0, 2, 1)) @ est_rel_r)
        gt_rel_t = np.einsum("nji,nj->ni", gt_r[i], gt_c[j] - gt_c[i])
        est_rel_t = np.einsum("nji,nj->ni", est_r[i], est_c[j] - est_c[i])
        translation = np.linalg.norm(gt_rel_t - est_rel_t, axis=1)
        pairs += len(i)
        rotation_squares += float((rotation ** 2).sum())
        translation_squares += float((translation ** 2).sum())
    return pairs, rotation_squares, translation_squares


def pose_errors(gt_c2w: np.ndarray, est_c2w: np.ndarray) -> tuple[dict, tuple]:
    """Errors of recovered camera-to-world poses est_c2w [n, 4, 4] (any consistent axes)
    against gt_c2w [n, 4, 4] after a Sim(3) alignment of the centres: a summary dict
    (alignment, rotation and translation error stats, ATE, RPE) and (s, Q, t)."""
    gt_c2w = np.asarray(gt_c2w, np.float64)
    errors = per_camera_errors(gt_c2w, est_c2w)
    scale, rotation, translation = errors["alignment"]
    aligned = errors["aligned"]
    rotation_error, translation_error = errors["rotation_degrees"], errors["translation"]
    spread = camera_spread(gt_c2w)
    pairs, rotation_squares, translation_squares = relative_pose_squares(gt_c2w, aligned)

    def stats(values):
        if not len(values):
            return None
        return {"mean": float(values.mean()), "median": float(np.median(values)), "max": float(values.max())}

    return {
        "alignment": {"scale": scale, "rotation": rotation.tolist(), "translation": translation.tolist(),
                      "method": "Umeyama Sim(3) on camera centres (recovered -> exact)"},
        "rotation_error_degrees": stats(rotation_error),
        "translation_error": stats(translation_error),
        "translation_error_over_spread": stats(translation_error / spread) if spread > 0 else None,
        "camera_spread": spread,
        "ate_rmse": ate_rmse(translation_error),
        "rpe": {"pairs": pairs,
                "rotation_rmse_degrees": float(np.sqrt(rotation_squares / pairs)) if pairs else None,
                "translation_rmse": float(np.sqrt(translation_squares / pairs)) if pairs else None},
    }, (scale, rotation, translation)
