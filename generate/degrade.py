"""Degraded training views (issue 35, items 1 and 2): pose noise, exposure, white balance
and vignetting, applied to the TRAIN split only. Validation and test views, depth,
normals, masks, instance ids, albedo and meshes stay exact (docs/conventions.md,
"Degradations").

Pose noise (the train transforms hold the perturbed poses; the images are rendered from the
exact ones, kept per frame as "exact_transform_matrix"):

    omega_i = (sigma_rot / sqrt(3)) * z_i,   z_i ~ N(0, I_3)        (a rotation vector, radians)
    R'_i    = R_i @ Exp(omega_i)                                     (perturbed in the camera frame)
    c'_i    = c_i + (tau * s / sqrt(3)) * u_i,  u_i ~ N(0, I_3)
    s       = sqrt(mean_i |c_i - mean_j c_j|^2)                      (the RMS spread of the train centres)

so the axis of omega_i is uniform on the sphere, E[angle^2] = sigma_rot^2 (sigma_rot is the
RMS rotation angle; the angle is Maxwell-distributed) and E|c' - c|^2 = (tau s)^2 (tau is
the RMS translation as a fraction of the spread).

Photometric pipeline on the LINEAR render, per train view i (premultiplied RGB scales as
straight RGB does; alpha is untouched; nothing is clipped in the EXR, the PNG's sRGB
encoding clips to [0, 1] as for every view):

    out[y, x, c] = rgb[y, x, c] * 2^EV_i * wb_i[c] * v(r(y, x))
    EV_i ~ N(0, sigma_ev^2);  wb_i = (2^a_i, 1, 2^b_i), a_i, b_i ~ N(0, sigma_wb^2)  (green is the reference)
    v(r) = 1 - k r^2,  r = |(x + 0.5, y + 0.5) - (cx, cy)| / sqrt((W/2)^2 + (H/2)^2)

r is 1 at the image corners, so k in [0, 1) keeps every factor positive. The two noise
passes are scaled by the same factors, so the noise JSON describes the stored image.

Seeds: every draw comes from np.random.default_rng([seed, TAG, ...]) where seed is
--degrade-seed, or the dataset's --seed when that is not given; each kind of degradation
has its own TAG (and each view its own stream), so turning one on never changes another's
draws, and the standard-normal draws are the same at every level (a level sweep scales one
set of directions).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core import arguments
from nerfgauge.core.camera import Intrinsics

POSE_TAG = 0x504F5345  # "POSE"
PHOTO_TAG = 0x50484F54  # "PHOT"
# Ranges (core.arguments.bounded): 45 degrees RMS is already no longer "noise" on a pose;
# a translation of 10 spreads leaves nothing of the layout; 10 EV is a factor of 1000.
ROTATION_NOISE_DEGREES = arguments.bounded(float, 0, 45)
TRANSLATION_NOISE_FRACTION = arguments.bounded(float, 0, 10)
EXPOSURE_SIGMA_EV = arguments.bounded(float, 0, 10)
WHITE_BALANCE_SIGMA = arguments.bounded(float, 0, 10)
VIGNETTING_K = arguments.bounded(float, 0, 1, below=True)  # v(corner) = 1 - k must stay > 0
RANGES = {"pose_noise_rotation": ROTATION_NOISE_DEGREES, "pose_noise_translation": TRANSLATION_NOISE_FRACTION,
          "exposure_ev": EXPOSURE_SIGMA_EV, "white_balance": WHITE_BALANCE_SIGMA, "vignetting": VIGNETTING_K,
          "degrade_seed": arguments.SEED}
FIELDS = ("pose_noise_rotation", "pose_noise_translation", "exposure_ev", "white_balance", "vignetting",
          "degrade_seed")
FORMULAS = {
    "pose_noise": "omega ~ N(0, (rotation_deg/sqrt 3)^2 I3) (rotation vector, axis uniform, RMS angle = rotation_deg); "
                  "R' = R Exp(omega); c' = c + N(0, (translation * spread / sqrt 3)^2 I3) (RMS offset = "
                  "translation * spread); spread = RMS distance of the exact train camera centres from their mean",
    "photometric": "linear rgb * 2^ev * wb[c] * (1 - k r^2), r = distance of the pixel centre from (cx, cy) over "
                   "the half-diagonal sqrt((w/2)^2 + (h/2)^2); ev ~ N(0, exposure_ev^2); wb = (2^a, 1, 2^b), "
                   "a, b ~ N(0, white_balance^2); alpha untouched; no clipping in the EXR",
}


@dataclass(frozen=True)
class Photometric:
    """One train view's camera pipeline: exposure (EV), white-balance gains [3] (R, G, B)
    and the vignetting coefficient k."""

    exposure_ev: float
    wb_gains: tuple
    vignetting: float

    def to_json(self) -> dict:
        return {"exposure_ev": self.exposure_ev, "gain": 2.0 ** self.exposure_ev, "wb_gains": list(self.wb_gains),
                "vignetting_k": self.vignetting}

    def factors(self, intrinsics: Intrinsics) -> np.ndarray:
        """The per-pixel, per-channel multiplier 2^EV wb[c] (1 - k r^2). [H, W, 3] float64."""
        return (2.0 ** self.exposure_ev) * vignetting_map(intrinsics, self.vignetting)[..., None] \
            * np.asarray(self.wb_gains, np.float64)


def vignetting_map(intrinsics: Intrinsics, k: float) -> np.ndarray:
    """v = 1 - k r^2 at every pixel centre, r normalised by the half-diagonal. [H, W] float64."""
    w, h = intrinsics.width, intrinsics.height
    x = np.arange(w, dtype=np.float64) + 0.5 - intrinsics.cx
    y = np.arange(h, dtype=np.float64) + 0.5 - intrinsics.cy
    r2 = (x[None, :] ** 2 + y[:, None] ** 2) / ((w / 2.0) ** 2 + (h / 2.0) ** 2)
    return 1.0 - k * r2


@dataclass(frozen=True)
class Degradations:
    """The train-view degradations of a dataset (GenerateConfig's fields of the same names).
    All zero: none, and the dataset is byte for byte the clean one."""

    pose_noise_rotation: float = 0.0  # RMS rotation angle, degrees
    pose_noise_translation: float = 0.0  # RMS centre offset as a fraction of the train cameras' spread
    exposure_ev: float = 0.0  # std of the per-view exposure, EV (stops)
    white_balance: float = 0.0  # std of the per-view log2 R and B gains (G = 1)
    vignetting: float = 0.0  # k of v(r) = 1 - k r^2, the same for every train view
    degrade_seed: Optional[int] = None  # None: the dataset's seed

    @classmethod
    def of(cls, config) -> "Degradations":
        """The degradations of a GenerateConfig (or anything with these attributes)."""
        return cls(**{name: getattr(config, name) for name in FIELDS})

    def validate(self) -> None:
        """InputError (one line, naming the flag and its range) for a value out of range,
        non-finite or not a number; vignetting k >= 1 would make the corner factor <= 0."""
        arguments.check_fields(self, RANGES)

    @property
    def poses(self) -> bool:
        return self.pose_noise_rotation != 0 or self.pose_noise_translation != 0

    @property
    def photometric(self) -> bool:
        return self.exposure_ev != 0 or self.white_balance != 0 or self.vignetting != 0

    @property
    def any(self) -> bool:
        return self.poses or self.photometric

    def seed(self, dataset_seed: int) -> int:
        return int(dataset_seed if self.degrade_seed is None else self.degrade_seed)

    def view_photometric(self, dataset_seed: int, index: int) -> Photometric:
        """Train view `index`'s camera pipeline: its own stream, default_rng([seed, PHOTO_TAG, index])."""
        z = np.random.default_rng([self.seed(dataset_seed), PHOTO_TAG, int(index)]).standard_normal(3)
        return Photometric(float(self.exposure_ev * z[0]),
                           (float(2.0 ** (self.white_balance * z[1])), 1.0, float(2.0 ** (self.white_balance * z[2]))),
                           float(self.vignetting))

    def to_json(self, dataset_seed: int) -> dict:
        """scene.json's "degradations" (without the per-frame values, which are in the transforms)."""
        return {"split": "train", **{name: getattr(self, name) for name in FIELDS},
                "seed_used": self.seed(dataset_seed), "formulas": FORMULAS,
                "exact": "val and test views, depth, normals, masks, instance ids, albedo and meshes",
                "per_frame": "transforms_train.json and transforms.json train frames: exact_transform_matrix "
                             "(with pose noise; transform_matrix holds the perturbed pose) and photometric"}


def camera_spread(c2w: np.ndarray) -> float:
    """RMS distance of the camera centres from their mean: sqrt(mean_i |c_i - c_bar|^2).
    c2w [n, 4, 4] -> scalar (0 for one camera)."""
    centres = np.asarray(c2w, np.float64)[:, :3, 3]  # [n, 3]
    return float(np.sqrt(np.mean(np.sum((centres - centres.mean(axis=0)) ** 2, axis=1)))) if len(centres) else 0.0


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """Exp map (Rodrigues): rotation vectors [n, 3] (radians) -> rotation matrices [n, 3, 3]."""
    omega = np.asarray(omega, np.float64)
    theta = np.linalg.norm(omega, axis=-1)[:, None, None]  # [n, 1, 1]
    k = np.zeros(omega.shape[:-1] + (3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    k = k - np.swapaxes(k, 1, 2)  # skew(omega)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(theta > 1e-12, np.sin(theta) / theta, 1.0)
        b = np.where(theta > 1e-12, (1.0 - np.cos(theta)) / theta ** 2, 0.5)
    return np.eye(3) + a * k + b * (k @ k)


def perturb_poses(c2w: np.ndarray, degradations: Degradations, dataset_seed: int) -> np.ndarray:
    """The perturbed train poses (module docstring). c2w [n, 4, 4] -> [n, 4, 4] float64.
    The rotation and translation draws come from one stream, default_rng([seed, POSE_TAG]):
    z [n, 3] then u [n, 3]."""
    c2w = np.asarray(c2w, np.float64)
    n = len(c2w)
    rng = np.random.default_rng([degradations.seed(dataset_seed), POSE_TAG])
    z, u = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    sigma_rot = math.radians(degradations.pose_noise_rotation) / math.sqrt(3.0)
    sigma_t = degradations.pose_noise_translation * camera_spread(c2w) / math.sqrt(3.0)
    out = c2w.copy()
    out[:, :3, :3] = c2w[:, :3, :3] @ rotation_from_vector(sigma_rot * z)
    out[:, :3, 3] = c2w[:, :3, 3] + sigma_t * u
    return out


def degrade_images(images, photometric: Photometric, intrinsics: Intrinsics):
    """A render.ViewImages with its colour (and both noise passes) multiplied by the view's
    factors; alpha and everything else unchanged. float64 product, stored as the input dtype."""
    factors = photometric.factors(intrinsics)  # [H, W, 3]

    def scaled(rgba: np.ndarray) -> np.ndarray:
        out = rgba.copy()
        out[..., :3] = (rgba[..., :3].astype(np.float64) * factors).astype(rgba.dtype)
        return out

    passes = tuple((scaled(rgba), spp) for rgba, spp in images.passes)
    return dataclasses.replace(images, rgba=scaled(images.rgba), passes=passes)


def undo_photometric(rgba: np.ndarray, photometric: Photometric, intrinsics: Intrinsics) -> np.ndarray:
    """The inverse: a degraded linear RGBA [H, W, 4] divided by the recorded factors (float64)."""
    out = np.asarray(rgba, np.float64).copy()
    out[..., :3] /= photometric.factors(intrinsics)
    return out


def frame_extras(degradations: Degradations, dataset_seed: int, exact_poses: np.ndarray) -> list:
    """Per train frame, the keys added to its transforms entry: "exact_transform_matrix"
    (with pose noise) and "photometric" (with a photometric degradation)."""
    extras = [{} for _ in range(len(exact_poses))]
    for i, extra in enumerate(extras):
        if degradations.poses:
            extra["exact_transform_matrix"] = np.asarray(exact_poses[i], np.float64).tolist()
        if degradations.photometric:
            extra["photometric"] = degradations.view_photometric(dataset_seed, i).to_json()
    return extras


def train_poses(exact_poses: np.ndarray, degradations: Degradations, dataset_seed: int) -> np.ndarray:
    """What the train transforms hold: the perturbed poses with pose noise, else the exact ones."""
    return perturb_poses(exact_poses, degradations, dataset_seed) if degradations.poses else exact_poses


def add_frame_extras(transforms: dict, stems, extras: list, *, with_dot: bool) -> dict:
    """Merge frame_extras into the train frames of a transforms document (matched by
    file_path: "./train/r_000" in transforms_train.json, "train/r_000.png" in
    transforms.json). Returns the document, changed in place."""
    by_path = {("./" + stem if with_dot else stem + ".png"): extra for stem, extra in zip(stems, extras)}
    for frame in transforms["frames"]:
        frame.update(by_path.get(frame["file_path"], {}))
    return transforms
