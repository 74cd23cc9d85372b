"""Scene files: several assets at given poses, lights, an environment map and camera hints,
in a small versioned TOML or JSON file, usable wherever a scene name is.

The format is documented in docs/scene-files.md. Every key is checked: an unknown key, a
missing asset, a pose that is not rotation + uniform scale + translation, or a value of
the wrong kind is a one-line InputError naming the file and the entry.
Paths inside the file are relative to the file's folder.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from pathlib import Path

import numpy as np
from nerfgauge.scenes import library
from nerfgauge.scenes.asset_reader import read_asset
from nerfgauge.scenes.assets import (
    UNITS,
    AssetMaterial,
    AssetObject,
    apply_matrix,
    place_objects,
    unique_names,
    with_texture_period,
)
from nerfgauge.scenes.description import (
    BACKGROUNDS,
    CameraHint,
    ConstantEnvironment,
    GradientEnvironment,
    PointLight,
    RectangleLight,
    Scene,
    build_scene,
)
from nerfgauge.scenes.envmap import read_envmap
from nerfgauge.scenes.meshes import rotation_matrix

from nerfgauge.core import bounded
from nerfgauge.core.errors import InputError

VERSION = 1
TOP_KEYS = {"version", "asset", "light", "envmap", "camera", "background"}
ASSET_KEYS = {"path", "name", "translation", "rotation", "scale", "matrix", "material"}
MATERIAL_KEYS = {"base_color", "roughness", "metallic"}
LIGHT_KEYS = {
    "constant": {"type", "radiance"},
    "sky": {"type", "zenith", "horizon", "nadir", "sun_direction", "sun_radiance", "sun_angle"},
    "point": {"type", "position", "intensity"},
    "rectangle": {"type", "center", "size", "normal", "radiance"},
}
ENVMAP_KEYS = {"path", "rotation"}
CAMERA_KEYS = {"layout", "radius", "elevation", "eye", "target", "spread"}
RIGID_TOLERANCE = 1e-6  # relative: columns of a pose's 3x3 part equal in length and orthogonal


class _Where:
    """Names the file and entry in every error: "scene file S: [[asset]] 2: ..."."""

    def __init__(self, path: Path):
        self.path = path

    def error(self, where: str, message: str) -> InputError:
        return InputError(f"scene file {self.path}: {where}{': ' if where else ''}{message}")

    def table(self, value, where: str, known: set) -> dict:
        if not isinstance(value, dict):
            raise self.error(where, f"expected a table, got {type(value).__name__}")
        unknown = sorted(set(value) - known)
        if unknown:
            raise self.error(where, f"unknown key {unknown[0]!r}; known keys: {', '.join(sorted(known))}")
        return value

    def number(self, value, where: str, *, positive=False, nonnegative=False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(where, f"expected a finite number, got {value!r}")
        if positive and value <= 0 or nonnegative and value < 0:
            raise self.error(where, f"expected a {'positive' if positive else 'non-negative'} number, got {value!r}")
        return float(value)

    def vector(self, value, where: str, length: int = 3, nonnegative=False) -> tuple:
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise self.error(where, f"expected a list of {length} numbers, got {value!r}")
        return tuple(self.number(x, where, nonnegative=nonnegative) for x in value)


def read_scene_document(path: Path) -> tuple[dict, bytes]:
    """The parsed TOML/JSON of a scene file and its bytes."""
    if not path.is_file():
        raise InputError(f"scene file not found: {path}")
    is_toml = path.suffix.lower() == ".toml"
    content = bounded.read_bytes(path, bounded.MAX_TOML_BYTES if is_toml else bounded.MAX_JSON_BYTES, "scene file")
    try:
        if is_toml:
            document = bounded.loads_toml(content, f"scene file {path}")
        else:
            document = bounded.loads_json(content, f"scene file {path}")
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as error:
        detail = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"scene file {path}: not valid {path.suffix.lower()[1:].upper()} ({detail})") from None
    if not isinstance(document, dict):
        raise InputError(f"scene file {path}: expected a table at the top, got {type(document).__name__}")
    return document, content


def scene_from_file(path: Path, seed: int, units: str = "normalise") -> Scene:
    """Build the Scene a scene file describes (see docs/scene-files.md). units: as for
    mesh:PATH; "normalise" scales the whole composed scene into [-1, 1]^3 and moves lights
    and camera hints with it."""
    if units not in UNITS:
        raise InputError(f"--units must be one of {', '.join(UNITS)}, got {units!r}")
    where = _Where(path)
    document, content = read_scene_document(path)
    where.table(document, "", TOP_KEYS)
    if "version" not in document:
        raise where.error("", f"missing 'version' (this nerfgauge reads version = {VERSION})")
    if document["version"] != VERSION or isinstance(document["version"], bool):
        raise where.error("", f"version {document['version']!r} is not one this nerfgauge reads (version = {VERSION})")
    assets = document.get("asset")
    if not isinstance(assets, list) or not assets:
        raise where.error("", "needs at least one [[asset]] (a list of tables)")
    inputs = {str(path): hashlib.sha256(content).hexdigest()}
    objects, records = [], []
    for index, entry in enumerate(assets, 1):
        label = f"[[asset]] {index}"
        entry = where.table(entry, label, ASSET_KEYS)
        placed, record = _asset_objects(where, path, label, entry, inputs)
        objects += placed
        records.append(record)
    shapes, to_scene = place_objects(unique_names(objects), str(path), units)
    scale, shift = to_scene["scale"], np.asarray(to_scene["translation"])
    lights = [_light(where, f"[[light]] {i}", entry, scale, shift) for i, entry in
              enumerate(_list(where, document.get("light", []), "light"), 1)]
    params = {"path": str(path), "version": VERSION, "units": units, "to_scene": to_scene, "assets": records,
              "objects": [shape.name for shape in shapes], "inputs": inputs}
    envmap = None
    if "envmap" in document:
        table = where.table(document["envmap"], "[envmap]", ENVMAP_KEYS)
        if "path" not in table or not isinstance(table["path"], str):
            raise where.error("[envmap]", "needs path = \"FILE.exr\"")
        rotation = where.number(table.get("rotation", 0.0), "[envmap] rotation")
        envmap = read_envmap(path.parent / table["path"], rotation)
        inputs[envmap.path] = envmap.sha256
        params["envmap"] = {"path": envmap.path, "sha256": envmap.sha256, "rotation": envmap.rotation}
        lights.append(envmap)
    environments = [light for light in lights if not isinstance(light, (PointLight, RectangleLight))]
    if len(environments) > 1:
        raise where.error("", "more than one environment (constant, sky, [envmap]); the renderer takes one")
    if not lights:
        lights = [library.SOFT_SKY]
    background = document.get("background", "transparent")
    if background not in BACKGROUNDS:
        raise where.error("background", f"expected one of {', '.join(BACKGROUNDS)}, got {background!r}")
    cameras = _camera(where, document["camera"], scale, shift) if "camera" in document else None
    return with_texture_period(build_scene(str(path), seed, shapes, lights, background=background, params=params,
                                           cameras=cameras))


def _list(where: _Where, value, key: str) -> list:
    if not isinstance(value, list):
        raise where.error(key, f"expected a list of tables ([[{key}]]), got {type(value).__name__}")
    return value


def pose_matrix(where: _Where, label: str, entry: dict) -> np.ndarray:
    """4x4 from translation, rotation (Euler degrees, R = Rz Ry Rx) and a uniform scale, or
    from `matrix` (4x4 rows), which must be rotation times a positive uniform scale plus a
    translation: shear, non-uniform scale, mirroring and projection are refused."""
    if "matrix" in entry:
        clash = sorted({"translation", "rotation", "scale"} & set(entry))
        if clash:
            raise where.error(label, f"give either matrix or {', '.join(clash)}, not both")
        rows = entry["matrix"]
        if not isinstance(rows, list) or len(rows) != 4:
            raise where.error(f"{label} matrix", "expected 4 rows of 4 numbers")
        matrix = np.array([where.vector(row, f"{label} matrix", 4) for row in rows])
        if not np.allclose(matrix[3], [0, 0, 0, 1]):
            raise where.error(f"{label} matrix", f"last row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    else:
        scale = entry.get("scale", 1.0)
        if isinstance(scale, list):
            raise where.error(f"{label} scale", f"a pose is rigid with one uniform scale; got {scale!r} "
                                                "(non-uniform scale is not supported)")
        scale = where.number(scale, f"{label} scale", positive=True)
        matrix = np.eye(4)
        matrix[:3, :3] = rotation_matrix(where.vector(entry.get("rotation", [0, 0, 0]), f"{label} rotation")) * scale
        matrix[:3, 3] = where.vector(entry.get("translation", [0, 0, 0]), f"{label} translation")
    linear = matrix[:3, :3]
    lengths = np.linalg.norm(linear, axis=0)
    gram = linear.T @ linear
    size = float(lengths.max())
    if size <= 0 or not np.allclose(gram, np.eye(3) * size**2, rtol=0, atol=RIGID_TOLERANCE * size**2) \
            or np.linalg.det(linear) <= 0:
        raise where.error(f"{label} matrix", "not a rigid pose with one positive uniform scale "
                                             "(shear, non-uniform scale or mirroring)")
    return matrix


def _asset_objects(where: _Where, scene_path: Path, label: str, entry: dict, inputs: dict) -> tuple[list, dict]:
    if not isinstance(entry.get("path"), str) or not entry["path"]:
        raise where.error(label, "needs path = \"FILE\" (a .glb, .gltf, .obj, .ply, .stl or .off)")
    asset_path = scene_path.parent / entry["path"]
    matrix = pose_matrix(where, label, entry)
    try:
        asset = read_asset(asset_path)
    except InputError as error:
        raise where.error(label, str(error)) from None
    inputs.update(asset.inputs)
    name = entry.get("name", asset_path.stem)
    if not isinstance(name, str) or not name:
        raise where.error(f"{label} name", f"expected a non-empty string, got {name!r}")
    material = _material(where, f"{label} material", entry["material"]) if "material" in entry else None
    placed = []
    for obj in asset.objects:
        object_name = name if len(asset.objects) == 1 else f"{name}_{obj.name}"
        # A uniform scale keeps normals' directions: apply_matrix re-normalises them.
        placed.append(AssetObject(object_name, apply_matrix(obj.mesh, matrix), material or obj.material, obj.emission))
    record = {"name": name, "path": str(asset_path), "sha256": asset.inputs[str(asset_path)],
              "matrix": matrix.tolist(), "objects": [obj.name for obj in asset.objects]}
    return placed, record


def _material(where: _Where, label: str, table) -> AssetMaterial:
    table = where.table(table, label, MATERIAL_KEYS)
    base = where.vector(table.get("base_color", [0.6, 0.6, 0.6]), f"{label} base_color", nonnegative=True)
    if max(base) > 1:
        raise where.error(f"{label} base_color", f"albedo must be within [0, 1], got {list(base)}")
    roughness = table.get("roughness")
    metallic = table.get("metallic")
    for key, value in (("roughness", roughness), ("metallic", metallic)):
        if value is not None and not 0 <= where.number(value, f"{label} {key}") <= 1:
            raise where.error(f"{label} {key}", f"expected a number in [0, 1], got {value!r}")
    if (roughness is None) != (metallic is None):  # as glTF: the one not given is 1 for roughness, 0 for metal
        roughness, metallic = (1.0 if roughness is None else roughness), (0.0 if metallic is None else metallic)
    return AssetMaterial("override", base, None, False, None if roughness is None else float(roughness),
                         None if metallic is None else float(metallic))


def _light(where: _Where, label: str, entry, scale: float, shift: np.ndarray):
    """A light, moved into scene units: positions by the to_scene map, sizes by its scale,
    a point light's intensity by scale^2 (so the irradiance it gives is unchanged)."""
    if not isinstance(entry, dict) or entry.get("type") not in LIGHT_KEYS:
        kind = entry.get("type") if isinstance(entry, dict) else entry
        raise where.error(label, f"type must be one of {', '.join(LIGHT_KEYS)}, got {kind!r}")
    kind = entry["type"]
    where.table(entry, label, LIGHT_KEYS[kind])
    vec = lambda key, default=None, **kw: where.vector(entry.get(key, default), f"{label} {key}", **kw)  # noqa: E731
    if kind == "constant":
        return ConstantEnvironment(vec("radiance", nonnegative=True))
    if kind == "sky":
        sun = entry.get("sun_direction")
        return GradientEnvironment(vec("zenith", nonnegative=True), vec("horizon", nonnegative=True),
                                   vec("nadir", nonnegative=True),
                                   None if sun is None else vec("sun_direction"),
                                   vec("sun_radiance", [0, 0, 0], nonnegative=True),
                                   where.number(entry.get("sun_angle", 3.0), f"{label} sun_angle", positive=True))
    if kind == "point":
        position = np.asarray(vec("position")) * scale + shift
        return PointLight(tuple(float(x) for x in position),
                          tuple(float(x) * scale**2 for x in vec("intensity", nonnegative=True)))
    size = where.vector(entry.get("size"), f"{label} size", 2, nonnegative=True)
    normal = vec("normal")
    if np.linalg.norm(normal) == 0:
        raise where.error(f"{label} normal", "must not be zero")
    center = np.asarray(vec("center")) * scale + shift
    return RectangleLight(tuple(float(x) for x in center), (size[0] * scale, size[1] * scale), normal,
                          vec("radiance", nonnegative=True))


def _camera(where: _Where, table, scale: float, shift: np.ndarray) -> CameraHint:
    table = where.table(table, "[camera]", CAMERA_KEYS)
    layout = table.get("layout", "auto")
    if not isinstance(layout, str):
        raise where.error("[camera] layout", f"expected a layout name, got {layout!r}")
    point = lambda key: None if key not in table else tuple(  # noqa: E731
        float(x) for x in np.asarray(where.vector(table[key], f"[camera] {key}")) * scale + shift)
    length = lambda key: None if key not in table else where.number(table[key], f"[camera] {key}", positive=True) * scale  # noqa: E731
    elevation = None if "elevation" not in table else where.vector(table["elevation"], "[camera] elevation", 2)
    return CameraHint(layout, radius=length("radius"), elevation=elevation, eye=point("eye"), target=point("target"),
                      spread=length("spread"))
