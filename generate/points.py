"""Initial points for splatting methods, a controlled variable: `--points KIND[:COUNT]`.

    surface[:N]  N (default: 100,000, or one per 16 train pixels if fewer) samples of the ground-truth meshes (uniform by area) that some train view
                 sees, by the exact depth test of core/visibility.py's rule; each
                 coloured with the mean, over the first COLOUR_VIEWS (4) train views (in their
                 order) that see it, of the 8-bit sRGB PNG pixel it falls in. The points are on the triangles up to float64
                 rounding (points3D.bin keeps float64; the PLY float32).
    random[:N]   N (same default) points uniform in the scene's bounds (scene.json "bounds"), uniform random
                 colours: what splatting methods start from without SfM.
    sfm[:N]      what a real pipeline has: pycolmap extracts SIFT features from the train
                 images, matches them exhaustively and triangulates them with the exact poses
                 and intrinsics (sparse, noisy, only where features match); with N, the N
                 points of longest track (then smallest reprojection error). Needs pycolmap.

Every kind is seeded from the dataset's seed, so a dataset stays byte-deterministic
(`sfm` as far as COLMAP is: it runs single-threaded with its random seed set).

The points' distance to the ground-truth surface (scene.json "points") is the exact
point-to-triangle distance to the nearest of the candidate triangles holding a point's
`NEAREST_SAMPLES` nearest (approximately: scipy's eps = 1) area samples of the meshes and
face centroids: an upper bound of the distance to the surface, equal to it whenever the
nearest triangle is among the candidates (a far point's bound is off by at most the
samples' spacing's order). A `surface` point's distance is to the triangle it was drawn
on (about 1e-16).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError
from nerfgauge.core.outputs import ply_mark
from nerfgauge.core.surface import ground_truth_surface
from nerfgauge.core.triangle_distance import point_triangle_distance
from nerfgauge.core.visibility import GRAZING_CAP_DEGREES

KINDS = ("surface", "sfm", "random", "none")
DEFAULT_COUNT = {"surface": None, "random": None, "sfm": None, "none": 0}  # None: default_count (sfm: all)
MAX_DEFAULT_COUNT = 100_000
PIXELS_PER_DEFAULT_POINT = 16
MAX_COUNT = 10_000_000
DEFAULT_SPEC = "surface"
SEED_TAG = 3232  # the points' generator: default_rng([dataset seed, SEED_TAG])
DISTANCE_SAMPLES = 200_000
DISTANCE_METHOD = {
    "surface": "exact point-to-triangle distance to the triangle each point was sampled on, in scene units",
    "search": "exact point-to-triangle distance to the nearest candidate triangle (those of the 16 approximately "
              "nearest of 200000 area samples and the face centroids): an upper bound, in scene units",
}
NEAREST_SAMPLES = 16
MIN_SFM_POINTS = 10
COLOUR_VIEWS = 4  # a surface point's colour: the mean over the first train views (in order) that see it


@dataclass(frozen=True)
class PointsSpec:
    kind: str
    count: Optional[int]  # None: every point (sfm)

    def to_text(self) -> str:
        return self.kind if self.count == DEFAULT_COUNT[self.kind] else f"{self.kind}:{self.count}"


def parse_spec(text) -> PointsSpec:
    """"surface", "surface:5000", "random:100000", "sfm", "sfm:2000", "none" -> PointsSpec."""
    if isinstance(text, PointsSpec):
        return text
    match = re.fullmatch(r"\s*([a-z]+)\s*(?::\s*(-?\d+)\s*)?", str(text))
    if not match or match.group(1) not in KINDS:
        raise InputError(f"--points must be KIND[:COUNT] with KIND one of {', '.join(KINDS)}, got {text!r}")
    kind = match.group(1)
    if match.group(2) is None:
        return PointsSpec(kind, DEFAULT_COUNT[kind])
    if kind == "none":
        raise InputError("--points none takes no count")
    count = int(match.group(2))
    if not 0 < count <= MAX_COUNT:
        raise InputError(f"--points {kind}:{count}: the count must be between 1 and {MAX_COUNT:,}")
    return PointsSpec(kind, count)


@dataclass(frozen=True)
class InitialPoints:
    """xyz [n, 3] float64, rgb [n, 3] uint8, normals [n, 3] (0 where unknown), error [n]
    (COLMAP's reprojection error; 0 for surface, -1 for random), tracks (sfm: per point
    [k, 2] (image_id, point2D_idx)) and per image its 2D points (sfm: {image_id: (xys, ids)})."""

    xyz: np.ndarray
    rgb: np.ndarray
    normals: np.ndarray
    error: np.ndarray
    tracks: Optional[list] = None
    points2D: Optional[dict] = None
    faces: Optional[np.ndarray] = None  # surface: the triangle each point was sampled on


def default_count(train_views: int, width: int, height: int) -> int:
    """`surface` and `random` without a count: 100,000 points (what 3DGS starts synthetic
    scenes from), or one per 16 train pixels when the train images hold fewer (a 32 px test
    dataset gets hundreds, not a hundred thousand)."""
    return max(1, min(MAX_DEFAULT_COUNT, train_views * width * height // PIXELS_PER_DEFAULT_POINT))


def rng_for(seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), SEED_TAG])


# --- meshes -----------------------------------------------------------------------------


def has_meshes(ds) -> bool:
    """Whether the dataset lists ground-truth meshes (a scene with no geometry has none)."""
    return any(rel.startswith("meshes/") and rel.endswith(".ply") for rel in ds.manifest_files)


def read_meshes(ds) -> tuple[np.ndarray, np.ndarray]:
    """The union of the dataset's meshes/*.ply (read through its manifest): vertices [n, 3]
    float64, faces [m, 3] int64."""
    surface = ground_truth_surface(ds)
    return surface.vertices, surface.faces


def sample_triangles(vertices, faces, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """`count` points uniform by area: (points [count, 3], face index [count])."""
    triangles = vertices[faces]
    double_area = np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    total = double_area.sum()
    if not (total > 0 and math.isfinite(total)):
        raise InputError("the ground-truth meshes have zero surface area")
    face = rng.choice(len(faces), size=count, p=double_area / total)
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    a, b, c = (triangles[face, k] for k in range(3))
    points = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    return points, face


def face_normals(vertices, faces) -> np.ndarray:
    triangles = vertices[faces]
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)


def distance_to_surface(points: np.ndarray, vertices, faces, rng, known_faces=None) -> np.ndarray:
    """Upper bound of each point's distance to the mesh (module docstring). [n].
    known_faces [n]: the triangle each point was sampled on (surface samples): the distance
    to it, about 1e-16, is the bound, and no search is made."""
    if not len(points):
        return np.zeros(0)
    if known_faces is not None:  # the point's own triangle: its distance bounds the one to the surface
        face = faces[known_faces]
        return point_triangle_distance(points, vertices[face[:, 0]], vertices[face[:, 1]], vertices[face[:, 2]])
    from scipy.spatial import cKDTree  # scipy: only for points off the meshes

    samples, sample_face = sample_triangles(vertices, faces, DISTANCE_SAMPLES, rng)
    centroids = vertices[faces].mean(axis=1)
    reference = np.concatenate([samples, centroids])
    reference_face = np.concatenate([sample_face, np.arange(len(faces))])
    k = min(NEAREST_SAMPLES, len(reference))
    # eps=1: neighbours within twice the true k-th distance, 3x faster for points far from the
    # surface; only the candidate set loosens, each candidate's distance stays exact
    _, nearest = cKDTree(reference).query(points, k=k, eps=1.0)
    nearest = np.asarray(nearest).reshape(len(points), k)
    best = np.full(len(points), np.inf)
    for column in range(k):
        face = faces[reference_face[nearest[:, column]]]
        best = np.minimum(best, point_triangle_distance(points, vertices[face[:, 0]], vertices[face[:, 1]],
                                                        vertices[face[:, 2]]))
    return best


def distance_summary(distance: np.ndarray, diagonal: float) -> dict:
    if not len(distance):
        return {"mean": None, "p90": None, "max": None, "mean_over_diagonal": None}
    return {"mean": float(distance.mean()), "p90": float(np.percentile(distance, 90)), "max": float(distance.max()),
            "mean_over_diagonal": float(distance.mean() / diagonal), "max_over_diagonal": float(distance.max() / diagonal)}


# --- surface points ---------------------------------------------------------------------


def _seen(xyz, nrm, pose, intrinsics, depth, distortion=None) -> tuple[np.ndarray, np.ndarray]:
    """Columns of xyz [3, m] (unit normals nrm [3, m]) one view sees (core/visibility.py's depth
    test) and their pixels (flat index row * width + col). Component-wise arithmetic on
    contiguous rows: this runs once per train view over every candidate. distortion: the
    view's lens distortion (core.distortion), whose pixel grid its depth is on."""
    dx, dy, dz = xyz[0] - pose[0, 3], xyz[1] - pose[1, 3], xyz[2] - pose[2, 3]
    r = pose[:3, :3]
    depth_along = -(r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz)  # OpenGL camera looks along -Z
    front = np.flatnonzero(depth_along > 1e-12)
    dx, dy, dz, depth_along = dx[front], dy[front], dz[front], depth_along[front]
    x = (r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz) / depth_along
    y = -(r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz) / depth_along  # OpenCV axes: +y down
    if distortion is not None:
        x, y = distortion.distort(x, y)
    u = intrinsics.fx * x + intrinsics.cx
    v = intrinsics.fy * y + intrinsics.cy
    inside = np.flatnonzero((u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height))
    index = front[inside]
    dx, dy, dz = dx[inside], dy[inside], dz[inside]
    pixel = v[inside].astype(np.int64) * intrinsics.width + u[inside].astype(np.int64)
    recorded = depth.ravel()[pixel].astype(np.float64)
    distance = np.sqrt(dx * dx + dy * dy + dz * dz)
    cap = math.tan(math.radians(GRAZING_CAP_DEGREES))
    half_pixel = math.sqrt(2) / (2 * max(intrinsics.fx, intrinsics.fy))
    gap = np.abs(recorded - distance)
    near = np.flatnonzero((recorded > 0) & (gap <= distance * (half_pixel * cap + 1e-5)))  # widest tolerance first
    index, pixel, distance, gap = index[near], pixel[near], distance[near], gap[near]
    dx, dy, dz = dx[near], dy[near], dz[near]
    cos = np.clip(np.abs(nrm[0, index] * dx + nrm[1, index] * dy + nrm[2, index] * dz) / np.maximum(distance, 1e-300),
                  1e-12, 1.0)
    tan = np.minimum(np.sqrt(1 - cos ** 2) / cos, cap)
    ok = gap <= distance * (half_pixel * tan + 1e-5)
    return index[ok], pixel[ok]


def surface_points(ds, count: int, seed: int, vertices, faces) -> InitialPoints:
    """`count` mesh samples some train view sees, coloured from the train PNGs (module docstring);
    the depth test with the views' exact poses (Dataset.exact_cameras: what they were rendered from).
    No points when no train view resolves the meshes (a scene smaller than a pixel's footprint)."""
    cameras = ds.exact_cameras("train")
    rng = rng_for(seed)
    normals_of_face = face_normals(vertices, faces)
    kept_xyz, kept_rgb, kept_normal, kept_face, total = [], [], [], [], 0
    batch = max(1024, int(count * 1.25))
    for _ in range(8):  # rounds: each draws a fresh batch and keeps what some view sees
        points, face = sample_triangles(vertices, faces, batch, rng)
        normals = normals_of_face[face]
        xyz_rows, normal_rows = np.ascontiguousarray(points.T), np.ascontiguousarray(normals.T)
        colour_sum = np.zeros((len(points), 3))
        seen_by = np.zeros(len(points), np.int64)
        left = np.arange(len(points))  # samples seen by fewer than COLOUR_VIEWS views so far
        for index, pose in enumerate(cameras.c2w):
            if not len(left):
                break
            depth = ds.depth("train", index, kind="distance")
            which, pixel = _seen(xyz_rows, normal_rows, pose, cameras.intrinsics, depth, cameras.distortion)
            if not len(which):
                continue
            which = left[which]
            image = ds.image("train", index)[..., :3].reshape(-1, 3)
            colour_sum[which] += image[pixel]
            seen_by[which] += 1
            done = seen_by[left] >= COLOUR_VIEWS
            if done.sum() * 8 >= len(left):  # compact when it pays
                left = left[~done]
                xyz_rows, normal_rows = xyz_rows[:, ~done], normal_rows[:, ~done]
        visible = np.flatnonzero(seen_by > 0)
        kept_xyz.append(points[visible])
        kept_rgb.append(colour_sum[visible] / seen_by[visible, None])
        kept_normal.append(normals[visible])
        kept_face.append(face[visible])
        total += len(visible)
        if total >= count:
            break
        fraction = max(len(visible) / batch, 0.01)
        batch = max(1024, min(int((count - total) / fraction * 1.2), 20 * count))
    if total == 0:  # the export states the reason and writes its model without points (export.NO_VISIBLE_SURFACE)
        return InitialPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3)), np.zeros(0),
                             faces=np.zeros(0, np.int64))
    xyz = np.concatenate(kept_xyz)[:count]
    rgb = np.clip(np.rint(np.concatenate(kept_rgb)[:count] * 255), 0, 255).astype(np.uint8)
    return InitialPoints(xyz, rgb, np.concatenate(kept_normal)[:count], np.zeros(len(xyz)),
                         faces=np.concatenate(kept_face)[:count])


def random_points(count: int, seed: int, bounds: np.ndarray) -> InitialPoints:
    rng = rng_for(seed)
    lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
    xyz = lo + (hi - lo) * rng.random((count, 3))
    rgb = rng.integers(0, 256, size=(count, 3), dtype=np.uint8)
    return InitialPoints(xyz, rgb, np.zeros((count, 3)), np.full(count, -1.0))


# --- PLY ------------------------------------------------------------------------------


def ply_bytes(points: InitialPoints, kind: str) -> bytes:
    """Binary little-endian PLY: x y z nx ny nz (float) red green blue (uchar): what
    nerfstudio (ply_file_path) and the 3DGS code (sparse/0/points3D.ply) read."""
    rows = np.empty(len(points.xyz), dtype=[("xyz", "<f4", (3,)), ("n", "<f4", (3,)), ("rgb", "u1", (3,))])
    rows["xyz"], rows["n"], rows["rgb"] = points.xyz, points.normals, points.rgb
    header = ["ply", "format binary_little_endian 1.0", f"comment nerfgauge initial points: {kind}",
              f"element vertex {len(rows)}"]
    header += [f"property float {name}" for name in ("x", "y", "z", "nx", "ny", "nz")]
    header += [f"property uchar {name}" for name in ("red", "green", "blue")] + ["end_header"]
    return ply_mark(("\n".join(header) + "\n").encode("ascii") + rows.tobytes(), "points")
