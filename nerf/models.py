"""The two radiance-field models, each with one `render(origins, directions)` method.

- `CompactNeRF`: a voxel grid field, ray marching that skips empty space, coarse-to-fine
  resolution. Only what the scene needs: no view direction for diffuse scenes.
- `VanillaNeRF`: the original NeRF of Mildenhall et al. 2020 (positional encoding with 10 and 4 frequencies,
  8 x 256 MLP with a skip, view direction input, coarse and fine networks).
Both return premultiplied colour, opacity and expected ray distance per ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from nerfgauge.nerf.encoding import PositionalEncoding
from nerfgauge.nerf.grid_field import VoxelGridField, any_within
from nerfgauge.nerf.march_cpu import kernel_grids, render_compiled, tables_key
from nerfgauge.nerf.marching import (
    cell_of,
    keep_samples,
    march,
    march_segments,
    march_space,
    occupancy_pyramid,
    sample_deltas,
    segment_samples,
)
from nerfgauge.nerf.packed import (
    packed_distortion,
    packed_render,
    packed_render_early_stop,
    packed_transmittance,
    packed_transmittance_early_stop,
    render_front_to_back,
)
from nerfgauge.nerf.rendering import ray_aabb, render_rays
from nerfgauge.nerf.schedule import COLOUR_GROUP
from torch import nn

EARLY_STOP_WINDOW = 16  # samples per ray between early-termination checks (measured: 8-32 similar)
EARLY_STOP_SEGMENTS = 8  # 4-voxel segments per ray between checks (measured at 256 px: 3-8 best at 8)
# Training differentiates only the samples a ray reaches with at least this transmittance:
# what it drops moves a ray's colour by less than this (the ground truth's noise is ~2.5e-3).
TRAIN_MIN_TRANSMITTANCE = 1e-4


@dataclass
class RayOutput:
    """rgb [n, 3] premultiplied; opacity, depth [n]; n_samples: field evaluations made;
    coarse: the vanilla coarse pass (trained too), else None."""

    rgb: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    n_samples: int = 0
    coarse: Optional["RayOutput"] = None
    distortion: Optional[torch.Tensor] = None  # [n] (compact, training only)


class RadianceModel(nn.Module):
    """What the training loop, the renderers and the geometry tools ask of every model.

    Every model renders rays (`render`), adds its own regulariser to the loss
    (`regularisation`) and names its optimiser's parameter groups (`parameter_groups`).
    Two capabilities are declared rather than probed for:
    - has_grid: a coarse-to-fine voxel grid with an occupancy mask and a visibility mask
      (`update_occupancy`, `measure_visibility`, `samples_per_ray`, `upsample`, `field`,
      `sparse`); the loop grows, prunes and logs it.
    - has_density: a density field that can be queried at points (`density`), which
      normals and meshes are computed from.
    """

    has_grid = False
    has_density = False
    adam_options: dict = {}  # keyword arguments of torch.optim.Adam beyond the groups

    def render(self, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator | None = None,
               training: bool = False) -> RayOutput:
        raise NotImplementedError

    def regularisation(self, tv_weight: float) -> torch.Tensor:
        raise NotImplementedError

    def renders_compiled(self, device: torch.device) -> bool:
        """Whether inference on `device` renders a batch of rays on threads of its own (a
        compiled kernel on numba's threads, set by nerf.march_cpu.kernel_threads), rather than in torch ops that a frame's
        renderer splits over a pool of threads (nerf.frames.render_frame)."""
        return False

    def parameter_groups(self, lr: float, lr_mlp: float) -> list[dict]:
        """Adam's parameter groups, each with its "lr" and the "base_lr" the schedule decays
        from. lr, lr_mlp: the run's grid and MLP learning rates (TrainConfig)."""
        raise NotImplementedError


class CompactNeRF(RadianceModel):
    has_grid = True
    has_density = True
    # beta2 0.99 and a tiny eps, as Instant-NGP trains its grids: a voxel's gradient is
    # sparse, and the default 0.999 / 1e-8 let rarely hit voxels move too slowly
    adam_options = {"betas": (0.9, 0.99), "eps": 1e-15}

    def __init__(self, field: VoxelGridField, use_occupancy: bool = True, sparse: bool = True):
        """use_occupancy: skip empty space when marching. sparse: allocate finer grids only
        in occupied, visible cells and free rows no occupied cell touches (with
        use_occupancy); False keeps every node (the unpruned ablation)."""
        super().__init__()
        self.field = field
        self.use_occupancy = use_occupancy
        self.sparse = sparse and use_occupancy
        # surface opacity (nerf.packed.occupancy_rise_taus): 0 off, else its occupancy's
        # length in marching steps (SURFACE_RISE_STEPS), once a run turns it on
        self.rise_steps = 0.0
        self.register_buffer("occupancy", torch.ones(self._cells(), dtype=torch.bool))
        self._pyramid = None  # coarse-to-fine occupancy for marching, rebuilt when occupancy changes
        self._pyramid_of = None
        self._compiled = None  # (occupancy, march_cpu.KernelGrids: what the compiled renderer reads)
        self._inference_cells = None  # (occupancy, tables_key, cells): inference_cells' cache
        # Cells some training ray can see (transmittance reaches them); the rest (object
        # interiors, hidden corners) need not be sampled or stored. All, until measured.
        self.register_buffer("visible", torch.ones_like(self.occupancy))

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """World-space density: points [n, 3] (world) -> sigma [n] per world unit, whatever
        the parametrisation; differentiable w.r.t. points."""
        return self.field.density(points)

    def world_voxel(self, points: torch.Tensor) -> torch.Tensor:
        """The world length of one voxel of the current grid at points [n, 3] (the grid's
        voxel times its parametrisation's world length per grid unit there). Returns [n]."""
        field = self.field
        scale = torch.ones_like(points[:, 0]) if field.space is None else field.space.world_per_unit(points)
        return field.voxel * scale

    @torch.no_grad()
    def update_occupancy(self) -> float:
        """Recompute which cells can hold density. Returns the occupied fraction."""
        if self.use_occupancy:
            self.occupancy = self.field.occupancy() & self.visible
        else:
            self.occupancy = torch.ones(self._cells(), dtype=torch.bool, device=self.field.aabb.device)
        return float(self.occupancy.float().mean())

    def _cells(self) -> tuple[int, int, int]:
        return tuple(s - 1 for s in self.field.shape)

    def upsample(self, resolution: int) -> None:
        """A finer grid, allocated only inside the cells the current one finds occupied and
        visible (every cell without occupancy skipping): storage follows the scene."""
        keep = self.field.occupancy() & self.visible if self.sparse else None
        self.field.upsample(resolution, keep)
        self.visible = torch.ones(self._cells(), dtype=torch.bool, device=self.field.aabb.device)
        self.update_occupancy()

    @torch.no_grad()
    def measure_visibility(self, origins: torch.Tensor, directions: torch.Tensor, chunk: int = 65536,
                           threshold: float = 1e-3, block: int = 1) -> float:
        """Mark cells whose largest transmittance over these rays stays below `threshold`
        as hidden (grown by one cell for safety). Not differentiable. Returns the visible
        fraction. Hidden cells are then skipped and pruned from the saved model.
        block > 1 measures blocks of block^3 cells (a cell is visible when any ray sees its
        block): as safe with block^2 times fewer rays, at a slightly looser mask."""
        if not self.use_occupancy:
            return 1.0
        shape = self.occupancy.shape
        blocks = tuple(-(-n // block) for n in shape)
        best = torch.zeros(math.prod(blocks), device=origins.device)
        for start in range(0, origins.shape[0], chunk):
            o, d = origins[start:start + chunk], directions[start:start + chunk]
            samples = self._march(o, d)
            rays = samples.ray_index
            # front to back, stopping each ray behind its surface: the samples there would
            # only ever report transmittance below the threshold
            index, transmittance = packed_transmittance_early_stop(
                lambda i: self.field.density(o[rays[i]] + samples.t_mid[i, None] * d[rays[i]]), rays,
                samples.step, o.shape[0], window=EARLY_STOP_WINDOW, min_transmittance=threshold,
                rise_steps=self.rise_steps)
            positions = o[rays[index]] + samples.t_mid[index, None] * d[rays[index]]
            grid = positions if self.field.space is None else self.field.space.to_grid(positions)
            best.scatter_reduce_(0, cell_of(grid, self.field.aabb, shape, block), transmittance, reduce="amax")
        seen = best.view(blocks) > threshold
        if block > 1:
            seen = seen.repeat_interleave(block, 0).repeat_interleave(block, 1).repeat_interleave(block, 2)
            seen = seen[:shape[0], :shape[1], :shape[2]]
        self.visible = any_within(seen, 1, 1)
        self.update_occupancy()
        return float(self.visible.float().mean())

    @torch.no_grad()
    def samples_per_ray(self, origins: torch.Tensor, directions: torch.Tensor) -> float:
        """Mean number of samples marching keeps per ray [n, 3] (what a pass over them costs)."""
        return self._march(origins, directions).t_mid.numel() / max(1, origins.shape[0])

    @torch.no_grad()
    def inference_cells(self) -> torch.Tensor:
        """The cells whose samples inference evaluates, [nz, ny, nx] bool: the occupancy less
        the margin `update_occupancy` grows round the occupied cells (VoxelGridField.occupancy's
        dilation: the cells below the threshold next to one above it). Training needs the
        margin, so that density can spread into empty neighbours (gradients reach only the
        samples it takes); a render does not. Every node of a margin cell is below
        OCCUPANCY_ALPHA a marching step, and so is any sample in it (trilinear weights, a
        monotone softplus): each sample left out would have added less than that to its
        ray's opacity, and with surface opacity the next sample's rise takes its share up.
        Only the margin: a haze no cell of which reaches the threshold (a model early in
        training, whose occupancy is still every cell) is rendered whole, since there its
        faint samples are all there is. On the primitives' 1200-s model half the samples of a
        frame's centre rays, 0.80-0.84 of the frame's time, the test PSNR within 0.001 dB
        (docs/results.md, "Render time", third round).
        Cached per occupancy and table state; without occupancy skipping, every cell."""
        if not self.use_occupancy:
            return self.occupancy
        key = tables_key(self.field)
        cached = self._inference_cells
        if cached is None or cached[0] is not self.occupancy or cached[1] != key:
            hot = self.field.occupancy(dilate=0).to(self.occupancy.device)
            margin = any_within(hot, 1, 1) & ~hot
            self._inference_cells = cached = (self.occupancy, key, self.occupancy & ~margin)
        return cached[2]

    def _inference_samples(self, samples, origins, directions):
        """`samples` less those outside `inference_cells`, and the kept samples' world
        positions [m, 3] (found on the way, for the caller's field lookups)."""
        rays = samples.ray_index
        positions = torch.addcmul(origins.index_select(0, rays), samples.t_mid[:, None],
                                  directions.index_select(0, rays))
        grid = positions if self.field.space is None else self.field.space.to_grid(positions)
        cells = self.inference_cells()
        keep = cells.reshape(-1)[cell_of(grid, self.field.aabb, cells.shape)].nonzero()[:, 0]
        return keep_samples(samples, keep), positions.index_select(0, keep)

    def _march(self, origins, directions, jitter=None):
        if self.field.space is not None:
            return march_space(origins, directions, self.field.space, self.field.aabb, self.occupancy,
                               self.field.marching_step, jitter=jitter)
        return march(origins, directions, self.field.aabb, self.occupancy, self.field.marching_step,
                     jitter=jitter, levels=self._levels())

    def _levels(self):
        if self._pyramid is None or self._pyramid_of is not self.occupancy:
            self._pyramid, self._pyramid_of = occupancy_pyramid(self.occupancy), self.occupancy
        return self._pyramid

    def render(self, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator | None = None,
               training: bool = False) -> RayOutput:
        """origins, directions (unit): [n, 3]. Training jitters samples within each step."""
        inference = not training and not torch.is_grad_enabled()
        if inference and self.field.space is None and self.use_occupancy:
            return self._render_front_to_back(origins, directions)
        jitter = None
        if training:
            jitter = torch.rand(origins.shape[0], generator=generator).to(origins.device)
        samples = self._march(origins, directions, jitter)
        if inference:
            samples, _ = self._inference_samples(samples, origins, directions)
        rays = samples.ray_index  # [n_samples]

        def field_at(index):  # the field at the samples `index` [m] (a subset or all)
            ray = rays if index is None else rays.index_select(0, index)
            t = samples.t_mid if index is None else samples.t_mid.index_select(0, index)
            d = directions.index_select(0, ray)
            return self.field(torch.addcmul(origins.index_select(0, ray), t[:, None], d), d)

        if inference:  # stop rays behind surfaces
            colour, opacity, depth, evaluated = packed_render_early_stop(
                field_at, samples.t_mid, rays, samples.step, samples.near, samples.far, window=EARLY_STOP_WINDOW,
                rise_steps=self.rise_steps)
            return RayOutput(colour, opacity, depth, evaluated)
        if training:
            return self._render_in_front(samples, origins, directions)
        sigma, rgb = field_at(None)
        colour, opacity, depth, _ = packed_render(sigma, rgb, sample_deltas(samples), samples.t_mid, rays,
                                                  samples.near, samples.far, self.rise_steps)
        return RayOutput(colour, opacity, depth, int(rays.numel()))

    def _render_in_front(self, samples, origins, directions) -> RayOutput:
        """Training: a density pass over every marched sample finds where each ray's
        transmittance falls below TRAIN_MIN_TRANSMITTANCE, and the differentiable pass
        (density, colour, their gradients) runs only on the samples in front of that. A
        ray's colour and opacity move by less than TRAIN_MIN_TRANSMITTANCE; the step costs
        what the visible samples cost (57% of primitives' samples lie behind surfaces)."""
        rays = samples.ray_index
        d = directions.index_select(0, rays)
        positions = torch.addcmul(origins.index_select(0, rays), samples.t_mid[:, None], d)
        stencil = self.field.stencil(positions)  # the positions need no gradient: shared by both passes
        deltas = sample_deltas(samples)
        with torch.no_grad():
            sigma = self.field.density_at_stencil(stencil, positions)
            transmittance, _ = packed_transmittance(sigma, deltas, rays, origins.shape[0], self.rise_steps)
            # NaN compares false: a non-finite field stays in the pass and reaches the loss
            front = (~(transmittance <= TRAIN_MIN_TRANSMITTANCE)).nonzero()[:, 0]
        rays, t_mid, deltas = rays[front], samples.t_mid[front], deltas[front]
        sigma, rgb = self.field.at_stencil(tuple(part[front] for part in stencil), positions[front], d[front])
        colour, opacity, depth, weights = packed_render(sigma, rgb, deltas, t_mid, rays, samples.near, samples.far,
                                                        self.rise_steps)
        distortion = packed_distortion(weights, t_mid, deltas, rays, origins.shape[0])
        return RayOutput(colour, opacity, depth, int(rays.numel()), distortion=distortion)

    def renders_compiled(self, device: torch.device) -> bool:
        """Whether inference on `device` goes through the compiled renderer (nerf.march_cpu),
        which spreads one batch of rays over numba's threads itself (march_cpu.kernel_threads)."""
        return device.type == "cpu" and self.field.space is None and self.use_occupancy

    def _render_front_to_back(self, origins, directions) -> RayOutput:
        """Inference in a bounded box, each ray stopped once it turns opaque: on the CPU
        compiled (`nerf.march_cpu`: each ray stops at its own sample), elsewhere in batched
        torch ops (`_render_windows`)."""
        if not self.renders_compiled(origins.device):
            return self._render_windows(origins, directions)
        if self._compiled is None or self._compiled[0] is not self.occupancy or \
                self._compiled[1].key != tables_key(self.field):
            self._compiled = (self.occupancy, kernel_grids(self.field, self.occupancy, self.inference_cells()))
        colour, opacity, depth, evaluated = render_compiled(self.field, self._compiled[1], origins, directions,
                                                            rise_steps=self.rise_steps)
        return RayOutput(colour, opacity, depth, evaluated)

    def _render_windows(self, origins, directions) -> RayOutput:
        """Inference in a bounded box in batched torch ops: the march stops a level above
        the voxel grid and only the segments a ray reaches before it turns opaque are cut
        into samples, a window of EARLY_STOP_SEGMENTS segments per live ray at a time (about
        half of them at 256 px on primitives): the same image as marching everything
        first, up to the early stop's min_transmittance."""
        segments = march_segments(origins, directions, self.field.aabb, self.occupancy, self.field.marching_step,
                                  levels=self._levels(), keep_levels=1)

        def window_samples(chosen):
            samples, positions = self._inference_samples(segment_samples(segments, chosen), origins, directions)
            rays, t = samples.ray_index, samples.t_mid
            sigma, colour_at = self.field.density_then_colour(positions, directions.index_select(0, rays))
            return rays, t, sample_deltas(samples), sigma, colour_at

        colour, opacity, depth, evaluated = render_front_to_back(window_samples, segments.ray_index, segments.near,
                                                                 segments.far, window=EARLY_STOP_SEGMENTS,
                                                                 rise_steps=self.rise_steps)
        return RayOutput(colour, opacity, depth, evaluated)

    def regularisation(self, tv_weight: float) -> torch.Tensor:
        return tv_weight * self.field.total_variation() if tv_weight > 0 else self.field.aabb.new_zeros(())

    def parameter_groups(self, lr: float, lr_mlp: float) -> list[dict]:
        """The grid's values at `lr`, its density and its colour features each a group of
        their own (nerf.schedule's `lr_scales` may decay them apart); the view-dependent
        colour head, when there is one, at `lr_mlp`."""
        groups = [{"params": [self.field.density_table], "lr": lr, "base_lr": lr, "name": "density"},
                  {"params": [self.field.features], "lr": lr, "base_lr": lr, "name": COLOUR_GROUP}]
        if self.field.head is not None:
            groups.append({"params": self.field.head.parameters(), "lr": lr_mlp, "base_lr": lr_mlp, "name": "head"})
        return groups


class NeRFMLP(nn.Module):
    """The original NeRF's MLP: gamma(x) -> 8 x width ReLU (skip into layer 5) -> sigma and a
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


class VanillaNeRF(RadianceModel):
    # The original NeRF's learning rate (Mildenhall et al. 2020), whatever the run's config says.
    LEARNING_RATE = 5e-4

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

    def parameter_groups(self, lr: float, lr_mlp: float) -> list[dict]:
        """Every weight at the original NeRF's rate (lr and lr_mlp are the compact model's)."""
        return [{"params": self.parameters(), "lr": self.LEARNING_RATE, "base_lr": self.LEARNING_RATE, "name": "all"}]
