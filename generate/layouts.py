"""Camera layouts: where the train, val and test cameras stand (OpenGL camera-to-world).

Every layout draws all views of all splits as one set and then deals them out to the
splits, so no two views coincide. Cameras look at the AABB centre unless the layout says
otherwise (the light field looks straight ahead, "forward" faces one target, "inside"
looks outwards).

Orbiting layouts refuse cameras inside the AABB (a mistake there); "forward" and
"inside" are for scenes whose cameras belong among the content (LLFF-style captures,
rooms) and allow it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.camera import look_at
from nerfgauge.core.errors import InputError

LAYOUTS = ("hemisphere", "sphere", "orbit", "spiral", "lightfield", "forward", "inside")
SPLITS = ("train", "val", "test")
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class LayoutSpec:
    """layout: one of LAYOUTS. sampling: "fibonacci" (even) or "random" (seeded).
    elevation: (min, max) degrees above the horizon through the AABB centre.
    radius: camera distance from the AABB centre (scene units).
    eye, target, spread: "forward" (cluster centre, the point faced, cluster radius) and
    "inside" (spread = half-size of the box around the AABB centre the cameras stand in);
    target also centres the orbiting layouts (a scene whose objects sit in a far larger
    world orbits them, inside its AABB, on purpose); None picks a default from the AABB."""

    layout: str
    counts: tuple  # (train, val, test)
    radius: float
    elevation: tuple = (10.0, 75.0)
    sampling: str = "fibonacci"
    eye: Optional[tuple] = None
    target: Optional[tuple] = None
    spread: Optional[float] = None


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
    if spec.spread is not None and not (spec.spread > 0 and math.isfinite(spec.spread)):
        raise InputError(f"camera spread must be positive, got {spec.spread}")
    centre = (aabb[0] + aabb[1]) / 2
    total = sum(spec.counts)
    if spec.layout == "lightfield":
        poses = lightfield_poses(spec, aabb, rng)
    elif spec.layout == "forward":
        poses = forward_poses(spec, aabb, rng)
    elif spec.layout == "inside":
        poses = inside_poses(spec, aabb, rng)
    else:
        if spec.layout == "sphere":
            lo, hi = -89.0, 89.0
        directions = _directions(spec.layout, spec.sampling, total, lo, hi, rng)
        # A target comes from a scene's camera hint; otherwise cameras inside the AABB are
        # a radius that is too small, and a layout meant to look in would look out.
        centre = centre if spec.target is None else np.asarray(spec.target, np.float64)
        eyes = centre + spec.radius * directions
        inside = np.all((eyes >= aabb[0]) & (eyes <= aabb[1]), axis=1)
        if spec.target is None and inside.any():
            raise InputError(f"camera radius {spec.radius:g} puts cameras inside the scene's AABB "
                             f"{aabb[0].round(3).tolist()}..{aabb[1].round(3).tolist()}; use a larger --radius")
        stacked = np.stack([look_at(eye, centre) for eye in eyes])
        order = rng.permutation(total) if spec.layout in ("hemisphere", "sphere") else _interleave(spec.counts)
        poses = _deal(stacked[order], spec.counts)
    _refuse_coinciding(poses)
    return poses


def _refuse_coinciding(poses: dict) -> None:
    """Two identical cameras (e.g. an elevation band of zero width at a pole, where every
    azimuth is the same point) would put a test view in the training set."""
    stacked = np.concatenate([p for p in poses.values() if len(p)])  # [n, 4, 4]
    distinct = len(np.unique(stacked[:, :3, :].reshape(len(stacked), -1).round(9), axis=0))
    if distinct < len(stacked):
        raise InputError(f"this layout puts {len(stacked) - distinct + 1} cameras on the same pose; "
                         f"widen --elevation or choose another layout")


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


def _disc(n: int, sampling: str, rng: np.random.Generator) -> np.ndarray:
    """n points in the unit disc: a sunflower (even) or seeded uniform. Returns [n, 2]."""
    if sampling == "fibonacci":
        radius = np.sqrt((np.arange(n) + 0.5) / n)
        angle = GOLDEN_ANGLE * np.arange(n)
    else:
        radius, angle = np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * math.pi, n)
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def forward_poses(spec: LayoutSpec, aabb: np.ndarray, rng: np.random.Generator) -> dict:
    """LLFF-style forward-facing capture: every camera has the same orientation (facing
    `target` from `eye`) and stands on a disc of radius `spread` around `eye`, across the
    view direction. Defaults: eye `radius` from the AABB centre on its -Y side at the
    middle of the elevation band, facing the centre; spread a tenth of the radius."""
    centre = (aabb[0] + aabb[1]) / 2
    if spec.eye is None:
        elevation = math.radians(sum(spec.elevation) / 2)
        eye = centre + spec.radius * np.array([0.0, -math.cos(elevation), math.sin(elevation)])
    else:
        eye = np.asarray(spec.eye, np.float64)
    target = centre if spec.target is None else np.asarray(spec.target, np.float64)
    spread = 0.1 * spec.radius if spec.spread is None else spec.spread
    orientation = look_at(eye, target)
    offsets = _disc(sum(spec.counts), spec.sampling, rng) * spread  # [n, 2] along camera right, up
    poses = np.repeat(orientation[None], len(offsets), axis=0)
    poses[:, :3, 3] = eye + offsets[:, :1] * orientation[:3, 0] + offsets[:, 1:] * orientation[:3, 1]
    return _deal(poses[rng.permutation(len(poses))], spec.counts)


def inside_poses(spec: LayoutSpec, aabb: np.ndarray, rng: np.random.Generator) -> dict:
    """Cameras inside the scene looking outwards (a room, a ring of objects around the
    viewer): positions seeded-uniform in a box of half-size `spread` around the AABB
    centre (default a fifth of the AABB's smallest half-extent), view directions evenly
    spread in azimuth (golden angle) within the elevation band."""
    centre = (aabb[0] + aabb[1]) / 2
    spread = 0.2 * float((aabb[1] - aabb[0]).min()) / 2 if spec.spread is None else spec.spread
    total = sum(spec.counts)
    eyes = centre + rng.uniform(-spread, spread, size=(total, 3))
    lo, hi = (math.radians(a) for a in spec.elevation)
    elevation = lo + (hi - lo) * (np.arange(total) + 0.5) / total
    azimuth = GOLDEN_ANGLE * np.arange(total)
    directions = _from_angles(elevation, azimuth)
    poses = np.stack([look_at(eye, eye + d) for eye, d in zip(eyes, directions)])
    return _deal(poses[rng.permutation(total)], spec.counts)
