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
sub-frame at most MAX_SUBFRAME_MOTION_PX: the image motion over a window is the fastest
image speed, along the exposed part of the path, of 27 points of the scene's bounding box
(corners, edge and face centres, centre) while they are in or near the image, times the
exposure, and at least the rotation's f * angle (`image_motion`). A view that needs more than
MAX_SUBFRAMES sub-frames is refused before anything renders (`check_paths`), and so is one
whose path carries a visible point of the box from the image to behind the camera between
two samples (its image motion has no bound). The measure used to be the motion between the
window's two ends, and a point behind the camera at either end (NaN) was left out: a path
long enough to take the scene behind the camera at both ends measured 0 px and rendered one
sub-frame, the sharp mid-frame image, while the transforms recorded the motion.
Sub-frame k renders with seed (view seed + k * SUBFRAME_SEED_STRIDE).
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

from nerfgauge.core import arguments
from nerfgauge.core.camera import project
from nerfgauge.core.errors import InputError

MOTION_TAG = 0x4D4F54  # "MOT": the per-view path generator's stream
SUBFRAME_SEED_STRIDE = 0xC2B2AE35  # odd: sub-frame k renders with seed + k * stride
MAX_SUBFRAME_MOTION_PX = 0.5
MAX_SUBFRAMES = 64  # at most 32 px of image motion per exposure: more is refused, never under-sampled
SPEED_STEPS = 256  # steps along the exposed part of a path at which the image speed is measured
ON_IMAGE_MARGIN = 1.0  # a point within this many image sizes of the image counts as visible
# The path's ranges, checked for the command line and the API alike and shown in --help.
# Travel is in scene diagonals per frame: cameras sit within a few diagonals of the scene, so
# a camera that moves ten in one frame has gone through or past it (and check_paths refuses
# far less at any resolution); 1e308 overflowed the recorded path to inf after every view
# had rendered. Rotation: at most a full turn per frame.
TRAVEL = arguments.bounded(float, 0, 10)
ROTATION_DEGREES = arguments.bounded(float, 0, 360)
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
        TRAVEL.check(self.travel, "--motion-blur travel (scene diagonals per frame)")
        ROTATION_DEGREES.check(self.rotation, "--motion-blur rotation (degrees per frame)")
        if self.readout < 0:
            raise InputError(f"--motion-blur readout must be >= 0, got {self.to_text()}")
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

    def __post_init__(self):
        values = (self.c2w_mid, self.direction, self.axis, self.distance, self.angle)
        if not all(np.isfinite(np.asarray(value, np.float64)).all() for value in values):
            raise InputError(f"the camera path of a moving view is not finite (travel {self.distance!r} scene units, "
                             f"rotation {self.angle!r} rad from a pose with centre {np.asarray(self.c2w_mid)[:3, 3]}); "
                             "check the scene's bounds and --motion-blur")

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


def box_points(aabb: np.ndarray) -> np.ndarray:
    """The 27 points of a box: corners, edge centres, face centres and centre. [27, 3]."""
    lo, hi = np.asarray(aabb[0], np.float64), np.asarray(aabb[1], np.float64)
    axes = [np.array([lo[i], (lo[i] + hi[i]) / 2, hi[i]]) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def image_motion(path: CameraPath, blur: MotionBlur, intrinsics, aabb: np.ndarray) -> float:
    """The largest image motion over one row's exposure, in pixels (module docstring): the
    fastest image speed of the box's points (`box_points`) along the exposed part of the
    path (every row's window: [1/2 - (readout + exposure)/2, 1/2 + (readout + exposure)/2],
    SPEED_STEPS steps), counted while a point is in or near the image (ON_IMAGE_MARGIN),
    times the exposure; at least f * the rotation over the exposure. inf when a point near
    the image at one step is behind the camera at the next (the path runs into the scene)."""
    half = (blur.readout + blur.exposure) / 2
    times = np.linspace(0.5 - half, 0.5 + half, SPEED_STEPS + 1)
    points = box_points(aabb)
    u, v = np.empty((len(times), len(points))), np.empty((len(times), len(points)))
    for k, t in enumerate(times):
        u[k], v[k], _ = project(points, path.pose(t), intrinsics)
    ahead = np.isfinite(u) & np.isfinite(v)  # [T, P]
    margin_u, margin_v = ON_IMAGE_MARGIN * intrinsics.width, ON_IMAGE_MARGIN * intrinsics.height
    with np.errstate(invalid="ignore"):  # NaN behind the camera compares False: not near the image
        near = ahead & (u > -margin_u) & (u < intrinsics.width + margin_u) & (v > -margin_v) \
            & (v < intrinsics.height + margin_v)
    if ((near[:-1] & ~ahead[1:]) | (~ahead[:-1] & near[1:])).any():
        return math.inf
    counted = ahead[:-1] & ahead[1:] & (near[:-1] | near[1:])  # [T - 1, P]
    step = np.where(counted, np.hypot(np.diff(np.where(ahead, u, 0.0), axis=0),
                                      np.diff(np.where(ahead, v, 0.0), axis=0)), 0.0)
    speed = float(step.max()) * SPEED_STEPS / (2 * half) if step.size else 0.0  # pixels per frame
    return max(speed * blur.exposure, max(intrinsics.fx, intrinsics.fy) * path.angle * blur.exposure)


def subframe_count(path: CameraPath, blur: MotionBlur, intrinsics, aabb: np.ndarray, view: str = "a view") -> int:
    """K (module docstring): the image motion over one row's window (`image_motion`) over
    MAX_SUBFRAME_MOTION_PX, rounded up; 1 for a still camera. More than MAX_SUBFRAMES, or a
    path into the scene, is an InputError naming `view` and the limit."""
    if blur.is_still:
        return 1
    motion = image_motion(path, blur, intrinsics, aabb)
    if not math.isfinite(motion):
        raise InputError(f"--motion-blur {blur.to_text()}: {view}'s camera runs into the scene during its exposure "
                         "(a point of the scene's box goes from the image to behind the camera), an image motion no "
                         "number of sub-frames samples; lower the travel or rotation")
    count = max(1, math.ceil(motion / MAX_SUBFRAME_MOTION_PX))
    if count > MAX_SUBFRAMES:
        raise InputError(f"--motion-blur {blur.to_text()}: {view}'s image moves {motion:.1f} px during its exposure; "
                         f"sampled at {MAX_SUBFRAME_MOTION_PX:g} px per sub-frame that needs {count} sub-frames, more "
                         f"than the limit of {MAX_SUBFRAMES} ({MAX_SUBFRAMES * MAX_SUBFRAME_MOTION_PX:g} px); lower the "
                         "travel, rotation, exposure or resolution")
    return count


def check_paths(poses, blur: MotionBlur, aabb: np.ndarray, config_seed: int, intrinsics, names) -> list:
    """Every moving view's sub-frame count, before anything renders: the paths of the views
    with mid-frame poses `poses` [n, 4, 4] (named `names`) finite, and each within
    MAX_SUBFRAMES sub-frames (subframe_count's InputError otherwise). Returns the counts."""
    return [subframe_count(view_path(pose, blur, aabb, config_seed, index), blur, intrinsics, aabb, name)
            for index, (pose, name) in enumerate(zip(poses, names))]


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
