"""OBJ + MTL: one object per `o`/`g` group (split further by `usemtl`), with the
materials and textures of its .mtl files.

Read here rather than by trimesh because trimesh's OBJ loader renames split objects after
the first one ("first", "first_1", ...), losing the names the file gives.
"""

from __future__ import annotations

import hashlib

import numpy as np
from nerfgauge.scenes.assets import (
    UNNAMED,
    AssetMaterial,
    AssetObject,
    checked_mesh,
    read_image,
    texture_from_image,
    warn,
)
from nerfgauge.scenes.meshes import MeshData

from nerfgauge.core.errors import InputError


def _floats(parts, count, path, line_number) -> list:
    try:
        values = [float(x) for x in parts[:count]]
    except ValueError:
        raise InputError(f"cannot read mesh {path}: not a valid .obj mesh (line {line_number}: "
                         f"expected numbers, got {' '.join(parts[:count])[:40]!r})") from None
    if len(values) < count:
        raise InputError(f"cannot read mesh {path}: not a valid .obj mesh (line {line_number}: too few numbers)")
    return values


def read_obj(path: Path, content: bytes, inputs: dict, warnings: list) -> list:
    """Objects of an OBJ: one per (o/g name, usemtl) pair, in the order they first appear."""
    text = content.decode("utf-8", errors="replace")
    positions, colors, texcoords, normals = [], [], [], []
    chunks: dict = {}  # (group, material) -> list of corner triples (v, vt, vn), -1 when absent
    group, material_name, libraries, named = None, None, [], False
    parsed: dict = {}  # corner token -> (v, vt, vn): a vertex is shared by ~6 faces of a closed mesh
    for number, raw in enumerate(text.splitlines(), 1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        key, rest = parts[0], parts[1:]
        if key == "v":
            positions.append(_floats(rest, 3, path, number))
            colors.append(_floats(rest[3:], 3, path, number) if len(rest) >= 6 else None)
        elif key == "vt":
            texcoords.append((_floats(rest, 2, path, number) if len(rest) >= 2 else _floats(rest, 1, path, number) + [0.0]))
        elif key == "vn":
            normals.append(_floats(rest, 3, path, number))
        elif key == "f":
            corners = []
            for token in rest:
                corner = parsed.get(token)
                if corner is None:
                    corner = _corner(token, (len(positions), len(texcoords), len(normals)), path, number)
                    if "-" not in token:  # relative indices mean another vertex on another line
                        parsed[token] = corner
                corners.append(corner)
            if len(corners) < 3:
                raise InputError(f"cannot read mesh {path}: not a valid .obj mesh (line {number}: a face needs 3 corners)")
            fan = [(corners[0], corners[i], corners[i + 1]) for i in range(1, len(corners) - 1)]
            chunks.setdefault((group, material_name), []).extend(fan)
        elif key in ("o", "g"):
            group, named = " ".join(rest) or None, True
        elif key == "usemtl":
            material_name = " ".join(rest) or None
        elif key == "mtllib":
            libraries.append(raw.split("#", 1)[0].strip()[len("mtllib"):].strip())
    materials = {}
    for library in libraries:
        materials.update(_read_mtl(path, path.parent / library, inputs, warnings))
    position_array = np.asarray(positions, np.float64).reshape(-1, 3)
    texcoord_array = np.asarray(texcoords, np.float64).reshape(-1, 2)
    normal_array = np.asarray(normals, np.float64).reshape(-1, 3)
    has_colors = bool(colors) and all(c is not None for c in colors)
    color_array = np.asarray(colors if has_colors else [], np.float64).reshape(-1, 3)
    undefined = sorted({mtl for _, mtl in chunks if mtl is not None and mtl not in materials})
    if undefined and len(materials) + len(libraries) > 0 and all((path.parent / lib).is_file() for lib in libraries):
        message = f"{path} uses material(s) {', '.join(map(repr, undefined))} that its .mtl does not define: grey"
        warn(message)
        warnings.append(message)
    groups_with = {}
    for key in chunks:
        groups_with.setdefault(key[0], []).append(key[1])
    objects = []
    for (group_name, mtl), triangles in chunks.items():
        corners = np.asarray(triangles, np.int64).reshape(-1, 3)  # [3F, (v, vt, vn)]
        table, inverse = unique_rows(corners)
        faces = inverse.reshape(-1, 3)
        vertices = position_array[table[:, 0]]
        uv = texcoord_array[table[:, 1]] if (table[:, 1] >= 0).all() and len(texcoord_array) else None
        vertex_normals = normal_array[table[:, 2]] if (table[:, 2] >= 0).all() and len(normal_array) else None
        vertex_colors = color_array[table[:, 0]] if has_colors else None
        if group_name is None:
            name = mtl if (mtl is not None and len(chunks) > 1) else UNNAMED
        else:
            name = group_name if len(groups_with[group_name]) == 1 else f"{group_name}_{mtl}"
        mesh = checked_mesh(path, vertices, faces, vertex_normals, uv, vertex_colors)
        material, emission = (None, None)
        if mtl is not None and mtl in materials:
            material, emission = materials[mtl]
            if material.texture is not None and uv is None:
                material = AssetMaterial(material.name, material.base_color, None, False,
                                         material.roughness, material.metallic)
        if vertex_colors is not None:
            base = material.base_color if material is not None else (1.0, 1.0, 1.0)
            mesh = MeshData(mesh.vertices, mesh.faces, mesh.normals, mesh.uv, mesh.colors * np.asarray(base))
            material = AssetMaterial("vertex_colors", (1.0, 1.0, 1.0), None, True,
                                     None if material is None else material.roughness,
                                     None if material is None else material.metallic)
        objects.append(AssetObject(name, mesh, material, emission))
    return objects


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(rows, axis=0, return_inverse=True) for [N, 3] indices >= -1, through one
    int64 key per row when the index ranges allow (several times faster)."""
    span = rows.max(axis=0).astype(object) + 2  # Python ints: the product must not overflow
    if len(rows) and span[0] * span[1] * span[2] < 2**62:
        shifted = rows + 1
        keys = (shifted[:, 0] * int(span[1]) + shifted[:, 1]) * int(span[2]) + shifted[:, 2]
        unique_keys, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        return rows[first], inverse.reshape(-1)
    table, inverse = np.unique(rows, axis=0, return_inverse=True)
    return table, inverse.reshape(-1)


def _corner(token: str, counts, path, line_number) -> tuple:
    """"v", "v/vt", "v//vn" or "v/vt/vn" (1-based, negative from the end) -> 0-based, -1 absent."""
    out = []
    pieces = token.split("/")
    if len(pieces) > 3:
        raise InputError(f"cannot read mesh {path}: not a valid .obj mesh (line {line_number}: bad corner {token[:20]!r})")
    for piece, count in zip(pieces + [""] * (3 - len(pieces)), counts):
        if piece == "":
            out.append(-1)
            continue
        try:
            index = int(piece)
        except ValueError:
            raise InputError(f"cannot read mesh {path}: not a valid .obj mesh "
                             f"(line {line_number}: bad corner {token[:20]!r})") from None
        index = index - 1 if index > 0 else count + index
        if not 0 <= index < count:
            raise InputError(f"mesh {path} has a face (line {line_number}) indexing {piece}, "
                             f"but only {count} are defined before it")
        out.append(index)
    if out[0] < 0:
        raise InputError(f"cannot read mesh {path}: not a valid .obj mesh (line {line_number}: corner without a vertex)")
    return tuple(out)


def _read_mtl(obj_path: Path, path: Path, inputs: dict, warnings: list) -> dict:
    """{material name: (AssetMaterial, emission or None)} from an MTL file. Kd and Ke are
    taken as linear RGB, map_Kd as an sRGB image; Pr and Pm (the PBR extension) give
    roughness and metallic. A missing MTL or texture is a warning, not an error."""
    if not path.is_file():
        message = f"{obj_path} refers to missing {path}: its objects are grey"
        warn(message)
        warnings.append(message)
        return {}
    content = path.read_bytes()
    inputs[str(path)] = hashlib.sha256(content).hexdigest()
    entries: dict = {}
    current = None
    for number, raw in enumerate(content.decode("utf-8", errors="replace").splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        parts = line.split()
        if not parts:
            continue
        key, rest = parts[0], parts[1:]
        if key == "newmtl":
            current = " ".join(rest)
            entries[current] = {}
        elif current is None:
            continue
        elif key in ("Kd", "Ke"):
            entries[current][key] = _floats(rest, 3, path, number)
        elif key in ("Pr", "Pm", "d"):
            entries[current][key] = _floats(rest, 1, path, number)[0]
        elif key == "Tr":
            entries[current]["d"] = 1.0 - _floats(rest, 1, path, number)[0]
        elif key == "map_Kd" and rest:
            entries[current][key] = rest[-1]  # options (-s, -o, ...) come first; the file name last
        elif key in ("map_d", "map_Ke"):
            entries[current][key] = True
    materials = {}
    for name, entry in entries.items():
        if entry.get("d", 1.0) < 1.0 or entry.get("map_d"):
            raise InputError(f"material {name!r} in {path} is transparent (d < 1 or map_d), "
                             "which nerfgauge cannot render; make it opaque")
        if entry.get("map_Ke"):
            raise InputError(f"material {name!r} in {path} has an emission texture (map_Ke), "
                             "which nerfgauge cannot render; use a constant Ke")
        base = tuple(float(x) for x in entry.get("Kd", (0.6, 0.6, 0.6)))
        texture = None
        if "map_Kd" in entry:
            texture_path = path.parent / entry["map_Kd"]
            if not texture_path.is_file():
                message = f"texture {texture_path} of material {name!r} is missing: using its base colour {base}"
                warn(message)
                warnings.append(message)
            else:
                data = texture_path.read_bytes()
                inputs[str(texture_path)] = hashlib.sha256(data).hexdigest()
                texture = texture_from_image(str(texture_path), read_image(texture_path, data), base)
        roughness, metallic = entry.get("Pr"), entry.get("Pm")
        if (roughness is None) != (metallic is None):
            roughness, metallic = (1.0 if roughness is None else roughness), (0.0 if metallic is None else metallic)
        emission = tuple(float(x) for x in entry["Ke"]) if any(x > 0 for x in entry.get("Ke", ())) else None
        materials[name] = (AssetMaterial(name, base, texture, False, roughness, metallic), emission)
    return materials
