"""The training stage's one config, and how "model only what the scene needs" is decided.

`TrainConfig` is frozen and saved as RUN/config.json. Fields left as None ("auto") are
resolved from the dataset's scene.json by `resolve`, and every resolved choice is written
with the reason it was made, so a run states what it modelled and why.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from nerfgauge.core.errors import InputError

MODELS = ("compact", "vanilla")
BACKGROUNDS = ("random", "white", "black")
# A dense 256^3 grid with Adam state is ~1 GB for a diffuse scene, ~3.5 GB with view-dependent
# features; 512^3 would be 8x that. Cameras inside the scene's bounding sphere (rooms,
# forward-facing captures) ask for more than any CPU can hold: they get this cap.
MAX_AUTO_RESOLUTION = 256


@dataclass(frozen=True)
class TrainConfig:
    dataset: str
    model: str = "compact"
    seed: int = 0
    steps: Optional[int] = None  # stop after this many steps ...
    budget_seconds: Optional[float] = None  # ... or after this much training time
    batch_rays: int = 4096
    lr: float = 0.1  # voxel grids (DVGO-style large steps); MLP heads use lr_mlp
    lr_mlp: float = 5e-3
    background: str = "random"  # training background per ray: random makes alpha learnable
    # compact: None = decide from scene.json (see `resolve`)
    view_dependent: Optional[bool] = None
    final_resolution: Optional[int] = None  # voxels along the AABB's longest side
    start_resolution: Optional[int] = None
    prune: bool = True
    occupancy: bool = True  # empty-space skipping
    tv_weight: float = 0.0
    distortion_weight: float = 1e-3  # mip-NeRF 360 distortion loss: solid surfaces, exact depth
    step_ratio: float = 0.5  # ray-marching step in voxels
    feature_channels: int = 12  # view-dependent colour: grid features fed to a small MLP
    # vanilla (the lecture's NeRF)
    n_coarse: int = 64
    n_fine: int = 128
    width: int = 256
    depth: int = 8
    vanilla_batch_rays: int = 1024
    # logging
    eval_every_seconds: float = 10.0  # val PSNR points along the way (training clock)
    eval_views: int = 4
    eval_rays: int = 8192  # val pixels per PSNR point (a fixed strided subset of eval_views)
    threads: int = 2
    device: str = "auto"

    def validate(self) -> None:
        if self.model not in MODELS:
            raise InputError(f"unknown model {self.model!r}; choose one of {', '.join(MODELS)}")
        if (self.steps is None) == (self.budget_seconds is None):
            raise InputError("give exactly one of --steps N or --budget-seconds T")
        if self.steps is not None and (not isinstance(self.steps, int) or self.steps <= 0):
            raise InputError(f"--steps must be a positive integer, got {self.steps!r}")
        if self.budget_seconds is not None and not (self.budget_seconds > 0 and math.isfinite(self.budget_seconds)):
            raise InputError(f"--budget-seconds must be positive, got {self.budget_seconds!r}")
        if self.background not in BACKGROUNDS:
            raise InputError(f"unknown background {self.background!r}; choose one of {', '.join(BACKGROUNDS)}")
        for name in ("batch_rays", "n_coarse", "width", "depth", "vanilla_batch_rays", "threads", "feature_channels",
                     "eval_views", "eval_rays"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise InputError(f"{name} must be a positive integer, got {value!r}")
        for name in ("final_resolution", "start_resolution"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or not 4 <= value <= 1024):
                raise InputError(f"{name} must be an integer in [4, 1024], got {value!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"--seed must be a non-negative integer, got {self.seed!r}")
        if not self.eval_every_seconds > 0:
            raise InputError(f"--eval-every must be positive seconds, got {self.eval_every_seconds!r}")
        if not self.step_ratio > 0 or self.tv_weight < 0 or self.distortion_weight < 0 or self.lr <= 0 \
                or self.lr_mlp <= 0:
            raise InputError("step_ratio, lr and lr_mlp must be positive; tv_weight and distortion_weight >= 0")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def footprint_resolution(aabb: np.ndarray, c2w: np.ndarray, focal: float, nyquist_period: Optional[float]) -> tuple[int, str]:
    """Voxels along the AABB's longest side so a voxel is no smaller than what a pixel
    resolves: the pixel footprint at the nearest content (camera distance to the AABB's
    bounding sphere), and no coarser than half the finest texture period (Nyquist).
    Returns (resolution, reason)."""
    centre = (aabb[0] + aabb[1]) / 2
    bound = float(np.linalg.norm(aabb[1] - aabb[0])) / 2
    nearest = max(float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).min()) - bound, 1e-6)
    footprint = nearest / focal  # scene units per pixel at the nearest content
    longest = float((aabb[1] - aabb[0]).max())
    voxel = footprint
    reason = f"pixel footprint {footprint:.4g} at distance {nearest:.3g}"
    if nyquist_period is not None and nyquist_period / 2 < voxel:
        voxel = nyquist_period / 2
        reason = f"half the finest texture period {nyquist_period:.4g}"
    wanted = math.ceil(longest / voxel)
    resolution = int(min(max(wanted, 16), MAX_AUTO_RESOLUTION))
    if wanted > MAX_AUTO_RESOLUTION:
        reason += f" asks for {wanted} voxels; capped at {MAX_AUTO_RESOLUTION} (dense-grid memory)"
    return resolution, reason


def resolve(config: TrainConfig, needs: Optional[dict], aabb: np.ndarray, train_c2w: np.ndarray,
            focal: float) -> tuple[TrainConfig, dict]:
    """Fill the automatic choices. Returns the resolved config and {choice: reason}."""
    reasons = {}
    updates = {}
    if config.view_dependent is None:
        if needs is None:
            updates["view_dependent"] = True
            reasons["view_dependent"] = "no scene.json: a safe general default"
        else:
            updates["view_dependent"] = bool(needs.get("view_dependent", True))
            reasons["view_dependent"] = f"scene.json needs.view_dependent = {needs.get('view_dependent')}"
    else:
        reasons["view_dependent"] = "set on the command line"
    if config.final_resolution is None:
        period = None if needs is None else needs.get("finest_texture_period")
        updates["final_resolution"], why = footprint_resolution(aabb, train_c2w, focal, period)
        reasons["final_resolution"] = why
    else:
        reasons["final_resolution"] = "set on the command line"
    final = updates.get("final_resolution", config.final_resolution)
    if config.start_resolution is None:
        updates["start_resolution"] = max(16, min(final, round(final / 4)))
        reasons["start_resolution"] = "a quarter of the final resolution (coarse to fine)"
    return dataclasses.replace(config, **updates), reasons
