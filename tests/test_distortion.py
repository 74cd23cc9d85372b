"""Lens distortion (issue 35, item 4): the camera model maths against OpenCV's own
implementation (cv2.projectPoints / cv2.undistortPointsIter and cv2.fisheye.*), the fold
check, and the rays of a distorted camera.

Conventions (docs/conventions.md, "Lens distortion"): normalised coordinates in OpenCV axes
(x right, y down); pixel u = fx xd + cx. The cv2 calls get the same K, so no half-pixel
shift enters the comparison (OpenCV's own pixel-centre convention only moves cx, cy).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from nerfgauge.core.camera import Intrinsics, look_at, pixel_rays, project  # noqa: E402
from nerfgauge.core.distortion import Distortion, parse_distortion  # noqa: E402
from nerfgauge.core.errors import InputError, NumericalError  # noqa: E402

PIXEL_TOLERANCE = 1e-3  # px, the bound; the maths is exact to ~1e-10 px

OPENCV_CASES = ["opencv:-0.3,0.1,0.001,-0.002", "opencv:0.2,0.05,0,0,0.01", "opencv:-0.15,0.02,0.003,0.002,-0.004",
                "opencv:0,0,0,0"]
FISHEYE_CASES = ["fisheye:0.1,-0.05,0.01,-0.002", "fisheye:-0.02,0.003,0,0", "fisheye:0,0,0,0"]


def camera_matrix(intrinsics: Intrinsics) -> np.ndarray:
    return np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1.0]])


def pixel_grid(intrinsics: Intrinsics, steps: int = 17) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions over the whole image, edges included. [steps^2] each."""
    u, v = np.meshgrid(np.linspace(0, intrinsics.width, steps), np.linspace(0, intrinsics.height, steps))
    return u.ravel(), v.ravel()


def cv_undistort(distortion: Distortion, intrinsics: Intrinsics, u, v) -> np.ndarray:
    """OpenCV's inverse with a tight stopping rule (its default, 5 iterations, is coarse). [n, 2]."""
    points = np.stack([u, v], -1).reshape(-1, 1, 2)
    k = camera_matrix(intrinsics)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    if distortion.model == "opencv":
        out = cv2.undistortPointsIter(points, k, distortion.coefficients, None, None, criteria)
    else:
        out = cv2.fisheye.undistortPoints(points, k, distortion.coefficients, criteria=criteria)
    return out.reshape(-1, 2)


def cv_project(distortion: Distortion, intrinsics: Intrinsics, points_cv: np.ndarray) -> np.ndarray:
    """OpenCV's projection of camera-space points (OpenCV axes, z > 0). [n, 2] pixels."""
    k = camera_matrix(intrinsics)
    zero = np.zeros(3)
    if distortion.model == "opencv":
        out, _ = cv2.projectPoints(points_cv.reshape(-1, 1, 3), zero, zero, k, distortion.coefficients)
    else:
        out, _ = cv2.fisheye.projectPoints(points_cv.reshape(-1, 1, 3), zero, zero, k, distortion.coefficients)
    return out.reshape(-1, 2)


@pytest.mark.parametrize("spec", OPENCV_CASES + FISHEYE_CASES)
def test_projection_agrees_with_opencv(spec):
    distortion = Distortion.parse(spec)
    intrinsics = Intrinsics.from_fov(64, 48, 60.0)
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.5, 0.5, 400), rng.uniform(-0.4, 0.4, 400), rng.uniform(0.8, 3.0, 400)])
    expected = cv_project(distortion, intrinsics, points)
    # ours takes OpenGL camera axes: (X, -Y, -Z) of the OpenCV point
    u, v = distortion.project(points[:, 0], -points[:, 1], -points[:, 2], intrinsics)
    assert np.abs(np.column_stack([u, v]) - expected).max() < PIXEL_TOLERANCE


@pytest.mark.parametrize("spec", OPENCV_CASES + FISHEYE_CASES)
def test_undistortion_agrees_with_opencv_and_inverts_its_projection(spec):
    distortion = Distortion.parse(spec)
    intrinsics = Intrinsics.from_fov(64, 48, 60.0)
    distortion.check_image(intrinsics)
    u, v = pixel_grid(intrinsics)
    x, y = distortion.undistort((u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy)
    theirs = cv_undistort(distortion, intrinsics, u, v)
    # compared in pixels of the undistorted (pinhole) image
    assert np.abs(intrinsics.fx * (np.column_stack([x, y]) - theirs)).max() < PIXEL_TOLERANCE
    # and OpenCV's forward model sends our undistorted rays back onto the pixels
    back = cv_project(distortion, intrinsics, np.column_stack([x, y, np.ones_like(x)]))
    assert np.abs(back - np.column_stack([u, v])).max() < PIXEL_TOLERANCE


@pytest.mark.parametrize("spec", ["opencv:-0.25,0.05,0.002,-0.001,0.01", "fisheye:0.05,-0.02,0.004,0"])
def test_pixel_rays_of_a_distorted_camera_project_onto_their_pixel_centres_with_opencv(spec):
    """The world rays pixel_rays gives a distorted camera (OpenGL c2w) land, through
    cv2.projectPoints with the COLMAP/OpenCV world-to-camera pose, on the pixel centres."""
    distortion = Distortion.parse(spec)
    intrinsics = Intrinsics.from_fov(40, 30, 70.0)
    c2w = look_at((2.0, -3.0, 1.5), (0.1, 0.2, 0.0))
    origins, directions = pixel_rays(c2w, intrinsics, distortion)
    points = (origins + 2.5 * directions).reshape(-1, 3)
    c2w_cv = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
    rotation = c2w_cv[:3, :3].T
    translation = -rotation @ c2w_cv[:3, 3]
    rvec, _ = cv2.Rodrigues(rotation)
    k = camera_matrix(intrinsics)
    if distortion.model == "opencv":
        pixels, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, translation, k, distortion.coefficients)
    else:
        pixels, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), rvec, translation, k, distortion.coefficients)
    cols, rows = np.meshgrid(np.arange(intrinsics.width) + 0.5, np.arange(intrinsics.height) + 0.5)
    assert np.abs(pixels.reshape(-1, 2) - np.column_stack([cols.ravel(), rows.ravel()])).max() < PIXEL_TOLERANCE
    # project (ours) agrees, and the pinhole rays differ by far more than the tolerance
    u, v, _ = project(points, c2w, intrinsics, distortion)
    assert np.abs(np.column_stack([u, v]) - pixels.reshape(-1, 2)).max() < PIXEL_TOLERANCE
    _, pinhole = pixel_rays(c2w, intrinsics)
    assert np.degrees(np.arccos(np.clip((pinhole * directions).sum(-1), -1, 1))).max() > 0.5


def test_zero_opencv_distortion_is_the_pinhole_bit_for_bit():
    intrinsics = Intrinsics.from_fov(20, 12, 50.0)
    c2w = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert Distortion.parse("opencv:0,0,0,0").is_identity
    for a, b in zip(pixel_rays(c2w, intrinsics, Distortion.parse("opencv:0,0,0,0")), pixel_rays(c2w, intrinsics)):
        assert np.array_equal(a, b)


def monotone_over_image(distortion: Distortion, intrinsics: Intrinsics) -> bool:
    """An independent look at the fold: sample the radial map densely from 0 until it first
    reaches the image's largest distorted radius; monotone if it got there without a step
    down (and, fisheye, before 90 degrees)."""
    reach = max(math.hypot(a / intrinsics.fx, b / intrinsics.fy)
                for a in (-intrinsics.cx, intrinsics.width - intrinsics.cx)
                for b in (-intrinsics.cy, intrinsics.height - intrinsics.cy))
    top = 20.0 if distortion.model == "opencv" else math.pi / 2 - 1e-3
    r = np.linspace(0, top, 400_001)
    if distortion.model == "opencv":
        values = r * (1 + distortion.k1 * r**2 + distortion.k2 * r**4 + distortion.k3 * r**6)
    else:
        values = r * (1 + distortion.k1 * r**2 + distortion.k2 * r**4 + distortion.k3 * r**6 + distortion.k4 * r**8)
    past = np.flatnonzero(values >= reach)
    end = past[0] if len(past) else len(r)
    return bool(len(past)) and bool(np.all(np.diff(values[: end + 1]) > 0))


@pytest.mark.parametrize("k1", [-0.6, -0.5, -0.45, -0.4, -0.3, 0.2])
@pytest.mark.parametrize("fov", [40.0, 60.0, 90.0])
def test_fold_check_agrees_with_a_dense_scan_of_the_radial_map(k1, fov):
    """k1 < 0 folds at r = sqrt(-1 / (3 k1)), distorted radius (2/3) r: a wide image
    reaches it, a narrow one does not."""
    intrinsics = Intrinsics.from_fov(64, 48, fov)
    distortion = Distortion("opencv", k1=k1)
    if monotone_over_image(distortion, intrinsics):
        distortion.check_image(intrinsics)
    else:
        with pytest.raises(InputError, match="folds"):
            distortion.check_image(intrinsics)


@pytest.mark.parametrize("spec, fov", [("fisheye:-0.3,0,0,0", 100.0), ("fisheye:0,0,0,0", 170.0),
                                       ("opencv:0.1,-0.4,0,0", 90.0), ("opencv:0,0,0,0,-0.5", 80.0)])
def test_folding_or_beyond_90_degree_distortions_are_refused(spec, fov):
    distortion = Distortion.parse(spec)
    intrinsics = Intrinsics.from_fov(32, 32, fov)
    assert not monotone_over_image(distortion, intrinsics)
    with pytest.raises(InputError) as error:
        distortion.check_image(intrinsics)
    assert "\n" not in str(error.value)


def test_newton_reports_points_past_the_fold_instead_of_a_wrong_answer():
    distortion = Distortion("opencv", k1=-0.5)  # the map peaks at rd = 0.544
    with pytest.raises(NumericalError):
        distortion.undistort(np.array([0.7]), np.array([0.0]))


@pytest.mark.parametrize("text", ["opencv:1,2,3", "opencv:1,2,3,4,5,6", "fisheye:1,2,3", "kb:1,2,3,4",
                                  "opencv:a,0,0,0", "opencv:nan,0,0,0", "fisheye:inf,0,0,0", "opencv"])
def test_bad_distortion_text_is_one_line(text):
    with pytest.raises(InputError) as error:
        parse_distortion(text)
    assert "\n" not in str(error.value)


def test_text_and_transforms_keys_round_trip():
    for spec in OPENCV_CASES[:3] + FISHEYE_CASES:
        distortion = Distortion.parse(spec)
        assert Distortion.parse(distortion.to_text()) == distortion
        assert Distortion.from_json(distortion.to_json(), "here") == (None if distortion.is_identity else distortion)
    assert parse_distortion("none") is None
