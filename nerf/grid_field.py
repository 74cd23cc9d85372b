"""The compact field: a sparse voxel grid (DVGO-style values, stored only where needed).

Chosen by measurement on 2 CPU cores (BENCHMARKS.md): a voxel grid with
occupancy skipping beat a plain-PyTorch hash grid and a positional-encoding MLP in PSNR
per second. Its values live in a table with one row per *allocated* grid node, and a
dense int32 `index` maps each node to its row (0: not allocated, read as empty space).
Every node is allocated while the grid is coarse; each coarse-to-fine step allocates
only the nodes of cells the coarser field found occupied (and visible), so storage,
optimizer state and the cost of an Adam step follow the occupied volume, not the box
(BENCHMARKS.md, "Cost that follows the scene"). Interpolation is trilinear between the
eight corner nodes, as `grid_sample(align_corners=True, padding_mode="border")` on the
dense grid would give.

Density: raw values are trilinearly interpolated, then activated,
    sigma = DENSITY_SCALE * softplus(raw + shift) / voxel_final,
so surfaces can be sharper than a voxel; `shift` makes a fresh grid nearly transparent
(alpha = ALPHA_INIT per marching step). Colour: diffuse scenes store sRGB logits (3
channels, no view direction); view-dependent scenes store `feature_channels` features
that a small MLP turns into colour with the view direction (degree-3 spherical harmonics).
A diffuse grid can take a residual colour head mid-run (`add_residual_head`): the 3 logits
gain `feature_channels - 3` features and colour = sigmoid(logits + MLP(all features)), with
the MLP's last layer at zero so the field's colours do not change when it is added. It
models colour that varies inside a cell (a texture edge) where trilinear logits cannot.
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
# Coarse to fine sharpens surfaces: at each upsample by a ratio k, raw densities above the
# level where a marching step of the finer grid reaches this opacity are steepened k times
# about that level (`sharpen_raw`), so a surface's density ramp keeps its width in voxels of
# the new grid instead of staying as wide as the coarse grid's. Without it, the field's
# surfaces sit 1.1-1.5 voxels behind the true ones (depth - truth, median; the ramp is
# ~3.5 voxels wide, and a grid trained at its final size from the start is no sharper:
# 1.7). Measured (BENCHMARKS.md, "Sharper surfaces"): primitives 128 px, 3000 steps:
# F-score at 1% 0.550 -> 0.747, depth offset 1.46 -> 1.19 voxels, PSNR 38.92 -> 38.80;
# 64 px, 600 steps +0.34 dB. Anchored lower it moves surfaces further forward but costs
# PSNR (alpha 5e-3: offset 0.29 voxels, -2.5 dB), higher it does less (0.05: +0.13 dB, 0.77).
# Bounded space only: chosen and checked on bounded captures; on depth-range (forward space,
# bench hard, 400 steps) it cost 0.18 dB and raised the resolved depth AbsRel from 0.076 to
# 0.101 (BENCHMARKS.md, "Edge pixels"), where a voxel of the log-depth grid is not a
# constant world length along the ray.
SHARPEN_ALPHA = 0.1


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


EMPTY_RAW = -30.0  # raw density of nodes with no row: softplus(-30 + shift) ~ 1e-13, empty space
# Rendering without gradients reads a dense copy through grid_sample's fused kernel (faster
# than the 8-row gather) when the copy holds at most this many floats (256 MB).
DENSE_RENDER_FLOATS = 64 * 1024 * 1024
CORNER_BITS = torch.tensor([[dz, dy, dx] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])  # [8, 3] zyx


class Blend(torch.autograd.Function):
    """sum_k weights[:, k] table[rows[:, k]]: table [n, C], rows [M, K] long, weights
    [M, K] -> [M, C]. F.embedding would do it, but its CPU backward was 3-6x slower than
    the index_add_ below (BENCHMARKS.md). Row 0 stands for every unallocated node: its
    gradient is zero, so it stays EMPTY_RAW (Adam never moves a row it has no gradient for)."""

    @staticmethod
    def forward(ctx, table, rows, weights):
        values = table[rows]  # [M, K, C]
        ctx.save_for_backward(rows, weights, values if weights.requires_grad else None)
        ctx.table_shape = table.shape
        return torch.bmm(weights[:, None, :], values)[:, 0]

    @staticmethod
    def backward(ctx, grad):
        rows, weights, values = ctx.saved_tensors
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            contributions = (weights[:, :, None] * grad[:, None, :]).reshape(-1, grad.shape[1])  # [M K, C]
            grad_table = grad.new_zeros(ctx.table_shape).index_add_(0, rows.reshape(-1), contributions)
            grad_table[0] = 0
        if ctx.needs_input_grad[2]:
            grad_weights = torch.bmm(values, grad[:, :, None])[:, :, 0]  # [M, K]
        return grad_table, None, grad_weights


def node_cells(nodes: int, cells_before: int) -> torch.Tensor:
    """For each of `nodes` evenly spaced nodes along an axis, the cell (of `cells_before`
    cells spanning the same extent) it lies in. Returns [nodes] long."""
    position = torch.arange(nodes, dtype=torch.float64) * (cells_before / (nodes - 1))
    return position.floor().long().clamp(0, cells_before - 1)


def any_within(mask: torch.Tensor, low: int, high: int) -> torch.Tensor:
    """out[i, j, k] = any of mask[i - low .. i + high, j - low .. j + high, k - low .. k + high]
    (outside the grid counts as False). mask [nz, ny, nx] bool -> the same shape.
    A separable box max on bools: 3 (low + high) logical ors, where max_pool3d on floats
    took 0.6 s at 218^3, every 16 training steps."""
    for dim in range(3):
        out = mask.clone()
        n = mask.shape[dim]
        for shift in range(1, min(high, n - 1) + 1):  # out[i] |= mask[i + shift]
            out.narrow(dim, 0, n - shift).logical_or_(mask.narrow(dim, shift, n - shift))
        for shift in range(1, min(low, n - 1) + 1):  # out[i] |= mask[i - shift]
            out.narrow(dim, shift, n - shift).logical_or_(mask.narrow(dim, 0, n - shift))
        mask = out
    return mask


def cells_touching(nodes: torch.Tensor) -> torch.Tensor:
    """Cells with at least one of their 8 corner nodes set. nodes [nz, ny, nx] bool ->
    [nz-1, ny-1, nx-1] bool."""
    return any_within(nodes, 0, 1)[:-1, :-1, :-1]


def node_mask(occupancy: torch.Tensor) -> torch.Tensor:
    """Grid nodes that are a corner of an occupied cell. occupancy [nz-1, ny-1, nx-1] ->
    [nz, ny, nx] bool."""
    return any_within(F.pad(occupancy, (0, 1, 0, 1, 0, 1), value=False), 1, 0)


class VoxelGridField(nn.Module):
    def __init__(self, aabb: torch.Tensor, resolution: int, final_resolution: int, view_dependent: bool,
                 feature_channels: int = 12, step_ratio: float = 0.5, space=None, allocate: bool = True):
        """aabb [2, 3]: the grid's box in grid coordinates (the world AABB when bounded);
        space: a `nerf.parametrisation.Space` mapping world points into it (None: bounded).
        Every node starts allocated with raw values 0 (allocate=False: none, for a field
        whose nodes are loaded next)."""
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.space = space if space is not None and space.kind != "bounded" else None
        self.view_dependent = view_dependent
        self.step_ratio = step_ratio
        longest = float((aabb[1] - aabb[0]).max())
        self.voxel_final = longest / final_resolution
        # alpha = 1 - exp(-DENSITY_SCALE * softplus(shift) * step_ratio) = ALPHA_INIT at a step
        self.shift = math.log(math.expm1(-math.log(1 - ALPHA_INIT) / (step_ratio * DENSITY_SCALE)))
        self.channels = feature_channels if view_dependent else 3
        self.resolution = resolution
        shape = grid_shape(self.aabb, resolution)
        self.register_buffer("index", torch.zeros(shape, dtype=torch.int32))
        n = math.prod(shape) if allocate else 0
        self._set_nodes(torch.full(shape, allocate), torch.zeros(n, 1), torch.zeros(n, self.channels))
        self.head = None
        self.residual_head = False  # see add_residual_head
        if view_dependent:
            self.head = nn.Sequential(nn.Linear(self.channels + 16, 64), nn.ReLU(), nn.Linear(64, 3))

    @torch.no_grad()
    def add_residual_head(self, channels: int) -> None:
        """Give a diffuse grid (3 colour logits) `channels` - 3 more feature channels, at 0,
        and a residual colour head over all of them whose output layer is 0: colours are
        unchanged now and can vary inside a cell once trained. nn.Linear draws the hidden
        layer's weights from torch's global generator (seed it around the call)."""
        if self.view_dependent or self.head is not None or channels <= 3:
            raise ValueError(f"a residual colour head needs a diffuse grid without a head and > 3 channels, "
                             f"got {channels}")
        extra = self.features.new_zeros(self.features.shape[0], channels - 3)
        self.features = nn.Parameter(torch.cat([self.features.data, extra], dim=1))
        self.channels = channels
        self._dense_key = None
        self.head = nn.Sequential(nn.Linear(channels, 64), nn.ReLU(), nn.Linear(64, 3)).to(self.aabb.device)
        nn.init.zeros_(self.head[2].weight)
        nn.init.zeros_(self.head[2].bias)
        self.residual_head = True

    # ----------------------------------------------------------------------------------
    # storage

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx) grid nodes."""
        return tuple(self.index.shape)

    @property
    def allocated(self) -> int:
        """Nodes with a row in the value tables."""
        return self.density_table.shape[0] - 1

    def grid_parameters(self) -> list:
        """The value tables (voxel learning rate); the head has its own."""
        return [self.density_table, self.features]

    def _set_nodes(self, mask: torch.Tensor, raw: torch.Tensor, features: torch.Tensor) -> None:
        """Allocate the nodes of `mask` [nz, ny, nx] bool (row order: flat zyx order), with
        raw density [n, 1] and features [n, C]; every other node reads as empty."""
        device = self.aabb.device
        mask = mask.to(device)
        index = torch.zeros(mask.shape, dtype=torch.int32, device=device)
        index[mask] = torch.arange(1, int(mask.sum()) + 1, dtype=torch.int32, device=device)
        self.index = index
        self._dense_key = None  # new tables: the rendering copy is stale
        empty = torch.full((1, 1), EMPTY_RAW, device=device)
        self.density_table = nn.Parameter(torch.cat([empty, raw.to(device).float()]))
        self.features = nn.Parameter(torch.cat([torch.zeros(1, self.channels, device=device),
                                                features.to(device).float()]))

    def reserve(self, rows: int) -> None:
        """Resize the tables to `rows` rows (row 0 included), zeroed: the shape a saved
        state_dict is then loaded into."""
        device = self.aabb.device
        self._dense_key = None
        self.density_table = nn.Parameter(torch.zeros(rows, 1, device=device))
        self.features = nn.Parameter(torch.zeros(rows, self.channels, device=device))

    def check_index(self) -> None:
        """ValueError unless the index addresses rows that exist (a loaded state)."""
        rows = self.density_table.shape[0]
        if self.features.shape[0] != rows:
            raise ValueError(f"density and feature tables hold {rows} and {self.features.shape[0]} rows")
        if int(self.index.min()) < 0 or int(self.index.max()) >= rows:
            raise ValueError(f"the node index addresses rows outside the {rows}-row tables")

    def load_nodes(self, mask: torch.Tensor, values: torch.Tensor) -> None:
        """Allocate the nodes of `mask` [nz, ny, nx] with values [n, 1 + C] (raw density first)."""
        if tuple(mask.shape) != self.shape or tuple(values.shape) != (int(mask.sum()), 1 + self.channels):
            raise ValueError(f"node mask {tuple(mask.shape)} and values {tuple(values.shape)} do not fit "
                             f"a {self.shape} grid of {1 + self.channels} channels")
        self._set_nodes(mask.bool(), values[:, :1], values[:, 1:])

    @torch.no_grad()
    def to_dense(self) -> torch.Tensor:
        """The grid as a dense tensor [1 + C, nz, ny, nx] (unallocated nodes: EMPTY_RAW, 0)."""
        table = torch.cat([self.density_table, self.features], dim=1)  # [n + 1, 1 + C]
        return table[self.index.long()].permute(3, 0, 1, 2).contiguous()

    def load_dense(self, grid: torch.Tensor) -> None:
        """Allocate every node with the values of a dense grid [1 + C, nz, ny, nx]."""
        if tuple(grid.shape) != (1 + self.channels, *self.shape):
            raise ValueError(f"grid shape {tuple(grid.shape)} does not match {(1 + self.channels, *self.shape)}")
        flat = grid.reshape(grid.shape[0], -1).t()
        self._set_nodes(torch.ones(self.shape, dtype=torch.bool), flat[:, :1], flat[:, 1:])

    def node_values(self, mask: torch.Tensor) -> torch.Tensor:
        """Values [n, 1 + C] of the nodes of `mask` [nz, ny, nx] (flat zyx order)."""
        rows = self.index[mask.to(self.index.device)].long()
        return torch.cat([self.density_table[rows], self.features[rows]], dim=1).detach()

    @torch.no_grad()
    def keep_rows(self, keep: torch.Tensor) -> torch.Tensor:
        """Free every allocated node outside `keep` [nz, ny, nx] bool. Returns the old row
        of each new row [n' + 1] (row 0 first), for moving optimizer state along."""
        mask = (self.index > 0) & keep.to(self.index.device)
        rows = torch.cat([torch.zeros(1, dtype=torch.long, device=mask.device), self.index[mask].long()])
        raw, features = self.density_table[rows[1:]], self.features[rows[1:]]
        self._set_nodes(mask, raw, features)
        return rows

    # ----------------------------------------------------------------------------------
    # lookups

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

    def corners(self, box_positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear stencil of points in the grid's box [M, 3] (clamped to it, like
        grid_sample's border padding): rows [M, 8] long (0: empty) and weights [M, 8],
        differentiable w.r.t. the positions."""
        nz, ny, nx = self.shape
        last = torch.tensor([nx - 1, ny - 1, nz - 1], device=box_positions.device, dtype=box_positions.dtype)
        scale = last / (self.aabb[1] - self.aabb[0])  # [3] nodes per unit
        u = torch.minimum(torch.addcmul(-self.aabb[0] * scale, box_positions, scale).clamp_min(0), last)
        base = torch.minimum(u.detach().floor(), last - 1)  # [M, 3] xyz, a cell's first node
        fraction = u - base  # [M, 3] in [0, 1]
        base = base.long()
        flat = (base[:, 2] * ny + base[:, 1]) * nx + base[:, 0]  # [M]
        bits = CORNER_BITS.to(box_positions.device)
        offsets = (bits[:, 0] * ny + bits[:, 1]) * nx + bits[:, 2]  # [8]
        rows = self.index.view(-1)[flat[:, None] + offsets].long()  # [M, 8]
        fx, fy, fz = fraction.unbind(-1)
        wx = torch.stack([1 - fx, fx], dim=-1)
        wy = torch.stack([1 - fy, fy], dim=-1)
        wz = torch.stack([1 - fz, fz], dim=-1)
        weights = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).reshape(-1, 8)  # [M, 8]
        return rows, weights

    @staticmethod
    def _blend(table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """sum_k weights[:, k] table[rows[:, k]]: [M, C]."""
        return Blend.apply(table, rows, weights)

    def _to_box(self, positions: torch.Tensor) -> torch.Tensor:
        return positions if self.space is None else self.space.to_grid(positions)

    def density(self, positions: torch.Tensor) -> torch.Tensor:
        """sigma (per world unit) at world positions [M, 3], differentiable w.r.t. them. Returns [M]."""
        return self.density_at_stencil(self.stencil(positions), positions)

    def _dense_for_rendering(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The grid as dense tensors for grid_sample, raw density [1, 1, nz, ny, nx] and
        features [1, C, nz, ny, nx], rebuilt when a table changed (Adam steps bump their
        version counters); None when they would be too large."""
        if (1 + self.channels) * math.prod(self.shape) > DENSE_RENDER_FLOATS:
            return None
        key = (self.index.data_ptr(), self.density_table.data_ptr(), self.density_table._version,
               self.features.data_ptr(), self.features._version)
        if getattr(self, "_dense_key", None) != key:
            dense = self.to_dense()[None]
            self._dense, self._dense_key = (dense[:, :1].contiguous(), dense[:, 1:].contiguous()), key
        return self._dense

    def _grid_coordinates(self, positions: torch.Tensor) -> torch.Tensor:
        """World positions [M, 3] as grid_sample's coordinates [1, 1, 1, M, 3] in [-1, 1]."""
        box = self._to_box(positions)
        return (2 * (box - self.aabb[0]) / (self.aabb[1] - self.aabb[0]) - 1).view(1, 1, 1, -1, 3)

    def forward(self, positions: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """positions, directions: [M, 3] (world, unit). Returns sigma [M], rgb [M, 3] in [0, 1]."""
        sigma, colour_at = self.density_then_colour(positions, directions)
        return sigma, colour_at(None)

    def density_then_colour(self, positions: torch.Tensor, directions: torch.Tensor):
        """sigma [M] at world positions [M, 3], and colour_at(index [k] or None for all) ->
        rgb [k, 3] of those samples: a renderer that knows which samples it can see asks
        colour (the features' lookup and the colour head, most of a sample's cost with a
        head) only for them. The values are forward's."""
        dense = None if torch.is_grad_enabled() else self._dense_for_rendering()
        if dense is None:
            stencil = self.stencil(positions)
            sigma = self.density_at_stencil(stencil, positions)

            def colour_at(index):
                rows, weights = stencil if index is None else (part.index_select(0, index) for part in stencil)
                chosen = directions if index is None else directions.index_select(0, index)
                return self._colour(self._blend(self.features, rows, weights), chosen)
            return sigma, colour_at
        # the same trilinear values (tests/test_sparse_field.py), one fused kernel
        density_grid, feature_grid = dense
        grid = self._grid_coordinates(positions)
        raw = F.grid_sample(density_grid, grid, mode="bilinear", align_corners=True, padding_mode="border").view(-1)

        def colour_at(index):
            chosen = grid if index is None else grid.index_select(3, index)
            features = F.grid_sample(feature_grid, chosen, mode="bilinear", align_corners=True,
                                     padding_mode="border").view(feature_grid.shape[1], -1).t()
            return self._colour(features, directions if index is None else directions.index_select(0, index))
        return self._world_density(raw, positions), colour_at

    def stencil(self, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The trilinear stencil (rows [M, 8], weights [M, 8]) of world positions [M, 3]:
        computed once, it serves a cheap density pass and the full pass on a subset."""
        return self.corners(self._to_box(positions))

    def density_at_stencil(self, stencil: tuple[torch.Tensor, torch.Tensor], positions: torch.Tensor) -> torch.Tensor:
        """sigma [M] (per world unit) from a `stencil` of world positions [M, 3]."""
        rows, weights = stencil
        return self._world_density(self._blend(self.density_table, rows, weights)[:, 0], positions)

    def at_stencil(self, stencil: tuple[torch.Tensor, torch.Tensor], positions: torch.Tensor,
                   directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What `forward` returns, from a `stencil` of the positions: sigma [M], rgb [M, 3]."""
        rows, weights = stencil
        raw, features = self._blend(self.density_table, rows, weights)[:, 0], self._blend(self.features, rows, weights)
        return self._activate(raw, features, positions, directions)

    def _activate(self, raw, features, positions, directions):
        return self._world_density(raw, positions), self._colour(features, directions)

    def _colour(self, features: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """rgb [M, 3] in [0, 1] from interpolated features [M, C] and unit directions [M, 3]."""
        if self.head is None:
            return torch.sigmoid(features)
        if self.residual_head:
            return torch.sigmoid(features[:, :3] + self.head(features))
        return torch.sigmoid(self.head(torch.cat([features, sh_basis_deg3(directions)], dim=-1)))

    # ----------------------------------------------------------------------------------
    # coarse to fine, occupancy, regularisation

    def sharpen_raw(self, raw: torch.Tensor, resolution: int) -> torch.Tensor:
        """Raw densities [n, 1] resampled for a grid of `resolution`, steepened about the
        level L where one marching step of that grid reaches opacity SHARPEN_ALPHA: values
        above L become L + k (raw - L), k = resolution / current resolution; values below
        (empty space, the faint front of a surface) stay. Returns [n, 1]."""
        ratio = resolution / self.resolution
        step = self.step_ratio * float((self.aabb[1] - self.aabb[0]).max()) / resolution
        # sigma * step = -ln(1 - alpha), sigma = DENSITY_SCALE softplus(L + shift) / voxel_final
        softplus_value = -math.log(1 - SHARPEN_ALPHA) * self.voxel_final / (DENSITY_SCALE * step)
        level = math.log(math.expm1(softplus_value)) - self.shift
        return torch.where(raw > level, level + ratio * (raw - level), raw)

    @torch.no_grad()
    def upsample(self, resolution: int, keep_cells: torch.Tensor | None = None, sharpen: bool = True) -> None:
        """Coarse to fine: trilinear resampling onto a finer grid (the box stays), the
        density steepened by `sharpen_raw` in bounded space (sharpen=False, or a contracted
        or forward space: plain resampling; SHARPEN_ALPHA says why).
        keep_cells: [nz-1, ny-1, nx-1] bool cells of the current grid; only new nodes in
        these cells, grown by one cell, are allocated. None: every node."""
        shape = grid_shape(self.aabb, resolution)
        if keep_cells is None:
            mask = torch.ones(shape, dtype=torch.bool)
        else:
            grown = any_within(keep_cells, 1, 1).cpu()
            cz, cy, cx = (node_cells(new, old) for new, old in zip(shape, grown.shape))
            mask = grown[cz[:, None, None], cy[None, :, None], cx[None, None, :]]
        nodes = mask.nonzero().to(self.aabb.device)  # [n, 3] zyx
        last = torch.tensor([shape[2] - 1, shape[1] - 1, shape[0] - 1], device=self.aabb.device)
        box = self.aabb[0] + nodes.flip(-1).float() / last * (self.aabb[1] - self.aabb[0])  # [n, 3]
        raw, features = [], []
        for start in range(0, box.shape[0], 1 << 18):
            rows, weights = self.corners(box[start:start + (1 << 18)])
            raw.append(self._blend(self.density_table, rows, weights))
            features.append(self._blend(self.features, rows, weights))
        raw = torch.cat(raw) if raw else torch.zeros(0, 1)
        if sharpen and resolution > self.resolution and self.space is None:
            raw = self.sharpen_raw(raw, resolution)
        self.index = torch.zeros(shape, dtype=torch.int32, device=self.aabb.device)
        self._set_nodes(mask, raw,
                        torch.cat(features) if features else torch.zeros(0, self.channels))
        self.resolution = resolution

    @torch.no_grad()
    def occupancy(self, dilate: int = 1) -> torch.Tensor:
        """Cells (between grid nodes) whose corner nodes reach OCCUPANCY_ALPHA, grown by
        `dilate` cells so density can still spread into neighbours. Not differentiable.
        Trilinear interpolation never exceeds its corners and softplus is monotone, so a
        cell whose corners are all below the threshold is below it everywhere.
        Returns [nz-1, ny-1, nx-1] bool."""
        sigma = self.density_from_raw(self.density_table[:, 0])
        hot_rows = -torch.expm1(-sigma * self.marching_step) > OCCUPANCY_ALPHA  # [rows] bool
        occupied = cells_touching(hot_rows[self.index.long()])  # [nz-1, ny-1, nx-1]
        if dilate:
            occupied = any_within(occupied, dilate, dilate)
        return occupied

    def total_variation(self, of: str = "density") -> torch.Tensor:
        """Smoothness prior: along each axis the mean squared difference between
        neighbouring allocated nodes' raw densities (`of` "density") or colour features
        ("features": the mean over the pairs and the channels), summed over the axes."""
        table = {"density": self.density_table, "features": self.features}[of]
        total = table.new_zeros(())
        for dim in range(3):
            a = self.index.narrow(dim, 1, self.index.shape[dim] - 1)
            b = self.index.narrow(dim, 0, self.index.shape[dim] - 1)
            both = (a > 0) & (b > 0)
            if bool(both.any()):
                total = total + ((table[a[both].long()] - table[b[both].long()]) ** 2).mean()
        return total
