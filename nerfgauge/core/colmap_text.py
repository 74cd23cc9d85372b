"""A small reader of COLMAP's text model (cameras.txt, images.txt, points3D.txt).

Only what scoring renders against a COLMAP folder needs: per image its name, camera id and
pose, per camera its model, size and pinhole intrinsics, and the 3D points. The format
(COLMAP's docs, "Output format"):

    cameras.txt   CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    images.txt    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME   (then one line of 2D points,
                                                                  possibly empty)
    points3D.txt  POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)

'#' starts a comment line. The pose is world-to-camera: x_cam = R(q) x_world + t, with
OpenCV camera axes (+X right, +Y down, looking along +Z). Pixel (0, 0)'s centre is at
(0.5, 0.5), as in our own convention (docs/conventions.md), so cx, cy carry over as they are.

Camera models read: PINHOLE (fx, fy, cx, cy) and SIMPLE_PINHOLE (f, cx, cy); SIMPLE_RADIAL,
RADIAL, OPENCV and FULL_OPENCV only when every distortion parameter is 0 (a distorted model
needs undistorted images: `colmap image_undistorter`). Anything else: InputError.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nerfgauge.core.colmap import camera_to_world
from nerfgauge.core.errors import InputError

# model: (number of parameters, index of fx, fy, cx, cy in them (fy None: = fx), distortion slice)
MODELS = {
    "SIMPLE_PINHOLE": (3, (0, None, 1, 2), slice(3, 3)),
    "PINHOLE": (4, (0, 1, 2, 3), slice(4, 4)),
    "SIMPLE_RADIAL": (4, (0, None, 1, 2), slice(3, 4)),
    "RADIAL": (5, (0, None, 1, 2), slice(3, 5)),
    "OPENCV": (8, (0, 1, 2, 3), slice(4, 8)),
    "FULL_OPENCV": (12, (0, 1, 2, 3), slice(4, 12)),
}


@dataclass(frozen=True)
class Camera:
    """One cameras.txt row as a pinhole: size in pixels and fx, fy, cx, cy."""

    camera_id: int
    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class Image:
    """One images.txt entry: world-to-camera quaternion (w, x, y, z) and translation."""

    image_id: int
    qvec: tuple
    tvec: tuple
    camera_id: int
    name: str

    def c2w_opengl(self) -> np.ndarray:
        """[4, 4] camera-to-world in the OpenGL/NeRF convention (+Y up, looking along -Z)."""
        return camera_to_world(self.qvec, self.tvec)


def _lines(text: str):
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.lstrip().startswith("#"):
            yield number, line


def _numbers(fields, kind, where: str, number: int) -> list:
    try:
        values = [kind(field) for field in fields]
    except ValueError:
        raise InputError(f"{where} line {number}: expected numbers, got {' '.join(fields)!r}") from None
    if kind is float and not np.isfinite(values).all():
        raise InputError(f"{where} line {number}: NaN or inf in {' '.join(fields)!r}")
    return values


def read_cameras(text: str, where: str) -> dict:
    """cameras.txt -> {camera_id: Camera}."""
    cameras = {}
    for number, line in _lines(text):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 4:
            raise InputError(f"{where} line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {line!r}")
        camera_id, width, height = _numbers([fields[0], fields[2], fields[3]], int, where, number)
        model = fields[1]
        if model not in MODELS:
            raise InputError(f"{where} line {number}: camera model {model} is not read; undistort to PINHOLE "
                             f"(colmap image_undistorter) or use one of {', '.join(MODELS)}")
        count, (fx, fy, cx, cy), distortion = MODELS[model]
        params = _numbers(fields[4:], float, where, number)
        if len(params) != count:
            raise InputError(f"{where} line {number}: {model} has {count} parameters, got {len(params)}")
        if any(params[distortion]):
            raise InputError(f"{where} line {number}: camera {camera_id} ({model}) has distortion "
                             f"{params[distortion]}; undistort the images first (colmap image_undistorter)")
        if width < 1 or height < 1 or params[fx] <= 0 or (fy is not None and params[fy] <= 0):
            raise InputError(f"{where} line {number}: camera {camera_id} needs a positive size and focal length")
        cameras[camera_id] = Camera(camera_id, model, width, height, params[fx],
                                    params[fx if fy is None else fy], params[cx], params[cy])
    return cameras


def read_images(text: str, where: str) -> list:
    """images.txt -> [Image] in file order (each header line is followed by a 2D-point line)."""
    images, expect_points = [], False
    for number, line in _lines(text):
        if expect_points:  # the 2D points of the image before (may be empty)
            expect_points = False
            continue
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 10:
            raise InputError(f"{where} line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                             f"got {line!r}")
        image_id, camera_id = _numbers([fields[0], fields[8]], int, where, number)
        q = _numbers(fields[1:5], float, where, number)
        t = _numbers(fields[5:8], float, where, number)
        if np.linalg.norm(q) < 1e-8:
            raise InputError(f"{where} line {number}: image {image_id} has a zero quaternion")
        images.append(Image(image_id, tuple(q), tuple(t), camera_id, " ".join(fields[9:])))
        expect_points = True
    return images


def read_points(text: str, where: str) -> np.ndarray:
    """points3D.txt -> [n, 3] float64 positions (colours, errors and tracks are not kept)."""
    points = []
    for number, line in _lines(text):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 8:
            raise InputError(f"{where} line {number}: expected POINT3D_ID X Y Z R G B ERROR TRACK[], got {line!r}")
        points.append(_numbers(fields[1:4], float, where, number))
    return np.asarray(points, np.float64).reshape(-1, 3)
