"""Ray marching with empty-space skipping: samples only where the occupancy grid is set.

Two levels keep it cheap: rays are first walked in coarse segments of `fine_per_segment`
steps, each segment is tested against the occupancy grid at its midpoint, and only the
occupied segments are cut into fine steps. The kept samples are packed to the front of
each row, so the result is a dense [n_rays, K] layout (K = most kept samples on any ray)
that the volume-rendering functions of `nerf.rendering` take as they are: padding has
delta = 0 and so weight 0, and skipped empty space has transmittance 1, as it should.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerf.rendering import ray_aabb


@dataclass(frozen=True)
class MarchedSamples:
    """t_mid, delta: [n_rays, K]; valid: [n_rays, K] bool; near, far: [n_rays]."""

    t_mid: torch.Tensor
    delta: torch.Tensor
    valid: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor


def cell_lookup(positions: torch.Tensor, occupancy: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """Occupancy at world positions. positions [..., 3]; occupancy [nz, ny, nx] bool over
    the AABB [2, 3]. Positions outside the box are unoccupied. Returns [...] bool."""
    nz, ny, nx = occupancy.shape
    size = torch.tensor([nx, ny, nz], dtype=positions.dtype, device=positions.device)
    cell = ((positions - aabb[0]) / (aabb[1] - aabb[0]) * size).floor().long()  # [..., 3]
    inside = ((cell >= 0) & (cell < size.long())).all(dim=-1)
    cell = torch.minimum(cell.clamp_min(0), size.long() - 1)
    flat = (cell[..., 2] * ny + cell[..., 1]) * nx + cell[..., 0]
    return occupancy.reshape(-1)[flat] & inside


def _pack_columns(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Where each True of mask [n, S] lands when packed to the front of its row.
    Returns rows [m], cols [m] and K (the longest packed row)."""
    counts = mask.sum(dim=1)
    width = int(counts.max()) if mask.numel() else 0
    rows, source_cols = mask.nonzero(as_tuple=True)
    cols = (mask.cumsum(dim=1) - 1)[rows, source_cols]
    return rows, cols, width


@torch.no_grad()
def march(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, occupancy: torch.Tensor,
          step: float, fine_per_segment: int = 4, jitter: torch.Tensor | None = None) -> MarchedSamples:
    """Fine samples of length `step` inside occupied coarse segments. Not differentiable.

    origins, directions (unit): [n_rays, 3]; aabb [2, 3]; occupancy [nz, ny, nx] bool;
    jitter: optional [n_rays] in [0, 1), shifts every sample of a ray by jitter * step
    (stratified training samples); None puts samples at step centres (deterministic).
    """
    n_rays = origins.shape[0]
    near, far, hit = ray_aabb(origins, directions, aabb)  # [n_rays] each
    segment = step * fine_per_segment
    longest = float((far - near).max()) if n_rays else 0.0
    n_segments = max(int(torch.ceil(torch.tensor(longest / segment)).item()), 1)
    k = torch.arange(n_segments, dtype=origins.dtype, device=origins.device)  # [S]
    seg_start = near[:, None] + k * segment  # [n_rays, S]
    seg_mid = seg_start + 0.5 * segment
    in_ray = (seg_start < far[:, None]) & hit[:, None]  # [n_rays, S]
    positions = origins[:, None, :] + seg_mid[..., None] * directions[:, None, :]  # [n_rays, S, 3]
    occupied = in_ray & cell_lookup(positions, occupancy, aabb)  # [n_rays, S]

    rows, cols, width = _pack_columns(occupied)
    packed_start = seg_start.new_zeros((n_rays, max(width, 1)))  # [n_rays, Kc]
    packed_valid = torch.zeros((n_rays, max(width, 1)), dtype=torch.bool, device=origins.device)
    packed_start[rows, cols] = seg_start[occupied]
    packed_valid[rows, cols] = True

    offset = 0.5 if jitter is None else jitter[:, None, None]  # [n_rays, 1, 1] or scalar
    j = torch.arange(fine_per_segment, dtype=origins.dtype, device=origins.device)  # [m]
    t_mid = packed_start[..., None] + (j + offset) * step  # [n_rays, Kc, m]
    valid = packed_valid[..., None] & (t_mid < far[:, None, None]) & (t_mid > near[:, None, None])
    t_mid = t_mid.reshape(n_rays, -1)  # [n_rays, Kc * m]
    valid = valid.reshape(n_rays, -1)
    delta = torch.where(valid, torch.full_like(t_mid, step), torch.zeros_like(t_mid))
    t_mid = torch.where(valid, t_mid, near[:, None].expand_as(t_mid))
    return MarchedSamples(t_mid, delta, valid, near, far)
