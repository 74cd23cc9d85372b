"""Non-learned baselines (nearest view, two-plane light field, refocus), rendered into a
prediction folder: `nerfgauge baseline`.

    nerfgauge baseline DATASET --method METHOD --out DIR [--split test] [--evaluate]

Each method writes DIR/<split>/r_007.png (RGBA, 8-bit sRGB, straight alpha: the dataset's
own format) for every frame of the split, and DIR/timing.json; `nerfgauge evaluate DATASET
--pred DIR` scores them like any other method's renders. Colour only: no depth files.

- `nearest`: the training image whose camera is closest to the query camera under

      D = |c_q - c_k| / L + (1 - cos angle(f_q, f_k))

  c: camera centres, f: viewing directions (-Z of camera-to-world), L: the diagonal of the
  scene's AABB. The first term is a position offset in scene sizes, the second is 0 for the
  same direction and 2 for opposite ones, so a view turned by 60 degrees weighs like a
  camera moved half the scene's diagonal. The training view is copied unchanged (its
  depth would be wrong for another pose, so none is written).
- `lightfield-nearest`, `lightfield-quadrilinear`: the two-plane light field L(s, t, u, v)
  of a dataset made with `--layout lightfield` (plane in scene.json camera.lightfield).
  Each query ray meets the camera plane at (s, t) (grid units: node (i, j) is training
  camera row i along t_axis, column j along s_axis) and the focal plane, which is parallel
  to it at focal_plane_distance along view_axis, at a point F. The (u, v) of F in training
  camera k is F projected with the camera module's intrinsics, pixel centres at +0.5.
  nearest: the nearest grid camera, and its nearest pixel to F. quadrilinear: bilinear in
  (s, t) over the 4 surrounding cameras times bilinear in (u, v) over the 4 pixels around
  F in each: 16 samples. Samples are premultiplied RGBA in linear light (the PNG's sRGB
  decoded), so interpolation never mixes in the colour of transparent pixels and mixes
  radiance as a sensor or a lens does; the result is encoded back to sRGB. (s, t) beyond
  the grid and (u, v) beyond an image are clamped to the edge.
- `refocus`: synthetic-aperture refocusing (shift and add) over the same camera grid. A
  frame with a thin lens (aperture radius A, focus distance D; docs/conventions.md) is
  the mean over `samples` stratified lens points l (camera.lens_samples, seeded) of the
  light field along the thin-lens ray from l through the pixel's focus point P (on the
  plane z = -D of the query camera): the ray meets the camera plane at (s, t), and each of
  the 4 grid cameras around (s, t) is read bilinearly at its projection of P, weighted
  bilinearly in (s, t). For a query on the camera plane this is a light field's classic
  shift-and-add refocusing: every grid view shifted so that the plane in focus lines up, averaged
  with the weight of its cell's overlap with the aperture disc. Points on the plane in
  focus come out sharp, others blur by the thin-lens circle of confusion (sampled by the
  camera grid's spacing). Aperture 0 is view interpolation focused at D; a frame without
  a lens is refocused with aperture 0 at the light field's own focal plane. The mean over
  the lens is taken in linear light, as the ground truth's thin lens integrates radiance
  (docs/conventions.md, "Pixel footprint"): a dot blurred by a mean of sRGB values keeps
  a quarter of its light (tests/test_refocus.py).
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np

from nerfgauge.core import dataset, owned
from nerfgauge.core.camera import ThinLens, camera_directions, lens_samples, pixel_rays, thin_lens_rays
from nerfgauge.core.errors import InputError
from nerfgauge.core.files import write_json
from nerfgauge.core.folders import claim_folder, recipe_hash, remove_owned
from nerfgauge.core.images import linear_to_srgb, srgb_to_linear, write_png

METHODS = ("nearest", "lightfield-nearest", "lightfield-quadrilinear", "refocus")
REFOCUS_SAMPLES = 64  # lens samples per pixel of the refocus baseline
GRID_TOLERANCE = 1e-6  # training cameras must sit on grid nodes to this fraction of a cell


def _png_rgba_uint8(ds: dataset.Dataset, stem: str, intrinsics) -> np.ndarray:
    """The frame's PNG as RGBA uint8 [H, W, 4] (exactly as stored, alpha added if absent)."""
    rgba = ds.rgba_of(stem, intrinsics)  # checks the size
    return np.round(rgba * 255.0).astype(np.uint8)


# --- nearest view ------------------------------------------------------------------------


def pose_distance(query_c2w: np.ndarray, train_c2w: np.ndarray, scale: float) -> np.ndarray:
    """D = |c_q - c_k| / scale + (1 - f_q . f_k). query_c2w: [Q, 4, 4], train_c2w: [K, 4, 4].

    Returns [Q, K].
    """
    offset = query_c2w[:, None, :3, 3] - train_c2w[None, :, :3, 3]  # [Q, K, 3]
    forward_q = -query_c2w[:, :3, 2] / np.linalg.norm(query_c2w[:, :3, 2], axis=-1, keepdims=True)  # [Q, 3]
    forward_k = -train_c2w[:, :3, 2] / np.linalg.norm(train_c2w[:, :3, 2], axis=-1, keepdims=True)  # [K, 3]
    return np.linalg.norm(offset, axis=-1) / scale + (1.0 - forward_q @ forward_k.T)


def nearest_views(query_c2w: np.ndarray, train_c2w: np.ndarray, scale: float) -> np.ndarray:
    """argmin over k of pose_distance for each query: [Q] int. The queries are taken in
    blocks of POSE_PAIRS / K, so memory (~40 B a pair) does not grow with Q x K."""
    block = max(1, POSE_PAIRS // max(1, len(train_c2w)))
    return np.concatenate([np.argmin(pose_distance(query_c2w[start:start + block], train_c2w, scale), axis=1)
                           for start in range(0, len(query_c2w), block)] or [np.zeros(0, np.int64)])


POSE_PAIRS = 1 << 20  # (query, train) camera pairs compared at once


def scene_scale(root) -> float:
    """Diagonal of the AABB from scene.json's bounds (finite, min < max: checked on open).
    root: a dataset folder or an open Dataset (as for every function here)."""
    ds = dataset.open_dataset(root)
    if ds.bounds is None:
        raise InputError(f"{ds.root / 'scene.json'}: no 'bounds' [[x, y, z], [x, y, z]]; the nearest baseline needs the scene's size")
    return float(np.linalg.norm(ds.bounds[1] - ds.bounds[0]))


def render_nearest(root, split: str) -> dict:
    """{stem: RGBA uint8 [H, W, 4]}: each query frame's nearest training image."""
    ds = dataset.open_dataset(root)
    train, query = ds.cameras("train"), ds.cameras(split)
    if not train.stems:
        raise InputError(f"dataset {ds.root} has no training views to copy")
    nearest = nearest_views(query.c2w, train.c2w, scene_scale(ds))  # [Q]
    return {stem: _png_rgba_uint8(ds, train.stems[k], train.intrinsics) for stem, k in zip(query.stems, nearest)}


# --- two-plane light field ----------------------------------------------------------------


class LightField:
    """The training grid of a light-field dataset: premultiplied images and cameras by node."""

    def __init__(self, root, needed_by: str = "the lightfield baselines"):
        ds = dataset.open_dataset(root)
        root = ds.root
        camera = ds.scene.get("camera", {})
        plane = camera.get("lightfield") if isinstance(camera, dict) else None
        if not plane:
            raise InputError(f"dataset {root} is not a camera array: it was not made with --layout lightfield "
                             f"(camera.layout is {camera.get('layout') if isinstance(camera, dict) else None!r}); "
                             f"{needed_by} need its camera grid")
        try:
            self.origin = np.asarray(plane["camera_plane_origin"], np.float64)  # [3]
            self.axes = np.stack([np.asarray(plane[k], np.float64) for k in ("s_axis", "t_axis", "view_axis")])
            self.spacing = np.asarray(plane["spacing"], np.float64)  # [2]: s, t
            self.rows, self.cols = (int(n) for n in plane["grid"])
            self.focal_distance = float(plane["focal_plane_distance"])
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(f"{root / 'scene.json'}: camera.lightfield is malformed: {error!r}") from None
        train = ds.cameras("train")
        if train.distortion is not None:
            raise InputError(f"dataset {root}: {needed_by} resample pinhole training images, and its train views are "
                             f"distorted ({train.distortion.to_text()})")
        self.intrinsics = train.intrinsics
        if min(self.intrinsics.width, self.intrinsics.height) < 2 or min(self.rows, self.cols) < 2:
            raise InputError("the light field needs a grid of at least 2x2 cameras and images of at least 2x2 pixels")
        node = self.plane_coordinates(train.c2w[:, :3, 3])  # [K, 2]: (s, t)
        index = np.round(node).astype(int)
        on_grid = np.all(np.abs(node - index) < GRID_TOLERANCE, axis=1) & np.all(
            (index >= 0) & (index < [self.cols, self.rows]), axis=1)
        if not on_grid.all() or len(set(map(tuple, index))) != self.rows * self.cols or len(index) != self.rows * self.cols:
            raise InputError(f"the {len(index)} training cameras of {root} do not fill the {self.rows}x{self.cols} "
                             "grid of camera.lightfield one per node")
        order = np.argsort(index[:, 1] * self.cols + index[:, 0])  # row-major (t, s)
        self.c2w = train.c2w[order]  # [rows * cols, 4, 4]
        self.images = np.stack([_png_rgba_uint8(ds, train.stems[k], self.intrinsics) for k in order])  # [K, H, W, 4]

    def plane_coordinates(self, points: np.ndarray) -> np.ndarray:
        """Points on the camera plane -> (s, t) in grid units. points: [..., 3]. Returns [..., 2]."""
        rel = points - self.origin
        return np.stack([rel @ self.axes[0] / self.spacing[0], rel @ self.axes[1] / self.spacing[1]], axis=-1)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays [P, 3] -> (s, t) on the camera plane [P, 2] and the focal-plane point F [P, 3]."""
        normal = self.axes[2]
        cosine = directions @ normal  # [P]
        if np.any(np.abs(cosine) < 1e-12):
            raise InputError("a query ray runs parallel to the light field's planes")
        to_camera_plane = ((self.origin - origins) @ normal) / cosine  # [P]
        st = self.plane_coordinates(origins + to_camera_plane[:, None] * directions)
        to_focal_plane = ((self.origin + self.focal_distance * normal - origins) @ normal) / cosine  # [P]
        return st, origins + to_focal_plane[:, None] * directions

    def project(self, camera: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Continuous (col, row) pixel indices of points in grid cameras (centre of pixel j at j).

        camera: [P] flat grid index, points: [P, 3]. Returns [P, 2].
        """
        c2w = self.c2w[camera]  # [P, 4, 4]
        local = np.einsum("pji,pj->pi", c2w[:, :3, :3], points - c2w[:, :3, 3])  # R^T (F - C), [P, 3]
        depth = np.maximum(-local[:, 2], 1e-12)  # in front of the camera: -z > 0
        k = self.intrinsics
        u = k.fx * local[:, 0] / depth + k.cx  # image x of pixel centres is col + 0.5
        v = k.cy - k.fy * local[:, 1] / depth
        return np.stack([u - 0.5, v - 0.5], axis=-1)

    def sample(self, camera: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Premultiplied RGBA in [0, 1], colour in linear light, at integer pixels (clamped).
        All [P]. Returns [P, 4]."""
        col = np.clip(col, 0, self.intrinsics.width - 1)
        row = np.clip(row, 0, self.intrinsics.height - 1)
        rgba = self.images[camera, row, col].astype(np.float64) / 255.0  # [P, 4]
        return np.concatenate([srgb_to_linear(rgba[:, :3]) * rgba[:, 3:], rgba[:, 3:]], axis=-1)

    def render(self, c2w: np.ndarray, mode: str) -> np.ndarray:
        """Straight-alpha RGBA [H, W, 4] in [0, 1] seen by camera c2w [4, 4]; mode nearest|quadrilinear."""
        k = self.intrinsics
        origins, directions = pixel_rays(c2w, k)  # [H, W, 3] each
        st, focal = self.intersect(origins.reshape(-1, 3), directions.reshape(-1, 3))  # [P, 2], [P, 3]
        if mode == "nearest":
            s = np.clip(np.floor(st[:, 0] + 0.5), 0, self.cols - 1).astype(int)
            t = np.clip(np.floor(st[:, 1] + 0.5), 0, self.rows - 1).astype(int)
            camera = t * self.cols + s  # [P]
            pixel = np.floor(self.project(camera, focal) + 0.5).astype(int)  # [P, 2]
            premultiplied = self.sample(camera, pixel[:, 0], pixel[:, 1])  # [P, 4]
        elif mode == "quadrilinear":
            premultiplied = self.quadrilinear(st, focal)
        else:
            raise InputError(f"unknown light-field mode {mode!r}; choose nearest or quadrilinear")
        return _unpremultiply(premultiplied).reshape(k.height, k.width, 4)

    def quadrilinear(self, st: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Premultiplied RGBA [P, 4]: bilinear in (s, t) [P, 2] over the 4 grid cameras
        around it, each read bilinearly at its projection of `points` [P, 3]."""
        k = self.intrinsics
        base, frac = _cell(st, [self.cols, self.rows])  # [P, 2] each
        premultiplied = np.zeros((len(st), 4))
        for ds, dt in ((0, 0), (1, 0), (0, 1), (1, 1)):
            w_st = (frac[:, 0] if ds else 1 - frac[:, 0]) * (frac[:, 1] if dt else 1 - frac[:, 1])  # [P]
            camera = (base[:, 1] + dt) * self.cols + base[:, 0] + ds  # [P]
            pbase, pfrac = _cell(self.project(camera, points), [k.width, k.height])  # [P, 2] each
            for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
                w_uv = (pfrac[:, 0] if dc else 1 - pfrac[:, 0]) * (pfrac[:, 1] if dr else 1 - pfrac[:, 1])
                premultiplied += (w_st * w_uv)[:, None] * self.sample(camera, pbase[:, 0] + dc, pbase[:, 1] + dr)
        return premultiplied

    def refocus(self, c2w: np.ndarray, lens: ThinLens, samples: int = REFOCUS_SAMPLES, seed=0) -> np.ndarray:
        """Straight-alpha RGBA [H, W, 4] in [0, 1] of camera c2w [4, 4] through `lens`, by
        synthetic-aperture refocusing (module docstring) over `samples` lens points."""
        k = self.intrinsics
        focus = (lens.focus_distance * camera_directions(k) @ np.asarray(c2w)[:3, :3].T + np.asarray(c2w)[:3, 3])
        focus = focus.reshape(-1, 3)  # [P, 3]: where each pixel's lens rays meet
        disk = lens_samples(1 if lens.is_pinhole else samples, seed)  # [S, 2]
        premultiplied = np.zeros((len(focus), 4))
        for point in disk:  # one lens sample's rays at a time: [S, H, W, 3] at once grows with S x pixels
            origins, directions = thin_lens_rays(c2w, k, lens, point[None])  # [1, H, W, 3] each
            st, _ = self.intersect(origins.reshape(-1, 3), directions.reshape(-1, 3))
            premultiplied += self.quadrilinear(st, focus)
        return _unpremultiply(premultiplied / len(disk)).reshape(k.height, k.width, 4)


def _unpremultiply(premultiplied: np.ndarray) -> np.ndarray:
    """Premultiplied RGBA [P, 4], colour in linear light -> straight RGBA [P, 4] with sRGB
    colour, clipped to [0, 1] (colour 0 where alpha is 0)."""
    alpha = premultiplied[:, 3:]  # [P, 1]
    rgb = np.divide(premultiplied[:, :3], alpha, out=np.zeros((len(alpha), 3)), where=alpha > 0)
    return np.clip(np.concatenate([linear_to_srgb(rgb), alpha], -1), 0.0, 1.0)


def _cell(coords: np.ndarray, sizes) -> tuple[np.ndarray, np.ndarray]:
    """Lower corner (int) and fraction in [0, 1] of the cell holding each point, clamped to
    the grid [0, size - 1] per axis. coords: [P, 2]. Returns [P, 2] each."""
    top = np.asarray(sizes) - 2  # last valid lower corner
    base = np.clip(np.floor(coords).astype(int), 0, top)
    return base, np.clip(coords - base, 0.0, 1.0)


def render_lightfield(root, split: str, mode: str) -> dict:
    """{stem: RGBA uint8 [H, W, 4]} of every frame of `split` through the training light field."""
    ds = dataset.open_dataset(root)
    field = LightField(ds)
    query = ds.cameras(split)
    if query.intrinsics != field.intrinsics:
        raise InputError(f"split {split} has other intrinsics than the training grid: {query.intrinsics} vs {field.intrinsics}")
    return {stem: _straight_to_png(field.render(c2w, mode)) for stem, c2w in zip(query.stems, query.c2w)}


def render_refocus(root, split: str, samples: int = REFOCUS_SAMPLES, seed: int = 0,
                   lens: ThinLens | None = None) -> dict:
    """{stem: RGBA uint8 [H, W, 4]} of every frame of `split` refocused through its own
    thin lens (or `lens` for every frame, any aperture and focus distance); frames without
    a lens: aperture 0 at the light field's focal plane. Lens samples are seeded by
    (seed, frame index)."""
    if not (isinstance(samples, int) and samples > 0):
        raise InputError(f"refocus needs a positive number of lens samples, got {samples!r}")
    ds = dataset.open_dataset(root)
    field = LightField(ds, needed_by="synthetic-aperture refocusing")
    query = ds.cameras(split)
    if query.intrinsics != field.intrinsics:
        raise InputError(f"split {split} has other intrinsics than the training grid: {query.intrinsics} vs {field.intrinsics}")
    frames = {}
    for index, (stem, c2w) in enumerate(zip(query.stems, query.c2w)):
        frame_lens = lens or query.lens(index) or ThinLens(0.0, field.focal_distance)
        frames[stem] = _straight_to_png(field.refocus(c2w, frame_lens, samples, (seed, index)))
    return frames


def _straight_to_png(rgba: np.ndarray) -> np.ndarray:
    """Straight RGBA [H, W, 4] in [0, 1] -> uint8; colour 0 where alpha rounds to 0 (as the
    dataset's PNGs have it: a weight of 1e-15 on a covered pixel must not colour a hole)."""
    image = np.round(rgba * 255.0).astype(np.uint8)
    image[image[..., 3] == 0, :3] = 0
    return image


def write_baseline(root, method: str, out, split: str = "test", *, lens: ThinLens | None = None,
                   samples: int = REFOCUS_SAMPLES, seed: int = 0) -> dict:
    """Render `split` with `method` into out/<split>/ and write out/timing.json. Returns the timing.
    refocus only: `lens` for every frame instead of each frame's own, lens `samples` and `seed`."""
    if method not in METHODS:
        raise InputError(f"unknown baseline {method!r}; choose one of {', '.join(METHODS)}")
    ds, out = dataset.Dataset(root), Path(out)
    start = time.perf_counter()
    if method == "nearest":
        frames = render_nearest(ds, split)
    elif method == "refocus":
        frames = render_refocus(ds, split, samples, seed, lens)
    else:
        frames = render_lightfield(ds, split, method.removeprefix("lightfield-"))
    seconds = time.perf_counter() - start
    for stem, image in frames.items():
        owned.make_folder((out / stem).parent)
        write_png(out / (stem + ".png"), image)
    timing = {"method": method, "split": split, "frames": len(frames), "seconds": seconds,
              "ms_per_frame": 1000.0 * seconds / max(len(frames), 1)}
    if method == "refocus":
        timing |= {"lens_samples": samples, "lens_seed": seed, "lens": None if lens is None else lens.to_json()}
    write_json(out / "timing.json", timing)
    return timing


@contextlib.contextmanager
def baseline_folder(root, method: str, out, split: str, *, overwrite: bool = False, options=None):
    """Claim `out` as a "baseline" folder (core.folders.claim_folder) for the block. Its
    recipe is the method, the split and the dataset's content (manifest.json's hash), so a
    rerun on the same dataset continues and another one needs overwrite."""
    root, out = dataset.open_dataset(root).root, Path(out)
    recipe = recipe_hash({"method": method, "split": split, "dataset": dataset.manifest_sha256(root)}
                         | ({"options": options} if options else {}))
    made = [folder for folder in (out, *out.parents) if not folder.exists()]  # what claiming creates
    state = None
    try:
        with claim_folder(out, "baseline", recipe, overwrite=overwrite) as state:
            yield state
    except BaseException:
        if state == "new" and made:  # the baseline failed (bad input, interrupted): leave no folder behind
            remove_owned(out, "baseline")
            for parent in made[1:]:
                with contextlib.suppress(OSError):  # not empty any more: someone else's now
                    owned.remove_empty_folder(parent)
        raise
