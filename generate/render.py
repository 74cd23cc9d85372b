"""Render one view: RGBA with the path tracer, exact depth and normals from pixel-centre rays.

Depth is not the filtered depth AOV (averaged across edges, measured from a near-clip
shifted origin): every pixel's centre ray from `nerfgauge.core.camera.pixel_rays` is intersected
with the scene, giving the Euclidean ray distance from the camera centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.camera import (
    Intrinsics,
    ThinLens,
    pixel_rays,
    to_mitsuba,
    z_depth_from_distance,
)

NEAR_CLIP = 1e-3  # scene units; only clips what is closer than this to the camera


@dataclass(frozen=True)
class ViewImages:
    """rgba [H,W,4] linear premultiplied (alpha = coverage); distance, z_depth [H,W]
    (0 where the centre ray misses); normals [H,W,3] world shading normals (0 on
    misses); hit [H,W] bool."""

    rgba: np.ndarray
    distance: np.ndarray
    z_depth: np.ndarray
    normals: np.ndarray
    hit: np.ndarray


def sensor_dict(mi, c2w: np.ndarray, intrinsics: Intrinsics, spp: int, lens: Optional[ThinLens] = None) -> dict:
    """A Mitsuba perspective sensor for an OpenGL camera-to-world pose; Mitsuba's `thinlens`
    sensor (same pose and field of view) when `lens` has a non-zero aperture. A lens with
    aperture 0 is the pinhole: the same perspective sensor, so the same pixels bit for bit."""
    if abs(intrinsics.fx - intrinsics.fy) > 1e-9 * intrinsics.fx or \
            (intrinsics.cx, intrinsics.cy) != (intrinsics.width / 2, intrinsics.height / 2):
        raise ValueError("Mitsuba's perspective sensor needs square pixels and a centred principal point")
    optics = {"type": "perspective"}
    if lens is not None and not lens.is_pinhole:
        # focus_distance: along the optical axis, as camera.thin_lens_rays has it
        optics = {"type": "thinlens", "aperture_radius": float(lens.aperture_radius),
                  "focus_distance": float(lens.focus_distance)}
    return optics | {
        "fov": intrinsics.fov_x_degrees,
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "far_clip": 1e7,
        "to_world": mi.ScalarTransform4f(to_mitsuba(c2w).tolist()),
        "film": {"type": "hdrfilm", "width": intrinsics.width, "height": intrinsics.height,
                 "rfilter": {"type": "box"}, "pixel_format": "rgba", "component_format": "float32"},
        "sampler": sampler_dict(spp),
    }


def sampler_dict(spp: int) -> dict:
    """Multi-jittered samples when Mitsuba can lay `spp` out as a grid exactly; otherwise
    independent samples, so a view never gets a different count than scene.json states.

    Mitsuba's multijitter uses a = floor(sqrt(spp)) columns and ceil(spp / a) rows and
    rounds the count up to their product (32 -> 35)."""
    columns = math.isqrt(int(spp))
    exact = columns * -(-int(spp) // columns) == int(spp)
    return {"type": "multijitter" if exact else "independent", "sample_count": int(spp)}


def render_rgba(mi, scene, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                lens: Optional[ThinLens] = None) -> np.ndarray:
    """Path-traced linear premultiplied RGBA (through `lens` if given). Returns [H, W, 4] float32."""
    sensor = mi.load_dict(sensor_dict(mi, c2w, intrinsics, spp, lens))
    image = mi.render(scene, sensor=sensor, spp=int(spp), seed=int(seed))
    return np.array(image, dtype=np.float32).reshape(intrinsics.height, intrinsics.width, 4)


def cast_rays(mi, scene, origins: np.ndarray, directions: np.ndarray):
    """Intersect rays with the scene.

    origins, directions: [N, 3] (directions unit). Returns distance [N] (inf on miss),
    shading normal [N, 3] (0 on miss), hit [N] bool.
    """
    if mi.variant().startswith("scalar"):
        return _cast_rays_scalar(mi, scene, origins, directions)
    o = mi.Point3f(*(np.ascontiguousarray(origins[:, k], np.float32) for k in range(3)))
    d = mi.Vector3f(*(np.ascontiguousarray(directions[:, k], np.float32) for k in range(3)))
    si = scene.ray_intersect(mi.Ray3f(o, d))
    hit = np.array(si.is_valid(), dtype=bool)
    distance = np.where(hit, np.array(si.t, dtype=np.float64), np.inf)
    normals = np.stack([np.array(si.sh_frame.n[k], dtype=np.float64) for k in range(3)], -1)
    return distance, np.where(hit[:, None], normals, 0.0), hit


def _cast_rays_scalar(mi, scene, origins, directions):
    n = len(origins)
    distance, normals, hit = np.full(n, np.inf), np.zeros((n, 3)), np.zeros(n, bool)
    for index in range(n):
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*origins[index]), mi.Vector3f(*directions[index])))
        if si.is_valid():
            hit[index], distance[index] = True, si.t
            normals[index] = [si.sh_frame.n[0], si.sh_frame.n[1], si.sh_frame.n[2]]
    return distance, normals, hit


def render_geometry(mi, scene, c2w, intrinsics: Intrinsics):
    """Exact distance, z-depth, normals and hit mask from pixel-centre rays."""
    origins, directions = pixel_rays(c2w, intrinsics)
    shape = directions.shape[:2]
    distance, normals, hit = cast_rays(mi, scene, origins.reshape(-1, 3), directions.reshape(-1, 3))
    distance = np.where(hit, distance, 0.0).reshape(shape)
    z_depth = z_depth_from_distance(distance, directions, c2w)
    return (distance.astype(np.float32), z_depth.astype(np.float32),
            normals.reshape(*shape, 3).astype(np.float32), hit.reshape(shape))


def render_view(mi, scene, c2w, intrinsics: Intrinsics, spp: int, seed: int,
                lens: Optional[ThinLens] = None) -> ViewImages:
    """Colour through `lens` (None: pinhole); depth, normals and mask always from the
    pinhole pixel-centre rays, whatever the lens."""
    rgba = render_rgba(mi, scene, c2w, intrinsics, spp, seed, lens)
    distance, z_depth, normals, hit = render_geometry(mi, scene, c2w, intrinsics)
    return ViewImages(rgba, distance, z_depth, normals, hit)
