"""The compact field: a dense voxel grid (DVGO-style) with an occupancy grid.

Chosen by measurement on 2 CPU cores (DESIGN.md): a dense grid with occupancy skipping
beat a plain-PyTorch hash grid and a positional-encoding MLP in PSNR per second.

Density: raw values are trilinearly interpolated, then activated,
    sigma = DENSITY_SCALE * softplus(raw + shift) / voxel_final,
so surfaces can be sharper than a voxel; `shift` makes a fresh grid nearly transparent
(alpha = ALPHA_INIT per marching step). Colour: diffuse scenes store sRGB logits (3
channels, no view direction); view-dependent scenes store `feature_channels` features
that a small MLP turns into colour with the view direction (degree-3 spherical harmonics).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

ALPHA_INIT = 1e-3
# raw = 1 above the shift makes a half-voxel step opaque (tau ~ 5): surfaces become solid
# within the few hundred Adam steps a CPU affords, instead of soft shells with hazy insides.
DENSITY_SCALE = 10.0
OCCUPANCY_ALPHA = 5e-3  # a cell is empty when no node reaches this opacity per step (init: 1e-3)


def sh_basis_deg3(directions: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to degree 3 of unit directions [M, 3]. Returns [M, 16]."""
    x, y, z = directions.unbind(-1)
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    return torch.stack([
        torch.full_like(x, 0.28209479177387814),
        -0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x,
        1.0925484305920792 * xy, -1.0925484305920792 * yz, 0.31539156525252005 * (2 * zz - xx - yy),
        -1.0925484305920792 * xz, 0.5462742152960396 * (xx - yy),
        -0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * xy * z,
        -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
        -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
        -0.5900435899266435 * x * (xx - 3 * yy),
    ], dim=-1)


def grid_shape(aabb: torch.Tensor, resolution: int) -> tuple[int, int, int]:
    """(nz, ny, nx) nodes so the longest AABB side has `resolution` voxels, cubic voxels."""
    extent = (aabb[1] - aabb[0]).tolist()
    voxel = max(extent) / resolution
    nx, ny, nz = (max(2, math.ceil(e / voxel) + 1) for e in extent)
    return nz, ny, nx


class VoxelGridField(nn.Module):
    def __init__(self, aabb: torch.Tensor, resolution: int, final_resolution: int, view_dependent: bool,
                 feature_channels: int = 12, step_ratio: float = 0.5, space=None):
        """aabb [2, 3]: the grid's box in grid coordinates (the world AABB when bounded);
        space: a `nerf.parametrisation.Space` mapping world points into it (None: bounded)."""
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.space = space if space is not None and space.kind != "bounded" else None
        self.view_dependent = view_dependent
        self.step_ratio = step_ratio
        longest = float((aabb[1] - aabb[0]).max())
        self.voxel_final = longest / final_resolution
        # alpha = 1 - exp(-DENSITY_SCALE * softplus(shift) * step_ratio) = ALPHA_INIT at a step
        self.shift = math.log(math.expm1(-math.log(1 - ALPHA_INIT) / (step_ratio * DENSITY_SCALE)))
        channels = feature_channels if view_dependent else 3
        self.grid = nn.Parameter(torch.zeros((1, 1 + channels) + grid_shape(self.aabb, resolution)))
        self.head = None
        if view_dependent:
            self.head = nn.Sequential(nn.Linear(channels + 16, 64), nn.ReLU(), nn.Linear(64, 3))
        self.resolution = resolution

    @property
    def voxel(self) -> float:
        return float((self.aabb[1] - self.aabb[0]).max()) / self.resolution

    @property
    def marching_step(self) -> float:
        return self.step_ratio * self.voxel

    def density_from_raw(self, raw: torch.Tensor) -> torch.Tensor:
        return DENSITY_SCALE * F.softplus(raw + self.shift) / self.voxel_final

    def _world_density(self, raw: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        """Grid-unit density of raw values [M] at world positions [M, 3] -> world sigma [M]."""
        sigma = self.density_from_raw(raw)
        return sigma if self.space is None else sigma / self.space.world_per_unit(positions)

    def _normalised(self, positions: torch.Tensor) -> torch.Tensor:
        """World [M, 3] -> grid_sample coordinates [1, 1, 1, M, 3] in [-1, 1]."""
        if self.space is not None:
            positions = self.space.to_grid(positions)
        scale = 2.0 / (self.aabb[1] - self.aabb[0])  # [3]
        return torch.addcmul(-1.0 - self.aabb[0] * scale, positions, scale).view(1, 1, 1, -1, 3)

    def density(self, positions: torch.Tensor) -> torch.Tensor:
        """sigma (per world unit) at world positions [M, 3], differentiable w.r.t. them. Returns [M]."""
        raw = F.grid_sample(self.grid[:, :1], self._normalised(positions), mode="bilinear", align_corners=True,
                            padding_mode="border")
        return self._world_density(raw.view(-1), positions)

    def forward(self, positions: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """positions, directions: [M, 3] (world, unit). Returns sigma [M], rgb [M, 3] in [0, 1]."""
        values = F.grid_sample(self.grid, self._normalised(positions), mode="bilinear",
                               align_corners=True, padding_mode="border")  # [1, C, 1, 1, M]
        values = values.view(self.grid.shape[1], -1).t()  # [M, C]
        sigma = self._world_density(values[:, 0], positions)
        if self.head is None:
            return sigma, torch.sigmoid(values[:, 1:])
        features = torch.cat([values[:, 1:], sh_basis_deg3(directions)], dim=-1)
        return sigma, torch.sigmoid(self.head(features))

    @torch.no_grad()
    def upsample(self, resolution: int) -> None:
        """Coarse to fine: trilinear resampling of the grid (the AABB stays)."""
        shape = grid_shape(self.aabb, resolution)
        self.grid = nn.Parameter(F.interpolate(self.grid.data, size=shape, mode="trilinear", align_corners=True))
        self.resolution = resolution

    @torch.no_grad()
    def occupancy(self, dilate: int = 1) -> torch.Tensor:
        """Cells (between grid nodes) whose corner nodes reach OCCUPANCY_ALPHA, grown by
        `dilate` cells so density can still spread into neighbours. Not differentiable.
        Trilinear interpolation never exceeds its corners and softplus is monotone, so a
        cell whose corners are all below the threshold is below it everywhere.
        Returns [nz-1, ny-1, nx-1] bool."""
        sigma = self.density_from_raw(self.grid[0, 0])
        alpha = -torch.expm1(-sigma * self.marching_step)  # [nz, ny, nx]
        corner_max = F.max_pool3d(alpha[None, None], kernel_size=2, stride=1)[0, 0]  # [nz-1, ny-1, nx-1]
        occupied = corner_max > OCCUPANCY_ALPHA
        if dilate:
            size = 2 * dilate + 1
            occupied = F.max_pool3d(occupied[None, None].float(), size, stride=1, padding=dilate)[0, 0] > 0
        return occupied

    def total_variation(self) -> torch.Tensor:
        """Mean squared difference of neighbouring raw densities (smoothness prior)."""
        d = self.grid[0, 0]
        return ((d[1:] - d[:-1]) ** 2).mean() + ((d[:, 1:] - d[:, :-1]) ** 2).mean() + \
            ((d[:, :, 1:] - d[:, :, :-1]) ** 2).mean()
