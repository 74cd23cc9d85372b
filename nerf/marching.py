"""Ray marching with empty-space skipping: samples only where the occupancy grid is set.

Two levels keep it cheap: rays are first walked in coarse segments of `fine_per_segment`
steps, each segment is tested against the occupancy grid at its midpoint, and only the
occupied segments are cut into fine steps. The result is packed (a flat list of samples with their ray index) for `nerf.packed`:
skipped empty space has transmittance 1, as it should.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from nerfgauge.nerf.rendering import ray_aabb


@dataclass(frozen=True)
class MarchedSamples:
    """Packed samples, sorted by ray then distance: t_mid, ray_index [n_samples];
    step: every sample's length; near, far: [n_rays] (0 for rays missing the box)."""

    t_mid: torch.Tensor
    ray_index: torch.Tensor
    step: float
    near: torch.Tensor
    far: torch.Tensor


def cell_lookup(voxel_positions: torch.Tensor, padded: torch.Tensor, size: int) -> torch.Tensor:
    """Occupancy at positions in voxel units (0 at the box's min corner, x y z order)
    [m, 3]; padded [nz + 2, ny + 2, nx + 2] bool: a grid of cells `size` voxels wide framed
    by one empty cell on every side (`pad_grid`). Positions must lie within one cell of the
    grid (march only asks about points inside the box, up to rounding): those just outside
    land in the empty frame, with no clamp on this hot path. Returns [m] bool.

    The flat index is one matrix-vector product of the floored cells, in float32 while
    every index is an exact float32 integer (< 2^24) and float64 beyond."""
    depth, height, width = padded.shape
    dtype = voxel_positions.dtype if padded.numel() < 2 ** 24 else torch.float64
    cell = (voxel_positions * (1.0 / size)).floor_().to(dtype)  # [m, 3]
    strides = torch.tensor([1.0, width, width * height], dtype=dtype, device=cell.device)
    frame = 1 + width + width * height  # +1 cell along every axis
    return padded.reshape(-1)[torch.mv(cell, strides).add_(frame).long()]


def pad_grid(occupancy: torch.Tensor) -> torch.Tensor:
    """Frame an occupancy grid [nz, ny, nx] with empty cells: [nz + 2, ny + 2, nx + 2]."""
    return F.pad(occupancy, (1, 1, 1, 1, 1, 1), value=False)


def occupancy_pyramid(occupancy: torch.Tensor, block: int = 16) -> list:
    """[(framed grid, cell size in voxels)] from `block`-voxel blocks down to the voxel grid, each
    level's blocks 4x smaller. Pooled levels are grown by one block, so a segment one block
    long, tested at its midpoint, never misses an occupied block it passes through."""
    levels = [(pad_grid(occupancy), 1)]
    size = 4
    while size <= block:
        pooled = F.max_pool3d(occupancy[None, None].float(), size, stride=size, ceil_mode=True)
        grown = F.max_pool3d(pooled, 3, stride=1, padding=1)[0, 0] > 0
        levels.insert(0, (pad_grid(grown), size))
        size *= 4
    return levels


@dataclass(frozen=True)
class MarchedSegments:
    """Ray segments the occupancy pyramid kept down to some level, packed (sorted by ray,
    then t): starts, ray_index [m]; and what cutting them into samples needs: the finer
    levels still to test, the segment size in voxels, the rays in voxel units
    (`per_ray` [n_rays, 7]: origin, direction, far), samples per voxel, the sample step,
    near and far [n_rays] and the jitter [n_rays] or None."""

    starts: torch.Tensor
    ray_index: torch.Tensor
    levels: list
    size: int
    per_ray: torch.Tensor
    voxel_steps: int
    step: float
    near: torch.Tensor
    far: torch.Tensor
    jitter: torch.Tensor | None


def _keep_occupied(starts, rays, per_ray, grid, size: int, length: float):
    """The segments (starts, rays) [m] of `length` whose midpoint lies in an occupied cell
    of `grid` (cells `size` voxels wide), and that start before their ray's far."""
    ray = per_ray.index_select(0, rays)  # [m, 7]
    # the midpoint of the part inside the box: a segment hanging out of the box must not
    # be tested (and dropped) at a point outside it. For starts < far that is
    # min(starts + length / 2, (starts + far) / 2); segments starting past `far` are
    # dropped, but their lookup must stay in the grid: pinned at far.
    far_of = ray[:, 6]
    mid = torch.minimum(torch.minimum(starts + 0.5 * length, (starts + far_of).mul_(0.5)), far_of)
    keep = (starts < far_of) & cell_lookup(torch.addcmul(ray[:, :3], ray[:, 3:6], mid[:, None]), grid, size)
    kept = keep.nonzero(as_tuple=True)[0]
    return starts.index_select(0, kept), rays.index_select(0, kept)


@torch.no_grad()
def march_segments(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, occupancy: torch.Tensor,
                   step: float, jitter: torch.Tensor | None = None, levels: list | None = None,
                   keep_levels: int = 0) -> MarchedSegments:
    """The coarse-to-fine part of `march`: segments tested against every level of the
    pyramid but the last `keep_levels` (0: down to the voxel grid). Rendering takes the
    segments above the voxel level so that it cuts into samples only those a ray reaches
    before it turns opaque (`segment_samples` on a subset). Arguments as for `march`."""
    levels = occupancy_pyramid(occupancy) if levels is None else levels
    n_rays = origins.shape[0]
    nz, ny, nx = occupancy.shape
    voxel = (aabb[1] - aabb[0]) / torch.tensor([nx, ny, nz], dtype=aabb.dtype, device=aabb.device)  # [3]
    near, far, hit = ray_aabb(origins, directions, aabb)  # [n_rays] each
    voxel_steps = max(1, round(float(voxel.max()) / step))  # samples per voxel segment
    # level 0: every ray cut into coarse segments
    size = levels[0][1]
    length = size * voxel_steps * step
    n_segments = max(math.ceil(float((far - near).max()) / length), 1) if n_rays else 1
    k = torch.arange(n_segments, dtype=origins.dtype, device=origins.device)
    seg_start = near[:, None] + k * length  # [n_rays, S]
    candidate = (seg_start < far[:, None]) & hit[:, None]
    rays, cols = candidate.nonzero(as_tuple=True)  # row-major: sorted by ray, then t
    starts = seg_start[rays, cols]  # [n_segments_total]
    # Rays in voxel units from the box's corner, so a level's cell is a floor away:
    # [n_rays, 7] origin, direction (per unit of t), far; one gather per level.
    per_ray = torch.cat([(origins - aabb[0]) / voxel, directions / voxel, far[:, None]], dim=1)
    starts, rays = _keep_occupied(starts, rays, per_ray, *levels[0], length)
    segments = MarchedSegments(starts, rays, levels[1:], size, per_ray, voxel_steps, step, near, far, jitter)
    return _refine(segments, max(0, len(levels) - 1 - keep_levels))


def _refine(segments: MarchedSegments, n_levels: int) -> MarchedSegments:
    """`segments` split and tested through their next `n_levels` levels."""
    starts, rays, size = segments.starts, segments.ray_index, segments.size
    for grid, finer in segments.levels[:n_levels]:
        parts = size // finer
        length = finer * segments.voxel_steps * segments.step
        offsets = torch.arange(parts, dtype=starts.dtype, device=starts.device) * length
        starts = (starts[:, None] + offsets).reshape(-1)
        rays = rays.repeat_interleave(parts)
        starts, rays = _keep_occupied(starts, rays, segments.per_ray, grid, finer, length)
        size = finer
    return dataclasses.replace(segments, starts=starts, ray_index=rays, levels=segments.levels[n_levels:], size=size)


def segment_samples(segments: MarchedSegments, chosen: torch.Tensor | None = None) -> MarchedSamples:
    """Packed samples of the segments `chosen` [m] (sorted; None: all): split and tested
    down to the voxel grid, each 1-voxel segment cut into `voxel_steps` samples."""
    if chosen is not None:
        segments = dataclasses.replace(segments, starts=segments.starts.index_select(0, chosen),
                                       ray_index=segments.ray_index.index_select(0, chosen))
    segments = _refine(segments, len(segments.levels))
    starts, rays, step, far = segments.starts, segments.ray_index, segments.step, segments.far
    offset = 0.5 if segments.jitter is None else segments.jitter[rays][:, None]
    j = torch.arange(segments.voxel_steps, dtype=starts.dtype, device=starts.device)
    t_mid = starts[:, None] + (j + offset) * step  # [n_kept, voxel_steps]
    ray_index = rays[:, None].expand(-1, segments.voxel_steps)
    keep = t_mid < far.index_select(0, rays)[:, None]
    return MarchedSamples(t_mid[keep], ray_index[keep], step, segments.near, far)


@torch.no_grad()
def march(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, occupancy: torch.Tensor,
          step: float, jitter: torch.Tensor | None = None, levels: list | None = None) -> MarchedSamples:
    """Packed samples of length `step` (e.g. half a voxel) where the occupancy grid is set.
    Not differentiable.

    Coarse to fine: rays are cut into segments one coarse block long, segments whose
    midpoint lies in an occupied block are cut into the next level's shorter segments,
    and so on down to 1-voxel segments tested against the voxel grid (grown by a voxel:
    a 1-voxel segment touches at most the neighbours of its midpoint's voxel), which are
    cut into voxel / step samples. Work grows with occupied space, not with ray length.

    origins, directions (unit): [n_rays, 3]; aabb [2, 3]; occupancy [nz, ny, nx] bool
    (one cell per voxel, already grown by one voxel); jitter: optional [n_rays] in [0, 1),
    shifts every sample of a ray by jitter * step (training); None: step centres.
    levels: `occupancy_pyramid(occupancy)`, passed in to reuse it across calls.
    """
    return segment_samples(march_segments(origins, directions, aabb, occupancy, step, jitter, levels))


def keep_samples(samples: MarchedSamples, keep: torch.Tensor) -> MarchedSamples:
    """The samples `keep` [m] (indices, increasing) of `samples`, in their order."""
    step = samples.step.index_select(0, keep) if isinstance(samples.step, torch.Tensor) else samples.step
    return MarchedSamples(samples.t_mid.index_select(0, keep), samples.ray_index.index_select(0, keep), step,
                          samples.near, samples.far)


def sample_deltas(samples: MarchedSamples) -> torch.Tensor:
    """Every sample's length [n_samples] (a scalar step broadcast, or the per-sample lengths)."""
    if isinstance(samples.step, torch.Tensor):
        return samples.step
    return torch.full_like(samples.t_mid, samples.step)


@torch.no_grad()
def march_space(origins: torch.Tensor, directions: torch.Tensor, space, box: torch.Tensor,
                occupancy: torch.Tensor, grid_step: float, jitter: torch.Tensor | None = None) -> MarchedSamples:
    """Packed samples for a non-bounded parametrisation (`nerf.parametrisation.Space`):
    the space's interval edges along each ray (about `grid_step` grid units apart), kept
    where the midpoint's grid cell is occupied. Not differentiable.

    origins, directions (unit): [n_rays, 3]; box [2, 3]: the grid's extent in grid
    coordinates; occupancy [nz, ny, nx] bool (already grown by one cell); jitter [n_rays]
    in [0, 1): each sample sits at that fraction of its interval (None: the middle).
    The result's `step` is a tensor of per-sample lengths (world units)."""
    edges = space.ray_edges(origins, directions, grid_step)  # [n_rays, m + 1]
    lengths = edges[:, 1:] - edges[:, :-1]  # [n_rays, m]
    fraction = 0.5 if jitter is None else jitter[:, None]
    t = edges[:, :-1] + fraction * lengths
    rays, cols = (lengths > 0).nonzero(as_tuple=True)  # row-major: sorted by ray, then t
    t, deltas = t[rays, cols], lengths[rays, cols]
    grid = space.to_grid(origins.index_select(0, rays) + t[:, None] * directions.index_select(0, rays))
    nz, ny, nx = occupancy.shape
    size = torch.tensor([nx, ny, nz], device=origins.device)
    index = ((grid - box[0]) / ((box[1] - box[0]) / size)).floor().long()  # [n, 3] x y z
    inside = ((index >= 0) & (index < size)).all(-1)
    index = torch.minimum(index.clamp_min(0), size - 1)
    keep = inside & occupancy.reshape(-1)[(index[:, 2] * ny + index[:, 1]) * nx + index[:, 0]]
    kept = keep.nonzero(as_tuple=True)[0]
    n_rays = origins.shape[0]
    valid = lengths > 0
    near = torch.where(valid.any(1), edges[:, 0], torch.zeros(n_rays, dtype=edges.dtype, device=edges.device))
    far = edges.max(dim=1).values if edges.shape[1] else near
    return MarchedSamples(t[kept], rays[kept], deltas[kept], near, far)


def cell_of(grid_positions: torch.Tensor, box: torch.Tensor, shape, block: int = 1) -> torch.Tensor:
    """Flat cell index [n] of grid-coordinate positions [n, 3] in a grid of `shape`
    (nz, ny, nx) cells over `box` [2, 3], clamped to the grid; with block > 1, the index
    of the block of block^3 cells that holds it, in a grid of ceil(shape / block) blocks."""
    nz, ny, nx = shape
    size = torch.tensor([nx, ny, nz], device=grid_positions.device)
    index = ((grid_positions - box[0]) / ((box[1] - box[0]) / size)).floor().long()
    index = torch.minimum(index.clamp_min(0), size - 1) // block
    blocks_y, blocks_x = -(-ny // block), -(-nx // block)
    return (index[:, 2] * blocks_y + index[:, 1]) * blocks_x + index[:, 0]
