"""Checks on what a dataset says about itself, run as it is read.

Every function here raises `InputError` with one line naming the file (and the frame)
and what was expected, and returns the checked value. All are pure but `confine`, which
asks the file system where a path really leads.

- Paths: a path read from a dataset file is relative, has no `..`, and resolves (symlinks
  followed, `Path.resolve`) inside the dataset root.
- Intrinsics: fl_x, fl_y finite and > 0; cx, cy finite; w, h integers in [1, MAX_IMAGE_SIDE].
- A split's camera (`camera`, for our transforms and every foreign format alike): one per
  split, from the document's keys and each frame's own (nerfstudio's per-frame w, h, fl_x,
  fl_y, cx, cy, camera_model, k1..k4, p1, p2), which must agree across the split; the
  intrinsics as above; camera_angle_x in (0, pi) and, with fl_x, agreeing with it; the
  lens distortion (OPENCV, OPENCV_FISHEYE) one-to-one over the image, and no coefficient
  under a pinhole model.
- scene.json: bounds [[x, y, z], [x, y, z]], finite, min < max on every axis; needs an
  object (finest_texture_period finite > 0 or null, view_dependent a boolean).
- Poses: 4x4 finite; rotation orthonormal (max |R^T R - I| <= POSE_TOLERANCE) with
  |det R - 1| <= POSE_TOLERANCE (no scale, shear or mirror); bottom row exactly 0 0 0 1.
- Frames: every frame file_path appears once in the whole dataset (normalised: "./a" is
  "a"): a frame listed twice in a split would be trained on (or scored) twice, and a frame
  in two splits (a test view that is also a training view) makes the scores meaningless.
- Images: the magic bytes match the extension (PNG 89 50 4E 47 0D 0A 1A 0A, JPEG FF D8 FF,
  EXR 76 2F 31 01), so JPEG bytes in a .png are refused. The size is read from the header
  (nerfgauge.core.images.image_header: a PNG's IHDR, a JPEG's frame header, an EXR's
  dataWindow, before the rest of the file is read) and refused BEFORE any pixel is decoded when a
  side exceeds MAX_IMAGE_SIDE = 8192 pixels, the generator's own cap
  (GenerateConfig.validate): at most 8192 * 8192 = 67,108,864 pixels, 1 GiB as float32
  RGBA, and below Pillow's decompression-bomb threshold (89,478,485 pixels), so its
  warning never fires for an image we accept.
- manifest.json: schema 2 {"schema": 2, "files": {rel: {"sha256": hex, "bytes": n}}};
  schema 1 {"schema": 1, "files": {rel: hex}} (no sizes) is still read. A file read from
  the dataset must be listed, have the listed size (compared on the file system before
  it is read: `content_size`) and (unless hashing is off) the listed sha256.
"""

from __future__ import annotations

import hashlib
import math
import numbers
import os
import posixpath
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core.camera import Intrinsics
from nerfgauge.core.distortion import Distortion
from nerfgauge.core.errors import InputError

MAX_IMAGE_SIDE = 8192
# The largest radiance (emitter radiance, point-light intensity, environment-map pixel)
# rendered. Mitsuba renders in float32 (largest finite value ~3.4e38 = 2^128): a pixel sums
# up to 2^16 samples (the --spp limit), an environment map's sampling distribution sums
# its pixels (up to 8192^2 = 2^26), and a path's weight (BSDF / pdf, MIS) multiplies a
# radiance by factors we bound at 2^32. 2^(16 + 26 + 32) = 2^74 of headroom leaves
# 2^54 ~ 1.8e16; a map holding 1e30 rendered NaN and left a partial view. Real HDR skies
# peak near 1e5 (the sun, in relative units), so no real input is near the bound.
MAX_RADIANCE = float(np.finfo(np.float32).max) / 2.0**74
# The most bytes one image decodes to: float32 RGBA at MAX_IMAGE_SIDE a side (1 GiB). An
# EXR header may declare any number of channels; 1000 channels of 8192^2 would be 256 GiB.
MAX_DECODED_BYTES = MAX_IMAGE_SIDE * MAX_IMAGE_SIDE * 4 * 4
POSE_TOLERANCE = 1e-4
MAGIC = {".png": b"\x89PNG\r\n\x1a\n", ".exr": b"\x76\x2f\x31\x01", ".jpg": b"\xff\xd8\xff", ".jpeg": b"\xff\xd8\xff"}
_OTHER_FORMATS = {b"\xff\xd8\xff": "JPEG", b"GIF8": "GIF", b"BM": "BMP", b"RIFF": "RIFF/WebP",
                  b"II*\x00": "TIFF", b"MM\x00*": "TIFF", b"\x89PNG": "PNG", b"\x76\x2f\x31\x01": "EXR"}
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


# --- paths -------------------------------------------------------------------------------


def relative_path(value, what: str) -> str:
    """A path as a dataset file states it -> normalised POSIX relative path ("./a//b" -> "a/b").

    Refuses non-strings, empty paths, absolute paths, backslashes and `..` components.
    """
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{what}: expected a relative path, got {value!r}")
    if "\\" in value or "\x00" in value:
        raise InputError(f"{what}: path {value!r} holds a backslash or NUL; use / separated relative paths")
    if value.startswith("/"):
        raise InputError(f"{what}: absolute path {value!r} refused; paths must stay inside the dataset")
    if ".." in value.split("/"):
        raise InputError(f"{what}: path {value!r} climbs out with '..'; paths must stay inside the dataset")
    normal = posixpath.normpath(value)
    if normal == ".":
        raise InputError(f"{what}: expected a relative path, got {value!r}")
    return normal


def confine(real_root: Path, rel: str, what: str = "") -> Path:
    """The real path of `rel` under `real_root` (already resolved), symlinks followed; an
    InputError if it leads outside the root. what: who asked (e.g. "frame test/r_000")."""
    label = f"{what}: " if what else ""
    rel = relative_path(rel, label + repr(rel))
    root = str(real_root)
    real = os.path.realpath(os.path.join(root, rel))  # what Path.resolve() does, without the objects
    if not real.startswith(root.rstrip(os.sep) + os.sep):
        raise InputError(f"{label}{rel} resolves to {real}, outside the dataset {real_root}")
    return Path(real)


# --- numbers from transforms and scene.json ----------------------------------------------


def _real(value, name: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise InputError(f"{where}: {name} must be a finite number, got {value!r}")
    return float(value)


def _side(value, name: str, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputError(f"{where}: {name} must be a whole number of pixels, got {value!r}")
    if not 1 <= value <= MAX_IMAGE_SIDE:
        raise InputError(f"{where}: {name} = {value} is outside 1..{MAX_IMAGE_SIDE} pixels")
    return int(value)


MAX_RAY_TANGENT = 1000.0  # tan of 89.94 deg: a pinhole's field of view up to 179.89 deg


def intrinsics(meta: dict, where: str) -> Intrinsics:
    """Intrinsics from a transforms document's w, h, fl_x, fl_y, cx, cy."""
    missing = [key for key in ("w", "h", "fl_x", "fl_y", "cx", "cy") if key not in meta]
    if missing:
        raise InputError(f"{where}: missing camera field(s) {', '.join(missing)}")
    width, height = _side(meta["w"], "w", where), _side(meta["h"], "h", where)
    fx, fy = _real(meta["fl_x"], "fl_x", where), _real(meta["fl_y"], "fl_y", where)
    if fx <= 0 or fy <= 0:
        raise InputError(f"{where}: focal lengths must be > 0, got fl_x={fx} fl_y={fy}")
    cx, cy = _real(meta["cx"], "cx", where), _real(meta["cy"], "cy", where)
    # The farthest pixel edge from the principal point, in focal lengths: a pinhole ray's
    # tangent off the axis. Past MAX_RAY_TANGENT the rays are within 0.06 deg of 90 and
    # their directions overflow or vanish in float arithmetic (a fresh fuzz seed:
    # fl_y = 1e-300 gave zero-length rays deep in training).
    tangent = max(max(abs(cx), abs(width - cx)) / fx, max(abs(cy), abs(height - cy)) / fy)
    if not tangent <= MAX_RAY_TANGENT:
        raise InputError(f"{where}: fl_x={fx:g}, fl_y={fy:g}, cx={cx:g}, cy={cy:g} put the image's edge "
                         f"{tangent:.3g} focal lengths off the axis (at most {MAX_RAY_TANGENT:g}: a pinhole "
                         "image within 89.94 deg of its axis)")
    return Intrinsics(width, height, fx, fy, cx, cy)


# The keys that state a camera in a transforms document; nerfstudio reads each per frame too.
CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model", "k1", "k2", "k3", "k4", "p1", "p2")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = (None, "PINHOLE", "SIMPLE_PINHOLE")
ANGLE_TOLERANCE = 1e-3  # relative: camera_angle_x against fl_x, where a document gives both


def camera(meta: dict, frames: list, where: str, frame_names=None, image_size=None) -> tuple:
    """The one camera of a split: (Intrinsics, Distortion or None), checked.

    meta: the transforms document; frames: the split's frame objects, each of which may
    state any CAMERA_KEYS itself (nerfstudio's rule: the frame's value wins over the
    document's). Every frame must give the same camera: nerfgauge renders and scores one
    camera per split, so a frame that differs is refused naming the key and the frame,
    never ignored. frame_names: how errors name the frames (default their index).
    image_size(): (width, height) from the first image's header, for NeRF-synthetic
    documents that state only camera_angle_x (fx = fy = w / (2 tan(angle / 2)), cx = w / 2,
    cy = h / 2, as the Blender loaders of NeRF, nerfstudio and NerfBaselines take them).
    """
    names = list(frame_names) if frame_names is not None else [str(k) for k in range(len(frames))]
    top = {key: meta[key] for key in CAMERA_KEYS if key in meta}
    cameras = [top | {key: frame[key] for key in CAMERA_KEYS if key in frame} for frame in frames]
    stated = cameras[0] if cameras else top
    for name, other in zip(names[1:], cameras[1:]):
        # `is` first: a document's own NaN is the same object in every frame (refused below, as NaN)
        key = next((key for key in CAMERA_KEYS if not (other.get(key) is stated.get(key)
                                                       or other.get(key) == stated.get(key))), None)
        if key is not None:
            raise InputError(f"{where}: frame {name} has {key}={other.get(key)!r} but frame {names[0]} has "
                             f"{stated.get(key)!r}; nerfgauge scores one camera per split (give each camera its "
                             "own split, or undistort and resize the images to one camera)")
    stated = dict(stated)
    angle = None
    if "camera_angle_x" in meta:
        angle = _real(meta["camera_angle_x"], "camera_angle_x", where)
        if not 0 < angle < math.pi:
            raise InputError(f"{where}: camera_angle_x must be in (0, pi), got {angle}")
    if angle is not None and not any(key in stated for key in ("fl_x", "fl_y", "cx", "cy")):
        if "w" in stated or "h" in stated or image_size is None:
            width, height = _side(stated.get("w"), "w", where), _side(stated.get("h"), "h", where)
        else:
            width, height = image_size()
        focal = 0.5 * width / math.tan(0.5 * angle)
        stated.update(w=width, h=height, fl_x=focal, fl_y=focal, cx=width / 2.0, cy=height / 2.0)
    if angle is None and not any(key in stated for key in ("fl_x", "fl_y", "cx", "cy")) and image_size is not None:
        raise InputError(f"{where}: needs camera_angle_x (or w, h, fl_x, fl_y, cx, cy)")
    checked = intrinsics(stated, where)
    if angle is not None:
        implied = 0.5 * checked.width / math.tan(0.5 * angle)
        if abs(implied - checked.fx) > ANGLE_TOLERANCE * checked.fx:
            raise InputError(f"{where}: camera_angle_x {angle:.6g} means fl_x {implied:.6g} at w "
                             f"{checked.width}, but fl_x is {checked.fx:.6g}")
    return checked, lens_distortion(stated, checked, where)


def lens_distortion(stated: dict, checked: Intrinsics, where: str) -> Optional[Distortion]:
    """A camera's lens distortion from its camera_model and k1..k4, p1, p2 (None for a
    pinhole), checked one-to-one over the image. A coefficient other than 0 under a
    pinhole model (or without a camera_model) is refused: it would be ignored."""
    model = stated.get("camera_model")
    if model in PINHOLE_MODELS:
        for key in DISTORTION_KEYS:
            if key in stated and _real(stated[key], key, where) != 0.0:
                raise InputError(f"{where}: {key}={stated[key]!r} under camera_model {model or '(none given)'}, "
                                 "which has no distortion; state camera_model OPENCV or OPENCV_FISHEYE, or "
                                 "undistort the images")
        return None
    distortion = Distortion.from_json(stated, where)
    if distortion is not None:
        distortion.check_image(checked, f"{where}: camera_model {model}")
    return distortion


BOUNDS_LIMIT = 1e9


def bounds(value, where: str) -> np.ndarray:
    """[[xmin, ymin, zmin], [xmax, ymax, zmax]] -> [2, 3] float64, finite, min < max."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: bounds must be [[x, y, z], [x, y, z]] of numbers, got {value!r}") from None
    if array.shape != (2, 3) or any(isinstance(v, (bool, str)) for row in value for v in row):
        raise InputError(f"{where}: bounds must be [[x, y, z], [x, y, z]] of numbers, got {value!r}")
    if not np.isfinite(array).all():
        raise InputError(f"{where}: bounds hold NaN or inf: {array.tolist()}")
    if np.abs(array).max() > BOUNDS_LIMIT:
        # Training samples rays in float32 across the box: beyond this its steps are not
        # representable (at 1e308 the extent itself overflows to inf).
        raise InputError(f"{where}: bounds reach {np.abs(array).max():.3g}, beyond the +-{BOUNDS_LIMIT:.0e} "
                         f"scene units nerfgauge can sample: {array.tolist()}")
    if not (array[0] < array[1]).all():
        axes = ", ".join("xyz"[k] for k in np.flatnonzero(~(array[0] < array[1])))
        raise InputError(f"{where}: bounds need min < max on every axis, not on {axes}: {array.tolist()}")
    return array


def needs(value, where: str) -> Optional[dict]:
    """scene.json's `needs` (what the scene asks of a model): None, or an object whose
    finest_texture_period, if given and not null, is a finite number > 0 and whose
    view_dependent, if given, is true or false."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise InputError(f"{where}: needs must be an object, got {value!r}")
    period = value.get("finest_texture_period")
    if period is not None and (_real(period, "needs.finest_texture_period", where) <= 0):
        raise InputError(f"{where}: needs.finest_texture_period must be > 0, got {period!r}")
    if "view_dependent" in value and not isinstance(value["view_dependent"], bool):
        raise InputError(f"{where}: needs.view_dependent must be true or false, got {value['view_dependent']!r}")
    return value


def pose(matrix, frame: str, where: str, *, position_limit: float | None = BOUNDS_LIMIT) -> np.ndarray:
    """A rigid camera-to-world matrix -> [4, 4] float64 (see the module docstring).
    position_limit: the farthest a camera may sit from the origin on any axis, for a
    dataset's cameras (rays from beyond it are not representable in float32); None for a
    method's own estimated poses, whose frame has any scale (eval.poses aligns it by a
    similarity and has its own limit)."""
    try:
        array = np.array(matrix, dtype=np.float64)
        numeric = all(not isinstance(v, (bool, str)) for row in matrix for v in row)
    except (TypeError, ValueError):
        array, numeric = None, False
    if array is None or not numeric or array.shape != (4, 4):
        raise InputError(f"{where}: transform_matrix must be 4x4 numbers for frame {frame}")
    if not np.isfinite(array).all():
        raise InputError(f"{where}: transform_matrix holds NaN or inf for frame {frame}")
    if array[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise InputError(f"{where}: transform_matrix bottom row must be 0 0 0 1 for frame {frame}, got {array[3].tolist()}")
    rotation, position = array[:3, :3], array[:3, 3]
    if position_limit is not None and np.abs(position).max() > position_limit:
        raise InputError(f"{where}: transform_matrix places frame {frame} at {position.tolist()}, beyond the "
                         f"+-{position_limit:.0e} scene units nerfgauge can sample")
    # A rotation's entries lie in [-1, 1]; one far outside is no rotation, and R^T R of it
    # would overflow before the check below could say so.
    error = (float(np.abs(rotation).max()) - 1.0 if np.abs(rotation).max() > 2.0
             else float(np.abs(rotation.T @ rotation - np.eye(3)).max()))
    det = float(np.linalg.det(rotation)) if error <= POSE_TOLERANCE else float("nan")
    if error > POSE_TOLERANCE or abs(det - 1.0) > POSE_TOLERANCE:
        measured = f"max |R^T R - I| = {error:.3g}" + (f", det R = {det:.6g}" if det == det else "")
        raise InputError(f"{where}: transform_matrix is not a rigid camera-to-world for frame {frame} "
                         f"({measured}; need <= {POSE_TOLERANCE} and det R = 1)")
    return array


def distinct_frames(split_stems: dict, root) -> None:
    """Refuse a frame listed more than once: twice in one split or in two splits.
    split_stems: {split: normalised stems in file order}; root: the dataset, named in errors."""
    seen = {}
    for split, stems in split_stems.items():
        for index, stem in enumerate(stems):
            if stem in seen:
                first_split, first_index = seen[stem]
                where = (f"twice in transforms_{split}.json (frames {first_index} and {index})" if first_split == split
                         else f"in transforms_{first_split}.json (frame {first_index}) and in transforms_{split}.json "
                              f"(frame {index})")
                why = ("would be trained on or scored twice" if first_split == split
                       else "would be both a training and a held-out view, which makes the scores meaningless"
                       if "train" in (first_split, split) else "would be scored in two splits")
                raise InputError(f"dataset {root}: frame {stem} is listed {where}; it {why}; list each frame once")
            seen[stem] = (split, index)


# --- radiance ------------------------------------------------------------------------------


def radiance(values, where: str) -> None:
    """Refuse radiance values above MAX_RADIANCE (they overflow float32 while rendering)."""
    array = np.asarray(values, dtype=np.float64)
    peak = float(np.nanmax(array)) if array.size else 0.0
    if peak > MAX_RADIANCE:
        raise InputError(f"{where}: radiance {peak:.3g} is above {MAX_RADIANCE:.3g}, where float32 rendering "
                         "overflows (sums over samples, map pixels and path weights)")


# --- image headers -----------------------------------------------------------------------


def image_magic(data: bytes, path) -> None:
    """The leading bytes of `data` match the extension of `path` (.png, .jpg/.jpeg or .exr)."""
    suffix = os.path.splitext(str(path))[1].lower()
    magic = MAGIC.get(suffix)
    if magic is None or data.startswith(magic):
        return
    found = next((name for prefix, name in _OTHER_FORMATS.items() if data.startswith(prefix)), None)
    what = f"{found} data" if found else f"no {suffix[1:].upper()} signature (starts {data[:8].hex(' ') or 'empty'})"
    raise InputError(f"{path}: holds {what}, but its extension says {suffix[1:].upper()}")


def image_size(width: int, height: int, path) -> None:
    """Refuse an image whose header states a side above MAX_IMAGE_SIDE (before decoding)."""
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise InputError(f"{path}: header says {width}x{height} pixels; images above {MAX_IMAGE_SIDE} "
                         "pixels on a side are refused before decoding")


def decoded_size(width: int, height: int, channels: int, path, bytes_per_value: int = 4) -> None:
    """Refuse an image whose header declares more than MAX_DECODED_BYTES of pixels."""
    total = width * height * channels * bytes_per_value
    if total > MAX_DECODED_BYTES:
        raise InputError(f"{path}: header declares {channels} channels of {width}x{height} pixels "
                         f"({total / 2**30:.3g} GiB decoded); at most {MAX_DECODED_BYTES >> 30} GiB are decoded")


def header_matches(width: int, height: int, expected, path) -> None:
    """The header's size equals the transforms' (expected: Intrinsics or (width, height))."""
    want = (expected.width, expected.height) if isinstance(expected, Intrinsics) else tuple(expected)
    if (width, height) != want:
        raise InputError(f"{path} is {width}x{height}, but the transforms say {want[0]}x{want[1]}")


# --- manifest ----------------------------------------------------------------------------


@dataclass(frozen=True)
class ManifestEntry:
    """One file as manifest.json recorded it; size is None in schema-1 manifests."""

    sha256: str
    size: Optional[int]


def manifest(document: dict, path) -> dict:
    """A parsed manifest.json -> {relative path: ManifestEntry} (schema 1 or 2)."""
    schema, files = document.get("schema"), document.get("files")
    if schema not in (1, 2) or not isinstance(files, dict):
        raise InputError(f"{path}: expected {{\"schema\": 1 or 2, \"files\": {{...}}}}, "
                         f"got schema {schema!r} and files of type {type(files).__name__}")
    entries = {}
    for rel, entry in files.items():
        if schema == 1:
            digest, size = entry, None
        elif isinstance(entry, dict):
            digest, size = entry.get("sha256"), entry.get("bytes")
        else:
            digest, size = None, None
        if not isinstance(digest, str) or not _SHA256.match(digest) or (
                schema == 2 and (isinstance(size, bool) or not isinstance(size, int) or size < 0)):
            raise InputError(f"{path}: entry {rel!r} is malformed; expected "
                             + ("a sha256 hex digest" if schema == 1 else '{"sha256": hex, "bytes": size}'))
        entries[relative_path(rel, f"{path}: entry")] = ManifestEntry(digest, size)
    return entries


def content_size(size: int, entry: ManifestEntry, path) -> None:
    """A file of `size` bytes has the size the manifest recorded (schema 2; schema 1 has none)."""
    if entry.size is not None and size != entry.size:
        raise InputError(f"{path} changed since the manifest was written ({size} bytes, manifest says {entry.size})")


def content(data: bytes, entry: ManifestEntry, path, check_hash: bool = True) -> None:
    """`data` (a file's bytes) has the size and sha256 the manifest recorded."""
    content_size(len(data), entry, path)
    if check_hash and hashlib.sha256(data).hexdigest() != entry.sha256:
        raise InputError(f"{path} changed since the manifest was written (sha256 differs)")
