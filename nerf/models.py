"""The two radiance-field models, each with one `render(origins, directions)` method.

- `CompactNeRF`: a voxel grid field, ray marching that skips empty space, coarse-to-fine
  resolution. Only what the scene needs: no view direction for diffuse scenes.
- `VanillaNeRF`: the lecture's NeRF (positional encoding with 10 and 4 frequencies,
  8 x 256 MLP with a skip, view direction input, coarse and fine networks).
Both return premultiplied colour, opacity and expected ray distance per ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerf.encoding import PositionalEncoding
from nerf.grid_field import VoxelGridField
from nerf.marching import march
from nerf.rendering import accumulate_along_rays, expected_depth, ray_aabb, render_rays, weights_from_density


@dataclass
class RayOutput:
    """rgb [n, 3] premultiplied; opacity, depth [n]; n_samples: field evaluations made;
    coarse: the vanilla coarse pass (trained too), else None."""

    rgb: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    n_samples: int = 0
    coarse: Optional["RayOutput"] = None


class CompactNeRF(nn.Module):
    def __init__(self, field: VoxelGridField, use_occupancy: bool = True):
        super().__init__()
        self.field = field
        self.use_occupancy = use_occupancy
        self.register_buffer("occupancy", torch.ones(tuple(s - 1 for s in field.grid.shape[2:]), dtype=torch.bool))

    @torch.no_grad()
    def update_occupancy(self) -> float:
        """Recompute which cells can hold density. Returns the occupied fraction."""
        if self.use_occupancy:
            self.occupancy = self.field.occupancy()
        else:
            self.occupancy = torch.ones(tuple(s - 1 for s in self.field.grid.shape[2:]), dtype=torch.bool,
                                        device=self.field.grid.device)
        return float(self.occupancy.float().mean())

    def upsample(self, resolution: int) -> None:
        self.field.upsample(resolution)
        self.update_occupancy()

    def render(self, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator | None = None,
               training: bool = False) -> RayOutput:
        """origins, directions (unit): [n, 3]. Training jitters samples within each step."""
        jitter = None
        if training:
            jitter = torch.rand(origins.shape[0], generator=generator, device=origins.device)
        samples = march(origins, directions, self.field.aabb, self.occupancy, self.field.marching_step, jitter=jitter)
        n_rays, width = samples.t_mid.shape
        sigma = samples.t_mid.new_zeros((n_rays, width))  # [n_rays, K]
        rgb = samples.t_mid.new_zeros((n_rays, width, 3))  # [n_rays, K, 3]
        kept = samples.valid
        n_kept = int(kept.sum())
        if n_kept:
            positions = origins[:, None, :] + samples.t_mid[..., None] * directions[:, None, :]  # [n_rays, K, 3]
            view = directions[:, None, :].expand(-1, width, -1)
            sigma_kept, rgb_kept = self.field(positions[kept], view[kept])
            sigma = sigma.index_put((kept,), sigma_kept)
            rgb = rgb.index_put((kept,), rgb_kept)
        weights, _, _ = weights_from_density(sigma, samples.delta)  # [n_rays, K]
        opacity = accumulate_along_rays(weights)
        colour = accumulate_along_rays(weights, rgb)
        depth = expected_depth(weights, samples.t_mid, opacity, samples.near, samples.far)
        return RayOutput(colour, opacity, depth, n_kept)

    def regularisation(self, tv_weight: float) -> torch.Tensor:
        return tv_weight * self.field.total_variation() if tv_weight > 0 else self.field.grid.new_zeros(())


class NeRFMLP(nn.Module):
    """The lecture's MLP: gamma(x) -> 8 x width ReLU (skip into layer 5) -> sigma and a
    feature; feature + gamma(d) -> width/2 -> rgb."""

    def __init__(self, width: int = 256, depth: int = 8, pos_frequencies: int = 10, dir_frequencies: int = 4):
        super().__init__()
        self.encode_pos = PositionalEncoding(3, pos_frequencies)
        self.encode_dir = PositionalEncoding(3, dir_frequencies)
        pos_dim, dir_dim = self.encode_pos.out_dim, self.encode_dir.out_dim
        self.skip = depth // 2
        layers = []
        for i in range(depth):
            in_dim = pos_dim if i == 0 else width + (pos_dim if i == self.skip else 0)
            layers.append(nn.Linear(in_dim, width))
        self.layers = nn.ModuleList(layers)
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.colour = nn.Sequential(nn.Linear(width + dir_dim, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def forward(self, positions: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """positions, directions: [..., 3]. Returns sigma [...], rgb [..., 3]."""
        encoded = self.encode_pos(positions)
        h = encoded
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, encoded], dim=-1)
            h = torch.relu(layer(h))
        sigma = torch.relu(self.sigma(h)[..., 0])
        rgb = torch.sigmoid(self.colour(torch.cat([self.feature(h), self.encode_dir(directions)], dim=-1)))
        return sigma, rgb


class VanillaNeRF(nn.Module):
    def __init__(self, aabb: torch.Tensor, n_coarse: int = 64, n_fine: int = 128, width: int = 256, depth: int = 8):
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.n_coarse, self.n_fine = n_coarse, n_fine
        self.coarse = NeRFMLP(width, depth)
        self.fine = NeRFMLP(width, depth)

    def _field(self, network):
        centre, half = (self.aabb[0] + self.aabb[1]) / 2, (self.aabb[1] - self.aabb[0]).max() / 2

        def field_fn(positions, directions):
            return network((positions - centre) / half, directions)  # encode in [-1, 1]
        return field_fn

    def render(self, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator | None = None,
               training: bool = False) -> RayOutput:
        near, far, hit = ray_aabb(origins, directions, self.aabb)
        far = torch.where(hit, far, near)
        out = render_rays(self._field(self.coarse), origins, directions, near, far, self.n_coarse,
                          n_importance=self.n_fine, fine_field_fn=self._field(self.fine), perturb=training,
                          generator=generator)
        n = origins.shape[0]
        coarse = RayOutput(out.coarse.rgb, out.coarse.opacity, out.coarse.depth, n * self.n_coarse)
        return RayOutput(out.rgb, out.opacity, out.depth, n * (2 * self.n_coarse + self.n_fine + 1), coarse)

    def regularisation(self, tv_weight: float) -> torch.Tensor:
        return self.aabb.new_zeros(())
