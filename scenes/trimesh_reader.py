"""Asset files read through trimesh: glTF/GLB scene graphs (one object per node that holds a
mesh, at the node's world transform), PLY, STL and OFF (one unnamed object), with their
glTF materials. A module of its own so that trimesh (1.4 s to import, with scipy and
networkx) is loaded only when such a file is read (scenes/asset_reader.py imports it then),
not by every `nerfgauge` command that imports the scene recipes.
"""

from __future__ import annotations

import hashlib
import io
import struct
import urllib.parse
from pathlib import Path

import numpy as np
import trimesh
import trimesh.resolvers
from nerfgauge.scenes.assets import (UNNAMED, AssetMaterial, AssetObject, TextureImage, apply_matrix, checked_mesh,
                                     read_image, texture_from_image, warn)

from nerfgauge.core import bounded
from nerfgauge.core.errors import InputError


class RecordingResolver(trimesh.resolvers.FilePathResolver):
    """trimesh's resolver for files a mesh refers to (glTF buffers and images), noting the
    sha256 of each one it reads (they are inputs too) and each one that is missing."""

    def __init__(self, mesh_path: Path):
        super().__init__(str(mesh_path))
        self.read, self.missing = {}, []

    def get(self, name: str):
        try:
            data = super().get(name)
        except (FileNotFoundError, IsADirectoryError):
            self.missing.append(str(Path(self.parent) / name))
            raise
        self.read[str(Path(self.parent) / name)] = hashlib.sha256(data).hexdigest()
        return data


def gltf_json(suffix: str, content: bytes) -> dict:
    """The JSON document of a .gltf, or of a .glb's first chunk; {} if there is none."""
    try:
        if suffix == ".gltf":
            document = bounded.loads_json(content, "glTF")
        else:
            length, kind = struct.unpack_from("<I4s", content, 12)
            document = bounded.loads_json(content[20:20 + length], "glTF") if kind == b"JSON" else {}
    except (ValueError, struct.error):
        return {}  # not readable as glTF: trimesh's own error names the problem
    return document if isinstance(document, dict) else {}


def check_gltf_images(path: Path, suffix: str, content: bytes) -> None:
    """A glTF image file that exists but does not decode is an error (trimesh would drop
    the texture silently). Missing ones are left to the resolver's warning."""
    images = gltf_json(suffix, content).get("images")
    for image in images if isinstance(images, list) else []:
        uri = image.get("uri") if isinstance(image, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:"):
            image_path = path.parent / urllib.parse.unquote(uri)
            if image_path.is_file():
                read_image(image_path, image_path.read_bytes())


def read_with_trimesh(path, suffix, content, inputs, warnings) -> list:
    exact_factors = {}
    if suffix in (".gltf", ".glb"):
        check_gltf_images(path, suffix, content)
        exact_factors = gltf_base_color_factors(gltf_json(suffix, content))
    resolver = RecordingResolver(path)
    try:
        loaded = trimesh.load(io.BytesIO(content), file_type=suffix[1:], resolver=resolver, process=False)
    except ImportError as error:  # an optional parser trimesh reaches for: one line, not a missing-module trace
        needs = ("its text is not UTF-8, and guessing another encoding needs the optional package charset_normalizer"
                 if error.name == "charset_normalizer" else f"reading it needs the optional package {error.name or error}")
        raise InputError(f"cannot read mesh {path}: not a valid {suffix} mesh ({needs})") from None
    except Exception as error:  # trimesh raises many types for malformed files
        if resolver.missing:
            raise InputError(f"cannot read mesh {path}: it refers to {resolver.missing[0]}, which is missing") from None
        detail = str(error).splitlines()[0] if str(error).strip() else type(error).__name__
        raise InputError(f"cannot read mesh {path}: not a valid {suffix} mesh ({detail})") from None
    inputs.update(resolver.read)
    if resolver.missing:
        message = f"{path} refers to missing {', '.join(resolver.missing)}: using the base colour instead"
        warn(message)
        warnings.append(message)
    if isinstance(loaded, trimesh.Scene):
        objects = []
        for node in loaded.graph.nodes_geometry:
            matrix, geometry_name = loaded.graph[node]
            geometry = loaded.geometry[geometry_name]
            if isinstance(geometry, trimesh.Trimesh):
                objects.append(_trimesh_object(path, str(node), geometry, np.asarray(matrix, np.float64),
                                              exact_factors))
        return objects
    if isinstance(loaded, trimesh.Trimesh):
        return [_trimesh_object(path, UNNAMED, loaded, np.eye(4))]
    return []


def gltf_base_color_factors(document: dict) -> dict:
    """{material name: baseColorFactor [4]} as the glTF file states it (trimesh keeps the
    factor as 8-bit, 0.5 -> 128/255); only names that occur once."""
    materials = document.get("materials")
    factors, seen = {}, set()
    for material in materials if isinstance(materials, list) else []:
        if not isinstance(material, dict) or not isinstance(material.get("name"), str):
            continue
        name = material["name"]
        factor = (material.get("pbrMetallicRoughness") or {}).get("baseColorFactor") \
            if isinstance(material.get("pbrMetallicRoughness"), dict) else None
        if name in seen:
            factors.pop(name, None)
        elif isinstance(factor, list) and len(factor) == 4 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and 0 <= x <= 1 for x in factor):
            factors[name] = [float(x) for x in factor]
        seen.add(name)
    return factors


def _trimesh_object(path, name, geometry: trimesh.Trimesh, matrix: np.ndarray, exact_factors=None) -> AssetObject:
    vertices = np.asarray(geometry.vertices, np.float64)
    faces = np.asarray(geometry.faces, np.int64)
    # The file's normals: trimesh keeps normals it was given in its cache (it would
    # compute some on access otherwise, and a flat-shaded file must stay flat).
    normals = geometry._cache.cache.get("vertex_normals")
    visual = geometry.visual
    uv = getattr(visual, "uv", None) if visual.kind == "texture" else None
    colors = None
    if visual.kind == "vertex":
        colors = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255
    elif visual.kind == "face":  # one colour per face: every corner its own vertex
        checked_mesh(path, vertices, faces)  # faces index existing vertices before they are unshared
        corners = faces.reshape(-1)
        vertices, faces = vertices[corners], np.arange(len(corners)).reshape(-1, 3)
        normals = None if normals is None else np.asarray(normals)[corners]
        colors = np.repeat(np.asarray(visual.face_colors, np.float64)[:, :3] / 255, 3, axis=0)
    if uv is not None and len(uv) != len(vertices):
        uv = None
    mesh = checked_mesh(path, vertices, faces, normals, uv, colors)
    mesh = apply_matrix(mesh, matrix)
    material, emission = None, None
    if visual.kind == "texture" and getattr(visual, "material", None) is not None:
        material, emission = _gltf_material(path, visual.material, has_uv=uv is not None,
                                            exact_factors=exact_factors or {})
    if colors is not None:
        material = AssetMaterial("vertex_colors", (1.0, 1.0, 1.0), vertex_colors=True)
    return AssetObject(name, mesh, material, emission)


def _gltf_material(path, material, has_uv: bool, exact_factors: dict):
    """(AssetMaterial, emission or None) from a trimesh PBRMaterial or SimpleMaterial;
    the base colour factor as the file states it where `exact_factors` has it."""
    name = str(getattr(material, "name", None) or "material")
    if isinstance(material, trimesh.visual.material.SimpleMaterial):
        material = material.to_pbr()
    stored = material.baseColorFactor
    if name in exact_factors:
        factor = np.asarray(exact_factors[name], np.float64)
    elif stored is None:
        factor = np.ones(4)
    else:
        factor = np.asarray(stored, np.float64)
        factor = factor / 255 if np.asarray(stored).dtype.kind in "iu" or factor.max() > 1 else factor
    alpha_mode = str(getattr(material, "alphaMode", None) or "OPAQUE").upper()
    if alpha_mode in ("BLEND", "MASK"):
        raise InputError(f"mesh {path}: material {name!r} is transparent (alphaMode {alpha_mode}), "
                         "which nerfgauge cannot render; make it OPAQUE")
    if getattr(material, "emissiveTexture", None) is not None:
        raise InputError(f"mesh {path}: material {name!r} has an emissive texture, which nerfgauge cannot render; "
                         "remove it (a constant emissiveFactor is supported)")
    emissive = getattr(material, "emissiveFactor", None)
    emission = None
    if emissive is not None and np.any(np.asarray(emissive, np.float64) > 0):
        emission = tuple(float(x) for x in np.asarray(emissive, np.float64)[:3])
    base = tuple(float(x) for x in factor[:3])
    texture = None
    image = getattr(material, "baseColorTexture", None)
    if image is not None and has_uv:
        texture = texture_from_image(f"{path}#{name}", image, base)
    roughness = None if material.roughnessFactor is None else float(material.roughnessFactor)
    metallic = None if material.metallicFactor is None else float(material.metallicFactor)
    packed = getattr(material, "metallicRoughnessTexture", None)
    roughness_texture = metallic_texture = None
    if packed is not None and has_uv:  # the factors (default 1) scale the texture's G and B
        roughness = 1.0 if roughness is None else roughness
        metallic = 1.0 if metallic is None else metallic
        channels = np.asarray(packed.convert("RGB"), np.float64) / 255  # linear, not sRGB
        roughness_texture = TextureImage.from_pixels(f"{path}#{name}/roughness", channels[..., 1:2] * roughness)
        metallic_texture = TextureImage.from_pixels(f"{path}#{name}/metallic", channels[..., 2:3] * metallic)
    if (roughness is None) != (metallic is None):  # glTF's default for the one not given is 1
        roughness, metallic = (1.0 if roughness is None else roughness), (1.0 if metallic is None else metallic)
    return AssetMaterial(name, base, texture, False, roughness, metallic, roughness_texture, metallic_texture), emission
