"""Compiled inference rendering on the CPU: the compact model's early-terminated render of
bounded space (`CompactNeRF._render_front_to_back`) as one numba kernel per batch of rays.

The samples are `nerf.marching.march`'s: a ray is cut into 1-voxel segments from its box
entry, and a segment whose midpoint (of its part inside the box) lies in an occupied voxel
is cut into `voxel_steps` samples at the centres of its steps, of which those in a cell
outside `sampled` (`CompactNeRF.inference_cells`: the occupancy less training's margin) are
left out, as the torch paths leave them out (`CompactNeRF._inference_samples`). (`march` reaches the same
segments through its pyramid of coarser grids, each grown by a block so that it never drops
a segment that passes an occupied voxel.) Empty space is skipped by a distance grid
(`skip_distances`): from a midpoint whose voxel has no occupied voxel within r - 1 voxels
(Chebyshev), the next midpoints that move at most r - 1 voxels along every axis are empty
too, and are stepped over without a lookup.

The field's value at a sample is `VoxelGridField.corners`'s trilinear stencil of the sparse
tables (row 0: empty), sigma = DENSITY_SCALE softplus(raw + shift) / voxel_final, and the
quadrature is `nerf.packed`'s:

    tau_i = min(sigma_i step, TAU_MAX_PACKED),  w_i = T_i (1 - exp(-tau_i)),  T_{i+1} = T_i exp(-tau_i)
    C = sum_i w_i c_i,  A = 1 - T_end,  D = sum_i w_i t_i / max(A, DEPTH_EPS) clamped to [near, far]

(with surface opacity, `rise_steps` > 0, alpha_i is `nerf.packed.occupancy_rise_taus`'s, from
the occupancy the ray reached at its previous sample, and t_i in the depth lies half a step
before the sample: `nerf.packed.weight_positions`).

Each ray walks its samples nearest first and stops after the first sample that takes T below
`min_transmittance`: the colour it leaves out is at most that (the torch path,
`CompactNeRF._render_windows`, stops at the end of a window of segments instead, so the two
differ by at most min_transmittance a ray). A sample's colour is asked for only where its
weight exceeds COLOUR_MIN_WEIGHT, as the torch path does.

Why compiled: a 128 px frame of the 600-s primitives model holds ~16k centre rays and ~8k
sub-rays with ~220k samples in front of their surfaces; the batched torch path spent ~30 ops
a window of segments on them, and its marching and grid_sample's 3D kernel cost 100-200 ns
a sample (docs/results.md, "Render time"). Here a ray is one loop: its empty space skipped,
its samples, its stop. Rays are independent and each is written by one thread, so the result
does not depend on the thread count (numba's prange over strided lanes of rays, so that every
thread gets a share of the image's costly middle).

A field with a colour head (view-dependent, or a residual head) has its colour computed in
torch (`VoxelGridField._colour`) from the features this kernel interpolates: a first pass
counts each ray's coloured samples, a second writes them at their offsets.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from nerfgauge.nerf.grid_field import DENSE_RENDER_FLOATS, DENSITY_SCALE, any_within
from nerfgauge.nerf.packed import COLOUR_MIN_WEIGHT, RISE_ALPHA_MAX_GAP, TAU_MAX_PACKED
from nerfgauge.nerf.rendering import DEPTH_EPS

# Lanes of rays the prange splits over the threads: lane k renders blocks k, k + LANES, ...
# of BLOCK consecutive rays, so every thread's share crosses the whole image (a frame's
# middle costs the most), while consecutive rays, which read the same grid nodes, stay
# together in a thread's cache.
LANES = 256
BLOCK = 32
# Rays are rendered in Morton order of where they begin, in cells this many voxels wide.
LOCALITY_CELL = 2
# softplus(x) = x above this, as torch's F.softplus (threshold 20)
SOFTPLUS_THRESHOLD = 20.0
# below this, softplus(x) = log1p(exp(x)) is exp(x) to a relative exp(x) / 2 < 2.3e-5
SOFTPLUS_TAIL = -10.0
# below this, 1 - exp(-tau) is its Taylor polynomial to the third order within a relative
# tau^3 / 24 < 4.2e-11
SMALL_TAU = 1e-3
# The distance grid counts up to this many voxels (uint8); a ray through wider empty space
# looks up once every MAX_SKIP - 1 voxels.
MAX_SKIP = 16


@contextlib.contextmanager
def kernel_threads(threads: int):
    """Within the block, the compiled renderer runs on `threads` threads (at most numba's
    NUMBA_NUM_THREADS, the machine's cores by default); torch's own ops on one, since an
    idle torch worker spinning for its next op would take a core from the kernel's (on 2
    cores, 2 + 2 threads rendered no faster than 1). Both restored after."""
    before = numba.get_num_threads(), torch.get_num_threads()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    torch.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before[0])
        torch.set_num_threads(before[1])


@torch.no_grad()
def skip_distances(occupancy: torch.Tensor, cap: int = MAX_SKIP) -> np.ndarray:
    """For every voxel of `occupancy` [nz, ny, nx] bool, the Chebyshev distance in voxels to
    the nearest occupied one, capped at `cap`: 0 occupied; r: every voxel within r - 1 of
    it (a (2r - 1)^3 cube) is empty. Returns [nz, ny, nx] uint8 (numpy)."""
    distance = torch.zeros(occupancy.shape, dtype=torch.uint8)
    reached = occupancy.cpu().bool()
    for _ in range(cap):
        distance += ~reached
        reached = any_within(reached, 1, 1)
    return distance.numpy()


def node_table(field) -> tuple:
    """The field's values as the kernel reads them: (index, table [R, 1 + C] float32, raw
    density then features). Where a dense copy fits (grid_field.DENSE_RENDER_FLOATS), a row
    per grid node and an empty index: one load a corner; else the sparse tables' rows (row
    0: empty) and the node index [nz * ny * nx] int32 that addresses them."""
    table = torch.cat([field.density_table.detach(), field.features.detach()], dim=1)  # [rows, 1 + C]
    if table.shape[1] * math.prod(field.shape) <= DENSE_RENDER_FLOATS:
        return np.zeros(0, np.int32), table[field.index.reshape(-1).long()].contiguous().numpy()
    return field.index.reshape(-1).contiguous().numpy(), table.contiguous().numpy()


@numba.njit(cache=True)
def _lane_rays(lane, lanes, order, size):
    """The rays of `lane`: blocks lane, lane + lanes, ... of `size` consecutive rays of `order`."""
    rays = []
    n = order.shape[0]
    for block in range(lane, -(-n // size), lanes):
        for k in range(block * size, min(n, (block + 1) * size)):
            rays.append(order[k])
    return rays


@numba.njit(cache=True)
def _render_lane(lane, lanes, block, order, origins, directions, near_of, far_of, distance, voxel, lo_box,
                 segment, voxel_steps, step, sampled, index, table, nodes, scale, shift, density_scale, rise_steps,
                 min_transmittance, colour_min_weight, inline_colour, write_offsets, out_rgb, out_opacity,
                 out_depth, out_evaluated, out_coloured, out_rows, out_features, out_weights):
    """Rays lane, lane + lanes, ... (one thread's share), each front to back: its opacity,
    depth, samples evaluated and coloured. inline_colour: sigmoid(features) w added to
    out_rgb; else, where write_offsets holds rows, each coloured sample's ray, features and
    weight written from the ray's row on."""
    gz, gy, gx = distance.shape
    nx, ny, nz = nodes[0], nodes[1], nodes[2]
    channels = table.shape[1] - 1
    dense = index.shape[0] == 0
    check_cells = sampled.shape[0] > 0
    depth_shift = 0.5 * step if rise_steps > 0.0 else 0.0  # `nerf.packed.weight_positions`
    rows = np.zeros(8, np.int64)
    weights = np.zeros(8)
    for i in _lane_rays(lane, lanes, order, block):
        near, far = near_of[i], far_of[i]
        transmittance, weighted_t = 1.0, 0.0
        reached = 0.0  # surface opacity: the occupancy at the ray's previous sample
        evaluated, coloured = 0, 0
        write_from = write_offsets[i] if write_offsets.shape[0] else -1
        # the ray in voxel units from the box's corner (the march's), and in the field's nodes
        ox = (origins[i, 0] - lo_box[0]) / voxel[0]
        oy = (origins[i, 1] - lo_box[1]) / voxel[1]
        oz = (origins[i, 2] - lo_box[2]) / voxel[2]
        dx, dy, dz = directions[i, 0] / voxel[0], directions[i, 1] / voxel[1], directions[i, 2] / voxel[2]
        # voxels a midpoint moves along its fastest axis from one segment to the next
        stride = segment * max(abs(dx), abs(dy), abs(dz))
        nx0 = (origins[i, 0] - lo_box[0]) * scale[0]
        ny0 = (origins[i, 1] - lo_box[1]) * scale[1]
        nz0 = (origins[i, 2] - lo_box[2]) * scale[2]
        ndx, ndy, ndz = directions[i, 0] * scale[0], directions[i, 1] * scale[1], directions[i, 2] * scale[2]
        k = 0
        while far > near:
            s = near + k * segment
            if s >= far:
                break
            mid = min(s + 0.5 * segment, 0.5 * (s + far))
            x = int(math.floor(ox + dx * mid))
            y = int(math.floor(oy + dy * mid))
            z = int(math.floor(oz + dz * mid))
            if x < 0 or y < 0 or z < 0 or x >= gx or y >= gy or z >= gz:
                k += 1
                continue
            r = distance[z, y, x]
            if r > 0:  # empty: so are the next midpoints that stay within r - 1 voxels
                k += 1 + max(0, int(math.floor((r - 1) / stride))) if stride > 0 else 1
                continue
            k += 1
            stop = False
            for j in range(voxel_steps):
                t = s + (j + 0.5) * step
                if t >= far:
                    break
                # `VoxelGridField.corners`: the point clamped into the box, its cell's 8 nodes
                ux = min(max(nx0 + ndx * t, 0.0), nx - 1.0)
                uy = min(max(ny0 + ndy * t, 0.0), ny - 1.0)
                uz = min(max(nz0 + ndz * t, 0.0), nz - 1.0)
                bx = min(math.floor(ux), nx - 2.0)
                by = min(math.floor(uy), ny - 2.0)
                bz = min(math.floor(uz), nz - 2.0)
                if check_cells and sampled[int(bz), int(by), int(bx)] == 0:
                    continue  # in the margin training keeps round the occupied cells
                fx, fy, fz = ux - bx, uy - by, uz - bz
                flat = (int(bz) * ny + int(by)) * nx + int(bx)
                raw = 0.0
                c = 0
                for cz in range(2):
                    wz = fz if cz else 1.0 - fz
                    for cy in range(2):
                        wzy = wz * (fy if cy else 1.0 - fy)
                        corner = flat + (cz * ny + cy) * nx
                        row0 = corner if dense else index[corner]
                        row1 = corner + 1 if dense else index[corner + 1]
                        rows[c], rows[c + 1] = row0, row1
                        weights[c], weights[c + 1] = wzy * (1.0 - fx), wzy * fx
                        raw += weights[c] * table[row0, 0] + weights[c + 1] * table[row1, 0]
                        c += 2
                arg = raw + shift
                if arg < SOFTPLUS_TAIL:
                    # softplus(x) = log1p(e^x) = e^x to a relative e^x / 2 < 2.3e-5, and for a
                    # small tau, 1 - e^-tau to its third order: one transcendental call, not
                    # three, for the faint density in front of every surface
                    tau = density_scale * step * math.exp(arg)
                    alpha = tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0))) if tau < SMALL_TAU else -math.expm1(-tau)
                else:
                    softplus = arg if arg > SOFTPLUS_THRESHOLD else math.log1p(math.exp(arg))
                    tau = min(density_scale * softplus * step, TAU_MAX_PACKED)
                    alpha = -math.expm1(-tau)
                if rise_steps > 0.0:  # `nerf.packed.occupancy_rise_taus`
                    occupied = -math.expm1(-min(tau * rise_steps, TAU_MAX_PACKED))
                    alpha = min(max((occupied - reached) / max(1.0 - reached, RISE_ALPHA_MAX_GAP), 0.0),
                                1.0 - RISE_ALPHA_MAX_GAP)
                    reached = occupied
                weight = transmittance * alpha
                evaluated += 1
                if weight > colour_min_weight:
                    if inline_colour:
                        for channel in range(3):
                            value = 0.0
                            for c in range(8):
                                value += weights[c] * table[rows[c], 1 + channel]
                            out_rgb[i, channel] += weight / (1.0 + math.exp(-value))
                    elif write_from >= 0:
                        row = write_from + coloured
                        out_rows[row] = i
                        out_weights[row] = weight
                        for channel in range(channels):
                            value = 0.0
                            for c in range(8):
                                value += weights[c] * table[rows[c], 1 + channel]
                            out_features[row, channel] = value
                    coloured += 1
                weighted_t += weight * (t - depth_shift)
                transmittance *= 1.0 - alpha
                if transmittance < min_transmittance:
                    stop = True
                    break
            if stop:
                break
        opacity = 1.0 - transmittance
        out_opacity[i] = opacity
        out_depth[i] = min(max(weighted_t / max(opacity, DEPTH_EPS), near), far) if opacity > 0.0 else 0.0
        out_evaluated[i] = evaluated
        out_coloured[i] = coloured


@numba.njit(parallel=True, cache=True)
def _render_rays(block, order, origins, directions, near, far, distance, voxel, lo_box, segment,
                 voxel_steps, step, sampled, index, table, nodes, scale, shift, density_scale, rise_steps,
                 min_transmittance, colour_min_weight, inline_colour, write_offsets, out_rgb, out_opacity,
                 out_depth, out_evaluated, out_coloured, out_rows, out_features, out_weights):
    """`_render_lane` of every lane of rays, the lanes spread over numba's threads."""
    lanes = min(-(-origins.shape[0] // block), LANES)
    for lane in numba.prange(lanes):
        _render_lane(lane, lanes, block, order, origins, directions, near, far, distance, voxel, lo_box,
                     segment, voxel_steps, step, sampled, index, table, nodes, scale, shift, density_scale, rise_steps,
                     min_transmittance, colour_min_weight, inline_colour, write_offsets, out_rgb, out_opacity,
                     out_depth, out_evaluated, out_coloured, out_rows, out_features, out_weights)


@numba.njit(cache=True, inline="always")
def _spread_bits(x):
    """The low 10 bits of x, two zero bits after each (a Morton code's interleave)."""
    x &= 0x3FF
    x = (x | (x << 16)) & 0x30000FF
    x = (x | (x << 8)) & 0x300F00F
    x = (x | (x << 4)) & 0x30C30C3
    return (x | (x << 2)) & 0x9249249


@numba.njit(cache=True)
def _enter_box(origins, directions, lo, hi, cell, out_near, out_far, out_key):
    """`nerf.rendering.ray_aabb` of every ray (the slab method: near and far, both 0 for a
    ray that misses the box or only grazes it), and the Morton key of where it enters
    (origin + near direction, in cells `cell` wide from the box's corner; rays that miss:
    past every other key)."""
    for i in range(origins.shape[0]):  # 0.5 ms for 65k rays: not worth a parallel region's compile
        t_near, t_far = 0.0, math.inf
        for axis in range(3):
            o, d = float(origins[i, axis]), float(directions[i, axis])
            if d == 0.0:
                if o < lo[axis] or o > hi[axis]:
                    t_near, t_far = math.inf, -math.inf
                continue
            t_lo, t_hi = (lo[axis] - o) / d, (hi[axis] - o) / d
            t_near = max(t_near, min(t_lo, t_hi))
            t_far = min(t_far, max(t_lo, t_hi))
        if t_far > t_near:
            out_near[i], out_far[i] = t_near, t_far
            key = 0
            for axis in range(3):
                position = (float(origins[i, axis]) + t_near * float(directions[i, axis]) - lo[axis]) / cell
                key |= _spread_bits(min(max(int(math.floor(position)), 0), 0x3FF)) << axis
            out_key[i] = key
        else:
            out_near[i], out_far[i] = 0.0, 0.0
            out_key[i] = 1 << 62


# The keys of rays that miss the box (1 << 62) sort as this one, past every 30-bit Morton key.
MISS_KEY = 1 << 30


@numba.njit(cache=True)
def morton_order(key):
    """np.argsort(key, kind="stable") of `_enter_box`'s keys [n] int64 (30-bit Morton keys,
    and 1 << 62 for a ray that misses), by a least-significant-digit radix sort of 3 digits
    of 11 bits: a frame's 16k rays in about a tenth of numpy's comparison sort's time."""
    n = key.shape[0]
    order, swap = np.arange(n), np.empty(n, np.int64)
    counts = np.empty(1 << 11, np.int64)
    for shift in (0, 11, 22):
        counts[:] = 0
        for i in range(n):
            counts[(min(key[i], MISS_KEY) >> shift) & 0x7FF] += 1
        total = 0
        for digit in range(1 << 11):
            counts[digit], total = total, total + counts[digit]
        for i in range(n):  # in the order of the digits sorted so far: stable
            ray = order[i]
            digit = (min(key[ray], MISS_KEY) >> shift) & 0x7FF
            swap[counts[digit]] = ray
            counts[digit] += 1
        order, swap = swap, order
    return order


@dataclass(frozen=True)
class KernelGrids:
    """What the kernel reads of a field and its occupancy: the skip distances [nz, ny, nx]
    uint8 (`skip_distances`), the cells whose samples it evaluates ([nz, ny, nx] uint8, or
    empty: every marched sample), and the node index and value table (`node_table`); `key`
    says which state of the field's tables they hold (`tables_key`)."""

    distance: np.ndarray
    sampled: np.ndarray
    index: np.ndarray
    table: np.ndarray
    key: tuple


def tables_key(field) -> tuple:
    """Changes whenever the field's index or value tables do (an Adam step bumps a table's
    version; an upsample or a load replaces it)."""
    return (field.index.data_ptr(), field.density_table.data_ptr(), field.density_table._version,
            field.features.data_ptr(), field.features._version)


@torch.no_grad()
def kernel_grids(field, occupancy: torch.Tensor, sampled: torch.Tensor | None = None) -> KernelGrids:
    """`KernelGrids` of a field and its occupancy [nz, ny, nx] bool (cells), which the march
    follows; sampled: the cells [nz, ny, nx] bool within it whose samples are evaluated
    (`CompactNeRF.inference_cells`; None: every marched sample)."""
    cells = np.zeros((0, 0, 0), np.uint8) if sampled is None else sampled.cpu().numpy().astype(np.uint8)
    return KernelGrids(skip_distances(occupancy), cells, *node_table(field), tables_key(field))


@torch.no_grad()
def render_compiled(field, grids: KernelGrids, origins: torch.Tensor, directions: torch.Tensor,
                    min_transmittance: float = 1e-3,
                    colour_min_weight: float = COLOUR_MIN_WEIGHT, rise_steps: float = 0.0) -> tuple:
    """Early-terminated render of rays [n, 3] (unit directions, CPU) through a bounded
    `VoxelGridField` and its occupancy (`kernel_grids`). Not differentiable. Runs on numba's threads
    (`kernel_threads`). rise_steps > 0: surface opacity (`nerf.packed.occupancy_rise_taus`).
    Returns premultiplied rgb [n, 3], opacity [n], depth [n] (in the rays' dtype) and the
    samples evaluated (int)."""
    n = origins.shape[0]
    aabb = field.aabb
    distance = grids.distance
    cells = torch.tensor([distance.shape[2], distance.shape[1], distance.shape[0]], dtype=torch.float64)
    voxel = ((aabb[1] - aabb[0]).double() / cells).numpy()  # [3] x y z: the march's voxel
    step = field.marching_step
    voxel_steps = max(1, round(float(voxel.max()) / step))
    nz, ny, nx = field.shape
    scale = (torch.tensor([nx - 1, ny - 1, nz - 1], dtype=torch.float64) / (aabb[1] - aabb[0]).double()).numpy()
    channels = grids.table.shape[1] - 1
    inline = field.head is None
    o, d = origins.contiguous().numpy(), directions.contiguous().numpy()
    lo, hi = aabb[0].double().numpy(), aabb[1].double().numpy()
    near, far, key = np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
    _enter_box(o, d, lo, hi, LOCALITY_CELL * field.voxel, near, far, key)
    # rays that begin close together read the same grid nodes: rendered one after another
    # they find those in the thread's cache (at 256 px: 1.4x faster than the image's order)
    order = morton_order(key)
    arrays = (o, d, near, far)
    constants = (distance, voxel, lo, float(voxel_steps * step), voxel_steps, float(step), grids.sampled,
                 grids.index, grids.table, np.array([nx, ny, nz], dtype=np.int64), scale, float(field.shift),
                 DENSITY_SCALE / field.voxel_final, float(rise_steps), float(min_transmittance),
                 float(colour_min_weight), inline)
    rgb, opacity, depth = np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    evaluated, coloured = np.zeros(n, np.int64), np.zeros(n, np.int64)
    outputs = (rgb, opacity, depth, evaluated, coloured)
    _render_rays(BLOCK, order, *arrays, *constants, np.zeros(0, np.int64), *outputs, np.zeros(0, np.int64),
                 np.zeros((0, channels), np.float32), np.zeros(0))
    rgb_t = torch.from_numpy(rgb)
    if not inline:  # the head's colour, in torch, from the coloured samples' features
        write = np.cumsum(coloured) - coloured
        total = int(coloured.sum())
        rays, values = np.zeros(total, np.int64), np.zeros((total, channels), np.float32)
        weights = np.zeros(total)
        _render_rays(BLOCK, order, *arrays, *constants, write, *outputs, rays, values, weights)
        rays_t = torch.from_numpy(rays)
        colour = field._colour(torch.from_numpy(values), directions.index_select(0, rays_t)).double()
        weighted = torch.from_numpy(weights)[:, None] * colour
        rgb_t = torch.zeros((n, 3), dtype=torch.float64).index_add_(0, rays_t, weighted)
    dtype = origins.dtype
    return (rgb_t.to(dtype), torch.from_numpy(opacity).to(dtype), torch.from_numpy(depth).to(dtype),
            int(evaluated.sum()))
