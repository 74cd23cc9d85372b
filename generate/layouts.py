"""Camera layouts: where the train, val and test cameras stand (OpenGL camera-to-world).

Every layout draws all views of all splits as one set and then deals them out to the
splits, so no two views coincide. Cameras look at the AABB centre unless the layout says
otherwise (the light field looks straight ahead).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from generate.camera import look_at
from nerfgauge.errors import InputError

LAYOUTS = ("hemisphere", "sphere", "orbit", "spiral", "lightfield")
SPLITS = ("train", "val", "test")
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class LayoutSpec:
    """layout: one of LAYOUTS. sampling: "fibonacci" (even) or "random" (seeded).
    elevation: (min, max) degrees above the horizon through the AABB centre.
    radius: camera distance from the AABB centre (scene units)."""

    layout: str
    counts: tuple  # (train, val, test)
    radius: float
    elevation: tuple = (10.0, 75.0)
    sampling: str = "fibonacci"


def default_radius(aabb: np.ndarray, fov_x_degrees: float, width: int, height: int, margin: float = 1.1) -> float:
    """Distance at which the AABB's bounding sphere fits the narrower field of view."""
    half_x = math.radians(fov_x_degrees) / 2
    half_y = math.atan(math.tan(half_x) * height / width)
    bound = float(np.linalg.norm(aabb[1] - aabb[0])) / 2
    return margin * bound / math.sin(min(half_x, half_y))


def camera_poses(spec: LayoutSpec, aabb: np.ndarray, rng: np.random.Generator) -> dict:
    """{split: [n, 4, 4]} camera-to-world matrices for each split."""
    if spec.layout not in LAYOUTS:
        raise InputError(f"unknown layout {spec.layout!r}; choose one of {', '.join(LAYOUTS)}")
    if spec.sampling not in ("fibonacci", "random"):
        raise InputError(f"unknown sampling {spec.sampling!r}; choose fibonacci or random")
    lo, hi = spec.elevation
    if not -90 <= lo <= hi <= 90:
        raise InputError(f"elevation band must satisfy -90 <= min <= max <= 90, got {spec.elevation}")
    if spec.radius <= 0 or not math.isfinite(spec.radius):
        raise InputError(f"camera radius must be positive, got {spec.radius}")
    centre = (aabb[0] + aabb[1]) / 2
    total = sum(spec.counts)
    if spec.layout == "lightfield":
        poses = lightfield_poses(spec, aabb, rng)
    else:
        if spec.layout == "sphere":
            lo, hi = -89.0, 89.0
        directions = _directions(spec.layout, spec.sampling, total, lo, hi, rng)
        eyes = centre + spec.radius * directions
        inside = np.all((eyes >= aabb[0]) & (eyes <= aabb[1]), axis=1)
        if inside.any():
            raise InputError(f"camera radius {spec.radius:g} puts cameras inside the scene's AABB "
                             f"{aabb[0].round(3).tolist()}..{aabb[1].round(3).tolist()}; use a larger --radius")
        stacked = np.stack([look_at(eye, centre) for eye in eyes])
        order = rng.permutation(total) if spec.layout in ("hemisphere", "sphere") else _interleave(spec.counts)
        poses = _deal(stacked[order], spec.counts)
    return poses


def _directions(layout, sampling, n, lo_deg, hi_deg, rng) -> np.ndarray:
    """Unit vectors from the centre to the cameras. Returns [n, 3]."""
    z_lo, z_hi = math.sin(math.radians(lo_deg)), math.sin(math.radians(hi_deg))
    if layout == "orbit":
        elevation = np.full(n, math.radians((lo_deg + hi_deg) / 2))
        azimuth = 2 * math.pi * np.arange(n) / n
        return _from_angles(elevation, azimuth)
    if layout == "spiral":
        t = (np.arange(n) + 0.5) / n
        elevation = np.radians(lo_deg + (hi_deg - lo_deg) * t)
        return _from_angles(elevation, 2 * math.pi * 3 * t)  # three turns
    if sampling == "fibonacci":
        z = z_lo + (z_hi - z_lo) * (np.arange(n) + 0.5) / n  # equal-area bands
        azimuth = GOLDEN_ANGLE * np.arange(n)
    else:
        z = rng.uniform(z_lo, z_hi, n)
        azimuth = rng.uniform(0, 2 * math.pi, n)
    ring = np.sqrt(np.clip(1 - z**2, 0, 1))
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def _from_angles(elevation, azimuth) -> np.ndarray:
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], 1)


def _interleave(counts) -> np.ndarray:
    """For paths: spread each split's views evenly along the path instead of shuffling."""
    total = sum(counts)
    order, taken = [], np.zeros(total, bool)
    for count in counts:
        free = np.flatnonzero(~taken)
        pick = free[np.round(np.linspace(0, len(free) - 1, count)).astype(int)] if count else np.array([], int)
        taken[pick] = True
        order.append(pick)
    return np.concatenate(order)


def _deal(poses, counts) -> dict:
    out, start = {}, 0
    for split, count in zip(SPLITS, counts):
        out[split] = poses[start:start + count]
        start += count
    return out


def lightfield_grid(counts) -> tuple[int, int]:
    """(rows, cols) of the training grid: the train count must be a perfect square."""
    side = math.isqrt(counts[0])
    if side * side != counts[0] or side < 2:
        raise InputError(f"the lightfield layout needs --views to be a square >= 4 (e.g. 100 = 10x10), got {counts[0]}")
    return side, side


def lightfield_plane(spec: LayoutSpec, aabb: np.ndarray) -> dict:
    """The two-plane parametrisation: camera plane (s, t) and focal plane (u, v).

    Cameras stand on the plane y = centre_y - radius, facing +Y (up is +Z); the grid spans
    half the AABB's width and height. The focal plane passes through the AABB centre.
    """
    rows, cols = lightfield_grid(spec.counts)
    centre = (aabb[0] + aabb[1]) / 2
    size = aabb[1] - aabb[0]
    span = np.array([size[0], size[2]]) * 0.5
    origin = centre + np.array([-span[0] / 2, -spec.radius, -span[1] / 2])
    if spec.radius <= size[1] / 2:
        raise InputError(f"camera radius {spec.radius:g} puts the light-field camera plane inside the scene's AABB")
    return {
        "camera_plane_origin": origin.tolist(),  # grid node (0, 0)
        "s_axis": [1.0, 0.0, 0.0], "t_axis": [0.0, 0.0, 1.0], "view_axis": [0.0, 1.0, 0.0],
        "spacing": [float(span[0] / (cols - 1)), float(span[1] / (rows - 1))],
        "grid": [rows, cols],
        "focal_plane_distance": float(spec.radius),
    }


def lightfield_poses(spec: LayoutSpec, aabb: np.ndarray, rng: np.random.Generator) -> dict:
    """Train: the regular s,t grid (row-major, t up). Val/test: random off-grid positions."""
    plane = lightfield_plane(spec, aabb)
    rows, cols = plane["grid"]
    origin, spacing = np.array(plane["camera_plane_origin"]), np.array(plane["spacing"])
    grid = [(i, j) for i in range(rows) for j in range(cols)]  # (t index, s index)
    held_out = spec.counts[1] + spec.counts[2]
    # Off-grid: inside a cell, at least 0.15 cell from every node, so no view coincides.
    cell = rng.integers(0, [rows - 1, cols - 1], size=(held_out, 2))
    frac = rng.uniform(0.15, 0.85, size=(held_out, 2))
    positions = [(i, j) for i, j in grid] + [tuple(c + f) for c, f in zip(cell, frac)]
    rotation = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # columns: right=+X, up=+Z, back=-Y
    poses = []
    for t_index, s_index in positions:
        c2w = np.eye(4)
        c2w[:3, :3] = rotation
        c2w[:3, 3] = origin + s_index * spacing[0] * np.array([1.0, 0, 0]) + t_index * spacing[1] * np.array([0, 0, 1.0])
        poses.append(c2w)
    return _deal(np.stack(poses), spec.counts)
