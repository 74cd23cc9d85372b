"""Ground truth that nerfgauge did not write: NeRF-synthetic, nerfstudio and COLMAP folders.

`Dataset(root)` opens such a folder when it has no manifest.json and no nerfgauge marker
(.nerfgauge.json: a dataset of ours without a manifest is unfinished, and stays refused).
What is read (formats' own conventions):

- "nerf-synthetic": transforms_{train,val,test}.json with `camera_angle_x` and
  `transform_matrix` per frame (OpenGL axes), `file_path` extension-less (the image is the
  first of .png, .jpg, .jpeg that exists) or with its extension. w, h, fl_x, fl_y, cx, cy
  when given; else the size comes from the images' headers, fx = fy = w / (2 tan(angle/2)),
  cx = w / 2, cy = h / 2 (the Blender loaders of NeRF, nerfstudio and NerfBaselines). Given
  both, fl_x must agree with camera_angle_x (1e-3 relative).
- "nerfstudio": transforms.json, fl_x, fl_y, cx, cy, w, h at the top (a frame may repeat
  them, equal), camera_model PINHOLE or OPENCV with zero distortion, paths with their
  extension; splits from {train,val,test}_filenames, else every 8th frame (sorted by
  path, index % 8 == 0) is test and the rest train.
- "colmap": a text model (cameras.txt, images.txt, points3D.txt in sparse/0/, sparse/ or
  the root; nerfgauge.core.colmap_text) and images/NAME; one pinhole camera for all images;
  every 8th image by sorted name is test (NerfBaselines' and mip-NeRF 360's "llffhold 8"),
  the rest train. A binary model (cameras.bin) is refused naming the converter.

Validated as ours are: every listed image exists and its header's size equals the
intrinsics' (checked on open, naming the frame), poses are rigid, a frame appears once.
Files are confined to the folder and hashed as they are read (Dataset.files_read: {rel:
sha256}): the metrics document records them in place of our manifest.

What such a folder cannot give is named in `UNAVAILABLE` with the reason: depth, hit masks,
the noise ceiling, co-visibility, instance ids, meshes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from nerfgauge.core import colmap_text, validate
from nerfgauge.core.camera import Intrinsics, SplitCameras
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_from_bytes

FORMATS = ("nerf-synthetic", "nerfstudio", "colmap")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
COLMAP_MODEL_DIRS = ("sparse/0", "sparse", ".")
TEST_EVERY = 8  # splits of folders that state none: index % 8 == 0 is test
ANGLE_TOLERANCE = 1e-3

UNAVAILABLE = {
    "depth": "{format} folders carry no ground-truth depth",
    "masks": "{format} folders carry no hit mask (which pixels' centre rays hit geometry)",
    "noise_ceiling": "no Monte Carlo noise estimate: the images were not rendered by nerfgauge",
    "covisibility": "co-visibility needs ground-truth depth of the train views",
    "instances": "no instance ids",
    "meshes": "no ground-truth meshes",
}


@dataclass
class ForeignLayout:
    """A foreign folder as read: its format, cameras per split, each frame's image file, the
    split rule, COLMAP's 3D points (None elsewhere)."""

    format: str
    cameras: dict  # {split: dataset.SplitCameras}
    images: dict  # {stem: relative image path}
    split_rule: str
    points: Optional[np.ndarray] = None
    unavailable: dict = field(default_factory=dict)


def colmap_model_dir(root: Path) -> Optional[Path]:
    for name in COLMAP_MODEL_DIRS:
        folder = root / name
        if (folder / "cameras.txt").is_file() and (folder / "images.txt").is_file():
            return folder
    return None


def detect(root: Path) -> Optional[str]:
    """The format of a folder without a manifest, or None when it is none of FORMATS."""
    root = Path(root)
    if any((root / f"transforms_{split}.json").is_file() for split in ("train", "val", "test")):
        return "nerf-synthetic"
    if (root / "transforms.json").is_file():
        return "nerfstudio"
    if colmap_model_dir(root) is not None:
        return "colmap"
    if any((root / name / "cameras.bin").is_file() for name in COLMAP_MODEL_DIRS):
        raise InputError(f"{root} holds a binary COLMAP model; convert it: colmap model_converter --input_path "
                         f"MODEL --output_path MODEL --output_type TXT")
    return None


def read(ds, fmt: str) -> ForeignLayout:
    """The layout of `ds` (a Dataset in foreign mode: its read_bytes hashes what it reads)."""
    reader = {"nerf-synthetic": _nerf_synthetic, "nerfstudio": _nerfstudio, "colmap": _colmap}[fmt]
    layout = reader(ds)
    layout.unavailable = {key: reason.format(format=fmt) for key, reason in UNAVAILABLE.items()}
    for split, cameras in layout.cameras.items():
        for stem in cameras.stems:
            _check_header(ds, layout.images[stem], cameras.intrinsics, stem)
    return layout


# --- helpers -----------------------------------------------------------------------------------


def _json(ds, rel: str) -> dict:
    meta = json_from_bytes(ds.read_bytes(rel), ds.root / rel, finite=False)
    if not isinstance(meta, dict):
        raise InputError(f"{ds.root / rel}: expected a JSON object")
    return meta


def _image_of(ds, path: str, where: str) -> tuple[str, str]:
    """(stem, image rel) of a frame path with or without its extension."""
    rel = validate.relative_path(path, where)
    if Path(rel).suffix in IMAGE_EXTENSIONS:
        if not (ds.root / rel).is_file():
            raise InputError(f"{where}: image {ds.root / rel} does not exist")
        return rel[: -len(Path(rel).suffix)], rel
    for extension in IMAGE_EXTENSIONS:
        if (ds.root / (rel + extension)).is_file():
            return rel, rel + extension
    raise InputError(f"{where}: no image {ds.root / rel}.png|.jpg|.jpeg")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from an image's header, nothing decoded."""
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, ValueError, SyntaxError) as error:
        raise InputError(f"cannot read image {path}: {error}") from None


def _check_header(ds, rel: str, intrinsics: Intrinsics, stem: str) -> None:
    path = validate.confine(ds._real_root, rel, f"frame {stem}")
    width, height = image_size(path)
    if (width, height) != (intrinsics.width, intrinsics.height):
        raise InputError(f"frame {stem}: image {ds.root / rel} is {width}x{height}, the cameras say "
                         f"{intrinsics.width}x{intrinsics.height}")


def _split_cameras(split: str, stems: list, poses: list, intrinsics: Intrinsics):
    c2w = np.stack(poses) if poses else np.zeros((0, 4, 4))
    c2w.flags.writeable = False
    return SplitCameras(split, tuple(stems), c2w, intrinsics)


def _every_eighth(items: list) -> dict:
    """{split: [items]}: index % TEST_EVERY == 0 of the sorted items is test, the rest train."""
    ordered = sorted(items)
    return {"train": [x for i, x in enumerate(ordered) if i % TEST_EVERY],
            "test": [x for i, x in enumerate(ordered) if i % TEST_EVERY == 0]}


def _number(meta: dict, key: str, where: str) -> float:
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


# --- NeRF-synthetic ----------------------------------------------------------------------------


def _synthetic_intrinsics(ds, meta: dict, where: str, first_image: Optional[str]) -> Intrinsics:
    full = all(key in meta for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"))
    angle = _number(meta, "camera_angle_x", where) if "camera_angle_x" in meta else None
    if angle is not None and not 0 < angle < np.pi:
        raise InputError(f"{where}: camera_angle_x must be in (0, pi), got {angle}")
    if full:
        intrinsics = validate.intrinsics(meta, where)
        if angle is not None:
            implied = 0.5 * intrinsics.width / np.tan(0.5 * angle)
            if abs(implied - intrinsics.fx) > ANGLE_TOLERANCE * intrinsics.fx:
                raise InputError(f"{where}: camera_angle_x {angle:.6g} means fl_x {implied:.6g} at w "
                                 f"{intrinsics.width}, but fl_x is {intrinsics.fx:.6g}")
        return intrinsics
    if angle is None:
        raise InputError(f"{where}: needs camera_angle_x (or w, h, fl_x, fl_y, cx, cy)")
    if "w" in meta and "h" in meta:
        sized = validate.intrinsics({**meta, "fl_x": 1, "fl_y": 1, "cx": 0, "cy": 0}, where)
        width, height = sized.width, sized.height
    elif first_image is not None:
        width, height = image_size(validate.confine(ds._real_root, first_image))
    else:
        width, height = 1, 1  # a split without frames
    focal = 0.5 * width / np.tan(0.5 * angle)
    return Intrinsics(width, height, focal, focal, width / 2.0, height / 2.0)


def _nerf_synthetic(ds) -> ForeignLayout:
    cameras, images = {}, {}
    for split in ("train", "val", "test"):
        name = f"transforms_{split}.json"
        if not (ds.root / name).is_file():
            continue
        where = str(ds.root / name)
        meta = _json(ds, name)
        frames = meta.get("frames")
        if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames):
            raise InputError(f"{where}: 'frames' must be a list of objects")
        stems, poses = [], []
        for k, frame in enumerate(frames):
            if "file_path" not in frame or "transform_matrix" not in frame:
                raise InputError(f"{where}: frame {k} needs file_path and transform_matrix")
            stem, rel = _image_of(ds, frame["file_path"], f"{where}: frame {k}")
            stems.append(stem)
            images[stem] = rel
            poses.append(validate.pose(frame["transform_matrix"], stem, where))
        intrinsics = _synthetic_intrinsics(ds, meta, where, images[stems[0]] if stems else None)
        cameras[split] = _split_cameras(split, stems, poses, intrinsics)
    return ForeignLayout("nerf-synthetic", cameras, images, "the folder's transforms_<split>.json")


# --- nerfstudio -------------------------------------------------------------------------------------


def _nerfstudio(ds) -> ForeignLayout:
    name = "transforms.json"
    where = str(ds.root / name)
    meta = _json(ds, name)
    model = meta.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE"):
        raise InputError(f"{where}: camera_model {model!r} is not a pinhole; undistort the images first")
    for key in ("k1", "k2", "k3", "k4", "p1", "p2"):
        if key in meta and _number(meta, key, where) != 0.0:
            raise InputError(f"{where}: distortion {key}={meta[key]} is not 0; undistort the images first")
    intrinsics = validate.intrinsics(meta, where)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames) or not frames:
        raise InputError(f"{where}: 'frames' must be a non-empty list of objects")
    poses, images = {}, {}
    for k, frame in enumerate(frames):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise InputError(f"{where}: frame {k} needs file_path and transform_matrix")
        for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            if key in frame and _number(frame, key, f"{where}: frame {k}") != float(getattr(
                    intrinsics, {"w": "width", "h": "height", "fl_x": "fx", "fl_y": "fy"}.get(key, key))):
                raise InputError(f"{where}: frame {k} has its own {key}={frame[key]}, unlike the folder's; "
                                 "nerfgauge scores one camera per split")
        stem, rel = _image_of(ds, frame["file_path"], f"{where}: frame {k}")
        if stem in poses:
            raise InputError(f"{where}: frame {stem} is listed twice")
        poses[stem], images[stem] = validate.pose(frame["transform_matrix"], stem, where), rel
    by_path = {rel: stem for stem, rel in images.items()}
    listed = {split: meta.get(f"{split}_filenames") for split in ("train", "val", "test")}
    if any(value is not None for value in listed.values()):
        splits, rule = {}, "the folder's {train,val,test}_filenames"
        for split, names in listed.items():
            if names is None:
                continue
            if not isinstance(names, list):
                raise InputError(f"{where}: {split}_filenames must be a list of paths")
            stems = []
            for path in names:
                rel = validate.relative_path(path, f"{where}: {split}_filenames")
                if rel not in by_path:
                    raise InputError(f"{where}: {split}_filenames lists {rel}, which no frame has")
                stems.append(by_path[rel])
            splits[split] = stems
    else:
        splits, rule = _every_eighth(list(poses)), f"no split lists: every {TEST_EVERY}th frame by path is test"
    cameras = {split: _split_cameras(split, stems, [poses[s] for s in stems], intrinsics)
               for split, stems in splits.items()}
    return ForeignLayout("nerfstudio", cameras, images, rule)


# --- COLMAP ------------------------------------------------------------------------------------------


def _colmap(ds) -> ForeignLayout:
    folder = colmap_model_dir(ds.root)
    model = folder.relative_to(ds.root).as_posix()
    prefix = "" if model == "." else model + "/"
    text = {name: ds.read_bytes(prefix + name).decode("utf-8", "replace")
            for name in ("cameras.txt", "images.txt") + (("points3D.txt",) if (folder / "points3D.txt").is_file() else ())}
    cams = colmap_text.read_cameras(text["cameras.txt"], str(folder / "cameras.txt"))
    entries = colmap_text.read_images(text["images.txt"], str(folder / "images.txt"))
    points = colmap_text.read_points(text["points3D.txt"], str(folder / "points3D.txt")) if "points3D.txt" in text else None
    if not entries:
        raise InputError(f"{folder / 'images.txt'} lists no image")
    used = {entry.camera_id for entry in entries}
    unknown = sorted(used - set(cams))
    if unknown:
        raise InputError(f"{folder / 'images.txt'} names camera {unknown[0]}, which {folder / 'cameras.txt'} lacks")
    pinholes = {(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for i, c in cams.items() if i in used}
    if len(pinholes) > 1:
        raise InputError(f"{folder / 'cameras.txt'}: the images use {len(pinholes)} different cameras; "
                         "nerfgauge scores one camera per split")
    width, height, fx, fy, cx, cy = pinholes.pop()
    intrinsics = Intrinsics(width, height, fx, fy, cx, cy)
    poses, images = {}, {}
    for entry in entries:
        rel = validate.relative_path("images/" + entry.name, f"{folder / 'images.txt'}: image {entry.image_id}")
        if not (ds.root / rel).is_file():
            raise InputError(f"{folder / 'images.txt'}: image {entry.image_id} {entry.name}: {ds.root / rel} does not exist")
        stem = rel[: -len(Path(rel).suffix)] if Path(rel).suffix else rel
        if stem in poses:
            raise InputError(f"{folder / 'images.txt'}: image {entry.name} is listed twice")
        poses[stem] = validate.pose(entry.c2w_opengl().tolist(), stem, str(folder / "images.txt"))
        images[stem] = rel
    splits = _every_eighth(list(poses))
    cameras = {split: _split_cameras(split, stems, [poses[s] for s in stems], intrinsics)
               for split, stems in splits.items()}
    return ForeignLayout("colmap", cameras, images,
                         f"every {TEST_EVERY}th image by name is test (llffhold {TEST_EVERY})", points)
