"""Depth ground truth is exact: against an analytic sphere, and against the dataset's own
meshes re-cast with trimesh from cameras read by a minimal NeRF-synthetic loader."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from nerfgauge.scenes.description import (
    ConstantEnvironment,
    Diffuse,
    Sphere,
    build_scene,
)

from nerfgauge.core.camera import Intrinsics, look_at, pixel_rays
from nerfgauge.core.images import read_exr_single, read_png


def analytic_sphere_distance(origins, directions, center, radius):
    """Nearest positive root of |o + t d - c|^2 = r^2 (unit d). Returns t [N], hit [N]."""
    oc = origins - center
    b = np.einsum("ij,ij->i", oc, directions)
    c = np.einsum("ij,ij->i", oc, oc) - radius**2
    disc = b * b - c
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    return np.where(hit, t, 0.0), hit, disc


@pytest.mark.parametrize("width,height", [(48, 48), (64, 40)])
def test_depth_of_an_analytic_sphere(mi, tmp_path, width, height):
    from nerfgauge.generate.mitsuba_scene import scene_dict
    from nerfgauge.generate.render import render_geometry

    center, radius = np.array([0.2, -0.1, 0.3]), 0.7
    scene = build_scene("sphere", 0, [Sphere("ball", tuple(center), radius, Diffuse((0.5, 0.5, 0.5)))],
                        [ConstantEnvironment((1.0, 1.0, 1.0))])
    mitsuba_scene = mi.load_dict(scene_dict(mi, scene, {}, max_depth=2))
    c2w = look_at((1.5, -2.5, 1.2), (0.0, 0.0, 0.2))
    intrinsics = Intrinsics.from_fov(width, height, 45.0)
    distance, z_depth, normals, hit = render_geometry(mi, mitsuba_scene, c2w, intrinsics)

    origins, directions = pixel_rays(c2w, intrinsics)
    t, analytic_hit, disc = analytic_sphere_distance(origins.reshape(-1, 3), directions.reshape(-1, 3), center, radius)
    # Grazing rays (discriminant within float32 reach of 0) may go either way.
    certain = np.abs(disc) > 1e-4 * radius**2
    np.testing.assert_array_equal(hit.ravel()[certain], analytic_hit[certain])
    both = hit.ravel() & analytic_hit & certain
    assert both.sum() > 0.2 * both.size  # the sphere fills a good part of the view
    # Mitsuba intersects in float32 relative to the sphere centre: ~1e-6 relative.
    np.testing.assert_allclose(distance.ravel()[both], t[both], rtol=1e-4)
    assert (distance[~hit] == 0).all() and (z_depth[~hit] == 0).all()
    cosine = (directions @ -c2w[:3, 2])
    np.testing.assert_allclose(z_depth[hit], distance[hit] * cosine[hit], rtol=1e-6)
    # Normals: unit and radial on the sphere.
    points = origins.reshape(-1, 3)[both] + t[both, None] * directions.reshape(-1, 3)[both]
    np.testing.assert_allclose(normals.reshape(-1, 3)[both], (points - center) / radius, atol=1e-3)


def load_nerf_synthetic(root, split):
    """The least a NeRF-synthetic loader reads: camera_angle_x and transform_matrix."""
    meta = json.loads((root / f"transforms_{split}.json").read_text())
    frames = []
    for frame in meta["frames"]:
        image = read_png(root / (frame["file_path"] + ".png"))
        height, width = image.shape[:2]
        focal = 0.5 * width / math.tan(0.5 * meta["camera_angle_x"])
        j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        dirs = np.stack([(j - width / 2) / focal, -(i - height / 2) / focal, -np.ones_like(i)], -1)
        c2w = np.array(frame["transform_matrix"])
        d = dirs @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        frames.append((frame["file_path"], np.broadcast_to(c2w[:3, 3], d.shape), d))
    return frames


def cast_against_meshes(root, origins, directions):
    """Nearest hit distance over every meshes/*.ply (trimesh, float64). 0 on a miss."""
    best = np.full(len(origins), np.inf)
    for path in sorted((root / "meshes").glob("*.ply")):
        mesh = trimesh.load(path, force="mesh", process=False)
        locations, ray_index, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
        t = np.linalg.norm(locations - origins[ray_index], axis=1)
        np.minimum.at(best, ray_index, t)
    return np.where(np.isfinite(best), best, 0.0)


def test_user_mesh_dataset_depth_matches_trimesh_ray_casts(tmp_path, make_dataset):
    """A box mesh is rendered from the very triangles in meshes/: depth agrees to float32."""
    mesh_file = tmp_path / "boxy.ply"
    trimesh.creation.box(extents=(1.0, 0.6, 0.8)).export(mesh_file)
    root = make_dataset(tmp_path / "ds", scene=f"mesh:{mesh_file}", width=40, height=30)
    for stem, origins, directions in load_nerf_synthetic(root, "test"):
        stored = read_exr_single(root / (stem + "_distance.exr"))
        cast = cast_against_meshes(root, origins.reshape(-1, 3), directions.reshape(-1, 3)).reshape(stored.shape)
        hit_both = (stored > 0) & (cast > 0)
        silhouette = (stored > 0) != (cast > 0)
        assert hit_both.sum() > 100
        # Rays that graze an edge may hit in one tracer and not the other: a few pixels at most.
        assert silhouette.sum() <= 0.02 * stored.size
        # Mitsuba stores float32 vertices and intersects in float32: relative ~1e-6.
        np.testing.assert_allclose(stored[hit_both], cast[hit_both], rtol=1e-4)


def test_primitives_dataset_depth_matches_meshes_within_tessellation(tiny_dataset):
    """Spheres are analytic in Mitsuba but icospheres on disk: they differ by at most the
    tessellation's sagitta along the normal, r (1 - cos(half edge angle)), so along a ray
    by sagitta / cos(incidence)."""
    root = tiny_dataset
    radius = 0.4  # the primitives spheres
    half_edge = math.radians(63.43 / 16) / 2  # icosahedron edge angle, halved 4 times
    sagitta = radius * (1 - math.cos(half_edge))
    for stem, origins, directions in load_nerf_synthetic(root, "train"):
        stored = read_exr_single(root / (stem + "_distance.exr"))
        normals = np.stack([read_exr_exact(root / (stem + "_normal.exr"), c) for c in "XYZ"], -1)
        cast = cast_against_meshes(root, origins.reshape(-1, 3), directions.reshape(-1, 3)).reshape(stored.shape)
        cos_incidence = np.abs(np.einsum("hwc,hwc->hw", normals, directions))
        usable = (stored > 0) & (cast > 0) & (cos_incidence > 0.3)
        assert usable.sum() > 50
        bound = 2 * sagitta / cos_incidence[usable] + 1e-4 * stored[usable]
        assert (np.abs(stored[usable] - cast[usable]) <= bound).all()


def read_exr_exact(path, channel):
    from nerfgauge.core.images import read_exr

    channels, _ = read_exr(path)
    return channels[channel]
