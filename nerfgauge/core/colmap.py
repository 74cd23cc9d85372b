"""COLMAP sparse models: our cameras in COLMAP's conventions, written (and read) with numpy.

The format is COLMAP's documented one (https://colmap.github.io/format.html), binary
(`cameras.bin`, `images.bin`, `points3D.bin`, little-endian) and text (`*.txt`); this module
needs no pycolmap, so generating a dataset does not either. pycolmap is the independent
reader in the tests (tests/test_colmap.py).

Conventions (docs/conventions.md, "COLMAP"):
- an image's pose is world-to-camera: x_cam = R x_world + t, R as the unit quaternion
  (qw, qx, qy, qz) with qw >= 0, camera axes OpenCV's (+X right, +Y down, looks along +Z):
  c2w_cv = c2w_gl @ diag(1, -1, -1, 1), R = c2w_cv[:3, :3]^T, t = -R c2w_cv[:3, 3];
- pixel (row i, col j) has its centre at (j + 0.5, i + 0.5), COLMAP's convention and ours,
  so the intrinsics carry over unchanged: PINHOLE (fx, fy, cx, cy) states ours exactly;
- ids start at 1; a point3D's track and an image's points2D may be empty (points that are
  not feature observations: `surface` and `random` initial points).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfgauge.core import owned
from nerfgauge.core.camera import Intrinsics
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_bytes_atomic

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# COLMAP's camera models: id -> (name, number of parameters).
CAMERA_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}
MODEL_IDS = {name: model_id for model_id, (name, _) in CAMERA_MODELS.items()}
FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class Camera:
    camera_id: int
    model: str
    width: int
    height: int
    params: tuple


@dataclass(frozen=True)
class Image:
    """qvec (w, x, y, z) and tvec: world-to-camera, OpenCV axes. xys [n, 2] and
    point3D_ids [n] (-1: no point) are the image's 2D points."""

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


@dataclass(frozen=True)
class Points:
    """xyz [n, 3] float64, rgb [n, 3] uint8, error [n] float64, ids [n] (from 1), tracks:
    per point an [k, 2] int array of (image_id, point2D_idx) (None: all empty)."""

    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    ids: np.ndarray
    tracks: list | None = None

    @classmethod
    def make(cls, xyz, rgb, error=None, tracks=None) -> "Points":
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        n = len(xyz)
        error = np.zeros(n) if error is None else np.asarray(error, np.float64).reshape(n)
        return cls(xyz, np.asarray(rgb, np.uint8).reshape(n, 3), error, np.arange(1, n + 1, dtype=np.int64), tracks)


def pinhole_camera(intrinsics: Intrinsics, camera_id: int = 1) -> Camera:
    """Our intrinsics as COLMAP's PINHOLE model (exact: same pixel-centre convention)."""
    values = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    if not all(math.isfinite(v) for v in values) or intrinsics.fx <= 0 or intrinsics.fy <= 0:
        raise InputError(f"COLMAP's PINHOLE model cannot express intrinsics {values}")
    return Camera(camera_id, "PINHOLE", int(intrinsics.width), int(intrinsics.height), tuple(float(v) for v in values))


def camera_model(intrinsics: Intrinsics, distortion=None, camera_id: int = 1) -> Camera:
    """Our intrinsics and lens distortion (a core.distortion.Distortion, None: pinhole) as
    the COLMAP model that states them exactly: PINHOLE; OPENCV (fx fy cx cy k1 k2 p1 p2);
    FULL_OPENCV when k3 != 0 (OPENCV has no k3; FULL_OPENCV's radial factor is
    (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 + k6 r6), here with k4 = k5 = k6 = 0);
    OPENCV_FISHEYE (fx fy cx cy k1 k2 k3 k4) for the fisheye model."""
    if distortion is None or distortion.is_identity:
        return pinhole_camera(intrinsics, camera_id)
    base = pinhole_camera(intrinsics, camera_id)
    d = distortion
    if d.model == "fisheye":
        model, extra = "OPENCV_FISHEYE", (d.k1, d.k2, d.k3, d.k4)
    elif d.k3 == 0:
        model, extra = "OPENCV", (d.k1, d.k2, d.p1, d.p2)
    else:
        model, extra = "FULL_OPENCV", (d.k1, d.k2, d.p1, d.p2, d.k3, 0.0, 0.0, 0.0)
    return Camera(camera_id, model, base.width, base.height, base.params + tuple(float(v) for v in extra))


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix [3, 3] (Shepperd's method:
    the largest of the four diagonal combinations divides, so no branch loses precision)."""
    m = np.asarray(rotation, np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = math.sqrt(1.0 + trace) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def world_to_camera(c2w_gl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(qvec, tvec) of COLMAP's world-to-camera pose for our OpenGL camera-to-world [4, 4]."""
    c2w_cv = np.asarray(c2w_gl, np.float64) @ GL_TO_CV
    rotation = c2w_cv[:3, :3].T
    return rotation_to_quaternion(rotation), -rotation @ c2w_cv[:3, 3]


def camera_to_world(qvec, tvec) -> np.ndarray:
    """Our OpenGL camera-to-world [4, 4] from COLMAP's (qvec, tvec) (inverse of world_to_camera)."""
    rotation = quaternion_to_rotation(qvec)
    c2w = np.eye(4)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = -rotation.T @ np.asarray(tvec, np.float64)
    return c2w @ GL_TO_CV


def project(points: np.ndarray, c2w_gl: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [n, 2] (x right, y down, pixel centres at +0.5) and depth along
    the optical axis [n] of world points [n, 3] seen by our camera: the projection COLMAP's
    PINHOLE model makes of the same pose (x = fx X/Z + cx in OpenCV camera axes)."""
    c2w = np.asarray(c2w_gl, np.float64)
    local = (np.asarray(points, np.float64) - c2w[:3, 3]) @ c2w[:3, :3]  # OpenGL camera axes
    depth = -local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = intrinsics.fx * local[:, 0] / depth + intrinsics.cx
        y = -intrinsics.fy * local[:, 1] / depth + intrinsics.cy
    return np.stack([x, y], axis=1), depth


def model_images(c2w: np.ndarray, names, camera_id: int = 1) -> list[Image]:
    """One Image per pose [n, 4, 4] (ids 1..n in order) with the given file names."""
    images = []
    for index, (pose, name) in enumerate(zip(c2w, names), start=1):
        qvec, tvec = world_to_camera(pose)
        images.append(Image(index, qvec, tvec, camera_id, str(name)))
    return images


# --- binary ----------------------------------------------------------------------------


def cameras_bin(cameras) -> bytes:
    parts = [struct.pack("<Q", len(cameras))]
    for camera in cameras:
        model_id = MODEL_IDS[camera.model]
        if len(camera.params) != CAMERA_MODELS[model_id][1]:
            raise ValueError(f"{camera.model} takes {CAMERA_MODELS[model_id][1]} parameters, got {camera.params}")
        parts.append(struct.pack("<iiQQ", camera.camera_id, model_id, camera.width, camera.height))
        parts.append(np.asarray(camera.params, "<f8").tobytes())
    return b"".join(parts)


def images_bin(images) -> bytes:
    parts = [struct.pack("<Q", len(images))]
    for image in images:
        name = image.name.encode("utf-8")
        if b"\0" in name:
            raise ValueError(f"image name {image.name!r} holds a NUL byte")
        parts.append(struct.pack("<I", image.image_id))
        parts.append(np.concatenate([image.qvec, image.tvec]).astype("<f8").tobytes())
        parts.append(struct.pack("<I", image.camera_id) + name + b"\0")
        points = np.empty(len(image.xys), dtype=[("xy", "<f8", (2,)), ("id", "<i8")])
        points["xy"], points["id"] = image.xys, image.point3D_ids
        parts.append(struct.pack("<Q", len(points)) + points.tobytes())
    return b"".join(parts)


def points3D_bin(points: Points) -> bytes:
    n = len(points.xyz)
    if points.tracks is None:  # one structured array: fast for a million points
        rows = np.empty(n, dtype=[("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"),
                                  ("track", "<u8")])
        rows["id"], rows["xyz"], rows["rgb"], rows["error"], rows["track"] = points.ids, points.xyz, points.rgb, \
            points.error, 0
        return struct.pack("<Q", n) + rows.tobytes()
    parts = [struct.pack("<Q", n)]
    head = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"), ("track", "<u8")])
    for k in range(n):
        track = np.asarray(points.tracks[k], "<i4").reshape(-1, 2)
        row = np.array([(points.ids[k], points.xyz[k], points.rgb[k], points.error[k], len(track))], dtype=head)
        parts.append(row.tobytes() + track.tobytes())
    return b"".join(parts)


# --- text ------------------------------------------------------------------------------


def _number(value: float) -> str:
    """Shortest text that reads back as the same double (Python's repr)."""
    return repr(float(value))


def cameras_txt(cameras) -> bytes:
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras)}"]
    for camera in cameras:
        lines.append(" ".join([str(camera.camera_id), camera.model, str(camera.width), str(camera.height)]
                              + [_number(p) for p in camera.params]))
    return ("\n".join(lines) + "\n").encode()


def images_txt(images) -> bytes:
    observations = sum(len(image.xys) for image in images)
    mean = observations / len(images) if images else 0.0
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(images)}, mean observations per image: {mean:g}"]
    for image in images:
        if any(c.isspace() for c in image.name):
            raise ValueError(f"image name {image.name!r} holds white space, which COLMAP's text format cannot hold")
        lines.append(" ".join([str(image.image_id)] + [_number(v) for v in (*image.qvec, *image.tvec)]
                              + [str(image.camera_id), image.name]))
        lines.append(" ".join(f"{_number(x)} {_number(y)} {int(i)}" for (x, y), i in zip(image.xys, image.point3D_ids)))
    return ("\n".join(lines) + "\n").encode()


def points3D_txt(points: Points) -> bytes:
    n = len(points.xyz)
    lengths = [0] * n if points.tracks is None else [len(t) for t in points.tracks]
    mean = sum(lengths) / n if n else 0.0
    head = ["# 3D point list with one line of data per point:",
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
            f"# Number of points: {n}, mean track length: {mean:g}"]
    ids, xyz, rgb, error = points.ids.tolist(), points.xyz.tolist(), points.rgb.tolist(), points.error.tolist()
    if points.tracks is None:
        lines = [f"{i} {x!r} {y!r} {z!r} {r} {g} {b} {e!r}" for i, (x, y, z), (r, g, b), e in zip(ids, xyz, rgb, error)]
    else:
        lines = [f"{i} {x!r} {y!r} {z!r} {r} {g} {b} {e!r}" + "".join(f" {a} {c}" for a, c in np.asarray(t).reshape(-1, 2).tolist())
                 for i, (x, y, z), (r, g, b), e, t in zip(ids, xyz, rgb, error, points.tracks)]
    return ("\n".join(head + lines) + "\n").encode()


def model_files(cameras, images, points: Points) -> dict:
    """{file name: bytes} of the binary and the text model."""
    return {"cameras.bin": cameras_bin(cameras), "images.bin": images_bin(images),
            "points3D.bin": points3D_bin(points), "cameras.txt": cameras_txt(cameras),
            "images.txt": images_txt(images), "points3D.txt": points3D_txt(points)}


def write_model(folder, cameras, images, points: Points) -> list[Path]:
    """Write the six files into `folder` (atomically each). Returns their paths."""
    folder = owned.make_folder(folder)
    written = []
    for name, data in model_files(cameras, images, points).items():
        write_bytes_atomic(folder / name, data)
        written.append(folder / name)
    return written


# --- reading the binary model back (for nerfgauge's own checks; pycolmap is the reference) ---


def read_cameras_bin(data: bytes) -> list[Camera]:
    (count,), at, cameras = struct.unpack_from("<Q", data), 8, []
    for _ in range(count):
        camera_id, model_id, width, height = struct.unpack_from("<iiQQ", data, at)
        at += 24
        name, n = CAMERA_MODELS[model_id]
        params = struct.unpack_from(f"<{n}d", data, at)
        at += 8 * n
        cameras.append(Camera(camera_id, name, width, height, tuple(params)))
    return cameras


def read_images_bin(data: bytes) -> list[Image]:
    (count,), at, images = struct.unpack_from("<Q", data), 8, []
    for _ in range(count):
        (image_id,) = struct.unpack_from("<I", data, at)
        pose = np.frombuffer(data, "<f8", 7, at + 4)
        (camera_id,) = struct.unpack_from("<I", data, at + 60)
        end = data.index(b"\0", at + 64)
        name = data[at + 64:end].decode("utf-8")
        (n,) = struct.unpack_from("<Q", data, end + 1)
        rows = np.frombuffer(data, [("xy", "<f8", (2,)), ("id", "<i8")], n, end + 9)
        at = end + 9 + 24 * n
        images.append(Image(image_id, pose[:4].copy(), pose[4:].copy(), camera_id, name, rows["xy"].copy(),
                            rows["id"].copy()))
    return images
