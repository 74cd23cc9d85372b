"""Motion blur and rolling shutter of the train views (issue 35, item 3; docs/conventions.md,
"Motion blur").

The camera of a train view moves during the frame along a straight path: over normalised
time t in [0, 1] its centre and rotation are

    centre(t)   = centre_mid + (t - 1/2) * travel * diagonal * direction
    rotation(t) = Rot(axis, (t - 1/2) * rotation_degrees) @ rotation_mid

(`direction` and `axis` unit vectors drawn per view from a generator seeded by (dataset
seed, view index), `diagonal` the scene's bounding-box diagonal), so the mid-frame pose
(t = 1/2) is the layout's pose: the transform recorded for the view, and the pose of its
depth, normals, masks, ids and albedo (sharp, global shutter: exact ground truth).

The shutter: every row is exposed for `exposure` of the frame (0 < exposure <= 1). A global
shutter exposes every row over [1/2 - exposure/2, 1/2 + exposure/2]; a rolling shutter with
`readout` r staggers them: row i (of H) is centred at 1/2 + r ((i + 0.5) / H - 1/2). Every
row's window must lie inside the frame, exposure + r (1 - 1/H) <= 1 (a shutter longer than
the path is refused).

The colour is the integral over each row's window, by K sub-frames at the midpoints of K
equal parts of the window (t_k = start + exposure (k + 1/2) / K): the mean of K renders, each
with the view's spp in two passes like any view (so the stored image is less noisy than a
sharp one, and its noise estimate stays valid: pass A of the view is the mean of the
sub-frames' passes A). K is the smallest count that keeps the image motion within one
sub-frame at most MAX_SUBFRAME_MOTION_PX (the largest motion of the scene's bounding-box
corners and centre between the window's ends, plus the rotation's f * angle), at most
MAX_SUBFRAMES. Sub-frame k renders with seed (view seed + k * SUBFRAME_SEED_STRIDE).
Global shutter: sub-frame k is an ordinary render of pose(t_k). Rolling shutter: every sample
gets its own row's pose (render.render_samples with a ray map; scalar_rgb: the per-sample
loop of generate.distorted).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.camera import project
from nerfgauge.core.errors import InputError

MOTION_TAG = 0x4D4F54  # "MOT": the per-view path generator's stream
SUBFRAME_SEED_STRIDE = 0xC2B2AE35  # odd: sub-frame k renders with seed + k * stride
MAX_SUBFRAME_MOTION_PX = 0.5
MAX_SUBFRAMES = 64
USAGE = ("--motion-blur must be TRAVEL or travel=T,rotation=DEG,exposure=E,readout=R (travel: the camera's path "
         "over the frame as a fraction of the scene's bounding-box diagonal; rotation in degrees; exposure and "
         "readout as fractions of the frame)")


@dataclass(frozen=True)
class MotionBlur:
    """travel >= 0 (fraction of the scene diagonal per frame), rotation >= 0 (degrees per
    frame), exposure in (0, 1] and readout >= 0 (fractions of the frame; readout 0: a global
    shutter), exposure + readout <= 1."""

    travel: float
    rotation: float = 0.0
    exposure: float = 1.0
    readout: float = 0.0

    def __post_init__(self):
        for name in ("travel", "rotation", "exposure", "readout"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"--motion-blur {name} must be a finite number, got {value!r}")
        if self.travel < 0 or self.rotation < 0 or self.readout < 0:
            raise InputError(f"--motion-blur travel, rotation and readout must be >= 0, got {self.to_text()}")
        if not 0 < self.exposure <= 1:
            raise InputError(f"--motion-blur exposure must be in (0, 1] (a fraction of the frame), got {self.exposure!r}")
        if self.exposure + self.readout > 1 + 1e-12:
            raise InputError(f"--motion-blur: the shutter (exposure {self.exposure:g} + readout {self.readout:g}) is "
                             f"longer than the camera's path (the frame, 1)")

    @classmethod
    def parse(cls, text) -> "MotionBlur":
        text = str(text).strip()
        if re.fullmatch(r"[^=,]+", text):
            text = f"travel={text}"
        values = {}
        for part in text.split(","):
            key, sep, value = part.partition("=")
            key = key.strip()
            if not sep or key not in ("travel", "rotation", "exposure", "readout") or key in values:
                raise InputError(f"{USAGE}, got {text!r}")
            try:
                values[key] = float(value)
            except ValueError:
                raise InputError(f"{USAGE}, got {text!r}") from None
        if "travel" not in values:
            raise InputError(f"{USAGE}: travel is required, got {text!r}")
        return cls(**values)

    def to_text(self) -> str:
        return (f"travel={self.travel!r},rotation={self.rotation!r},exposure={self.exposure!r},"
                f"readout={self.readout!r}")

    def to_json(self) -> dict:
        return {"travel": self.travel, "rotation_degrees": self.rotation, "exposure": self.exposure,
                "readout": self.readout}

    @property
    def is_still(self) -> bool:
        return self.travel == 0 and self.rotation == 0

    def row_centres(self, height: int) -> np.ndarray:
        """Each row's exposure centre in frame time. [H]."""
        return 0.5 + self.readout * ((np.arange(height) + 0.5) / height - 0.5)

    def check_rows(self, height: int) -> None:
        """Every row's window inside [0, 1] (true whenever exposure + readout <= 1)."""
        centres = self.row_centres(height)
        if centres.min() - self.exposure / 2 < -1e-12 or centres.max() + self.exposure / 2 > 1 + 1e-12:
            raise InputError(f"--motion-blur {self.to_text()}: a row's exposure leaves the frame")


def parse_motion_blur(text) -> Optional[MotionBlur]:
    if text is None or str(text).strip().lower() == "none":
        return None
    return MotionBlur.parse(text)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` radians about the unit `axis`. [3, 3]."""
    x, y, z = axis
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class CameraPath:
    """One view's path: the mid-frame pose c2w_mid [4, 4] (OpenGL), the unit direction and
    axis [3], the travel in scene units and the rotation in radians over the whole frame."""

    c2w_mid: np.ndarray
    direction: np.ndarray
    axis: np.ndarray
    distance: float
    angle: float

    def pose(self, t: float) -> np.ndarray:
        """c2w at frame time t in [0, 1]. [4, 4]."""
        s = float(t) - 0.5
        c2w = np.array(self.c2w_mid, np.float64, copy=True)
        c2w[:3, :3] = rotation_about(self.axis, s * self.angle) @ c2w[:3, :3]
        c2w[:3, 3] = c2w[:3, 3] + s * self.distance * self.direction
        return c2w

    def to_json(self) -> dict:
        return {"direction": self.direction.tolist(), "axis": self.axis.tolist(), "travel_distance": self.distance,
                "rotation_radians": self.angle, "start": self.pose(0.0).tolist(), "end": self.pose(1.0).tolist()}


def unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def view_path(c2w_mid: np.ndarray, blur: MotionBlur, aabb: np.ndarray, config_seed: int, index: int) -> CameraPath:
    """The path of train view `index` (module docstring)."""
    rng = np.random.default_rng([int(config_seed), MOTION_TAG, int(index)])
    diagonal = float(np.linalg.norm(np.asarray(aabb[1], np.float64) - np.asarray(aabb[0], np.float64)))
    return CameraPath(np.asarray(c2w_mid, np.float64), unit_vector(rng), unit_vector(rng), blur.travel * diagonal,
                      math.radians(blur.rotation))


def subframe_count(path: CameraPath, blur: MotionBlur, intrinsics, aabb: np.ndarray) -> int:
    """K (module docstring): the largest image motion over one row's window, in pixels,
    divided by MAX_SUBFRAME_MOTION_PX, rounded up; 1 for a still camera."""
    if blur.is_still:
        return 1
    lo, hi = np.asarray(aabb[0], np.float64), np.asarray(aabb[1], np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
                       + [(lo + hi) / 2])
    start, end = 0.5 - blur.exposure / 2, 0.5 + blur.exposure / 2  # a row's window, about its centre
    shift = 0.0
    for centre in (0.5 - blur.readout / 2, 0.5, 0.5 + blur.readout / 2):
        a, b = start + centre - 0.5, end + centre - 0.5
        ua, va, _ = project(corners, path.pose(a), intrinsics)
        ub, vb, _ = project(corners, path.pose(b), intrinsics)
        moved = np.hypot(ub - ua, vb - va)
        if np.isfinite(moved).any():
            shift = max(shift, float(np.nanmax(moved)))
    shift = max(shift, max(intrinsics.fx, intrinsics.fy) * path.angle * blur.exposure)
    return int(min(MAX_SUBFRAMES, max(1, math.ceil(shift / MAX_SUBFRAME_MOTION_PX))))


def subframe_times(blur: MotionBlur, count: int, height: int) -> np.ndarray:
    """t[i, k]: frame time of sub-frame k of row i. [H, K]."""
    offsets = blur.exposure * ((np.arange(count) + 0.5) / count - 0.5)  # [K]
    return blur.row_centres(height)[:, None] + offsets[None, :]


def subframe_seed(seed: int, k: int) -> int:
    return (int(seed) + int(k) * SUBFRAME_SEED_STRIDE) % (2**32)


def rolling_ray_map(path: CameraPath, times: np.ndarray, intrinsics, distortion=None):
    """The ray map of one rolling-shutter sub-frame: film positions (u, v) [n] -> world
    origins and unit directions [n, 3], each sample with the pose of its row's time
    (times: [H] for this sub-frame)."""
    height = intrinsics.height
    poses = np.stack([path.pose(t) for t in times])  # [H, 4, 4]

    def mapped(u, v):
        row = np.clip(np.floor(v).astype(np.int64), 0, height - 1)
        x, y = (u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy
        if distortion is not None:
            x, y = distortion.undistort(x, y)
        local = np.stack([x, -y, -np.ones_like(x)], -1)  # OpenGL camera axes
        rotation = poses[row, :3, :3]  # [n, 3, 3]
        d = np.einsum("nij,nj->ni", rotation, local)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return poses[row, :3, 3], d

    return mapped


def render_motion_view(mi, scene, path: CameraPath, blur: MotionBlur, intrinsics, spp, seed: int, *,
                       aabb: np.ndarray, integrator=None, legend: Optional[tuple] = None, distortion=None,
                       lens=None):
    """Everything one moving view writes (render.ViewImages): the colour integrated over
    each row's exposure by K sub-frames (module docstring), two passes each; depth, normals,
    mask, ids and albedo of the sharp mid-frame pose. Returns (images, K)."""
    from nerfgauge.generate import render  # the renderer (Mitsuba): this module's maths needs none of it

    if spp == "auto":
        raise InputError("--motion-blur renders a fixed --spp per sub-frame; --spp auto is not supported with it")
    if integrator is None or legend is None:
        integrator, legend = render._loaded_for(mi, scene)
    count = subframe_count(path, blur, intrinsics, aabb)
    times = subframe_times(blur, count, intrinsics.height)  # [H, K]
    pass_a, pass_b = render._Pass(), render._Pass()
    for k in range(count):
        if blur.readout == 0:  # global shutter: an ordinary render of the sub-frame's pose
            a, b = render.render_passes(mi, scene, path.pose(times[0, k]), intrinsics, spp, subframe_seed(seed, k),
                                        lens=lens, distortion=distortion)
        else:
            ray_map = rolling_ray_map(path, times[:, k], intrinsics, distortion)
            a, b = render.render_passes(mi, scene, path.c2w_mid, intrinsics, spp, subframe_seed(seed, k),
                                        ray_map=ray_map)
        pass_a.add(a.mean, a.spp)
        if b is not None:
            pass_b.add(b.mean, b.spp)
    pass_b = pass_b if pass_b.spp else None
    image = render.mean_of_passes(pass_a, pass_b)
    total = pass_a.spp + (pass_b.spp if pass_b else 0)
    albedo = render.render_albedo(mi, scene, integrator, path.c2w_mid, intrinsics, total, seed, distortion)
    passes = ((pass_a.mean, pass_a.spp),) + (() if pass_b is None else ((pass_b.mean, pass_b.spp),))
    distance, z_depth, normals, hit, instance = render.render_geometry_with_ids(mi, scene, path.c2w_mid, intrinsics,
                                                                                legend, distortion)
    return render.ViewImages(image[..., :4], distance, z_depth, normals, hit, instance, albedo, passes), count
