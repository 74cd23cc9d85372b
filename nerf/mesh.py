"""A mesh from a trained field: marching cubes on its density, `nerfgauge mesh`.

The field is sampled on a regular grid over the scene's bounds (`resolution` cells along
the longest side, cubic cells) through the model's world-space density query
`model.density(points [n, 3]) -> sigma [n]`, and skimage's marching cubes extracts the
level set sigma = level, where by default

    level = median over training rays (opacity >= 0.5) of sigma(o + D d),

D being the ray's rendered expected distance: the density at which the model's own
renders place the surface, so the mesh and the rendered depth agree. A fixed level such
as "opacity 0.5 over one voxel" (sigma = ln 2 / voxel) only suits a converged, sharp
field: a briefly trained grid renders opaque silhouettes from soft shells that never
reach it (measured: 113 steps on primitives, median 3.0 at the rendered surface, maximum
8.6, ln 2 / voxel = 14.3), and the mesh would be empty. `--level SIGMA` fixes it;
`voxel_level(model)` gives the fixed one. Triangles whose centroid no training camera
sees (behind every camera or outside every image) are dropped: the field there was never
constrained.

torch is imported inside the functions that use it, so `nerfgauge --help` and the `mesh`
command's argument errors do not pay torch's import.

Faces are oriented with their normals pointing out of the dense region (towards
decreasing density), as the ground-truth meshes' are.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfgauge.core.camera import Intrinsics, pixel_rays, project
from nerfgauge.core.errors import InputError
from nerfgauge.core.outputs import ply_mark
from nerfgauge.nerf.runs import open_run_dataset

OPACITY_LEVEL = 0.5  # opacity over one voxel of the fixed level, and the least opacity of a calibration ray
CALIBRATION_RAYS = 16384  # training rays (strided over every view) that set the level
DENSITY_CHUNK = 1 << 21  # points per density query (~100 MB of temporaries)
# A face is kept where some training view renders a surface within this many voxels (the
# model's, or the extraction grid's cell if coarser) of it (on_rendered_surface).
SURFACE_TOLERANCE_VOXELS = 3.0


class NoSurface(InputError):
    """The field has no surface to mesh (an empty scene, or a field trained too briefly):
    a fact about the model, which the pipeline reports as "geometry n/a" instead of failing."""


@dataclass(frozen=True)
class ExtractedMesh:
    """vertices [n, 3] float64 world, faces [m, 3] int64; level: the density extracted
    and how it was chosen; seconds: wall time of the extraction."""

    vertices: np.ndarray
    faces: np.ndarray
    level: float
    level_source: str
    resolution: int
    box: np.ndarray
    faces_culled: int
    seconds: float


def seen_by_any(points: np.ndarray, c2w: np.ndarray, intrinsics: Intrinsics, distortion=None) -> np.ndarray:
    """Points [n, 3] in front of and projecting into the image of at least one camera of
    c2w [m, 4, 4]. Returns [n] bool."""
    seen = np.zeros(len(points), bool)
    todo = np.arange(len(points))
    for pose in c2w:  # each camera only looks at the points no earlier one saw
        u, v, _ = project(points[todo], pose, intrinsics, distortion)
        with np.errstate(invalid="ignore"):
            inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        seen[todo[inside]] = True
        todo = todo[~inside]
        if not len(todo):
            break
    return seen


def on_rendered_surface(points: np.ndarray, model, c2w: np.ndarray, intrinsics: Intrinsics, tolerance: float,
                        device="cpu", distortion=None) -> np.ndarray:
    """Points [n, 3] that some camera of c2w [m, 4, 4] sees on the surface the model
    renders: they project into its image where the rendered opacity is >= OPACITY_LEVEL and
    their distance from the camera is within `tolerance` (world units) of the rendered
    expected ray distance there (nearest pixel). Surfaces behind what the model renders
    (a shell's inner side, what lies inside an object) and faint surfaces in front of it
    (floaters the renders see through) fail in every view. Returns [n] bool."""
    import torch  # torch: only when meshing

    from nerfgauge.nerf.rendering import render_rays_chunked  # torch, as above

    seen = np.zeros(len(points), bool)
    todo = np.arange(len(points))
    for pose in c2w:
        origins, directions = pixel_rays(pose, intrinsics, distortion)  # [H, W, 3], the views' own rays
        with torch.no_grad():
            _, opacity, depth = render_rays_chunked(
                model, torch.from_numpy(origins.reshape(-1, 3).astype(np.float32)).to(device),
                torch.from_numpy(directions.reshape(-1, 3).astype(np.float32)).to(device))
        opacity = opacity.cpu().numpy().reshape(intrinsics.height, intrinsics.width)
        depth = depth.cpu().numpy().reshape(intrinsics.height, intrinsics.width)
        u, v, _ = project(points[todo], pose, intrinsics, distortion)
        with np.errstate(invalid="ignore"):
            inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        column, row = np.floor(u[inside]).astype(np.int64), np.floor(v[inside]).astype(np.int64)
        distance = np.linalg.norm(points[todo[inside]] - pose[:3, 3], axis=1)
        hit = (opacity[row, column] >= OPACITY_LEVEL) & (np.abs(distance - depth[row, column]) <= tolerance)
        seen[todo[inside][hit]] = True
        todo = todo[~seen[todo]]
        if not len(todo):
            break
    return seen


def extraction_grid(box: np.ndarray, resolution: int) -> tuple[list[np.ndarray], float]:
    """Node coordinates along x, y, z of a grid with `resolution` cubic cells along the
    box's longest side (the box is grown to whole cells, centred). Returns ([xs, ys, zs], cell)."""
    box = np.asarray(box, np.float64)
    extent = box[1] - box[0]
    cell = float(extent.max()) / resolution
    axes = []
    for k in range(3):
        cells = max(1, math.ceil(extent[k] / cell - 1e-9))
        start = box[0, k] + 0.5 * (extent[k] - cells * cell)
        axes.append(start + cell * np.arange(cells + 1))
    return axes, cell


def density_volume(model, axes: list[np.ndarray], device: torch.device | str = "cpu") -> np.ndarray:
    """sigma on the grid nodes, [nx, ny, nz] float32 (x-major, as marching cubes' spacing
    expects), queried through `model.density` in chunks of whole x-slabs."""
    import torch  # torch: nerf.commands imports this module for `mesh`

    with torch.no_grad():
        xs, ys, zs = (torch.as_tensor(a, dtype=torch.float32, device=device) for a in axes)
        plane = torch.stack(torch.meshgrid(ys, zs, indexing="ij"), dim=-1).reshape(-1, 2)  # [ny * nz, 2]
        per_chunk = max(1, DENSITY_CHUNK // plane.shape[0])
        volume = np.empty((len(xs), len(ys), len(zs)), np.float32)
        for start in range(0, len(xs), per_chunk):
            x = xs[start:start + per_chunk]
            points = torch.cat([x.repeat_interleave(plane.shape[0])[:, None], plane.repeat(len(x), 1)], dim=1)
            sigma = model.density(points)
            volume[start:start + len(x)] = sigma.float().cpu().numpy().reshape(len(x), len(ys), len(zs))
        return volume


def model_voxel(model) -> float | None:
    """The length the model resolves (its grid cell), if it has one."""
    field = getattr(model, "field", None)
    voxel = getattr(field, "voxel", None)
    return float(voxel) if voxel is not None else None


def model_box(model) -> np.ndarray | None:
    field = getattr(model, "field", None)
    aabb = getattr(field, "aabb", getattr(model, "aabb", None))
    if aabb is None:
        return None
    import torch  # torch, as above

    return np.asarray(torch.as_tensor(aabb).cpu(), np.float64)


def extraction_box(scene_bounds: np.ndarray | None, model) -> np.ndarray:
    """The scene's bounds, cut to the model's own box when it has one. [2, 3]."""
    boxes = [np.asarray(b, np.float64) for b in (scene_bounds, model_box(model)) if b is not None]
    if not boxes:
        raise InputError("no scene bounds: the dataset has no scene.json bounds and the model no box")
    box = np.stack([np.max([b[0] for b in boxes], axis=0), np.min([b[1] for b in boxes], axis=0)])
    if not (box[0] < box[1]).all():
        raise InputError(f"the scene bounds {boxes[0].tolist()} and the model's box {boxes[-1].tolist()} do not overlap")
    return box


def voxel_level(model, cell: float) -> float:
    """sigma whose opacity over one model voxel (the extraction `cell` for a model without
    a grid) is OPACITY_LEVEL: -ln(1 - 0.5) / voxel."""
    return -math.log(1.0 - OPACITY_LEVEL) / (model_voxel(model) or cell)


def rendered_surface_level(model, c2w: np.ndarray, intrinsics: Intrinsics, rays: int = CALIBRATION_RAYS,
                           device: torch.device | str = "cpu") -> float | None:
    """Median density at the expected-depth points of `rays` training rays (an even stride
    over all views' pixels) whose opacity reaches OPACITY_LEVEL; None if no ray does."""
    import torch  # torch, as above

    with torch.no_grad():
        per_view = max(1, rays // max(len(c2w), 1))
        origins, directions = [], []
        for pose in c2w:
            o, d = pixel_rays(pose, intrinsics)
            pick = np.linspace(0, o.shape[0] * o.shape[1] - 1, per_view).astype(np.int64)
            origins.append(o.reshape(-1, 3)[pick]), directions.append(d.reshape(-1, 3)[pick])
        o = torch.as_tensor(np.concatenate(origins), dtype=torch.float32, device=device)
        d = torch.as_tensor(np.concatenate(directions), dtype=torch.float32, device=device)
        out = model.render(o, d)
        hit = out.opacity >= OPACITY_LEVEL
        if not bool(hit.any()):
            return None
        sigma = model.density(o[hit] + out.depth[hit, None] * d[hit])
        return float(sigma.median())


def extract_mesh(model, box: np.ndarray, resolution: int, train_c2w: np.ndarray | None = None,
                 intrinsics: Intrinsics | None = None, level: float | None = None,
                 device: torch.device | str = "cpu", distortion=None) -> ExtractedMesh:
    """Marching cubes on `model.density` over `box` [2, 3] at `resolution` cells along its
    longest side, at `level` (None: the rendered-surface level over the cameras train_c2w
    [m, 4, 4], else the voxel level); faces no camera of train_c2w sees are dropped (None:
    keep all, no calibration). distortion: the train views' lens distortion (their rays and
    projections go through it), None for pinholes. InputError when the field has no surface there."""
    from skimage.measure import marching_cubes  # scikit-image: only when meshing

    if not model.has_density:
        raise InputError(f"a {type(model).__name__} has no density query (model.density); "
                         "meshes need a model that has one (the compact model)")
    if not (isinstance(resolution, int) and 8 <= resolution <= 1024):
        raise InputError(f"--resolution must be an integer in [8, 1024], got {resolution!r}")
    if level is not None and not (math.isfinite(level) and level > 0):
        raise InputError(f"--level must be a positive density, got {level!r}")
    start = time.perf_counter()
    axes, cell = extraction_grid(box, resolution)
    source = "given"
    if level is None and train_c2w is not None:
        level = rendered_surface_level(model, train_c2w, intrinsics, device=device)
        source = "median density at the rendered surface of training rays"
    if level is None:
        level, source = voxel_level(model, cell), "opacity 0.5 over one voxel"
    volume = density_volume(model, axes, device)
    if not np.isfinite(volume).all():
        raise InputError(f"the field's density is NaN or inf at {int((~np.isfinite(volume)).sum())} grid points")
    if not volume.min() < level < volume.max():
        raise NoSurface(f"the field has no surface in {np.round(box, 4).tolist()}: density ranges over "
                         f"[{volume.min():.4g}, {volume.max():.4g}], the surface level is {level:.4g}")
    # gradient_direction="ascent": the inside is where values exceed the level (density), so
    # the faces' normals point out of the dense region
    vertices, faces, _, _ = marching_cubes(volume, level, spacing=(cell, cell, cell), gradient_direction="ascent")
    vertices = vertices.astype(np.float64) + np.array([a[0] for a in axes])
    faces = faces.astype(np.int64)
    culled = 0
    if train_c2w is not None and len(faces):
        centroids = vertices[faces].mean(axis=1)
        keep = seen_by_any(centroids, train_c2w, intrinsics, distortion)
        voxel = model_voxel(model)
        if voxel is not None:  # and on the surface the model renders (SURFACE_TOLERANCE_VOXELS)
            keep[keep] = on_rendered_surface(centroids[keep], model, train_c2w, intrinsics,
                                             SURFACE_TOLERANCE_VOXELS * max(voxel, cell), device, distortion)
        culled = int((~keep).sum())
        faces = faces[keep]
        used = np.unique(faces)
        remap = np.full(len(vertices), -1, np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = vertices[used], remap[faces]
    if not len(faces):
        raise NoSurface("no surface of the field lies where a training camera sees")
    return ExtractedMesh(vertices, faces, float(level), source, resolution, np.asarray(box, np.float64), culled,
                         time.perf_counter() - start)


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary PLY of a triangle mesh (trimesh's writer), marked as ours with the header
    line `comment nerfgauge-kind: mesh` (core.outputs: a rerun may replace it)."""
    import trimesh  # trimesh: only when meshing

    return ply_mark(trimesh.Trimesh(vertices, faces, process=False).export(file_type="ply"), "mesh")


def mesh_from_run(run_dir, resolution: int = 256, cull: bool = True, level: float | None = None) -> ExtractedMesh:
    """Load RUN/model.pt (weights only) and its dataset's bounds and training cameras
    (the dataset checked against the run's record, nerf.runs.open_run_dataset); extract."""
    from nerfgauge.nerf.checkpoint import load_model  # torch: nerf.commands imports this module for `mesh`

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    model, config = load_model(run_dir / "model.pt")
    model.eval()
    ds = open_run_dataset(run_dir, config)
    cameras = ds.cameras("train")
    box = extraction_box(ds.bounds, model)
    if not cull and level is None:  # the cameras still set the level
        level = rendered_surface_level(model, cameras.c2w, cameras.intrinsics)
    return extract_mesh(model, box, resolution, cameras.c2w if cull else None, cameras.intrinsics, level,
                        distortion=cameras.distortion)
