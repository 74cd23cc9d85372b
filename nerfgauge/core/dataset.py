"""The dataset on disk: file names, transforms JSON, manifest, and reading it back.

This module is the dataset convention the other stages import (nerf/ trains from it,
eval/ scores against it). It does not import mitsuba.

Layout of a dataset folder:
  config.json                      the generator's config (written first; used to resume)
  meshes/<shape>.ply               ground-truth meshes, world coordinates
  <split>/r_000.png                RGBA, 8-bit sRGB, straight alpha (alpha = coverage)
  <split>/r_000.exr                RGBA, linear float32, premultiplied
  <split>/r_000_distance.exr       depth as ray distance from the camera centre ("Z", 0 = miss)
  <split>/r_000_zdepth.exr         depth along the optical axis ("Z", 0 = miss)
  <split>/r_000_normal.exr         world-space shading normals ("X", "Y", "Z")
  <split>/r_000_mask.png           8-bit: 255 where the pixel-centre ray hits geometry
  transforms_{train,val,test}.json NeRF-synthetic
  transforms.json                  nerfstudio
  scene.json                       recipe, seed, bounds, needs, variant, versions
  manifest.json                    sha256 of every file above; written last
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core.camera import Intrinsics
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import read_json, sha256_file, write_json
from nerfgauge.core.images import read_exr_single, read_png

SPLITS = ("train", "val", "test")
MANIFEST = "manifest.json"
FRAME_SUFFIXES = {
    "png": ".png",
    "exr": ".exr",
    "distance": "_distance.exr",
    "z_depth": "_zdepth.exr",
    "normals": "_normal.exr",
    "mask": "_mask.png",
}
DEPTH_KINDS = {"distance": "ray_distance", "z": "z_depth"}


def frame_stem(split: str, index: int, count: int) -> str:
    """Extension-less frame path relative to the dataset root, e.g. "train/r_007"."""
    width = max(3, len(str(max(count - 1, 0))))
    return f"{split}/r_{index:0{width}d}"


def frame_files(stem: str) -> dict:
    """{kind: relative path} of every file one frame owns."""
    return {kind: stem + suffix for kind, suffix in FRAME_SUFFIXES.items()}


def synthetic_transforms(intrinsics: Intrinsics, stems, poses) -> dict:
    """transforms_<split>.json in the NeRF-synthetic format (plus w/h/fl_x/... extras)."""
    return {
        "camera_angle_x": intrinsics.camera_angle_x,
        "w": intrinsics.width, "h": intrinsics.height,
        "fl_x": intrinsics.fx, "fl_y": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
        "frames": [{"file_path": "./" + stem, "transform_matrix": np.asarray(pose).tolist(),
                    "depth_file_path": "./" + stem + FRAME_SUFFIXES["distance"],
                    "mask_path": "./" + stem + FRAME_SUFFIXES["mask"]}
                   for stem, pose in zip(stems, poses)],
    }


def nerfstudio_transforms(intrinsics: Intrinsics, split_stems: dict, split_poses: dict) -> dict:
    """transforms.json for nerfstudio. Its depth is z-depth in scene units (nerfstudio
    expects z-depth; pass --depth-unit-scale-factor 1 to its dataparser)."""
    frames, filenames = [], {}
    for split in SPLITS:
        filenames[f"{split}_filenames"] = [stem + ".png" for stem in split_stems[split]]
        for stem, pose in zip(split_stems[split], split_poses[split]):
            frames.append({"file_path": stem + ".png", "transform_matrix": np.asarray(pose).tolist(),
                           "depth_file_path": stem + FRAME_SUFFIXES["z_depth"],
                           "mask_path": stem + FRAME_SUFFIXES["mask"]})
    return {"camera_model": "OPENCV", "fl_x": intrinsics.fx, "fl_y": intrinsics.fy,
            "cx": intrinsics.cx, "cy": intrinsics.cy, "w": intrinsics.width, "h": intrinsics.height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames, **filenames}


def write_manifest(root: Path, relative_paths) -> None:
    """Hash every listed file and write manifest.json: the mark of a complete dataset."""
    files = {rel: sha256_file(root / rel) for rel in sorted(relative_paths)}
    write_json(root / MANIFEST, {"schema": 1, "files": files})


def verify_manifest(root) -> list[str]:
    """Relative paths whose content no longer matches manifest.json (missing counts)."""
    manifest = read_json(Path(root) / MANIFEST)
    return [rel for rel, digest in manifest.get("files", {}).items()
            if not (Path(root) / rel).is_file() or sha256_file(Path(root) / rel) != digest]


# --- reading, for nerf/ and eval/ ---------------------------------------------------


@dataclass(frozen=True)
class SplitCameras:
    """One split: frame stems (relative, extension-less), poses [n, 4, 4], intrinsics."""

    split: str
    stems: tuple
    c2w: np.ndarray
    intrinsics: Intrinsics


def require_complete(root) -> Path:
    """The dataset folder, or an InputError if it is missing or was never finished."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"dataset folder not found: {root}")
    if not (root / MANIFEST).is_file():
        raise InputError(f"dataset {root} is incomplete (no {MANIFEST}); finish it with nerfgauge generate")
    return root


def read_split(root, split: str) -> SplitCameras:
    """Cameras of one split from transforms_<split>.json (NeRF-synthetic, with our extras)."""
    if split not in SPLITS:
        raise InputError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    root = require_complete(root)
    meta = read_json(root / f"transforms_{split}.json")
    try:
        frames = meta["frames"]
        poses = np.array([frame["transform_matrix"] for frame in frames], dtype=np.float64)
        stems = tuple(frame["file_path"].removeprefix("./") for frame in frames)
        width, height = int(meta["w"]), int(meta["h"])
        intrinsics = Intrinsics(width, height, float(meta["fl_x"]), float(meta["fl_y"]),
                                float(meta["cx"]), float(meta["cy"]))
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{root / f'transforms_{split}.json'} is malformed: {error!r}") from None
    if len(frames) and poses.shape[1:] != (4, 4):
        raise InputError(f"transforms_{split}.json: transform_matrix must be 4x4, got {poses.shape[1:]}")
    if not np.isfinite(poses).all():
        bad = sorted({stems[i] for i in np.flatnonzero(~np.isfinite(poses.reshape(len(poses), -1)).all(axis=1))})
        raise InputError(f"{root / f'transforms_{split}.json'}: transform_matrix holds NaN or inf for {', '.join(bad[:3])}")
    return SplitCameras(split, stems, poses.reshape(-1, 4, 4), intrinsics)


def _check_size(array, intrinsics: Intrinsics, path) -> np.ndarray:
    if array.shape[:2] != (intrinsics.height, intrinsics.width):
        raise InputError(f"{path} is {array.shape[1]}x{array.shape[0]}, but the transforms say "
                         f"{intrinsics.width}x{intrinsics.height}")
    return array


def read_rgba(root, stem: str, intrinsics: Intrinsics) -> np.ndarray:
    """The frame's PNG as straight-alpha sRGB in [0, 1]. Returns [H, W, 4] float32."""
    path = Path(root) / (stem + FRAME_SUFFIXES["png"])
    image = _check_size(read_png(path), intrinsics, path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.shape[-1] == 3:
        image = np.concatenate([image, np.ones_like(image[..., :1])], axis=-1)
    return image


def read_depth(root, stem: str, intrinsics: Intrinsics, kind: str = "distance") -> np.ndarray:
    """Ground-truth depth: "distance" (along the ray) or "z" (along the optical axis). [H, W]."""
    if kind not in DEPTH_KINDS:
        raise InputError(f"unknown depth kind {kind!r}; choose distance or z")
    path = Path(root) / (stem + FRAME_SUFFIXES["distance" if kind == "distance" else "z_depth"])
    return _check_size(read_exr_single(path), intrinsics, path)


def read_mask(root, stem: str, intrinsics: Intrinsics) -> np.ndarray:
    """Pixels whose centre ray hits geometry. Returns [H, W] bool."""
    path = Path(root) / (stem + FRAME_SUFFIXES["mask"])
    return _check_size(read_png(path), intrinsics, path) > 0.5


def read_scene_json(root) -> dict:
    return read_json(Path(root) / "scene.json")
