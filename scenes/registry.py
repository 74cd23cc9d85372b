"""Scene names -> recipes, including user meshes (`mesh:PATH`)."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
import trimesh
import trimesh.resolvers
from nerfgauge.scenes import library
from nerfgauge.scenes.description import Diffuse, Scene, TriangleMesh, build_scene
from nerfgauge.scenes.hard import HARD_RECIPES
from nerfgauge.scenes.meshes import MeshData

from nerfgauge.core.errors import InputError

# name -> (recipe(seed) -> Scene, one-line description)
RECIPES = {
    "primitives": (library.primitives, "default: red sphere, blue box, green capped cylinder, checker sphere (diffuse)"),
    "glossy": (library.glossy, "view-dependent: rough plastic, rough gold, near-mirror aluminium under a sky with a sun"),
    "random": (library.random_objects, "3-6 objects whose shapes, materials and poses come from the seed"),
    **HARD_RECIPES,
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
    """A user's mesh, centred and uniformly scaled so its largest extent spans [-1, 1].

    The scene's params name every file read (the mesh and any buffers or materials it
    refers to) with the sha256 of the bytes that were parsed: `scene_inputs` gives them."""
    data, inputs = read_user_mesh(path)
    shape = TriangleMesh("user_mesh", data, Diffuse((0.6, 0.6, 0.6)), source=str(path))
    return build_scene(f"{MESH_PREFIX}{path}", seed, [shape], [library.SOFT_SKY],
                       params={"path": str(path), "sha256": inputs[str(path)], "inputs": inputs})


def scene_inputs(scene: Scene) -> dict:
    """{path: sha256} of every file a scene was made from (empty for procedural recipes)."""
    return dict(scene.params.get("inputs", {}))


class _RecordingResolver(trimesh.resolvers.FilePathResolver):
    """trimesh's resolver for files a mesh refers to (glTF buffers, OBJ materials), noting
    the sha256 of each one it reads: they are inputs too."""

    def __init__(self, mesh_path: Path):
        super().__init__(str(mesh_path))
        self.read = {}

    def get(self, name: str):
        data = super().get(name)
        self.read[str(Path(self.parent) / name)] = hashlib.sha256(data).hexdigest()
        return data


def load_user_mesh(path: Path) -> MeshData:
    """The mesh of `read_user_mesh`, without its file hashes."""
    return read_user_mesh(path)[0]


def read_user_mesh(path: Path) -> tuple[MeshData, dict]:
    """Read a mesh with trimesh, drop degenerate triangles, scale into [-1, 1]^3.
    Returns (mesh, {path: sha256} of the bytes parsed, the mesh file first).

    The file is read once, so the hash describes exactly what was parsed, and unprocessed:
    trimesh's processing would silently drop the faces of a vertex with NaN coordinates.
    Faces must index existing vertices with finite coordinates (an InputError otherwise).
    Zero-area triangles (collinear or repeated corners: twice the area below 1e-12 of the
    squared largest extent) are dropped, then every vertex no remaining face uses, so
    neither counts towards the bounds. What is left is centred and uniformly scaled so its
    largest extent spans [-1, 1]. A flat (planar) mesh keeps zero extent across its plane;
    the scene's AABB padding gives it thickness. OS errors (permission, I/O) propagate.
    """
    if not path.is_file():
        raise InputError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(f"mesh {path} has unsupported extension {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    content = path.read_bytes()
    if not content:
        raise InputError(f"mesh {path} is empty")
    resolver = _RecordingResolver(path)
    try:
        loaded = trimesh.load(io.BytesIO(content), file_type=suffix[1:], resolver=resolver, force="mesh",
                              process=False)
    except ImportError as error:  # an optional parser trimesh reaches for: one line, not a missing-module trace
        needs = ("its text is not UTF-8, and guessing another encoding needs the optional package charset_normalizer"
                 if error.name == "charset_normalizer" else f"reading it needs the optional package {error.name or error}")
        raise InputError(f"cannot read mesh {path}: not a valid {suffix} mesh ({needs})") from None
    except Exception as error:  # trimesh raises many types for malformed files
        detail = str(error).splitlines()[0] if str(error).strip() else type(error).__name__
        raise InputError(f"cannot read mesh {path}: not a valid {suffix} mesh ({detail})") from None
    inputs = {str(path): hashlib.sha256(content).hexdigest(), **resolver.read}
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64)  # [V, 3]
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), np.int64)  # [F, 3]
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or vertices.ndim != 2 or len(vertices) == 0:
        raise InputError(f"mesh {path} has no triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"mesh {path} has faces indexing vertices {faces.min()}..{faces.max()}, "
                         f"but only {len(vertices)} vertices")
    non_finite = ~np.isfinite(vertices[np.unique(faces)]).all(axis=1)  # [used V]
    if non_finite.any():
        raise InputError(f"mesh {path} has {int(non_finite.sum())} vertices with NaN or inf coordinates "
                         f"used by its triangles")

    def bounds(points):  # [N, 3] -> centre [3], largest extent (inf if float64 overflows)
        lo, hi = points.min(axis=0), points.max(axis=0)
        with np.errstate(over="ignore"):
            return (lo + hi) / 2, float((hi - lo).max())

    tri = vertices[faces]  # [F, 3, 3]
    centre, extent = bounds(tri.reshape(-1, 3))
    if not np.isfinite(centre).all() or not np.isfinite(extent):
        raise InputError(f"mesh {path} has coordinates too large for float64 arithmetic "
                         f"(up to {np.abs(tri).max():.3g})")
    if extent > 0:
        unit = (tri - centre) / extent  # [F, 3, 3], largest extent 1: areas neither underflow nor overflow
        area2 = np.linalg.norm(np.cross(unit[:, 1] - unit[:, 0], unit[:, 2] - unit[:, 0]), axis=1)  # [F]
        faces = faces[area2 > 1e-12]
    if extent <= 0 or len(faces) == 0:
        raise InputError(f"mesh {path} has only degenerate (zero-area) triangles")
    used, faces = np.unique(faces, return_inverse=True)  # drop vertices no kept triangle uses
    faces = faces.reshape(-1, 3)
    vertices = vertices[used]  # [V', 3]
    centre, extent = bounds(vertices)
    scaled = (vertices - centre) * (2.0 / extent)
    return MeshData(scaled, faces, None, np.zeros((len(scaled), 2))), inputs
