"""The project's one camera: pinhole, OpenGL/NeRF axes, rays through pixel centres.

Every file nerfgauge writes stores camera-to-world 4x4 matrices in the OpenGL/NeRF
convention: +X right, +Y up, the camera looks along -Z. Mitsuba's camera has +X left and
looks along +Z; `to_mitsuba` converts (the flip is its own inverse). Pixel (row i, col j)
has its ray through (j + 0.5, i + 0.5), row 0 at the top. Pure numpy; no renderer here.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError

GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels. Square pixels: fx == fy unless read from a file."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_degrees: float) -> "Intrinsics":
        """Horizontal field of view (NeRF-synthetic's camera_angle_x, Mitsuba's fov_axis='x')."""
        if not 0 < fov_x_degrees < 180:
            raise ValueError(f"fov must be in (0, 180) degrees, got {fov_x_degrees}")
        focal = 0.5 * width / math.tan(math.radians(fov_x_degrees) / 2)
        return cls(int(width), int(height), focal, focal, width / 2, height / 2)

    @property
    def camera_angle_x(self) -> float:
        """Horizontal field of view in radians."""
        return 2 * math.atan(0.5 * self.width / self.fx)

    @property
    def fov_x_degrees(self) -> float:
        return math.degrees(self.camera_angle_x)


def camera_directions(intrinsics: Intrinsics) -> np.ndarray:
    """Unnormalised camera-space ray directions with z = -1. Returns [H, W, 3] float64."""
    cols = np.arange(intrinsics.width) + 0.5
    rows = np.arange(intrinsics.height) + 0.5
    u, v = np.meshgrid(cols, rows)  # [H, W] each
    x = (u - intrinsics.cx) / intrinsics.fx
    y = -(v - intrinsics.cy) / intrinsics.fy  # row 0 is the top: +Y up
    return np.stack([x, y, -np.ones_like(x)], axis=-1)


def pixel_rays(c2w: np.ndarray, intrinsics: Intrinsics, distortion=None) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through every pixel centre.

    c2w: [4, 4] camera-to-world (OpenGL axes). distortion: a core.distortion.Distortion the
    pixel grid is seen through (None: the pinhole): each pixel centre's ray is that of its
    undistorted normalised coordinates (docs/conventions.md, "Lens distortion").
    Returns origins [H, W, 3] and unit directions [H, W, 3] (float64).
    """
    c2w = np.asarray(c2w, np.float64)
    if c2w.shape != (4, 4):
        raise ValueError(f"c2w must be 4x4, got shape {c2w.shape}")
    if not np.isfinite(c2w).all():
        raise InputError(f"camera-to-world matrix has non-finite entries: {c2w[:3].round(6).tolist()}")
    if abs(np.linalg.det(c2w[:3, :3])) < 1e-12:
        raise InputError(f"camera-to-world rotation is singular: {c2w[:3, :3].round(6).tolist()}")
    local = camera_directions(intrinsics) if distortion is None else distortion.camera_directions(intrinsics)
    d = local @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(c2w[:3, 3], d.shape).copy(), d


def pixel_coordinates(x: np.ndarray, y: np.ndarray, z: np.ndarray, intrinsics: Intrinsics
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates u, v [n] of points given in camera axes x, y, z [n] (OpenGL: the
    camera looks down -z; pixel_rays' convention: pixel (row i, col j) covers
    [j, j + 1) x [i, i + 1) in (u, v)). NaN for points not in front of the camera."""
    ahead = -z
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.where(ahead > 0, 1.0 / ahead, np.nan)
    return intrinsics.cx + intrinsics.fx * x * inverse, intrinsics.cy - intrinsics.fy * y * inverse


def project(points: np.ndarray, c2w: np.ndarray, intrinsics: Intrinsics,
            distortion=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates of world points in one camera (see pixel_coordinates; through
    `distortion`, a core.distortion.Distortion, when given).

    points [n, 3], c2w [4, 4]. Returns u, v [n] (NaN behind the camera) and the distance
    from the camera centre [n]."""
    c2w = np.asarray(c2w, np.float64)
    local = (np.asarray(points, np.float64) - c2w[:3, 3]) @ c2w[:3, :3]  # [n, 3] camera axes
    if distortion is not None:
        u, v = distortion.project(local[:, 0], local[:, 1], local[:, 2], intrinsics)
        return u, v, np.linalg.norm(local, axis=1)
    u, v = pixel_coordinates(local[:, 0], local[:, 1], local[:, 2], intrinsics)
    return u, v, np.linalg.norm(local, axis=1)


def z_depth_from_distance(distance: np.ndarray, directions: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Depth along the optical axis from distance along unit rays: z = t * cos(angle).

    distance: [...], directions: [..., 3] unit, c2w: [4, 4]. Returns [...] (0 stays 0).
    """
    forward = -np.asarray(c2w, np.float64)[:3, 2]
    return distance * (directions @ forward)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (OpenGL axes) at `eye` looking at `target`. Returns [4, 4].

        back = (eye - target) / |eye - target|,  right = up x back / |up x back|,
        true_up = back x right

    a right-handed orthonormal frame (det +1) whose -Z column points at the target. When
    the view direction is parallel to `up` (|up x back| < 1e-9 |up|: looking straight down
    or up), the world +Y axis stands in for up (+X if the view is along Y), so the pose
    stays defined; the roll then jumps, which is unavoidable at the pole.

    Raises InputError for non-finite input, a zero `up`, or `eye` equal to `target`.
    """
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    for name, value in (("eye", eye), ("target", target), ("up", up)):
        if value.shape != (3,) or not np.isfinite(value).all():
            raise InputError(f"camera {name} must be 3 finite numbers, got {value.tolist()}")
    back = eye - target
    norm = np.linalg.norm(back)
    if norm == 0:
        raise InputError(f"camera eye and target coincide at {eye.tolist()}")
    up_norm = np.linalg.norm(up)
    if up_norm == 0:
        raise InputError("camera up vector is zero")
    back /= norm
    right = np.cross(up / up_norm, back)
    for fallback in ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0)):
        if np.linalg.norm(right) >= 1e-9:
            break
        right = np.cross(np.array(fallback), back)
    overlap = right @ back  # 0 up to rounding; not negligible once |up x back| is tiny
    if overlap:
        right -= overlap * back  # Gram-Schmidt, so the frame stays orthonormal near the pole
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def to_mitsuba(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world -> Mitsuba sensor to_world (and back: the same flip)."""
    return np.asarray(c2w, np.float64) @ GL_TO_MITSUBA


# --- thin lens ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ThinLens:
    """A thin lens in front of the pinhole camera (Mitsuba's `thinlens` sensor).

    aperture_radius: radius of the lens disc in scene units (0: a pinhole).
    focus_distance: distance from the lens to the plane in focus, measured along the
    optical axis (the plane z = -focus_distance in camera space), scene units.
    """

    aperture_radius: float
    focus_distance: float

    def __post_init__(self):
        check_lens(self.aperture_radius, self.focus_distance)

    @property
    def is_pinhole(self) -> bool:
        return self.aperture_radius == 0

    def to_json(self) -> dict:
        return {"model": "thinlens", "aperture_radius": float(self.aperture_radius),
                "focus_distance": float(self.focus_distance)}

    @classmethod
    def from_json(cls, value, where: str) -> "ThinLens":
        """A frame's "lens" entry; InputError (one line, naming `where`) if malformed."""
        if not isinstance(value, dict) or value.get("model", "thinlens") != "thinlens":
            raise InputError(f"{where}: lens must be {{\"model\": \"thinlens\", \"aperture_radius\": R, "
                             f"\"focus_distance\": D}}, got {value!r}")
        try:
            radius, distance = float(value["aperture_radius"]), float(value["focus_distance"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{where}: lens needs numeric aperture_radius and focus_distance, got {value!r}") from None
        try:
            return cls(radius, distance)
        except InputError as error:
            raise InputError(f"{where}: {error}") from None


def check_lens(aperture_radius, focus_distance) -> None:
    """InputError unless aperture_radius >= 0 and focus_distance > 0 (in front of the camera), both finite."""
    def real(x):
        return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)

    if not (real(aperture_radius) and aperture_radius >= 0):
        raise InputError(f"lens aperture radius (--aperture) must be a finite number >= 0 in scene units, "
                         f"got {aperture_radius!r}")
    if not (real(focus_distance) and focus_distance > 0):
        raise InputError(f"lens focus distance (--focus-distance) must be a finite number > 0 (in front of the "
                         f"camera), got {focus_distance!r}")


def stratified_unit_square(count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` jittered samples in [0, 1)^2, one in each cell of an a x b grid (a * b = count,
    a the largest divisor of count not above sqrt(count)): every cell has the same area, so
    the estimate over them is stratified for any count. Returns [count, 2]."""
    if count < 1:
        raise ValueError(f"need at least one sample, got {count}")
    rows = max(a for a in range(1, math.isqrt(count) + 1) if count % a == 0)
    cols = count // rows
    j, i = np.meshgrid(np.arange(cols), np.arange(rows))
    jitter = rng.random((count, 2))
    return np.stack([(j.ravel() + jitter[:, 0]) / cols, (i.ravel() + jitter[:, 1]) / rows], axis=1)


def concentric_disk(square: np.ndarray) -> np.ndarray:
    """Shirley-Chiu concentric map of [0, 1)^2 onto the unit disc (area-preserving, so
    stratified squares stay stratified discs; Mitsuba's thinlens uses the same map).
    square: [n, 2]. Returns [n, 2]."""
    a = 2.0 * square[:, 0] - 1.0
    b = 2.0 * square[:, 1] - 1.0
    first = np.abs(a) > np.abs(b)
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    radius = np.where(first, a, b)
    angle = np.where(first, (math.pi / 4) * (b / safe_a), math.pi / 2 - (math.pi / 4) * (a / safe_b))
    radius = np.where((a == 0) & (b == 0), 0.0, radius)
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def lens_samples(count: int, seed) -> np.ndarray:
    """`count` stratified points on the unit disc from a seeded generator. Returns [count, 2]."""
    return concentric_disk(stratified_unit_square(count, np.random.default_rng(seed)))


def thin_lens_rays(c2w: np.ndarray, intrinsics: Intrinsics, lens: ThinLens,
                   disk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays of a thin-lens camera, one bundle per lens sample.

    The ray of pixel (i, j) for lens sample (u, v) in the unit disc starts on the lens at
    camera-space L = (R u, R v, 0) (R = aperture_radius) and passes through the point where
    that pixel's pinhole centre ray meets the focus plane, F = D * (x, y, -1) with
    (x, y, -1) = camera_directions: every ray of a pixel meets at F, so the plane
    z = -D (D = focus_distance) is imaged sharply and a point at another depth spreads
    into a disc (the circle of confusion).

    c2w: [4, 4] (OpenGL axes); disk: [S, 2] points in the unit disc (lens_samples).
    Returns origins [S, H, W, 3] and unit directions [S, H, W, 3] (float64). A pinhole lens
    (aperture 0) returns pixel_rays exactly, repeated S times.
    """
    origins, directions = pixel_rays(c2w, intrinsics)  # validates c2w
    disk = np.asarray(disk, np.float64).reshape(-1, 2)
    if lens.is_pinhole:
        return (np.broadcast_to(origins, (len(disk),) + origins.shape).copy(),
                np.broadcast_to(directions, (len(disk),) + directions.shape).copy())
    c2w = np.asarray(c2w, np.float64)
    rotation = c2w[:3, :3]
    focus = lens.focus_distance * camera_directions(intrinsics)  # [H, W, 3] camera space
    on_lens = np.concatenate([lens.aperture_radius * disk, np.zeros((len(disk), 1))], axis=1)  # [S, 3]
    local = focus[None] - on_lens[:, None, None, :]  # [S, H, W, 3]
    d = local @ rotation.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = on_lens @ rotation.T + c2w[:3, 3]  # [S, 3]
    return np.broadcast_to(o[:, None, None, :], d.shape).copy(), d


@dataclass(frozen=True)
class SplitCameras:
    """One split: frame stems (relative, extension-less), poses [n, 4, 4] (read-only),
    intrinsics, per frame the thin lens its colour was rendered through (None: a
    pinhole frame; an empty tuple when no frame has a lens), and the split's lens
    distortion (a core.distortion.Distortion; None: pinhole pixels)."""

    split: str
    stems: tuple
    c2w: np.ndarray
    intrinsics: Intrinsics
    lenses: tuple = ()
    distortion: object = None

    def rays(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame `index`'s pixel-centre rays through the split's distortion (pixel_rays).
        Returns origins, unit directions [H, W, 3] float64."""
        return pixel_rays(self.c2w[index], self.intrinsics, self.distortion)

    def lens(self, index: int) -> Optional[ThinLens]:
        """Frame `index`'s thin lens, None for a pinhole frame."""
        return self.lenses[index] if self.lenses else None
