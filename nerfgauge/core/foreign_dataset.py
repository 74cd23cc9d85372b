"""Ground truth that nerfgauge did not write: NeRF-synthetic, nerfstudio and COLMAP folders.

`Dataset(root)` opens such a folder when it has no manifest.json and no nerfgauge marker
(.nerfgauge.json: a dataset of ours without a manifest is unfinished, and stays refused).
What is read (formats' own conventions):

- "nerf-synthetic": transforms_{train,val,test}.json with `camera_angle_x` and
  `transform_matrix` per frame (OpenGL axes), `file_path` extension-less (the image is the
  first of .png, .jpg, .jpeg that exists) or with its extension. w, h, fl_x, fl_y, cx, cy
  when given; else the size comes from the first image's header, fx = fy = w / (2
  tan(angle/2)), cx = w / 2, cy = h / 2 (the Blender loaders of NeRF, nerfstudio and
  NerfBaselines). Given both, fl_x must agree with camera_angle_x (1e-3 relative).
- "nerfstudio": transforms.json, the camera (w, h, fl_x, fl_y, cx, cy, camera_model
  PINHOLE, OPENCV or OPENCV_FISHEYE, k1..k4, p1, p2) at the top and/or per frame (a frame's
  value wins, as in nerfstudio's dataparser), one camera per split: frames of a split
  that differ are refused naming the key; a lens distortion is honoured (the split's
  cameras carry it, nerfgauge.core.distortion); paths with their extension; splits from
  {train,val,test}_filenames, else every 8th frame (sorted by path, index % 8 == 0) is
  test and the rest train.
- "colmap": a text model (cameras.txt, images.txt, points3D.txt in sparse/0/, sparse/ or
  the root; read strictly by nerfgauge.core.colmap_text) and images/NAME; one camera for
  all images (its distortion honoured as nerfstudio's); every 8th image by sorted name is
  test (NerfBaselines' and mip-NeRF 360's "llffhold 8"), the rest train. A binary model
  (cameras.bin) is refused naming the converter.

Validated as ours are, by the same functions: the camera of each split
(nerfgauge.core.validate.camera), poses rigid, a frame listed once, and every listed
image's header (read alone, nerfgauge.core.images.image_header) states the camera's size,
checked on open naming the frame. Files are confined to the folder, their size checked on
the file system before they are read (JSON bounded.MAX_JSON_BYTES, COLMAP text
colmap_text.MAX_TEXT_BYTES, images what their header implies), and hashed as they are read
(Dataset.files_read: {rel: sha256}): the metrics document records them in place of our
manifest. A split without frames is refused when it is scored (eval.predictions).

What such a folder cannot give is named in `UNAVAILABLE` with the reason: depth, hit masks,
the noise ceiling, co-visibility, instance ids, meshes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core import bounded, colmap_text, images as image_files, validate
from nerfgauge.core.camera import Intrinsics, SplitCameras
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import json_from_bytes

FORMATS = ("nerf-synthetic", "nerfstudio", "colmap")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
COLMAP_MODEL_DIRS = ("sparse/0", "sparse", ".")
TEST_EVERY = 8  # splits of folders that state none: index % 8 == 0 is test
# nerfstudio keys that change which pixels or poses count and are not read here: refused
# by name rather than ignored.
UNREAD_KEYS = ("fisheye_crop_radius",)

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
    meta = json_from_bytes(ds.read_bytes(rel, limit=bounded.MAX_JSON_BYTES), ds.root / rel, finite=False)
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


def _check_header(ds, rel: str, intrinsics: Intrinsics, stem: str) -> None:
    """The image's header alone (its size checked before anything else is read) states the camera's size."""
    try:
        header = image_files.image_header(validate.confine(ds._real_root, rel, f"frame {stem}"))
    except InputError as error:
        raise InputError(f"frame {stem}: {error}") from None
    if (header.width, header.height) != (intrinsics.width, intrinsics.height):
        raise InputError(f"frame {stem}: image {ds.root / rel} is {header.width}x{header.height}, the cameras say "
                         f"{intrinsics.width}x{intrinsics.height}")


def _split_cameras(split: str, stems: list, poses: list, camera: tuple):
    """SplitCameras from stems, poses and (Intrinsics, Distortion or None)."""
    c2w = np.stack(poses) if poses else np.zeros((0, 4, 4))
    c2w.flags.writeable = False
    intrinsics, distortion = camera
    return SplitCameras(split, tuple(stems), c2w, intrinsics, (), distortion)


def _every_eighth(items: list) -> dict:
    """{split: [items]}: index % TEST_EVERY == 0 of the sorted items is test, the rest train."""
    ordered = sorted(items)
    return {"train": [x for i, x in enumerate(ordered) if i % TEST_EVERY],
            "test": [x for i, x in enumerate(ordered) if i % TEST_EVERY == 0]}


# --- NeRF-synthetic ----------------------------------------------------------------------------


def _refuse_unread(document: dict, where: str) -> None:
    for key in UNREAD_KEYS:
        if key in document:
            raise InputError(f"{where}: {key} is not read by nerfgauge; crop or mask the images first")


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
        _refuse_unread(meta, where)

        def first_size(first=images[stems[0]] if stems else None):
            if first is None:
                return 1, 1  # a split without frames (refused when scored)
            header = image_files.image_header(validate.confine(ds._real_root, first))
            return header.width, header.height

        camera = validate.camera(meta, frames, where, stems, image_size=first_size)
        cameras[split] = _split_cameras(split, stems, poses, camera)
    return ForeignLayout("nerf-synthetic", cameras, images, "the folder's transforms_<split>.json")


# --- nerfstudio -------------------------------------------------------------------------------------


def _nerfstudio(ds) -> ForeignLayout:
    name = "transforms.json"
    where = str(ds.root / name)
    meta = _json(ds, name)
    _refuse_unread(meta, where)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames) or not frames:
        raise InputError(f"{where}: 'frames' must be a non-empty list of objects")
    poses, images, frame_of = {}, {}, {}
    for k, frame in enumerate(frames):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise InputError(f"{where}: frame {k} needs file_path and transform_matrix")
        _refuse_unread(frame, f"{where}: frame {k}")
        stem, rel = _image_of(ds, frame["file_path"], f"{where}: frame {k}")
        if stem in poses:
            raise InputError(f"{where}: frame {stem} is listed twice")
        poses[stem], images[stem] = validate.pose(frame["transform_matrix"], stem, where), rel
        frame_of[stem] = frame
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
    # the camera of each split from the document's keys and its frames' own (validate.camera)
    cameras = {split: _split_cameras(split, stems, [poses[s] for s in stems],
                                     validate.camera(meta, [frame_of[s] for s in stems], where, stems))
               for split, stems in splits.items()}
    return ForeignLayout("nerfstudio", cameras, images, rule)


# --- COLMAP ------------------------------------------------------------------------------------------


def _colmap(ds) -> ForeignLayout:
    folder = colmap_model_dir(ds.root)
    model = folder.relative_to(ds.root).as_posix()
    prefix = "" if model == "." else model + "/"
    names = ("cameras.txt", "images.txt") + (("points3D.txt",) if (folder / "points3D.txt").is_file() else ())
    read = colmap_text.read_model({name: ds.read_bytes(prefix + name, limit=colmap_text.MAX_TEXT_BYTES) for name in names},
                                  {name: str(folder / name) for name in names})
    entries = read.images
    if not entries:
        raise InputError(f"{folder / 'images.txt'} lists no image")
    used = sorted({entry.camera_id for entry in entries})
    first = read.cameras[used[0]]
    where = f"{folder / 'cameras.txt'} line {first.line}"
    for camera_id in used[1:]:
        if read.cameras[camera_id].transforms != first.transforms:
            raise InputError(f"{folder / 'cameras.txt'}: the images use cameras {used[0]} and {camera_id}, which "
                             "differ; nerfgauge scores one camera per split")
    camera = validate.camera(first.transforms, [], where)  # the checks our own transforms get
    poses, images = {}, {}
    for entry in entries:
        at = f"{folder / 'images.txt'} line {entry.line}"
        rel = validate.relative_path("images/" + entry.name, f"{at}: image {entry.image_id}")
        if not (ds.root / rel).is_file():
            raise InputError(f"{at}: image {entry.image_id} {entry.name}: {ds.root / rel} does not exist")
        stem = rel[: -len(Path(rel).suffix)] if Path(rel).suffix else rel
        if stem in poses:
            raise InputError(f"{at}: image {entry.name} has the stem of another image ({stem})")
        poses[stem] = validate.pose(entry.c2w_opengl().tolist(), stem, at)
        images[stem] = rel
    splits = _every_eighth(list(poses))
    cameras = {split: _split_cameras(split, stems, [poses[s] for s in stems], camera)
               for split, stems in splits.items()}
    return ForeignLayout("colmap", cameras, images,
                         f"every {TEST_EVERY}th image by name is test (llffhold {TEST_EVERY})", read.points)
