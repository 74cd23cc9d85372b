"""A `scenes.Scene` as a Mitsuba scene. Meshes are loaded from the dataset's own
`meshes/*.ply`, so what is rendered is exactly the ground-truth geometry on disk.

`mi` is the mitsuba module with its variant already set (see generate.variant).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from nerfgauge.core import owned
from nerfgauge.generate.ply import write_ply
from nerfgauge.scenes.description import (
    Conductor,
    ConstantEnvironment,
    Dielectric,
    Diffuse,
    GradientEnvironment,
    PointLight,
    RectangleLight,
    RoughPlastic,
    Sphere,
    Textured,
)
from nerfgauge.scenes.assets import AssetMaterial
from nerfgauge.scenes.envmap import EnvironmentMap
from nerfgauge.scenes.meshes import MeshData, pose

ENVMAP_WIDTH = 512  # 0.7 degrees per texel: enough for a 3-degree sun disc
# Mitsuba's envmap is +Y up; ours is +Z up. Rotating 90 degrees about X maps +Y to +Z.
ENVMAP_TO_WORLD = pose((0, 0, 0), (90, 0, 0))


def rectangle_mesh(light: RectangleLight) -> MeshData:
    """A rectangle light as two triangles facing along `light.normal`."""
    normal = np.asarray(light.normal, np.float64)
    normal /= np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    hu, hv = light.size[0] / 2 * u, light.size[1] / 2 * v
    c = np.asarray(light.center, np.float64)
    vertices = np.stack([c - hu - hv, c + hu - hv, c + hu + hv, c - hu + hv])
    return MeshData(vertices, np.array([[0, 1, 2], [0, 2, 3]]), np.tile(normal, (4, 1)), np.zeros((4, 2)))


def ground_truth_meshes(scene) -> dict:
    """{file stem: MeshData} of everything a camera ray can hit (shapes and area lights)."""
    meshes = {shape.name: shape.mesh() for shape in scene.shapes}
    for index, light in enumerate(scene.lights):
        if isinstance(light, RectangleLight):
            meshes[f"light_{index}"] = rectangle_mesh(light)
    return meshes


def instance_names(scene) -> list:
    """The instance legend: names of everything a camera ray can hit (the keys of
    scene_dict's shapes and rectangle lights), sorted, so id k (1-based) names the same
    shape in every view and run. render.instance_legend reads the same list back from the
    loaded Mitsuba scene (its shape ids are these keys)."""
    names = [shape.name for shape in scene.shapes]
    names += [f"light_{index}" for index, light in enumerate(scene.lights) if isinstance(light, RectangleLight)]
    return sorted(names)


def write_meshes(scene, folder: Path) -> dict:
    """Write every ground-truth mesh as `folder/<name>.ply`. Returns {name: path}."""
    owned.make_folder(folder)
    paths = {}
    for name, mesh in ground_truth_meshes(scene).items():
        paths[name] = folder / f"{name}.ply"
        write_ply(paths[name], mesh)
    return paths


def _rgb(mi, value):
    return {"type": "rgb", "value": [float(x) for x in value]}


def bsdf_dict(mi, material, uv_extent) -> dict:
    """Mitsuba BSDF for a material. Opaque BSDFs are two-sided so thin plates shade on both."""
    if isinstance(material, Diffuse):
        bsdf = {"type": "diffuse", "reflectance": _rgb(mi, material.color)}
    elif isinstance(material, Textured):
        tile = material.tile()
        su, sv = (extent / material.period for extent in uv_extent)
        bsdf = {"type": "diffuse", "reflectance": {
            "type": "bitmap", "bitmap": mi.Bitmap(tile), "raw": True, "filter_type": "nearest",
            "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([su, sv, 1.0])}}
    elif isinstance(material, RoughPlastic):
        bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": float(material.roughness),
                "diffuse_reflectance": _rgb(mi, material.color)}
    elif isinstance(material, Conductor):
        if material.roughness == 0:
            bsdf = {"type": "conductor", "material": material.metal}
        else:
            bsdf = {"type": "roughconductor", "material": material.metal, "distribution": "ggx",
                    "alpha": float(material.roughness)}
    elif isinstance(material, Dielectric):
        return {"type": "dielectric", "int_ior": float(material.ior)}
    elif isinstance(material, AssetMaterial):
        bsdf = asset_bsdf_dict(mi, material)
    else:
        raise TypeError(f"no Mitsuba BSDF for material {type(material).__name__}")
    return {"type": "twosided", "bsdf": bsdf}


def asset_bsdf_dict(mi, material: AssetMaterial) -> dict:
    """A user asset's material: diffuse, or principled where the file gives roughness or
    metallic. The albedo is the texture (already times the base colour), the mesh's
    `vertex_color` attribute, or the base colour."""
    if material.texture is not None:
        # Asset uv has v up (OBJ/trimesh: v = 0 is the image's bottom row); Mitsuba's bitmap
        # puts v = 0 at row 0, so the rows are handed over bottom first.
        albedo = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(material.texture.pixels[::-1])),
                  "raw": True, "wrap_mode": "repeat"}
    elif material.vertex_colors:
        albedo = {"type": "mesh_attribute", "name": "vertex_color"}
    else:
        albedo = _rgb(mi, material.base_color)
    if not material.view_dependent:
        return {"type": "diffuse", "reflectance": albedo}

    def scalar_or_texture(value, texture):  # one-channel textures, rows bottom first as above
        if texture is None:
            return float(value)
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture.pixels[::-1])), "raw": True,
                "wrap_mode": "repeat"}

    return {"type": "principled", "base_color": albedo,
            "roughness": scalar_or_texture(material.roughness, material.roughness_texture),
            "metallic": scalar_or_texture(material.metallic, material.metallic_texture)}


def envmap_bitmap(light: GradientEnvironment, width: int = ENVMAP_WIDTH) -> np.ndarray:
    """Sample the sky at the directions of Mitsuba's lat-long texels. Returns [w/2, w, 3].

    Mitsuba maps a local direction v to (u, v) = (atan2(v.x, -v.z) / 2pi, acos(v.y) / pi);
    with ENVMAP_TO_WORLD, local (x, y, z) is world (x, -z, y).
    """
    rows = width // 2
    theta = (np.arange(rows) + 0.5) / rows * math.pi  # [rows] angle from world +Z
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi  # [width]
    sin_t = np.sin(theta)[:, None]
    local = np.stack(np.broadcast_arrays(sin_t * np.sin(phi), np.cos(theta)[:, None], -sin_t * np.cos(phi)), -1)
    world = np.stack([local[..., 0], -local[..., 2], local[..., 1]], -1)  # [rows, width, 3]
    return light.radiance(world)


# scalar_rgb seeds each pixel's sampler from its image block's number, and Mitsuba shrinks the
# blocks until every render thread has one: a fixed size keeps a view's noise independent of
# the thread count (the machine's cores, or a dask worker's share of them). 32 is Mitsuba's own.
SCALAR_BLOCK_SIZE = 32


def scene_dict(mi, scene, mesh_paths: dict, max_depth: int) -> dict:
    """The whole Mitsuba scene (without sensor: each view brings its own)."""
    # A transparent background hides the sky from camera rays; Mitsuba's switch hides every
    # directly seen emitter, so it is only set when there is a sky to hide (a scene without
    # one keeps its lamps visible, and its misses are transparent anyway).
    has_sky = any(isinstance(light, (ConstantEnvironment, GradientEnvironment, EnvironmentMap)) for light in scene.lights)
    out = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth),
                                           "hide_emitters": scene.needs.background == "transparent" and has_sky,
                                           "block_size": SCALAR_BLOCK_SIZE}}
    for shape in scene.shapes:
        if isinstance(shape, Sphere):
            entry = {"type": "sphere", "center": [float(x) for x in shape.center], "radius": float(shape.radius)}
        else:
            entry = {"type": "ply", "filename": str(mesh_paths[shape.name]),
                     "face_normals": shape.mesh().normals is None}
        entry["bsdf"] = bsdf_dict(mi, shape.material, shape.uv_extent())
        if shape.emission is not None:
            entry["emitter"] = {"type": "area", "radiance": _rgb(mi, shape.emission)}
        out[shape.name] = with_vertex_colors(mi, entry, shape)
    for index, light in enumerate(scene.lights):
        out[f"light_{index}"] = light_dict(mi, light, mesh_paths.get(f"light_{index}"))
    return out


def with_vertex_colors(mi, entry: dict, shape):
    """The shape as loaded, with its per-vertex colours as the `vertex_color` attribute
    the mesh_attribute texture reads; `entry` unchanged for shapes without colours. The PLY
    on disk keeps the vertex order of the MeshData, so the colours line up."""
    colors = None if entry["type"] != "ply" else shape.mesh().colors
    if colors is None:
        return entry
    loaded = mi.load_dict(entry)
    loaded.add_attribute("vertex_color", 3, np.asarray(colors, np.float32).ravel().tolist())
    return loaded


def envmap_to_world(rotation_degrees: float) -> np.ndarray:
    """Mitsuba envmap frame -> world: +Y up to +Z up, then `rotation_degrees` about +Z."""
    return pose((0, 0, 0), (0, 0, rotation_degrees)) @ ENVMAP_TO_WORLD


def light_dict(mi, light, mesh_path=None) -> dict:
    if isinstance(light, EnvironmentMap):
        return {"type": "envmap", "bitmap": mi.Bitmap(light.pixels),
                "to_world": mi.ScalarTransform4f(envmap_to_world(light.rotation).tolist())}
    if isinstance(light, ConstantEnvironment):
        return {"type": "constant", "radiance": _rgb(mi, light.radiance)}
    if isinstance(light, GradientEnvironment):
        return {"type": "envmap", "bitmap": mi.Bitmap(envmap_bitmap(light)),
                "to_world": mi.ScalarTransform4f(ENVMAP_TO_WORLD.tolist())}
    if isinstance(light, PointLight):
        return {"type": "point", "position": [float(x) for x in light.position],
                "intensity": _rgb(mi, light.intensity)}
    if isinstance(light, RectangleLight):
        return {"type": "ply", "filename": str(mesh_path), "face_normals": True,
                "bsdf": {"type": "diffuse", "reflectance": _rgb(mi, (0, 0, 0))},
                "emitter": {"type": "area", "radiance": _rgb(mi, light.radiance)}}
    raise TypeError(f"no Mitsuba emitter for light {type(light).__name__}")
