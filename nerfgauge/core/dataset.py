"""The dataset on disk: file names, transforms JSON, manifest, and reading it back.

This module is the dataset convention the other stages import (nerf/ trains from it,
eval/ scores against it). It does not import mitsuba.

Layout of a dataset folder:
  config.json                      what the dataset was made from (recipe, input hashes, versions)
  .nerfgauge.json                  ownership marker (kind, recipe hash); .nerfgauge.lock: the write lock
  meshes/<shape>.ply               ground-truth meshes, world coordinates
  <split>/r_000.png                RGBA, 8-bit sRGB, straight alpha (alpha = coverage)
  <split>/r_000.exr                RGBA, linear float32, premultiplied
  <split>/r_000_distance.exr       depth as ray distance from the camera centre ("Z", 0 = miss)
  <split>/r_000_zdepth.exr         depth along the optical axis ("Z", 0 = miss)
  <split>/r_000_normal.exr         world-space shading normals ("X", "Y", "Z")
  <split>/r_000_mask.png           8-bit: 255 where the pixel-centre ray hits geometry
  <split>/r_000_instance.png       16-bit gray: instance id of the pixel-centre ray's shape (0 = miss;
                                   names in scene.json "instances")
  <split>/r_000_albedo.exr         albedo of the first surface ("R", "G", "B"), linear, box-filtered
  <split>/r_000_noise.json         the view's Monte Carlo noise estimate and spp (docs/conventions.md)
  transforms_{train,val,test}.json NeRF-synthetic
  transforms.json                  nerfstudio
  scene.json                       recipe, seed, bounds, needs, variant, versions, instance
                                   legend, noise per frame and per split, initial points
  images/, sparse/0/               the COLMAP export of the train views (generate/export.py)
  manifest.json                    sha256 and size of every file above; written last

Reading goes through `Dataset` (validated on open, every file confined to the root and
checked against the manifest as it is read; see its docstring for the conventions of the
arrays): `ds.cameras(split)`, `ds.rgba_of(stem, intrinsics)`, `ds.depth_of(...)`,
`ds.mask_of(...)`, `ds.instance_of(...)`, `ds.scene`, or by split and index `ds.image(split,
i)`, `ds.depth(...)`, .... `open_dataset(x)` gives the Dataset for a caller handed a path
or an open Dataset.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import stat
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from nerfgauge.core import bounded, foreign_dataset, images, validate
from nerfgauge.core.camera import Intrinsics, SplitCameras, ThinLens  # SplitCameras: read here, defined with the cameras
from nerfgauge.core.distortion import Distortion
from nerfgauge.core.errors import InputError
from nerfgauge.core.folders import MARKER
from nerfgauge.core.files import atomic_path, json_from_bytes, read_json, sha256_file, write_json
from nerfgauge.core.images import read_colour, read_exr, read_exr_single, read_png

SPLITS = ("train", "val", "test")
SPARSE_VIEWS = "sparse_views.json"  # nested lists of train views (docs/conventions.md, "Extrapolation splits")
MANIFEST = "manifest.json"
MANIFEST_SCHEMA = 2  # {"files": {rel: {"sha256": hex, "bytes": n}}}; schema 1 ({rel: hex}) is still read
FRAME_SUFFIXES = {
    "png": ".png",
    "exr": ".exr",
    "distance": "_distance.exr",
    "z_depth": "_zdepth.exr",
    "normals": "_normal.exr",
    "mask": "_mask.png",
    "instance": "_instance.png",
    "albedo": "_albedo.exr",
    "noise": "_noise.json",
}
# Files a frame of an older dataset may lack (datasets made before instance ids, albedo
# and the noise estimate): readers say so in one line instead of failing the dataset.
OPTIONAL_FRAME_KINDS = ("instance", "albedo", "noise")
DEPTH_KINDS = {"distance": "ray_distance", "z": "z_depth"}
DEPTH_CHANNEL = "Z"  # the one channel of the depth EXRs nerfgauge writes; ground truth must use it (depth_of)
# The largest file a dataset's reader reads without a tighter cap of its own (images have
# the cap their header implies, JSON bounded.MAX_JSON_BYTES): an EXR of the generator's
# largest image (8192 px a side, RGBA float32) stored uncompressed is 1 GiB; meshes are
# far smaller. Checked on the file's size before it is read, as the manifest's size is.
MAX_FILE_BYTES = validate.MAX_DECODED_BYTES + (64 << 20)
IMAGE_SUFFIXES = (".png", ".exr", ".jpg", ".jpeg")


def frame_stem(split: str, index: int, count: int) -> str:
    """Extension-less frame path relative to the dataset root, e.g. "train/r_007"."""
    width = max(3, len(str(max(count - 1, 0))))
    return f"{split}/r_{index:0{width}d}"


def frame_files(stem: str) -> dict:
    """{kind: relative path} of every file one frame owns."""
    return {kind: stem + suffix for kind, suffix in FRAME_SUFFIXES.items()}


def write_instance_png(path, ids: np.ndarray) -> None:
    """ids [H, W] uint16 as a 16-bit grayscale PNG (Pillow mode "I;16"), atomically."""
    if ids.dtype != np.uint16 or ids.ndim != 2:
        raise ValueError(f"instance ids must be [H, W] uint16, got {ids.shape} {ids.dtype}")
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(ids)).save(tmp, format="PNG")


def _lens_entry(lens) -> dict:
    """A frame's "lens" key (camera.ThinLens.to_json), or nothing for a pinhole frame."""
    return {} if lens is None else {"lens": lens.to_json()}


def synthetic_transforms(intrinsics: Intrinsics, stems, poses, lens: Optional[ThinLens] = None,
                         distortion: Optional[Distortion] = None) -> dict:
    """transforms_<split>.json in the NeRF-synthetic format (plus w/h/fl_x/... extras; each
    frame's "lens" when its colour was rendered through a thin lens; the split's lens
    distortion as nerfstudio's camera_model and k1.. keys)."""
    return {
        "camera_angle_x": intrinsics.camera_angle_x,
        "w": intrinsics.width, "h": intrinsics.height,
        "fl_x": intrinsics.fx, "fl_y": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
        **({} if distortion is None else distortion.to_json()),
        "frames": [{"file_path": "./" + stem, "transform_matrix": np.asarray(pose).tolist(),
                    "depth_file_path": "./" + stem + FRAME_SUFFIXES["distance"],
                    "mask_path": "./" + stem + FRAME_SUFFIXES["mask"]} | _lens_entry(lens)
                   for stem, pose in zip(stems, poses)],
    }


NERFBASELINES_INFO = "nb-info.json"
FORWARD_FACING_LAYOUTS = ("forward", "lightfield")  # generate.layouts: cameras looking one way


def nerfbaselines_info(scene: dict) -> dict:
    """nb-info.json: NerfBaselines loads a folder with the loader this names. Without it both
    its nerfstudio and colmap loaders claim our folders (transforms.json and sparse/0) and it
    refuses to choose; its colmap loader would also split our train images by LLFF's every
    8th. Its nerfstudio loader reads transforms.json with our split lists, general
    intrinsics and distortion. Transparent backgrounds composite onto white, as the
    NeRF-synthetic scenes it knows do (its "nerf" evaluation protocol)."""
    transparent = scene["needs"]["background"] == "transparent"
    layout = scene["camera"]["layout"]
    return {"loader": "nerfstudio", "id": "nerfgauge", "scene": scene["recipe"],
            "type": "forward-facing" if layout in FORWARD_FACING_LAYOUTS else "object-centric",
            **({"background_color": [255, 255, 255], "evaluation_protocol": "nerf"} if transparent else {})}


def nerfstudio_transforms(intrinsics: Intrinsics, split_stems: dict, split_poses: dict,
                          split_lenses: Optional[dict] = None, split_distortions: Optional[dict] = None) -> dict:
    """transforms.json for nerfstudio. Its depth is z-depth in scene units (nerfstudio
    expects z-depth; pass --depth-unit-scale-factor 1 to its dataparser). With a lens
    distortion (split_distortions: {split: Distortion or None}) see distorted_transforms."""
    if any((split_distortions or {}).values()):
        return distorted_transforms(intrinsics, split_stems, split_poses, split_lenses, split_distortions)
    frames, filenames = [], {}
    for split in SPLITS:
        filenames[f"{split}_filenames"] = [stem + ".png" for stem in split_stems[split]]
        for stem, pose in zip(split_stems[split], split_poses[split]):
            frames.append({"file_path": stem + ".png", "transform_matrix": np.asarray(pose).tolist(),
                           "depth_file_path": stem + FRAME_SUFFIXES["z_depth"],
                           "mask_path": stem + FRAME_SUFFIXES["mask"]} | _lens_entry((split_lenses or {}).get(split)))
    return {"camera_model": "OPENCV", "fl_x": intrinsics.fx, "fl_y": intrinsics.fy,
            "cx": intrinsics.cx, "cy": intrinsics.cy, "w": intrinsics.width, "h": intrinsics.height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames, **filenames}


def distorted_transforms(intrinsics: Intrinsics, split_stems: dict, split_poses: dict, split_lenses, split_distortions
                         ) -> dict:
    """transforms.json of a dataset with distorted splits. nerfstudio's dataparser reads one
    camera_model for the file and the coefficients per frame when the top level has none:
    - opencv: camera_model OPENCV, every frame its own k1 k2 k3 p1 p2 (0 for pinhole frames,
      which OPENCV with zeros is);
    - fisheye: camera_model OPENCV_FISHEYE cannot state a pinhole frame (a fisheye with
      zeros is the equidistant projection), so the file lists the fisheye frames only, with
      no {split}_filenames (nerfstudio then splits them itself); the pinhole splits are in
      transforms_{split}.json."""
    models = {d.model for d in split_distortions.values() if d is not None}
    if len(models) != 1:
        raise ValueError(f"one distortion model per dataset, got {sorted(models)}")
    model = models.pop()
    frames, filenames = [], {}
    for split in SPLITS:
        distortion = split_distortions.get(split)
        if model == "fisheye" and distortion is None:
            continue
        keys = (distortion or Distortion("opencv")).to_json()
        keys.pop("camera_model")
        if model == "opencv":
            keys.setdefault("k3", 0.0)
        filenames[f"{split}_filenames"] = [stem + ".png" for stem in split_stems[split]]
        for stem, pose in zip(split_stems[split], split_poses[split]):
            frames.append({"file_path": stem + ".png", "transform_matrix": np.asarray(pose).tolist(),
                           "depth_file_path": stem + FRAME_SUFFIXES["z_depth"],
                           "mask_path": stem + FRAME_SUFFIXES["mask"], **keys}
                          | _lens_entry((split_lenses or {}).get(split)))
    out = {"camera_model": "OPENCV" if model == "opencv" else "OPENCV_FISHEYE", "fl_x": intrinsics.fx,
           "fl_y": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy, "w": intrinsics.width,
           "h": intrinsics.height, "frames": frames}
    return out | ({} if model == "fisheye" else filenames)


def write_manifest(root: Path, relative_paths) -> None:
    """Hash every listed file and write manifest.json (schema 2: sha256 and size in bytes):
    the mark of a complete dataset."""
    root = Path(root)
    files = {rel: {"sha256": sha256_file(root / rel), "bytes": (root / rel).stat().st_size}
             for rel in sorted(relative_paths)}
    write_json(root / MANIFEST, {"schema": MANIFEST_SCHEMA, "files": files})


def verify_manifest(root) -> list[str]:
    """Relative paths whose content no longer matches manifest.json (missing, moved out of
    the dataset through a symlink, resized or changed all count). The size is compared on
    the file system first; only a file of the recorded size is hashed, as a stream."""
    root = Path(root)
    real_root = root.resolve()
    changed = []
    for rel, entry in read_manifest(root).items():
        try:
            path = validate.confine(real_root, rel)
            validate.content_size(os.stat(path).st_size, entry, root / rel)
            if sha256_file(path) != entry.sha256:
                changed.append(rel)
        except (InputError, OSError):
            changed.append(rel)
    return changed


def manifest_sha256(root) -> str:
    """sha256 of the dataset's manifest.json: the dataset's identity by content (the
    manifest lists every file's sha256). A run records it (its recipe's dataset_sha256)
    and everything that reads a run with a dataset compares it (nerf.runs)."""
    return sha256_file(Path(root) / MANIFEST)


def read_manifest(root) -> dict:
    """manifest.json -> {relative path: validate.ManifestEntry}; InputError if garbled."""
    root = Path(root)
    validate.confine(root.resolve(), MANIFEST)
    return validate.manifest(read_json(root / MANIFEST, finite=True), root / MANIFEST)


# --- reading, for nerf/ and eval/ ---------------------------------------------------


class Dataset:
    """A dataset folder, validated on open, read one verified file at a time.

        ds = Dataset(root)             # InputError (one line) unless it is complete and sane
        ds.splits                      # ("train", "val", "test") minus splits without frames
        ds.frames("test")              # ("test/r_000", "test/r_001", ...): stems
        ds.intrinsics("test"), ds.K("test"), ds.c2w("test"), ds.bounds, ds.scene
        ds.image("test", 0)            # and image_linear, depth, normals, mask
        ds.instance("test", 0), ds.instance_names(), ds.albedo("test", 0), ds.noise("test", 0)
        ds.manifest_sha256             # sha256 of manifest.json: the dataset's identity (runs record it)

    Conventions (those of nerfgauge.core.camera and of the generator):
    - c2w: [n, 4, 4] float64 camera-to-world, OpenGL/NeRF axes: +X right, +Y up, the camera
      looks along -Z. Rigid: checked on open (nerfgauge.core.validate.pose).
    - K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels; pixel (row i, col j) is sampled by
      the ray through (j + 0.5, i + 0.5), row 0 at the top (camera.pixel_rays).
    - image: [H, W, 4] float32 sRGB in [0, 1], straight alpha (alpha = coverage): the PNG.
      image_linear: [H, W, 4] float32 linear RGB, premultiplied alpha: the EXR.
    - depth: [H, W] float32, 0 = miss. kind="distance": Euclidean distance from the camera
      centre along the pixel-centre ray; kind="z": depth along the optical axis, equal to
      distance * cos(angle between the ray and -Z of c2w).
    - normals: [H, W, 3] float32 world-space unit shading normals, 0 on misses.
    - mask: [H, W] bool, True where the pixel-centre ray hits geometry (== depth > 0).
    - instance: [H, W] int64 id of the shape the pixel-centre ray hits, 0 = miss (so
      instance > 0 == mask); instance_names() {id: shape name} from scene.json.
    - albedo: [H, W, 3] float32 linear, box-filtered, 0 where samples miss.
    - noise: the frame's Monte Carlo noise estimate (docs/conventions.md, "Noise").
    Datasets made before instance ids, albedo and noise lack those files
    (`manifest_files` says which are there; reading a missing one is an InputError).

    A frame (file_path) may appear only once in the whole dataset: twice in a split, or in
    two splits (a test view that is also a training view), is refused on open
    (validate.distinct_frames).

    Every file is read through one path: its name is confined to the root (no absolute
    paths or `..`; symlinks resolved and required to stay inside), it must be listed in
    manifest.json, it must be a regular file whose size (fstat, before anything is read)
    matches the manifest's (schema 2) and is within a stated cap (MAX_FILE_BYTES; JSON
    bounded.MAX_JSON_BYTES; an image what its header's pixels can take), and its sha256 is
    computed over the bytes read for decoding (verify_hashes=False skips only the hash).
    Images are checked before decoding: signature, size at most validate.MAX_IMAGE_SIDE a
    side, size equal to the transforms' w and h. Each split's camera is checked by
    validate.camera, as a foreign folder's is.
    """

    def __init__(self, root, *, verify_hashes: bool = True):
        self.root = Path(root)
        self.verify_hashes = verify_hashes
        if not self.root.is_dir():
            raise InputError(f"dataset folder not found: {self.root}")
        self._real_root = self.root.resolve()
        self.foreign = None  # a foreign_dataset.ForeignLayout for folders nerfgauge did not write
        self._exact_poses = {}  # split -> [n, 4, 4] where frames record exact_transform_matrix (pose noise)
        self.files_read = {}  # foreign folders: {relative path: sha256} of every file read
        if not (self.root / MANIFEST).is_file():
            fmt = None if (self.root / MARKER).exists() else foreign_dataset.detect(self.root)
            if fmt is None:
                raise InputError(f"dataset {self.root} is incomplete (no {MANIFEST}); finish it with nerfgauge generate"
                                 + ("" if (self.root / MARKER).exists() else
                                    " (or give a NeRF-synthetic, nerfstudio or COLMAP text-model folder)"))
            self._manifest = None
            self.foreign = foreign_dataset.read(self, fmt)
            self._cameras = {split: cams for split, cams in self.foreign.cameras.items()}
            validate.distinct_frames({split: cameras.stems for split, cameras in self._cameras.items()}, self.root)
            self.manifest_sha256 = None
            self.scene, self.bounds = {}, None
            return
        self._manifest = read_manifest(self.root)
        self._cameras = {}
        for split in SPLITS:
            name = f"transforms_{split}.json"
            if name in self._manifest or (self.root / name).exists():
                self._cameras[split] = self._read_transforms(split, name)
        if not self._cameras:
            raise InputError(f"dataset {self.root} has no transforms_<split>.json for any of {', '.join(SPLITS)}")
        validate.distinct_frames({split: cameras.stems for split, cameras in self._cameras.items()}, self.root)
        self.manifest_sha256 = manifest_sha256(self.root)
        has_scene = "scene.json" in self._manifest or (self.root / "scene.json").exists()
        self.scene = self._read_json("scene.json", finite=True) if has_scene else {}
        bounds = self.scene.get("bounds")
        self.bounds = None if bounds is None else validate.bounds(bounds, str(self.root / "scene.json"))
        validate.needs(self.scene.get("needs"), str(self.root / "scene.json"))

    # --- files --------------------------------------------------------------------------

    def read_bytes(self, rel: str, what: str = "", limit=MAX_FILE_BYTES) -> bytes:
        """The bytes of the dataset file `rel` (relative POSIX path), confined to the root
        and checked against the manifest. what: the frame, named in errors. limit: the most
        bytes read, or a function of the open file (bounded.read_bytes). The file's size
        is compared with the manifest's record, then with `limit`, on the file system
        before anything is read: a file that grew to gigabytes is refused unread."""
        label = f"{what}: " if what else ""
        rel = validate.relative_path(rel, f"{label}{rel!r} in dataset {self.root}")
        path = validate.confine(self._real_root, rel, what)
        shown = self.root / rel
        entry = None
        if self._manifest is not None:
            entry = self._manifest.get(rel)
            if entry is None:
                raise InputError(f"{label}{shown} is not listed in {self.root / MANIFEST}")
            if not path.exists():
                raise InputError(f"{label}{shown} is listed in {MANIFEST} but missing")

        def checked(handle, size: int) -> int:
            if entry is not None:
                validate.content_size(size, entry, shown)
            return limit(handle, size) if callable(limit) else limit

        try:
            data = bounded.read_bytes(path, checked, "dataset file")
        except InputError as error:
            message = str(error)
            raise InputError(message if message.startswith(label) else label + message) from None
        if entry is None:  # a foreign folder: no manifest to check against; hashed as read
            self.files_read[rel] = hashlib.sha256(data).hexdigest()
        else:
            validate.content(data, entry, shown, self.verify_hashes)
        return data

    def check_sizes(self, prefix: str) -> None:
        """Every manifest file whose path starts with `prefix` (e.g. "test/") has the size the
        manifest recorded, asked of the file system, nothing read: a command refuses a
        changed file before its slow work (loading LPIPS, say), not at the frame that reads
        it. Each read still checks its open file (read_bytes). Missing files and links out of
        the dataset are left to the read, which names the frame; a foreign folder has no
        manifest to check."""
        if self._manifest is None:
            return
        for rel, entry in self._manifest.items():
            if rel.startswith(prefix) and entry.size is not None:
                try:
                    status = validate.confine(self._real_root, rel).stat()
                except (FileNotFoundError, InputError):  # missing or leading outside: the read names the frame
                    continue
                if stat.S_ISREG(status.st_mode):  # a FIFO or device: the read refuses it, saying what it is
                    validate.content_size(status.st_size, entry, self.root / rel)

    def _read_json(self, rel: str, finite: bool) -> dict:
        data = self.read_bytes(rel, limit=bounded.MAX_JSON_BYTES)
        return json_from_bytes(data, self.root / rel, finite=finite)  # the bytes verified

    def _read_transforms(self, split: str, name: str) -> SplitCameras:
        where = str(self.root / name)
        meta = self._read_json(name, finite=False)  # NaN in a pose is refused naming the frame
        frames = meta.get("frames")
        if not isinstance(frames, list) or not all(isinstance(frame, dict) for frame in frames):
            raise InputError(f"{where}: 'frames' must be a list of objects")
        intrinsics, distortion = validate.camera(meta, frames, where)  # the same checks as foreign folders'
        stems, poses, lenses, exact = [], [], [], []
        for k, frame in enumerate(frames):
            if "file_path" not in frame or "transform_matrix" not in frame:
                raise InputError(f"{where}: frame {k} needs file_path and transform_matrix")
            stem = validate.relative_path(frame["file_path"], f"{where}: frame {k} file_path")
            for key in ("depth_file_path", "mask_path"):
                if key in frame:
                    validate.relative_path(frame[key], f"{where}: frame {stem} {key}")
            stems.append(stem)
            poses.append(validate.pose(frame["transform_matrix"], stem, where))
            lenses.append(ThinLens.from_json(frame["lens"], f"{where}: frame {stem}") if "lens" in frame else None)
            exact.append(validate.pose(frame["exact_transform_matrix"], stem, where) if "exact_transform_matrix" in frame
                         else poses[-1])
        c2w = np.stack(poses) if poses else np.zeros((0, 4, 4))
        c2w.flags.writeable = False  # shared by every caller of cameras(split)
        if any("exact_transform_matrix" in frame for frame in frames):
            self._exact_poses[split] = np.stack(exact)
            self._exact_poses[split].flags.writeable = False
        return SplitCameras(split, tuple(stems), c2w, intrinsics, tuple(lenses) if any(lenses) else (), distortion)

    def frame_file(self, stem: str, kind: str, decode, expected_size=None):
        """decode(path, verified bytes) of the frame's file of `kind` (a FRAME_SUFFIXES
        key); errors name the frame. An image's header is checked (its size against
        `expected_size`, Intrinsics or (width, height)) and its size on disk against what
        that header's pixels can take before it is read (nerfgauge.core.images); other
        files are bounded by bounded.MAX_JSON_BYTES."""
        rel = stem + FRAME_SUFFIXES[kind]
        if self.foreign is not None:
            rel = self.foreign.images.get(stem) if kind == "png" else None
            if rel is None:
                raise InputError(f"frame {stem}: the {self.foreign.format} folder {self.root} has no {kind} file "
                                 f"({self.unavailable_reason(kind)})")
        is_image = Path(rel).suffix.lower() in IMAGE_SUFFIXES
        limit = images.file_limit(self.root / rel, expected_size) if is_image else bounded.MAX_JSON_BYTES
        data = self.read_bytes(rel, f"frame {stem}", limit)
        try:
            return decode(self.root / rel, data)
        except InputError as error:
            raise InputError(f"frame {stem}: {error}") from None

    # --- cameras ------------------------------------------------------------------------

    def cameras(self, split: str) -> SplitCameras:
        """Stems, poses and intrinsics of `split` (empty for a split the dataset lacks)."""
        if split not in SPLITS:
            raise InputError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
        if split not in self._cameras:
            any_split = next(iter(self._cameras.values()))
            return SplitCameras(split, (), np.zeros((0, 4, 4)), any_split.intrinsics)
        return self._cameras[split]

    def exact_cameras(self, split: str) -> SplitCameras:
        """cameras(split) with the poses its images, depth and normals were rendered from:
        the frames' exact_transform_matrix in a dataset with pose noise (docs/conventions.md,
        "Degradations"; its transform_matrix is then perturbed), else cameras(split) itself.
        Ground-truth geometry (visibility, co-visibility) pairs depth maps with these."""
        cameras = self.cameras(split)
        exact = self._exact_poses.get(split)
        return cameras if exact is None else dataclasses.replace(cameras, c2w=exact)

    @property
    def splits(self) -> tuple:
        return tuple(split for split in SPLITS if self.cameras(split).stems)

    def sparse_train_views(self, count: int) -> list:
        """The train frame indices of the dataset's sparse list of `count` views (SPARSE_VIEWS,
        nested lists by farthest-point sampling on the camera centres; generate.holdout writes
        it), checked; one line when absent or damaged."""
        where = self.root / SPARSE_VIEWS
        if SPARSE_VIEWS not in self.manifest_files:
            raise InputError(f"{self.root} has no {SPARSE_VIEWS} (datasets generated before the sparse view lists "
                             f"have none); regenerate it to train on --sparse {count}")
        document = self._read_json(SPARSE_VIEWS, finite=True)
        lists = document.get("counts") if isinstance(document, dict) else None
        n_train = len(self.cameras("train").stems)
        if not isinstance(lists, dict) or str(count) not in lists:
            have = ", ".join(sorted(lists, key=lambda k: (len(k), k))) if isinstance(lists, dict) else "none"
            raise InputError(f"{where} has no list of {count} views (it has: {have})")
        indices = lists[str(count)]
        if (not isinstance(indices, list) or len(indices) != count or len(set(indices)) != count
                or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n_train for i in indices)):
            raise InputError(f"{where}: list {count} must be {count} distinct train frame indices below {n_train}")
        return indices

    def frames(self, split: str) -> tuple:
        return self.cameras(split).stems

    def intrinsics(self, split: str) -> Intrinsics:
        return self.cameras(split).intrinsics

    def K(self, split: str) -> np.ndarray:
        """[3, 3] float64 pinhole matrix in pixels."""
        i = self.intrinsics(split)
        return np.array([[i.fx, 0.0, i.cx], [0.0, i.fy, i.cy], [0.0, 0.0, 1.0]])

    def c2w(self, split: str) -> np.ndarray:
        """[n, 4, 4] float64 camera-to-world, OpenGL axes (a copy)."""
        return self.cameras(split).c2w.copy()

    # --- frames by stem (the index-based readers below call these) ---------------------

    def rgba_of(self, stem: str, intrinsics: Intrinsics) -> np.ndarray:
        """The frame's PNG (a foreign folder's PNG or JPEG) as straight-alpha sRGB in [0, 1];
        an image without alpha gets alpha 1. Returns [H, W, 4] float32."""
        image = self.frame_file(stem, "png", lambda path, data: read_colour(path, data, intrinsics), intrinsics)
        if image.ndim == 2:
            image = image[..., None]
        if image.shape[-1] in (1, 2):  # gray (+ alpha)
            image = np.concatenate([np.repeat(image[..., :1], 3, axis=-1), image[..., 1:]], axis=-1)
        if image.shape[-1] == 3:
            image = np.concatenate([image, np.ones_like(image[..., :1])], axis=-1)
        return image

    def depth_of(self, stem: str, intrinsics: Intrinsics, kind: str = "distance") -> np.ndarray:
        """Ground-truth depth: "distance" (along the ray) or "z" (along the optical axis). [H, W]."""
        if kind not in DEPTH_KINDS:
            raise InputError(f"unknown depth kind {kind!r}; choose distance or z")
        def decode(path, data):
            depth = read_exr_single(path, data, intrinsics, name=DEPTH_CHANNEL)
            # the convention is finite and >= 0 (0 = miss): NaN or inf would reach every
            # unprojection (co-visibility, geometry) as points at infinity
            bad = ~np.isfinite(depth) | (depth < 0)
            if bad.any():
                raise InputError(f"{path}: ground-truth depth holds {int(bad.sum())} NaN, inf or negative values; "
                                 "a nerfgauge depth is finite and >= 0 (0 = miss)")
            return depth

        return self.frame_file(stem, "distance" if kind == "distance" else "z_depth", decode, intrinsics)

    def mask_of(self, stem: str, intrinsics: Intrinsics) -> np.ndarray:
        """Pixels whose centre ray hits geometry. Returns [H, W] bool."""
        mask = self.frame_file(stem, "mask", lambda path, data: read_png(path, data, intrinsics), intrinsics)
        return (mask if mask.ndim == 2 else mask[..., 0]) > 0.5

    def instance_of(self, stem: str, intrinsics: Intrinsics) -> np.ndarray:
        """The frame's 16-bit instance PNG as integer ids. Returns [H, W] int64."""
        ids = self.frame_file(stem, "instance", lambda path, data: read_png(path, data, intrinsics), intrinsics)
        if ids.ndim != 2:
            raise InputError(f"frame {stem}: instance image must be one 16-bit channel, got shape {ids.shape}")
        return np.rint(ids.astype(np.float64) * 65535.0).astype(np.int64)

    # --- frames by split and index ------------------------------------------------------

    def _stem(self, split: str, index: int) -> str:
        return self.frames(split)[index]

    def image(self, split: str, index: int) -> np.ndarray:
        """[H, W, 4] float32 straight-alpha sRGB in [0, 1] (the PNG)."""
        return self.rgba_of(self._stem(split, index), self.intrinsics(split))

    def image_linear(self, split: str, index: int) -> np.ndarray:
        """[H, W, 4] float32 linear premultiplied RGBA (the EXR)."""
        def decode(path, data):
            channels, _ = read_exr(path, data, self.intrinsics(split))
            if "RGBA" in channels:
                return channels["RGBA"]
            if set("RGBA") <= set(channels):
                return np.stack([channels[c] for c in "RGBA"], axis=-1)
            raise InputError(f"{path} has no RGBA channels (has {sorted(channels)})")

        return self.frame_file(self._stem(split, index), "exr", decode, self.intrinsics(split))

    def depth(self, split: str, index: int, kind: str = "distance") -> np.ndarray:
        """[H, W] float32, 0 = miss; kind "distance" (along the ray) or "z" (optical axis)."""
        return self.depth_of(self._stem(split, index), self.intrinsics(split), kind)

    def normals(self, split: str, index: int) -> np.ndarray:
        """[H, W, 3] float32 world-space normals, 0 on misses."""
        def decode(path, data):
            channels, _ = read_exr(path, data, self.intrinsics(split))
            if not set("XYZ") <= set(channels):
                raise InputError(f"{path} has no X, Y, Z channels (has {sorted(channels)})")
            return np.stack([channels[c] for c in "XYZ"], axis=-1)

        return self.frame_file(self._stem(split, index), "normals", decode, self.intrinsics(split))

    def mask(self, split: str, index: int) -> np.ndarray:
        """[H, W] bool: the pixel-centre ray hits geometry."""
        return self.mask_of(self._stem(split, index), self.intrinsics(split))

    @property
    def manifest_files(self) -> frozenset:
        """Relative paths manifest.json lists (older datasets have no instance, albedo or
        noise files: ask before reading them). A foreign folder: its frames' images."""
        if self._manifest is None:
            return frozenset(self.foreign.images.values())
        return frozenset(self._manifest)

    def file_sha256(self, rel: str) -> Optional[str]:
        """The sha256 manifest.json records for the dataset file `rel` (None: not listed);
        in a foreign folder, the sha256 of the file as read (None: not read)."""
        if self._manifest is None:
            return self.files_read.get(rel)
        entry = self._manifest.get(rel)
        return None if entry is None else entry.sha256

    def has_frame_file(self, split: str, index: int, kind: str) -> bool:
        """Whether the manifest lists the frame's file of `kind` (a FRAME_SUFFIXES key)."""
        if self._manifest is None:
            return kind == "png"
        return self._stem(split, index) + FRAME_SUFFIXES[kind] in self._manifest

    def has(self, what: str) -> bool:
        """Whether the dataset gives `what` ("depth", "masks", "noise_ceiling",
        "covisibility", "instances", "meshes"): ours do; foreign folders do not
        (`unavailable_reason`)."""
        return self.foreign is None or what not in self.foreign.unavailable

    def unavailable_reason(self, what: str) -> str:
        """Why a foreign folder cannot give `what` (a FRAME_SUFFIXES kind or a `has` key)."""
        if self.foreign is None:
            return ""
        key = {"distance": "depth", "z_depth": "depth", "mask": "masks", "noise": "noise_ceiling",
               "instance": "instances"}.get(what, what)
        return self.foreign.unavailable.get(key, f"{self.foreign.format} folders have none")

    def ground_truth_record(self) -> dict:
        """What the metrics document records of the ground truth: ours, the manifest's
        sha256; a foreign folder, its format, split rule, and the sha256 of every file read
        (call after scoring, so the images are among them) with each frame's image."""
        if self.foreign is None:
            return {"format": "nerfgauge", "manifest_sha256": self.manifest_sha256}
        return {"format": self.foreign.format, "split_rule": self.foreign.split_rule,
                "files": dict(sorted(self.files_read.items())), "frames": dict(self.foreign.images),
                "unavailable": dict(self.foreign.unavailable)}

    def instance(self, split: str, index: int) -> np.ndarray:
        """[H, W] int64 instance ids of the pixel-centre rays' shapes, 0 = miss (the hit
        mask is exactly instance > 0); names in instance_names()."""
        return self.instance_of(self._stem(split, index), self.intrinsics(split))

    def instance_names(self) -> dict:
        """{id: shape name} from scene.json's "instances" legend ({} if it has none)."""
        legend = self.scene.get("instances", {}).get("names", [])
        if not isinstance(legend, list) or not all(isinstance(name, str) for name in legend):
            raise InputError(f"{self.root / 'scene.json'}: instances.names must be a list of shape names")
        return {number: name for number, name in enumerate(legend, start=1)}

    def albedo(self, split: str, index: int) -> np.ndarray:
        """[H, W, 3] float32 linear albedo of the first surface, box-filtered over the pixel
        like the RGBA (0 where samples miss)."""
        def decode(path, data):
            channels, _ = read_exr(path, data, self.intrinsics(split))
            if "RGB" in channels:  # OpenEXR's binding groups R, G, B on reading
                return channels["RGB"]
            if not set("RGB") <= set(channels):
                raise InputError(f"{path} has no R, G, B channels (has {sorted(channels)})")
            return np.stack([channels[c] for c in "RGB"], axis=-1)

        return self.frame_file(self._stem(split, index), "albedo", decode, self.intrinsics(split))

    def noise(self, split: str, index: int) -> dict:
        """The frame's noise estimate (docs/conventions.md, "Noise"): spp, passes,
        noise_psnr {linear, srgb_white, srgb_black} and psnr_ceiling {white, black} in dB,
        or None for both with a `reason` (spp 1)."""
        stem = self._stem(split, index)
        return self.frame_file(stem, "noise", lambda path, data: json_from_bytes(data, path, finite=True))


def open_dataset(root) -> Dataset:
    """`root` itself if it is a Dataset already, else Dataset(root): the one adapter for
    callers that are handed either; everything else reads through Dataset's methods."""
    return root if isinstance(root, Dataset) else Dataset(root)
