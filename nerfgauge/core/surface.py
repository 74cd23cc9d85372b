"""The ground-truth surface and any other surface file: read, then sampled by area.

A surface is what a mesh or point-cloud file holds (`Surface`: vertices, and faces unless
it is a point cloud); the ground truth is the union of a dataset's meshes/*.ply, read
through its manifest (`ground_truth_surface`). One definition for the two sides that use
it: the evaluator scores against it (eval.geometry) and the COLMAP export's initial points
sample it (generate.points).

Sampling: a mesh uniformly by area (`sample_surface`, an explicit numpy Generator), each
sample carrying its face's normal; a point cloud as given, a random subset if larger
(`point_set`). Which samples a dataset's cameras see: core.visibility.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from nerfgauge.core.dataset import Dataset
from nerfgauge.core.errors import InputError

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf")


@dataclass(frozen=True)
class Surface:
    """What a file holds: vertices [n, 3] float64 and faces [m, 3] int64 (None: a point
    cloud), normals [n, 3] of a point cloud's points when the file has them."""

    vertices: np.ndarray
    faces: Optional[np.ndarray]
    normals: Optional[np.ndarray] = None


@dataclass(frozen=True)
class PointSet:
    """points [n, 3] float64; normals [n, 3] unit or None."""

    points: np.ndarray
    normals: Optional[np.ndarray]


# --- reading -------------------------------------------------------------------------


def _declares_faces(data: bytes) -> bool:
    """A PLY header with an `element face` line: a mesh, even when it has zero faces."""
    if not data.startswith(b"ply"):
        return False
    header = data[:data.find(b"end_header")] if b"end_header" in data else data[:4096]
    return any(line.split()[:2] == [b"element", b"face"] for line in header.splitlines())


def surface_from_bytes(data: bytes, name: str, file_type: str) -> Surface:
    """Parse mesh or point-cloud bytes with trimesh; one-line InputError for anything that
    is not a non-empty, finite surface."""
    import trimesh  # trimesh: only when a mesh file is read (eval.check imports this module's importer)

    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=file_type, process=False)
    except Exception as error:  # trimesh raises many types for garbage
        text = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise InputError(f"{name} is not a readable mesh or point cloud: {text[:200]}") from None
    if isinstance(loaded, trimesh.Scene):
        parts = [g for g in loaded.geometry.values() if isinstance(g, (trimesh.Trimesh, trimesh.PointCloud))]
        meshes = [g for g in parts if isinstance(g, trimesh.Trimesh)]
        if meshes:
            loaded = trimesh.util.concatenate(meshes)
        elif parts:
            loaded = trimesh.PointCloud(np.concatenate([np.asarray(g.vertices) for g in parts]))
        else:
            raise InputError(f"{name} holds no mesh or points (an empty file, or not {file_type.upper()})")
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    if isinstance(loaded, trimesh.Trimesh):
        faces = np.asarray(loaded.faces, np.int64).reshape(-1, 3)
        normals = None
    elif isinstance(loaded, trimesh.PointCloud):
        if _declares_faces(data):
            raise InputError(f"{name} declares faces but has zero faces")
        faces = None
        normals = _point_normals(loaded, len(vertices))
    else:
        raise InputError(f"{name} is not a mesh or point cloud (trimesh read a {type(loaded).__name__})")
    if not len(vertices):
        raise InputError(f"{name} is empty: no vertices")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise InputError(f"{name} has {int(bad.sum())} vertices with NaN or inf coordinates")
    if faces is not None:
        if not len(faces):
            raise InputError(f"{name} has zero faces")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise InputError(f"{name} has faces indexing vertices outside 0..{len(vertices) - 1}")
    return Surface(vertices, faces, normals)


def _point_normals(cloud, count: int) -> Optional[np.ndarray]:
    """Per-point normals of a PLY point cloud (nx, ny, nz properties), if present and usable."""
    data = getattr(cloud, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
    names = set(data) if isinstance(data, dict) else set(getattr(getattr(data, "dtype", None), "names", None) or ())
    if data is None or not {"nx", "ny", "nz"} <= names:
        return None
    normals = np.stack([np.asarray(data[k]) for k in ("nx", "ny", "nz")], axis=-1).astype(np.float64).reshape(-1, 3)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if len(normals) != count or not (np.isfinite(normals).all() and (length > 0).all()):
        return None
    return normals / length


def read_surface(path) -> Surface:
    """A mesh or point cloud file (format from its suffix)."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: unknown mesh format {path.suffix!r}; expected one of {', '.join(MESH_SUFFIXES)}")
    if path.is_dir():
        raise InputError(f"{path} is a folder; expected a mesh or point cloud file")
    if not path.is_file():
        raise InputError(f"mesh file not found: {path}")
    return surface_from_bytes(path.read_bytes(), str(path), path.suffix.lower().lstrip("."))


def ground_truth_surface(ds: Dataset) -> Surface:
    """The union of DATASET/meshes/*.ply (read through the manifest check)."""
    folder = ds.root / "meshes"
    names = sorted(f"meshes/{path.name}" for path in folder.glob("*.ply")) if folder.is_dir() else []
    if not names:
        raise InputError(f"dataset {ds.root} has no ground-truth meshes (meshes/*.ply); regenerate it with "
                         "nerfgauge generate")
    vertices, faces, offset = [], [], 0
    for rel in names:
        surface = surface_from_bytes(ds.read_bytes(rel), str(ds.root / rel), "ply")
        if surface.faces is None:
            raise InputError(f"{ds.root / rel} is a point cloud; ground-truth meshes need faces")
        vertices.append(surface.vertices)
        faces.append(surface.faces + offset)
        offset += len(surface.vertices)
    return Surface(np.concatenate(vertices), np.concatenate(faces))


# --- sampling ------------------------------------------------------------------------


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator,
                   name: str = "mesh") -> PointSet:
    """`count` points uniform by area over the triangles, each with its face's unit normal.

    vertices [n, 3], faces [m, 3]. A face is drawn with probability area / total area, a
    point in it by the square-root barycentric map (uniform on the triangle)."""
    triangles = vertices[faces]  # [m, 3, 3]
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])  # [m, 3]
    double_area = np.linalg.norm(cross, axis=1)
    total = double_area.sum()
    if not (total > 0 and math.isfinite(total)):
        raise InputError(f"{name} has zero surface area (every face is degenerate)")
    face = rng.choice(len(faces), size=count, p=double_area / total)
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    a, b, c = (triangles[face, k] for k in range(3))
    points = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    normals = cross[face] / np.maximum(double_area[face], 1e-300)[:, None]
    return PointSet(points, normals)


def point_set(surface: Surface, count: int, rng: np.random.Generator, name: str) -> PointSet:
    """A mesh sampled by area; a point cloud as given (a random `count` of it if larger)."""
    if surface.faces is not None:
        return sample_surface(surface.vertices, surface.faces, count, rng, name)
    points, normals = surface.vertices, surface.normals
    if len(points) > count:
        pick = rng.choice(len(points), size=count, replace=False)
        points, normals = points[pick], None if normals is None else normals[pick]
    return PointSet(points, normals)
