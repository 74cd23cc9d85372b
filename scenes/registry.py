"""Scene names -> recipes, including user meshes (`mesh:PATH`)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import trimesh

from nerfgauge.errors import InputError
from scenes import library
from scenes.description import Diffuse, Scene, TriangleMesh, build_scene
from scenes.meshes import MeshData

# name -> (recipe(seed) -> Scene, one-line description)
RECIPES = {
    "primitives": (library.primitives, "default: red sphere, blue box, green capped cylinder, checker sphere (diffuse)"),
    "glossy": (library.glossy, "view-dependent: rough plastic, rough gold, near-mirror aluminium under a sky with a sun"),
    "random": (library.random_objects, "3-6 objects whose shapes, materials and poses come from the seed"),
}
MESH_PREFIX = "mesh:"
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")


def list_scenes() -> list[tuple[str, str]]:
    """(name, description) for every scene, user meshes last."""
    rows = [(name, text) for name, (_, text) in RECIPES.items()]
    rows.append((MESH_PREFIX + "PATH", "your mesh (.obj/.ply/.glb/.stl), scaled into [-1, 1]^3, grey diffuse"))
    return rows


def make_scene(spec: str, seed: int) -> Scene:
    """Build the scene named `spec` (a recipe name or `mesh:PATH`) from `seed`."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    if spec.startswith(MESH_PREFIX):
        return mesh_scene(Path(spec[len(MESH_PREFIX):]), int(seed))
    if spec not in RECIPES:
        known = ", ".join(list(RECIPES) + [MESH_PREFIX + "PATH"])
        raise InputError(f"unknown scene {spec!r}; known scenes: {known}")
    return RECIPES[spec][0](int(seed))


def mesh_scene(path: Path, seed: int) -> Scene:
    """A user's mesh, centred and uniformly scaled so its largest extent spans [-1, 1]."""
    data = load_user_mesh(path)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    shape = TriangleMesh("user_mesh", data, Diffuse((0.6, 0.6, 0.6)), source=str(path))
    return build_scene(f"{MESH_PREFIX}{path}", seed, [shape], [library.SOFT_SKY],
                       params={"path": str(path), "sha256": digest})


def load_user_mesh(path: Path) -> MeshData:
    """Read a mesh with trimesh, drop degenerate triangles, scale into [-1, 1]^3."""
    if not path.is_file():
        raise InputError(f"mesh file not found: {path}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"mesh {path} has unsupported extension {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as error:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh {path}: {str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), np.int64)
    if len(faces) == 0 or len(vertices) == 0:
        raise InputError(f"mesh {path} has no triangles")
    if not np.isfinite(vertices).all():
        raise InputError(f"mesh {path} has non-finite vertex coordinates")
    tri = vertices[faces]  # [F, 3, 3]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    lo, hi = vertices[faces].reshape(-1, 3).min(0), vertices[faces].reshape(-1, 3).max(0)
    extent = float((hi - lo).max())
    faces = faces[area2 > 1e-12 * max(extent, 1e-300) ** 2]
    if len(faces) == 0 or extent <= 0:
        raise InputError(f"mesh {path} has only degenerate (zero-area) triangles")
    scaled = (vertices - (lo + hi) / 2) * (2.0 / extent)
    return MeshData(scaled, faces, None, np.zeros((len(scaled), 2)))
