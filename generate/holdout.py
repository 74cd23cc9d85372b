"""Splits that test extrapolation (issue 35, item 6): held-out sectors, test views at other
distances, and the fixed sparse view lists published with every dataset.

- `--holdout azimuth:A:B` / `--holdout elevation:A:B` (degrees): a sector of camera
  directions about the orbit's centre (the AABB centre, or a scene's own orbit target;
  azimuth from +X towards +Y, elevation above the horizon). Train and val views stand only outside it; the test split holds
  ceil(test_views / 2) **extrapolation** views inside it, then floor(test_views / 2)
  **interpolation** views drawn outside it from the very pool the train and val views
  are dealt from, so the interpolation/extrapolation gap is measured on one dataset. The
  directions are those of the layout's elevation band (hemisphere 10..75 by default,
  sphere -89..89) restricted to the region: even (golden-ratio azimuths, equal-area
  elevation strata) or seeded random, as `--sampling` says.
- `--test-scales 0.5,2`: after those, test_views more test views per scale s != 1 at
  distance radius / s from the AABB centre (s = 2: twice as close, every surface twice as
  large in the image; s = 0.5: twice as far), directions drawn from the train region.
  The intrinsics stay those of every view: the change of a surface's pixel footprint by
  1/s is the change Mip-Splatting's single-scale-train / multi-scale-test protocol makes by
  rendering the test views at resolution x s; here the resolution (and so every reader
  of the split) stays one, at the price that the framing changes with the distance.
  Scale 1 is the test split's ordinary views.
- `sparse_views.json`: nested lists of train view indices for 3, 6, 9, 12 and 24 views
  (the counts below the train count, and that count itself if it is one of them), by
  farthest-point sampling on the camera centres: start at the train camera nearest the
  mean of all centres, then add the one farthest from those chosen (ties: lowest index).
  `nerfgauge train --sparse N` trains on list N.

Both options draw from their own generator, seeded (seed, 35): the camera set without
them is the layout's, unchanged.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core import arguments, dataset
from nerfgauge.core.camera import look_at
from nerfgauge.generate import layouts
from nerfgauge.core.errors import InputError

AXES = ("azimuth", "elevation")
ORBITING = ("hemisphere", "sphere")  # the layouts whose cameras stand on a sphere facing its centre
SPHERE_BAND = (-89.0, 89.0)  # layouts.camera_poses's band for "sphere"
SPARSE_COUNTS = (3, 6, 9, 12, 24)
SPARSE_FILE = dataset.SPARSE_VIEWS
SPARSE_RULE = ("farthest-point sampling on the train camera centres: start at the camera nearest their mean, "
               "then repeatedly add the camera farthest (Euclidean) from those chosen, ties to the lowest index; "
               "list N is the first N of that order, so the lists are nested")
MAX_SCALES = 8
SCALE_RANGE = (1 / 16, 16.0)
SCALE = arguments.bounded(float, *SCALE_RANGE)  # --test-scales: each scale
GOLDEN_FRACTION = (math.sqrt(5.0) - 1) / 2
RNG_TAG = 35  # issue 35: the extrapolation views' generator is seeded (seed, 35)
_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"


@dataclass(frozen=True)
class Sector:
    """A held-out sector: axis "azimuth" (lo..hi counter-clockwise from +X, may wrap past
    360) or "elevation" (lo..hi above the horizon), degrees."""

    axis: str
    lo: float
    hi: float

    def to_json(self) -> dict:
        return {"axis": self.axis, "min_degrees": self.lo, "max_degrees": self.hi}

    def __str__(self) -> str:
        return f"{self.axis}:{self.lo:g}:{self.hi:g}"


def parse_holdout(text: str) -> Sector:
    """"azimuth:0:60" or "elevation:60:90" -> Sector; InputError with the expected form."""
    match = re.fullmatch(rf"\s*(\w+)\s*:\s*({_NUMBER})\s*:\s*({_NUMBER})\s*", str(text))
    if not match or match.group(1) not in AXES:
        raise InputError(f"--holdout must be azimuth:MIN:MAX or elevation:MIN:MAX in degrees, got {text!r}")
    axis, lo, hi = match.group(1), float(match.group(2)), float(match.group(3))
    if axis == "azimuth" and not (-360 <= lo < hi <= 720 and hi - lo < 360):
        raise InputError(f"--holdout azimuth:MIN:MAX needs MIN < MAX, less than 360 degrees apart, got {text!r}")
    if axis == "elevation" and not -90 <= lo < hi <= 90:
        raise InputError(f"--holdout elevation:MIN:MAX needs -90 <= MIN < MAX <= 90, got {text!r}")
    return Sector(axis, lo, hi)


def parse_scales(text) -> tuple:
    """"0.5,1,2" (or a sequence of numbers) -> (0.5, 1.0, 2.0): distinct, each in
    SCALE_RANGE, at most MAX_SCALES."""
    items = text.split(",") if isinstance(text, str) else list(text)
    try:
        scales = tuple(float(item) for item in items)
    except (TypeError, ValueError):
        raise InputError(f"--test-scales must be numbers separated by commas (e.g. 0.5,1,2), got {text!r}") from None
    if not scales or len(scales) > MAX_SCALES:
        raise InputError(f"--test-scales takes 1 to {MAX_SCALES} scales, got {text!r}")
    for scale in scales:
        if not (math.isfinite(scale) and SCALE.contains(scale)):
            raise InputError(f"--test-scales: each scale must be {SCALE.wanted}, got {scale!r}")
    if len(set(scales)) != len(scales):
        raise InputError(f"--test-scales lists a scale twice: {text!r}")
    return scales


def check_layout(layout: str, holdout, test_scales) -> None:
    """Extrapolation splits need cameras on a sphere about the centre (hemisphere, sphere)."""
    if (holdout is not None or test_scales is not None) and layout not in ORBITING:
        flag = "--holdout" if holdout is not None else "--test-scales"
        raise InputError(f"{flag} needs the hemisphere or sphere layout (cameras around the scene), "
                         f"this dataset's layout is {layout}")


def _intervals_minus(band: tuple, cut: tuple) -> list:
    """The parts of interval `band` outside interval `cut` (each (lo, hi), lo < hi)."""
    parts = [(band[0], min(band[1], cut[0])), (max(band[0], cut[1]), band[1])]
    return [(lo, hi) for lo, hi in parts if hi - lo > 1e-9]


def _intersect(band: tuple, cut: tuple) -> list:
    lo, hi = max(band[0], cut[0]), min(band[1], cut[1])
    return [(lo, hi)] if hi - lo > 1e-9 else []


@dataclass(frozen=True)
class Region:
    """Directions with azimuth in [az_lo, az_lo + az_width] and elevation in the union of
    `bands` (degrees)."""

    az_lo: float
    az_width: float
    bands: tuple

    @property
    def empty(self) -> bool:
        return not self.bands or self.az_width <= 1e-9

    def sample(self, n: int, sampling: str, rng: np.random.Generator) -> np.ndarray:
        """n unit directions [n, 3], area-uniform: z = sin(elevation) uniform over the
        bands (strata (i + 0.5) / n when even), azimuth by the golden ratio when even."""
        z_parts = [(math.sin(math.radians(lo)), math.sin(math.radians(hi))) for lo, hi in self.bands]
        lengths = np.array([hi - lo for lo, hi in z_parts])
        if sampling == "fibonacci":
            u, v = (np.arange(n) + 0.5) / n, np.mod((np.arange(n) + 0.5) * GOLDEN_FRACTION, 1.0)
        else:
            u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
        along = u * lengths.sum()  # position along the concatenated z intervals
        edges = np.concatenate([[0.0], np.cumsum(lengths)])
        part = np.clip(np.searchsorted(edges, along, side="right") - 1, 0, len(z_parts) - 1)
        z = np.array([z_parts[p][0] for p in part]) + (along - edges[part])
        azimuth = np.radians(self.az_lo + self.az_width * v)
        ring = np.sqrt(np.clip(1 - z**2, 0, 1))
        return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], axis=1)


def regions(sector: Optional[Sector], band: tuple) -> tuple:
    """(inside, outside) Regions of the elevation band `band` for `sector` (inside None
    without a sector: everything is outside)."""
    if sector is None:
        return None, Region(0.0, 360.0, (band,))
    if sector.axis == "azimuth":
        width = sector.hi - sector.lo
        return Region(sector.lo, width, (band,)), Region(sector.hi, 360.0 - width, (band,))
    cut = (sector.lo, sector.hi)
    return Region(0.0, 360.0, tuple(_intersect(band, cut))), Region(0.0, 360.0, tuple(_intervals_minus(band, cut)))


def _poses(directions: np.ndarray, centre: np.ndarray, radius: float, aabb, what: str) -> np.ndarray:
    """Cameras at `centre` + radius x directions [n, 3] facing `centre`; inside `aabb` is
    refused (None: a scene's own orbit target, where layouts allows it too)."""
    eyes = centre + radius * directions
    if aabb is not None and np.all((eyes >= aabb[0]) & (eyes <= aabb[1]), axis=1).any():
        raise InputError(f"{what} at distance {radius:g} stand inside the scene's AABB; choose smaller --test-scales "
                         f"or a larger --radius")
    return np.stack([look_at(eye, centre) for eye in eyes]) if len(eyes) else np.zeros((0, 4, 4))


def extrapolation_split(spec, aabb: np.ndarray, poses: dict, holdout: Optional[str], test_scales, seed: int,
                        sampling: str) -> Optional[tuple]:
    """(poses {split: [n, 4, 4]}, record) with the held-out sector and scaled test views;
    None when neither is asked for (`poses`, the layout's, stand). spec: the resolved
    layouts.LayoutSpec; record: scene.json's "extrapolation" (per test frame index its
    group, whether it is in the sector, its scale)."""
    if holdout is None and test_scales is None:
        return None
    check_layout(spec.layout, holdout, test_scales)
    sector = None if holdout is None else parse_holdout(holdout)
    scales = () if test_scales is None else tuple(s for s in parse_scales(test_scales) if s != 1.0)
    band = SPHERE_BAND if spec.layout == "sphere" else tuple(spec.elevation)
    rng = np.random.default_rng([int(seed), RNG_TAG])
    # the orbit's centre as layouts.camera_poses has it: a scene's target, else the AABB centre
    centre = (aabb[0] + aabb[1]) / 2 if spec.target is None else np.asarray(spec.target, np.float64)
    aabb = aabb if spec.target is None else None
    n_train, n_val, n_test = spec.counts
    inside, outside = regions(sector, band)
    frames = []
    if sector is None:
        poses = {split: np.asarray(p) for split, p in poses.items()}
        frames += [{"group": "interpolation", "in_sector": False, "scale": 1.0}] * n_test
    else:
        if outside.empty:
            raise InputError(f"--holdout {sector} leaves no training view: the cameras' elevation band "
                             f"{band[0]:g}..{band[1]:g} lies inside it")
        n_extra = (n_test + 1) // 2
        if inside.empty and n_extra:
            raise InputError(f"--holdout {sector} holds out no camera direction: the cameras' elevation band "
                             f"{band[0]:g}..{band[1]:g} does not reach it")
        n_inter = n_test - n_extra
        pool = _poses(outside.sample(n_train + n_val + n_inter, sampling, rng), centre, spec.radius, aabb,
                      "cameras")[rng.permutation(n_train + n_val + n_inter)]
        extra = _poses(inside.sample(n_extra, sampling, rng), centre, spec.radius, aabb, "cameras")
        poses = {"train": pool[:n_train], "val": pool[n_train:n_train + n_val],
                 "test": np.concatenate([extra, pool[n_train + n_val:]])}
        frames += [{"group": "extrapolation", "in_sector": True, "scale": 1.0}] * n_extra
        frames += [{"group": "interpolation", "in_sector": False, "scale": 1.0}] * n_inter
    scaled = [poses["test"]]
    for scale in scales:
        scaled.append(_poses(outside.sample(n_test, sampling, rng), centre, spec.radius / scale, aabb,
                             f"--test-scales {scale:g}'s cameras"))
        frames += [{"group": "extrapolation", "in_sector": False, "scale": scale}] * n_test
    poses["test"] = np.concatenate(scaled)
    layouts._refuse_coinciding(poses)  # noqa: SLF001 (the one rule for every layout)
    record = {"holdout": None if sector is None else sector.to_json(),
              "test_scales": None if test_scales is None else [1.0, *scales],
              "radius": spec.radius, "elevation_band": list(band),
              "rule": ("train and val views outside the sector; test: ceil(n/2) views inside it (extrapolation), "
                       "floor(n/2) from the train views' pool (interpolation); per scale s != 1, n more test views "
                       "at distance radius / s from the train region (extrapolation), same intrinsics"),
              "frames": frames}
    return poses, record


def frame_record(record: dict, stems: list) -> dict:
    """scene.json's "extrapolation" with each test frame named by its stem."""
    return {**record, "frames": [{"name": stem, **frame} for stem, frame in zip(stems, record["frames"])]}


def farthest_point_order(centres: np.ndarray, count: int) -> list:
    """The first `count` indices of farthest-point sampling on points [n, 3] (SPARSE_RULE)."""
    centres = np.asarray(centres, np.float64)
    if not len(centres):
        return []
    first = int(np.argmin(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    order, nearest = [first], np.linalg.norm(centres - centres[first], axis=1)
    while len(order) < min(count, len(centres)):
        nxt = int(np.argmax(nearest))  # argmax returns the lowest index among ties
        order.append(nxt)
        nearest = np.minimum(nearest, np.linalg.norm(centres - centres[nxt], axis=1))
    return order


def sparse_views(train_c2w: np.ndarray, stems: list) -> dict:
    """sparse_views.json: {"rule", "counts": {"N": [train indices]}, "stems": {"N": [stems]}}
    for each N of SPARSE_COUNTS up to the train count."""
    counts = [n for n in SPARSE_COUNTS if n <= len(stems)]
    order = farthest_point_order(np.asarray(train_c2w)[:, :3, 3], max(counts, default=0))
    return {"rule": SPARSE_RULE, "split": "train",
            "counts": {str(n): order[:n] for n in counts},
            "stems": {str(n): [stems[i] for i in order[:n]] for n in counts}}
