"""Scene names -> recipes, including user meshes (`mesh:PATH`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from nerfgauge.scenes import library
from nerfgauge.scenes.asset_reader import read_asset
from nerfgauge.scenes.assets import MESH_SUFFIXES, UNITS, place_objects, with_texture_period
from nerfgauge.scenes.description import Scene, build_scene
from nerfgauge.scenes.checks import CHECK_RECIPES
from nerfgauge.scenes.envmap import EnvironmentMap, read_envmap
from nerfgauge.scenes.hard import HARD_RECIPES
from nerfgauge.scenes.meshes import MeshData
from nerfgauge.scenes.scene_file import scene_from_file

from nerfgauge.core import arguments
from nerfgauge.core.errors import InputError

# name -> (recipe(seed) -> Scene, one-line description)
RECIPES = {
    "primitives": (library.primitives, "default: red sphere, blue box, green capped cylinder, checker sphere (diffuse)"),
    "glossy": (library.glossy, "view-dependent: rough plastic, rough gold, near-mirror aluminium under a sky with a sun"),
    "random": (library.random_objects, "3-6 objects whose shapes, materials and poses come from the seed"),
    **HARD_RECIPES,
    **CHECK_RECIPES,  # for checking rules on captures nobody tuned them on; not in bench hard
}
MESH_PREFIX = "mesh:"
SCENE_FILE_SUFFIXES = (".toml", ".json")


def list_scenes() -> list[tuple[str, str]]:
    """(name, description) for every scene, user meshes last."""
    rows = [(name, text) for name, (_, text) in RECIPES.items()]
    rows.append((MESH_PREFIX + "PATH", "your asset (.glb/.gltf/.obj+.mtl/.ply/.stl/.off): its objects, names and "
                                        "materials, scaled into [-1, 1]^3 (--units keep: as is)"))
    rows.append(("FILE.toml", "a scene file: several assets at given poses, lights, envmap (docs/scene-files.md)"))
    return rows


def make_scene(spec: str, seed: int, *, units: str = "normalise", envmap=None, envmap_rotation: float = 0.0) -> Scene:
    """Build the scene named `spec` (a recipe name, `mesh:PATH` or a scene file
    `*.toml`/`*.json`) from `seed`.

    units: "normalise" (user assets scaled into [-1, 1]^3) or "keep" (the files' own
    coordinates; procedural recipes are authored in scene units either way). envmap: an
    equirectangular .exr/.hdr that replaces the scene's lights, turned `envmap_rotation`
    degrees about +Z."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    if units not in UNITS:
        raise InputError(f"--units must be one of {', '.join(UNITS)}, got {units!r}")
    arguments.encodable_path(spec, "scene")  # mesh:PATH and scene files: Mitsuba needs UTF-8 paths
    if spec.startswith(MESH_PREFIX):
        scene = mesh_scene(Path(spec[len(MESH_PREFIX):]), int(seed), units)
    elif Path(spec).suffix.lower() in SCENE_FILE_SUFFIXES:
        scene = scene_from_file(Path(spec), int(seed), units)
    elif spec not in RECIPES:
        known = ", ".join(list(RECIPES) + [MESH_PREFIX + "PATH", "FILE.toml"])
        raise InputError(f"unknown scene {spec!r}; known scenes: {known}")
    else:
        scene = RECIPES[spec][0](int(seed))
    if envmap is not None:
        scene = with_envmap(scene, read_envmap(envmap, envmap_rotation))
    return scene


def with_envmap(scene: Scene, light: EnvironmentMap) -> Scene:
    """`scene` lit by `light` alone; the map's file and hash join the scene's inputs."""
    params = dict(scene.params)
    params["inputs"] = {**params.get("inputs", {}), light.path: light.sha256}
    params["envmap"] = {"path": light.path, "sha256": light.sha256, "rotation": light.rotation}
    return dataclasses.replace(scene, lights=(light,), params=params)


def mesh_scene(path: Path, seed: int, units: str = "normalise") -> Scene:
    """A user's asset: one shape per object of the file, with its material and name.

    units "normalise": the whole asset is centred and uniformly scaled so its largest
    extent spans [-1, 1] (the transform is in params["to_scene"]); "keep": the file's
    coordinates are the scene's. The scene's params name every file read (the asset and
    any buffers, materials and textures it refers to) with the sha256 of the bytes that
    were parsed: `scene_inputs` gives them."""
    asset = read_asset(path)
    shapes, to_scene = place_objects(asset.objects, str(path), units)
    return with_texture_period(build_scene(
        f"{MESH_PREFIX}{path}", seed, shapes, [library.SOFT_SKY],
        params={"path": str(path), "sha256": asset.inputs[str(path)], "inputs": asset.inputs, "units": units,
                "to_scene": to_scene, "objects": [s.name for s in shapes]}))


def scene_inputs(scene: Scene) -> dict:
    """{path: sha256} of every file a scene was made from (empty for procedural recipes)."""
    return dict(scene.params.get("inputs", {}))


def load_user_mesh(path: Path) -> MeshData:
    """The mesh of `read_user_mesh`, without its file hashes."""
    return read_user_mesh(path)[0]


def read_user_mesh(path: Path) -> tuple[MeshData, dict]:
    """Every object of an asset as one mesh, normalised into [-1, 1]^3 (see place_objects).
    Returns (mesh, {path: sha256} of the bytes parsed, the mesh file first)."""
    asset = read_asset(path)
    shapes, _ = place_objects(asset.objects, str(path), "normalise")
    meshes = [shape.data for shape in shapes]
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    merged = MeshData(np.concatenate([m.vertices for m in meshes]),
                      np.concatenate([m.faces + offset for m, offset in zip(meshes, offsets)]), None,
                      np.concatenate([m.uv for m in meshes]))
    return merged, asset.inputs
