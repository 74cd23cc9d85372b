"""Adaptive density control (Kerbl et al. 2023, section 5.2): clone, split, prune, reset.

Between densifications each Gaussian accumulates the norm of its view-space positional
gradient, in normalised device units as the 3DGS code measures it (the pixel gradient of
its projected mean times (W/2, H/2)), over the views where it was drawn, and the largest
footprint radius it had on screen. At a densification, with g its mean gradient norm:

    clone  g >= densify_grad and max scale <= percent_dense x extent   (under-reconstructed: a copy)
    split  g >= densify_grad and max scale >  percent_dense x extent   (over-reconstructed: two
           Gaussians drawn from it, positions ~ N(mu, Sigma), scales / (0.8 x 2); it is removed)
    prune  opacity < prune_opacity; after the first opacity reset also max scale > max_world_scale
           x extent or screen radius > max_screen_radius pixels

and an opacity reset sets every opacity to at most 0.01 (their Adam moments to zero), so
Gaussians that do not matter fade and are pruned. `extent` is the cameras' spread (the 3DGS
code's cameras_extent: 1.1 x the largest distance of a camera centre from their mean).
Growth stops at max_gaussians: when more qualify, those of largest gradient go first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nerfgauge.splat.config import SplatConfig
from nerfgauge.splat.gaussians import GaussianAdam, Gaussians, logit
from nerfgauge.splat.projection import quaternion_to_rotation

SPLIT_INTO = 2
SPLIT_SHRINK = 0.8 * SPLIT_INTO  # the 3DGS code's divisor of a split Gaussian's scales
RESET_OPACITY = 0.01


def cameras_extent(centres: np.ndarray) -> float:
    """1.1 x the largest distance of a camera centre [n, 3] from their mean (3DGS's
    getNerfppNorm radius); a single camera: 1."""
    if len(centres) < 2:
        return 1.0
    radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    return 1.1 * radius if radius > 0 else 1.0


@dataclass
class DensityStats:
    """Per Gaussian: gradient_sum [N] (of view-space gradient norms), views [N] (in which it
    was drawn), max_radius [N] (pixels)."""

    gradient_sum: torch.Tensor
    views: torch.Tensor
    max_radius: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device="cpu") -> "DensityStats":
        return cls(torch.zeros(n, device=device), torch.zeros(n, device=device), torch.zeros(n, device=device))

    @torch.no_grad()
    def add_view(self, means2d_grad: torch.Tensor, radii: torch.Tensor, visible: torch.Tensor, width: int,
                 height: int) -> None:
        """Accumulate one view: means2d_grad [N, 2] pixel-space gradient, radii [N], visible [N]."""
        scale = torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device)
        norms = (means2d_grad.reshape(-1, 2) * scale).norm(dim=1)  # [N]
        self.gradient_sum += torch.where(visible, norms, torch.zeros_like(norms))
        self.views += visible.float()
        self.max_radius = torch.where(visible, torch.maximum(self.max_radius, radii.float()), self.max_radius)


@torch.no_grad()
def densify_and_prune(adam: GaussianAdam, stats: DensityStats, config: SplatConfig, extent: float,
                      prune_large: bool, generator: torch.Generator) -> dict:
    """One densification (module docstring). Returns {"cloned", "split", "pruned"}: counts."""
    gaussians = adam.gaussians
    n = len(gaussians)
    mean_gradient = stats.gradient_sum / stats.views.clamp_min(1)  # [N]
    largest = torch.exp(gaussians.log_scales).max(dim=1).values  # [N]
    wanted = mean_gradient >= config.densify_grad  # [N]
    room = max(config.max_gaussians - n, 0)
    if int(wanted.sum()) > room:  # growth capped: the largest gradients first (a split adds one net)
        order = torch.argsort(torch.where(wanted, mean_gradient, torch.full_like(mean_gradient, -1.0)),
                              descending=True)
        wanted = torch.zeros_like(wanted)
        wanted[order[:room]] = True
    clone = wanted & (largest <= config.percent_dense * extent)  # [N]
    split = wanted & ~clone  # [N]
    new = {name: tensor[clone].detach().clone() for name, tensor in gaussians.tensors().items()}
    split_new = _split(gaussians, split, generator)
    adam.append({name: torch.cat([new[name], split_new[name]]) for name in new})
    grown = len(gaussians)
    opacity = torch.sigmoid(gaussians.opacity_logits)  # [grown]
    remove = torch.cat([split, torch.zeros(grown - n, dtype=torch.bool, device=split.device)])  # the split originals
    remove |= opacity < config.prune_opacity
    if prune_large:
        radius = torch.cat([stats.max_radius, torch.zeros(grown - n, device=stats.max_radius.device)])
        remove |= radius > config.max_screen_radius
        remove |= torch.exp(gaussians.log_scales).max(dim=1).values > config.max_world_scale * extent
    adam.keep(~remove)
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(remove.sum()) - int(split.sum())}


def _split(gaussians: Gaussians, mask: torch.Tensor, generator: torch.Generator) -> dict:
    """SPLIT_INTO new Gaussians for each masked one: positions drawn from it, scales shrunk."""
    tensors = {name: tensor[mask].detach() for name, tensor in gaussians.tensors().items()}
    scales = torch.exp(tensors["log_scales"]).repeat(SPLIT_INTO, 1)  # [S * k, 3]
    noise = torch.randn(scales.shape, generator=generator, device="cpu").to(scales.device) * scales  # [S * k, 3]
    rotation = quaternion_to_rotation(tensors["quats"]).repeat(SPLIT_INTO, 1, 1)  # [S * k, 3, 3]
    new = {name: tensor.repeat(SPLIT_INTO, *([1] * (tensor.dim() - 1))) for name, tensor in tensors.items()}
    new["means"] = new["means"] + (rotation @ noise[:, :, None])[:, :, 0]
    new["log_scales"] = torch.log(scales / SPLIT_SHRINK)
    return new


@torch.no_grad()
def reset_opacity(adam: GaussianAdam) -> None:
    """Every opacity to at most RESET_OPACITY, its Adam moments to zero."""
    logits = adam.gaussians.opacity_logits
    adam.replace("opacity_logits", torch.minimum(logits, torch.full_like(logits, logit(RESET_OPACITY))))
