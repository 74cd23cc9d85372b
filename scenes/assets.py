"""Reading a user's asset file into named objects with their materials, in the file's units.

A GLB/glTF scene graph gives one object per node that holds a mesh (trimesh.load without
force="mesh" returns a trimesh.Scene; `scene.graph[node]` gives the node's world transform
and geometry). An OBJ gives one object per `o`/`g` group (split further by `usemtl`), read
by scenes/obj_mtl.py because trimesh's OBJ loader renames split objects after the first
one ("first", "first_1", ...). PLY/STL/OFF files hold one unnamed object. The reader is
chosen by suffix in scenes/asset_reader.py; this module holds the asset's types,
scenes/trimesh_reader.py the trimesh reader.

Materials follow glTF's metallic-roughness model: a linear base colour, optionally times
an sRGB base-colour texture (and per-vertex colours, taken as linear like glTF's COLOR_0),
optional roughness and metallic (then rendered with Mitsuba's principled BSDF, else
diffuse). Coordinates stay in the file's units here: registry.py normalises (or not).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from nerfgauge.scenes.description import Diffuse, TriangleMesh
from nerfgauge.scenes.meshes import MeshData

from nerfgauge.core.errors import InputError
from nerfgauge.core.images import srgb_to_linear

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
UNITS = ("normalise", "keep")
DEFAULT_GREY = Diffuse((0.6, 0.6, 0.6))  # objects without a material, as before assets kept theirs
UNNAMED = "user_mesh"  # the name of the one object of a file that names none (PLY, STL, OBJ without o/g)


@dataclass(frozen=True)
class TextureImage:
    """A texture read from an asset: where it came from and its size. The pixels (linear
    RGB [H, W, 3] float32, row 0 at the top of the image as stored) are an attribute
    outside the dataclass fields, so scene.json (dataclasses.asdict) records the source
    and hash, not a million numbers."""

    source: str
    sha256: str
    width: int
    height: int

    @classmethod
    def from_pixels(cls, source: str, pixels: np.ndarray) -> "TextureImage":
        pixels = np.ascontiguousarray(pixels, np.float32)
        image = cls(source, hashlib.sha256(pixels.tobytes()).hexdigest(), int(pixels.shape[1]), int(pixels.shape[0]))
        object.__setattr__(image, "pixels", pixels)
        return image


@dataclass(frozen=True)
class AssetMaterial:
    """An asset's material. base_color is linear RGB; texture (if any) is already
    multiplied by it. vertex_colors: the mesh's per-vertex colours (already multiplied by
    base_color) are the albedo. roughness/metallic: None when the file gives neither
    (then the surface is diffuse)."""

    name: str
    base_color: tuple = (0.6, 0.6, 0.6)
    texture: Optional[TextureImage] = None
    vertex_colors: bool = False
    roughness: Optional[float] = None
    metallic: Optional[float] = None
    roughness_texture: Optional[TextureImage] = None  # [H, W, 1], already times `roughness`
    metallic_texture: Optional[TextureImage] = None  # [H, W, 1], already times `metallic`

    @property
    def view_dependent(self) -> bool:
        return self.roughness is not None or self.metallic is not None


@dataclass(frozen=True, eq=False)
class AssetObject:
    """One named object of an asset: its mesh in the file's world coordinates (uv are
    texture coordinates, v up as in OBJ), its material (None: the default grey) and a
    constant emission (None: not a light)."""

    name: str
    mesh: MeshData = field(repr=False)
    material: Optional[AssetMaterial] = None
    emission: Optional[tuple] = None


@dataclass(frozen=True, eq=False)
class Asset:
    """objects, {path: sha256} of every file read (the asset first), warning lines."""

    path: Path
    objects: list
    inputs: dict
    warnings: list


def warn(message: str) -> None:
    """One warning line on stderr (what the run still does despite the problem)."""
    print(f"warning: {message}", file=sys.stderr)


def unique_names(objects: list) -> list:
    """File-name-safe, unique names (they name meshes/<name>.ply and Mitsuba shapes);
    `light_*` is left to the scene's lights."""
    seen, out = set(), []
    for obj in objects:
        base = re.sub(r"[^A-Za-z0-9_-]+", "_", obj.name).strip("_") or "object"
        base = "object_" + base if base.startswith("light_") else base
        name, count = base, 1
        while name in seen:
            count += 1
            name = f"{base}_{count}"
        seen.add(name)
        out.append(AssetObject(name, obj.mesh, obj.material, obj.emission))
    return out


def checked_mesh(path: Path, vertices, faces, normals=None, uv=None, colors=None) -> MeshData:
    """A MeshData after the checks every format shares: faces index existing vertices whose
    coordinates are finite. normals None: flat shading; uv None: zeros."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return MeshData(vertices, faces, None, np.zeros((len(vertices), 2)))
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"mesh {path} has faces indexing vertices {faces.min()}..{faces.max()}, "
                         f"but only {len(vertices)} vertices")
    non_finite = ~np.isfinite(vertices[np.unique(faces)]).all(axis=1)  # [used V]
    if non_finite.any():
        raise InputError(f"mesh {path} has {int(non_finite.sum())} vertices with NaN or inf coordinates "
                         f"used by its triangles")
    if normals is not None and np.asarray(normals).size != vertices.size:
        normals = None  # not one per vertex: flat shading rather than misaligned normals
    if colors is not None and np.asarray(colors).size != vertices.size:
        colors = None
    if uv is not None and np.asarray(uv).size != 2 * len(vertices):
        uv = None
    if normals is not None:
        normals = np.asarray(normals, np.float64).reshape(-1, 3)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        # Unusable file normals (zero or non-finite) mean flat shading rather than NaN shading.
        normals = normals / length if np.isfinite(normals).all() and (length > 0).all() else None
    uv = np.zeros((len(vertices), 2)) if uv is None else np.asarray(uv, np.float64).reshape(-1, 2)
    if not np.isfinite(uv).all():
        uv = np.nan_to_num(uv, nan=0.0, posinf=0.0, neginf=0.0)
    if colors is not None:
        colors = np.clip(np.asarray(colors, np.float64).reshape(-1, 3), 0, None)
    return MeshData(vertices, faces, normals, uv, colors)


# --- placing objects in the scene ----------------------------------------------------------


def place_objects(objects: list, label: str, units: str, source: str = "") -> tuple[list, dict]:
    """Clean the objects' triangles and place them in scene units. Returns (TriangleMesh
    shapes, {"scale", "translation"}: scene point = scale * file point + translation).

    Zero-area triangles (twice the area below 1e-12 of the squared largest extent of all
    objects) are dropped, then every vertex no remaining face uses, so neither counts
    towards the bounds; an object left without triangles is dropped. A flat (planar) asset
    keeps zero extent across its plane; the scene's AABB padding gives it thickness."""
    if units not in UNITS:
        raise InputError(f"--units must be one of {', '.join(UNITS)}, got {units!r}")
    triangles = np.concatenate([obj.mesh.vertices[obj.mesh.faces].reshape(-1, 3) for obj in objects])
    centre, extent = _bounds(triangles)
    if not np.isfinite(centre).all() or not np.isfinite(extent):
        raise InputError(f"mesh {label} has coordinates too large for float64 arithmetic "
                         f"(up to {np.abs(triangles).max():.3g})")
    kept = []
    for obj in objects:
        if extent <= 0:
            break
        unit = (obj.mesh.vertices[obj.mesh.faces] - centre) / extent  # [F, 3, 3]: areas neither underflow nor overflow
        area2 = np.linalg.norm(np.cross(unit[:, 1] - unit[:, 0], unit[:, 2] - unit[:, 0]), axis=1)  # [F]
        if (area2 > 1e-12).any():
            kept.append((obj, obj.mesh.subset(area2 > 1e-12)))
    if not kept:
        raise InputError(f"mesh {label} has only degenerate (zero-area) triangles")
    if units == "keep":
        scale, translation = 1.0, np.zeros(3)
    else:
        centre, extent = _bounds(np.concatenate([mesh.vertices for _, mesh in kept]))
        scale = 2.0 / extent
        translation = -centre * scale
    shapes = []
    for obj, mesh in kept:
        placed = mesh if units == "keep" else mesh.scaled(scale, translation)
        material = obj.material if obj.material is not None else DEFAULT_GREY
        shapes.append(TriangleMesh(obj.name, placed, material, source=source or label, emission=obj.emission))
    return shapes, {"scale": float(scale), "translation": [float(x) for x in translation]}


def texel_size(mesh: MeshData, texture: TextureImage) -> Optional[float]:
    """One texel's side on the surface, in scene units: sqrt(world area per uv area / texels),
    the median over triangles with non-zero uv area (robust to a few stretched ones)."""
    corners, uv = mesh.vertices[mesh.faces], mesh.uv[mesh.faces]  # [F, 3, 3], [F, 3, 2]
    world = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    texture_area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    usable = texture_area > 1e-12
    if not usable.any():
        return None
    ratio = float(np.median(world[usable] / texture_area[usable]))
    return math.sqrt(ratio / (texture.width * texture.height)) if ratio > 0 else None


def with_texture_period(scene):
    """`scene` whose needs.finest_texture_period also counts the assets' textures (a texel
    on the surface), so a radiance field's grid is sized for them as for procedural ones."""
    sizes = [texel_size(shape.mesh(), shape.material.texture) for shape in scene.shapes
             if isinstance(shape.material, AssetMaterial) and shape.material.texture is not None]
    sizes = [s for s in sizes if s is not None and s > 0]
    if not sizes:
        return scene
    current = scene.needs.finest_texture_period
    period = min(sizes + ([current] if current is not None else []))
    return dataclasses.replace(scene, needs=dataclasses.replace(scene.needs, finest_texture_period=float(period)))


def _bounds(points):
    """[N, 3] -> centre [3], largest extent (inf if float64 overflows)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        return (lo + hi) / 2, float((hi - lo).max())


def apply_matrix(mesh: MeshData, matrix: np.ndarray) -> MeshData:
    """Points by the 4x4 `matrix`; normals by its inverse transpose (then unit); a mirroring
    matrix (det < 0) also reverses the winding so faces keep facing out."""
    linear = matrix[:3, :3]
    if np.allclose(matrix, np.eye(4)):
        return mesh
    vertices = mesh.vertices @ linear.T + matrix[:3, 3]
    normals = None
    if mesh.normals is not None:
        normals = mesh.normals @ np.linalg.inv(linear)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    faces = mesh.faces[:, ::-1] if np.linalg.det(linear) < 0 else mesh.faces
    return MeshData(vertices, np.ascontiguousarray(faces), normals, mesh.uv, mesh.colors)


def texture_from_image(source: str, image, base_color) -> TextureImage:
    """A PIL image (sRGB) times the linear `base_color` as a TextureImage."""
    # float32 throughout: a 4k texture is 200 MB as float32 (what Mitsuba holds anyway).
    rgb = np.asarray(image.convert("RGB"), np.float32) / np.float32(255)  # [H, W, 3]
    return TextureImage.from_pixels(source, srgb_to_linear(rgb) * np.asarray(base_color, np.float32))


def read_image(path: Path, data: bytes):
    from nerfgauge.core.images import open_pillow  # Pillow and OpenEXR: only when an asset carries an image

    try:
        image = open_pillow(data, path)
        image.load()
        return image
    except InputError as error:
        raise InputError(f"cannot read texture {path}: {error}") from None
    except Exception as error:  # PIL raises several types for bad images
        detail = ("unknown image format" if type(error).__name__ == "UnidentifiedImageError"
                  else str(error).splitlines()[0] if str(error).strip() else type(error).__name__)
        raise InputError(f"cannot read texture {path}: not an image ({detail})") from None
