"""Any supported asset file into an `assets.Asset`: the one entry point, choosing the reader
by suffix (OBJ + MTL: scenes/obj_mtl.py; GLB, glTF, PLY, STL, OFF: trimesh, in
scenes/assets.py, which also defines the asset's types)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError
from nerfgauge.scenes.assets import MESH_SUFFIXES, Asset, unique_names
from nerfgauge.scenes.obj_mtl import read_obj


def read_asset(path: Path) -> Asset:
    """Read every object of `path` with its material, in the file's own coordinates.
    Bad files raise a one-line InputError; a missing texture is a warning (the base colour
    is used instead). OS errors (permission, I/O) propagate."""
    path = Path(arguments.encodable_path(path, "mesh file"))  # Mitsuba and our JSON need UTF-8 paths
    if not path.is_file():
        raise InputError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(f"mesh {path} has unsupported extension {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    content = path.read_bytes()
    if not content:
        raise InputError(f"mesh {path} is empty")
    inputs = {str(path): hashlib.sha256(content).hexdigest()}
    warnings: list = []
    if suffix == ".obj":
        objects = read_obj(path, content, inputs, warnings)
    else:
        from nerfgauge.scenes.trimesh_reader import read_with_trimesh  # trimesh (1.4 s): only for these files

        objects = read_with_trimesh(path, suffix, content, inputs, warnings)
    objects = [obj for obj in objects if len(obj.mesh.faces)]
    if not objects:
        raise InputError(f"mesh {path} has no triangles")
    return Asset(path, unique_names(objects), inputs, warnings)
