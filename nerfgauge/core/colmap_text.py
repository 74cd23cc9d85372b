"""A strict reader of COLMAP's text model (cameras.txt, images.txt, points3D.txt).

What scoring renders against a COLMAP folder needs: per image its name, camera id and pose,
per camera its model, size and parameters as a transforms document states them, and the 3D
points. The format (COLMAP's docs, "Output format"; its reader, reconstruction_io_text.cc):

    cameras.txt   CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    images.txt    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME   then, on the next line,
                  POINTS2D[] as (X, Y, POINT3D_ID) triples, possibly empty (-1: no 3D point)
    points3D.txt  POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX) pairs

Blank lines and lines starting with '#' are skipped where a record may start, as COLMAP
skips them; the line after an image line is always its POINTS2D line. The pose is
world-to-camera: x_cam = R(q) x_world + t, with OpenCV camera axes (+X right, +Y down,
looking along +Z). Pixel (0, 0)'s centre is at (0.5, 0.5), as in our own convention
(docs/conventions.md), so cx, cy carry over as they are.

The structure is checked, so that a damaged model is refused naming its line instead of
being read as another model. COLMAP's own reader (and pycolmap) takes an images.txt without
its empty POINTS2D lines as half the images, each second image line read as points, and
drops a last image line without its POINTS2D line; here a POINTS2D line must be X Y
POINT3D_ID triples of numbers (an image line or a comment in its place is refused), and
every image line needs one. Refused as COLMAP refuses them: a camera, image or 3D point id
given twice, an image naming a camera cameras.txt lacks, a track naming an image images.txt
lacks or a 2D point index past that image's points. Refused beyond COLMAP: a POINTS2D entry
naming a 3D point points3D.txt lacks, a track of odd length, an image name given twice.
Image ids need not be in order (COLMAP writes them in any order).

Camera models, mapped to the transforms keys nerfgauge.core.validate.camera checks (the
same checks our own transforms get): SIMPLE_PINHOLE, PINHOLE; SIMPLE_RADIAL, RADIAL, OPENCV
and FULL_OPENCV (without its rational k4..k6) as OPENCV; OPENCV_FISHEYE. COLMAP's OPENCV
and OPENCV_FISHEYE are OpenCV's models, which nerfgauge.core.distortion implements.
Anything else: InputError naming the model.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from nerfgauge.core.colmap import camera_to_world
from nerfgauge.core.errors import InputError

# The most bytes of one text file of a model: a real reconstruction's images.txt (the 2D
# points of hundreds of images) or points3D.txt (a million points) is tens of MB.
MAX_TEXT_BYTES = 256 << 20
# The longest line read: a POINTS2D line of an image with 500,000 features (COLMAP extracts
# at most 8192 by default) at about 30 bytes each. A line is split into its numbers, so a
# longer one would hold the file's size many times over as Python objects.
MAX_LINE_BYTES = 16 << 20

# model: (parameter names in COLMAP's order, transforms camera_model)
MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), "PINHOLE"),
    "PINHOLE": (("fx", "fy", "cx", "cy"), "PINHOLE"),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k1"), "OPENCV"),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), "OPENCV"),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), "OPENCV"),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), "OPENCV"),
    "OPENCV_FISHEYE": (("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"), "OPENCV_FISHEYE"),
}
RATIONAL = ("k4", "k5", "k6")  # FULL_OPENCV's denominator: not in nerfgauge.core.distortion


@dataclass(frozen=True)
class Camera:
    """One cameras.txt row: its id, model, size, and the camera as transforms keys (w, h,
    fl_x, fl_y, cx, cy, camera_model, k1.. p2) for nerfgauge.core.validate.camera."""

    camera_id: int
    model: str
    line: int
    transforms: dict


@dataclass(frozen=True)
class Image:
    """One images.txt entry: world-to-camera quaternion (w, x, y, z) and translation, the
    number of its 2D points and the 3D point ids they name (-1: none)."""

    image_id: int
    qvec: tuple
    tvec: tuple
    camera_id: int
    name: str
    line: int
    points2d: int = 0
    point3d_ids: tuple = ()

    def c2w_opengl(self) -> np.ndarray:
        """[4, 4] camera-to-world in the OpenGL/NeRF convention (+Y up, looking along -Z)."""
        return camera_to_world(self.qvec, self.tvec)


@dataclass(frozen=True)
class Model:
    cameras: dict  # {camera_id: Camera}
    images: list  # [Image] in file order
    points: np.ndarray | None  # [n, 3] float64, None without points3D.txt
    colours: np.ndarray | None = None  # [n, 3] the points' R G B as written (0-255), None without points3D.txt


def _lines(data: bytes, where: str):
    """(line number, text) of every line, one at a time (no list of a large file's lines);
    a line longer than MAX_LINE_BYTES is refused."""
    for number, raw in enumerate(io.BytesIO(data), start=1):
        if len(raw) > MAX_LINE_BYTES:
            raise InputError(f"{where} line {number}: {len(raw)} bytes long; lines of at most "
                             f"{MAX_LINE_BYTES >> 20} MiB are read")
        yield number, raw.decode("utf-8", "replace").rstrip("\r\n")


def _records(lines):
    """The lines where a record may start: blank and '#' lines skipped, as COLMAP does."""
    for number, line in lines:
        if line.strip() and not line.lstrip().startswith("#"):
            yield number, line


def _shown(line: str) -> str:
    return repr(line if len(line) <= 80 else line[:77] + "...")


def _numbers(fields, kind, where: str, number: int) -> list:
    try:
        values = [kind(field) for field in fields]
    except ValueError:
        raise InputError(f"{where} line {number}: expected numbers, got {_shown(' '.join(fields))}") from None
    if kind is float and not np.isfinite(values).all():
        raise InputError(f"{where} line {number}: NaN or inf in {_shown(' '.join(fields))}")
    return values


def _column(fields, dtype, where: str, number: int, what: str) -> np.ndarray:
    try:
        values = np.array(fields, dtype=dtype)
    except (ValueError, OverflowError):
        raise InputError(f"{where} line {number}: {what} must be numbers") from None
    if dtype is float and not np.isfinite(values).all():
        raise InputError(f"{where} line {number}: NaN or inf among the {what}")
    return values


def read_cameras(data: bytes, where: str) -> dict:
    """cameras.txt -> {camera_id: Camera}; a camera id given twice is refused."""
    cameras = {}
    for number, line in _records(_lines(data, where)):
        fields = line.split()
        if len(fields) < 4:
            raise InputError(f"{where} line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {_shown(line)}")
        camera_id, width, height = _numbers([fields[0], fields[2], fields[3]], int, where, number)
        model = fields[1]
        if model not in MODELS:
            raise InputError(f"{where} line {number}: camera model {model} is not read; undistort to PINHOLE "
                             f"(colmap image_undistorter) or use one of {', '.join(MODELS)}")
        names, camera_model = MODELS[model]
        params = _numbers(fields[4:], float, where, number)
        if len(params) != len(names):
            raise InputError(f"{where} line {number}: {model} has {len(names)} parameters, got {len(params)}")
        if camera_id in cameras:
            raise InputError(f"{where} line {number}: camera {camera_id} is given twice (first on line "
                             f"{cameras[camera_id].line})")
        values = dict(zip(names, params))
        rational = [name for name in RATIONAL if values.get(name)]
        if model == "FULL_OPENCV" and rational:
            raise InputError(f"{where} line {number}: camera {camera_id} (FULL_OPENCV) has rational distortion "
                             f"{rational[0]}={values[rational[0]]}, which is not read; undistort the images first "
                             "(colmap image_undistorter)")
        focal = {"fl_x": values.get("fx", values.get("f")), "fl_y": values.get("fy", values.get("f"))}
        transforms = {"w": width, "h": height, **focal, "cx": values["cx"], "cy": values["cy"],
                      "camera_model": camera_model,
                      **{name: values[name] for name in ("k1", "k2", "k3", "k4", "p1", "p2") if name in values
                         and not (model == "FULL_OPENCV" and name == "k4")}}
        cameras[camera_id] = Camera(camera_id, model, number, transforms)
    return cameras


def read_images(data: bytes, where: str) -> list:
    """images.txt -> [Image] in file order, each image line followed by its POINTS2D line
    (module docstring). Image ids and names given twice are refused."""
    images, ids, names = [], {}, {}
    lines = _lines(data, where)
    for number, line in _records(lines):
        fields = line.split()
        if len(fields) < 10:
            raise InputError(f"{where} line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                             f"got {_shown(line)}")
        image_id, camera_id = _numbers([fields[0], fields[8]], int, where, number)
        q = _numbers(fields[1:5], float, where, number)
        t = _numbers(fields[5:8], float, where, number)
        if np.linalg.norm(q) < 1e-8:
            raise InputError(f"{where} line {number}: image {image_id} has a zero quaternion")
        name = " ".join(fields[9:])
        if image_id in ids:
            raise InputError(f"{where} line {number}: image id {image_id} is given twice (first on line {ids[image_id]})")
        if name in names:
            raise InputError(f"{where} line {number}: image {name} is listed twice (first on line {names[name]})")
        ids[image_id], names[name] = number, number
        point_line = next(lines, None)
        if point_line is None:
            raise InputError(f"{where} line {number}: image {image_id} has no POINTS2D line (the file ends); each "
                             "image takes two lines, the second its 2D points, possibly empty")
        point_number, points_text = point_line
        count, point3d_ids = _points2d(points_text, image_id, where, point_number)
        images.append(Image(image_id, tuple(q), tuple(t), camera_id, name, number, count, point3d_ids))
    return images


def _points2d(text: str, image_id: int, where: str, number: int) -> tuple:
    """(number of 2D points, the distinct 3D point ids they name) of a POINTS2D line."""
    fields = text.split()
    expected = f"the POINTS2D line of image {image_id} (X Y POINT3D_ID triples, possibly empty)"
    if text.lstrip().startswith("#"):
        raise InputError(f"{where} line {number}: expected {expected}, got a comment {_shown(text)}")
    if len(fields) % 3:
        raise InputError(f"{where} line {number}: expected {expected}, got {len(fields)} fields {_shown(text)} "
                         "(an image line here means the POINTS2D line before it is missing)")
    if not fields:
        return 0, ()
    _column(fields[0::3] + fields[1::3], float, where, number, f"2D point coordinates of image {image_id}")
    ids = _column(fields[2::3], np.int64, where, number, f"3D point ids of image {image_id}")
    if (ids < -1).any():
        raise InputError(f"{where} line {number}: image {image_id} names 3D point {int(ids[ids < -1][0])}; ids are "
                         ">= 0, or -1 for none")
    return len(ids), tuple(np.unique(ids[ids >= 0]).tolist())


def read_points(data: bytes, where: str, images: list) -> tuple:
    """points3D.txt -> ([n, 3] float64 positions, [n, 3] float64 colours R G B as written,
    {point ids}); each track's (IMAGE_ID, POINT2D_IDX) must name an image of `images` and one
    of its 2D points."""
    points, colours, ids = [], [], {}
    counts = {image.image_id: image.points2d for image in images}
    for number, line in _records(_lines(data, where)):
        fields = line.split()
        if len(fields) < 8:
            raise InputError(f"{where} line {number}: expected POINT3D_ID X Y Z R G B ERROR TRACK[], got {_shown(line)}")
        (point_id,) = _numbers(fields[:1], int, where, number)
        if point_id in ids:
            raise InputError(f"{where} line {number}: 3D point {point_id} is given twice (first on line {ids[point_id]})")
        ids[point_id] = number
        points.append(_numbers(fields[1:4], float, where, number))
        colours.append(_numbers(fields[4:8], float, where, number)[:3])  # colour and error: numbers
        track = fields[8:]
        if len(track) % 2:
            raise InputError(f"{where} line {number}: 3D point {point_id} has a track of {len(track)} numbers; "
                             "it must be (IMAGE_ID, POINT2D_IDX) pairs")
        if track:
            pairs = _column(track, np.int64, where, number, f"track of 3D point {point_id}").reshape(-1, 2)
            for image_id, index in pairs.tolist():
                if image_id not in counts:
                    raise InputError(f"{where} line {number}: 3D point {point_id} is seen by image {image_id}, which "
                                     "images.txt lacks")
                if not 0 <= index < counts[image_id]:
                    raise InputError(f"{where} line {number}: 3D point {point_id} is 2D point {index} of image "
                                     f"{image_id}, which has {counts[image_id]}")
    return np.asarray(points, np.float64).reshape(-1, 3), np.asarray(colours, np.float64).reshape(-1, 3), set(ids)


def read_model(texts: dict, wheres: dict) -> Model:
    """The model from the bytes of cameras.txt, images.txt and (if present) points3D.txt
    (texts, wheres: {file name: bytes / path shown in errors}), cross-checked: every image's
    camera exists, every 3D point its 2D points name exists."""
    cameras = read_cameras(texts["cameras.txt"], wheres["cameras.txt"])
    images = read_images(texts["images.txt"], wheres["images.txt"])
    where = wheres["images.txt"]
    for image in images:
        if image.camera_id not in cameras:
            raise InputError(f"{where} line {image.line}: image {image.image_id} names camera {image.camera_id}, which "
                             f"{wheres['cameras.txt']} lacks")
    points, colours, point_ids = None, None, set()
    if "points3D.txt" in texts:
        points, colours, point_ids = read_points(texts["points3D.txt"], wheres["points3D.txt"], images)
    for image in images:
        missing = [point for point in image.point3d_ids if point not in point_ids]
        if missing:
            lacking = "there is no points3D.txt" if points is None else f"{wheres['points3D.txt']} lacks it"
            raise InputError(f"{where} line {image.line + 1}: image {image.image_id}'s 2D points name 3D point "
                             f"{missing[0]}, but {lacking}")
    return Model(cameras, images, points, colours)
