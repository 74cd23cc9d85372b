"""Issue 52, item 2: the compact model's compiled CPU render (nerf.march_cpu), checked against
the torch implementations it replaces on the CPU: the full pass over every marched sample
(`march` + `packed_render`, no early stop), the batched early-stopped render
(`CompactNeRF._render_windows`), `ray_aabb`, and a brute-force Chebyshev distance.

Grouped by fault class: which samples it takes (skip distances, box entry), what it
computes from them (the quadrature, a colour head, the sparse tables), and what must not
change it (the thread count, the order rays are given in)."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_compact_nerf import blob_model

import nerfgauge.nerf.march_cpu as march_cpu
from nerfgauge.nerf.grid_field import DENSITY_SCALE, OCCUPANCY_ALPHA, node_mask
from nerfgauge.nerf.march_cpu import kernel_grids, kernel_threads, render_compiled, skip_distances
from nerfgauge.nerf.marching import keep_samples, sample_deltas
from nerfgauge.nerf.packed import packed_render
from nerfgauge.nerf.rendering import ray_aabb


def _rays(g: torch.Generator, aabb: torch.Tensor, n: int = 2500):
    """Rays from a camera-like cluster over the box, some past its edges (they miss)."""
    origins = torch.randn((n, 3), generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])
    targets = aabb[0] + torch.rand((n, 3), generator=g) * (aabb[1] - aabb[0]) * 1.3 - 0.15 * (aabb[1] - aabb[0])
    return origins, F.normalize(targets - origins, dim=-1)


def _sampled_cells(model) -> torch.Tensor:
    """The cells inference samples, worked out here from the field's nodes: the occupied
    cells less the margin training grows round the hot ones (a cell is hot when a corner's
    opacity over one marching step exceeds OCCUPANCY_ALPHA; the margin: the cells that are
    not, with a hot one among their 26 neighbours). [nz, ny, nx] bool."""
    field = model.field
    alpha = -torch.expm1(-field.density_from_raw(field.to_dense()[0]) * field.marching_step)  # [nodes]
    hot = F.max_pool3d(alpha[None, None], 2, stride=1)[0, 0] > OCCUPANCY_ALPHA
    near_hot = F.max_pool3d(hot[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    return model.occupancy & (hot | ~near_hot)


def _full_pass(model, origins, directions):
    """Every marched sample in a sampled cell (`_sampled_cells`) composited:
    `nerf.packed.packed_render`, the torch quadrature, with no early stop and every
    sample's colour. Cells found in float64, as the kernel finds them."""
    samples = model._march(origins, directions)
    cells = _sampled_cells(model)
    aabb = model.field.aabb.double()
    size = torch.tensor(cells.shape[::-1], dtype=torch.float64)  # x y z cells
    at = origins.double()[samples.ray_index] + samples.t_mid.double()[:, None] * directions.double()[samples.ray_index]
    xyz = torch.minimum(((at - aabb[0]) / (aabb[1] - aabb[0]) * size).floor().clamp_min(0), size - 1).long()
    samples = keep_samples(samples, cells[xyz[:, 2], xyz[:, 1], xyz[:, 0]].nonzero()[:, 0])
    rays, t, deltas = samples.ray_index, samples.t_mid, sample_deltas(samples)
    d = directions.index_select(0, rays)
    sigma, rgb = model.field(torch.addcmul(origins.index_select(0, rays), t[:, None], d), d)
    rgb_out, opacity, depth, _ = packed_render(sigma, rgb, deltas, t, rays, samples.near, samples.far)
    return rgb_out, opacity, depth, int(rays.numel())


def _compiled(model, origins, directions, **kwargs):
    grids = kernel_grids(model.field, model.occupancy, model.inference_cells())
    return render_compiled(model.field, grids, origins, directions, **kwargs)


# --------------------------------------------------------------------------------------
# the quadrature


@pytest.mark.parametrize("step_ratio", [0.5, 1.0])
def test_without_early_stop_it_is_the_full_pass_over_every_marched_sample(step_ratio):
    """min_transmittance 0 and every sample's colour: the same samples and the same sums as
    march + packed_render, to float32 rounding: the torch pass takes its sample positions
    in float32 (~3e-7 off at |o + t d| ~ 3), which the blobs' steep raw density (up to ~50
    a voxel of 0.083) turns into ~2e-4 of a sample's tau; the kernel works in float64.
    A slip in the maths (a sample missed or doubled, a weight off) shows at 1e-2."""
    g = torch.Generator().manual_seed(3)
    model, aabb = blob_model(g, step_ratio)
    origins, directions = _rays(g, aabb)
    with torch.no_grad():
        rgb, opacity, depth, evaluated = _compiled(model, origins, directions, min_transmittance=0.0,
                                                   colour_min_weight=-1.0)
        full = _full_pass(model, origins, directions)
    assert (full[1] > 0.999).sum() > 100 and ((full[1] > 0.05) & (full[1] < 0.9)).sum() > 20
    assert evaluated == full[3]
    torch.testing.assert_close(rgb, full[0], rtol=0, atol=1e-4)
    torch.testing.assert_close(opacity, full[1], rtol=0, atol=1e-4)
    seen = full[1] > 1e-3
    torch.testing.assert_close(depth[seen], full[2][seen], rtol=1e-4, atol=1e-4)
    assert torch.equal(depth[~seen] == 0, full[2][~seen] == 0)


def test_the_early_stop_leaves_out_at_most_the_transmittance_where_it_stops(monkeypatch):
    """With the render's settings (stop below T = 1e-3, colour only above a weight of 1e-5):
    colour and opacity within 1e-3 (+ the colours skipped, each weight < 1e-5) of the full
    pass, like the batched torch render, which stops at the end of a window instead (one
    4-voxel segment a window, so this 24-voxel box takes several)."""
    import nerfgauge.nerf.models as models_module
    monkeypatch.setattr(models_module, "EARLY_STOP_SEGMENTS", 1)
    g = torch.Generator().manual_seed(4)
    model, aabb = blob_model(g)
    model.eval()
    origins, directions = _rays(g, aabb)
    with torch.no_grad():
        rgb, opacity, depth, evaluated = _compiled(model, origins, directions)
        windows = model._render_windows(origins, directions)
        full = _full_pass(model, origins, directions)
    samples_per_ray = full[3] / len(origins)
    colour_bound = 1e-3 + 1e-5 * samples_per_ray + 1e-5
    for got in ((rgb, opacity), (windows.rgb, windows.opacity)):
        assert (got[0] - full[0]).abs().max() <= colour_bound
        assert (got[1] - full[1]).abs().max() <= 1e-3 + 1e-5
    assert evaluated < windows.n_samples < full[3]  # each ray stops at its own sample, not a window's end
    seen = full[1] > 0.5
    near, far, _ = ray_aabb(origins, directions, aabb)
    bound = 1e-3 * (far - near)[seen] / (full[1][seen] - 1e-3) + 1e-4
    assert ((depth - full[2])[seen].abs() <= bound).all()


def test_model_render_goes_through_the_compiled_kernel_on_the_cpu():
    g = torch.Generator().manual_seed(6)
    model, aabb = blob_model(g)
    model.eval()
    origins, directions = _rays(g, aabb, 400)
    assert model.renders_compiled(torch.device("cpu")) and not model.renders_compiled(torch.device("meta"))
    with torch.no_grad():
        out = model.render(origins, directions)
        rgb, opacity, depth, evaluated = _compiled(model, origins, directions)
    assert torch.equal(out.rgb, rgb) and torch.equal(out.opacity, opacity) and out.n_samples == evaluated


@pytest.mark.parametrize("head", ["view-dependent", "residual"])
def test_a_colour_head_gets_the_features_of_every_sample_that_weighs(head):
    """A field with a colour head: its colour in torch from the features the kernel
    interpolates (two passes: count, then write). The same sums as the full pass."""
    g = torch.Generator().manual_seed(7)
    model, aabb = blob_model(g)
    field = model.field
    if head == "residual":
        torch.manual_seed(0)
        field.add_residual_head(6)
        torch.nn.init.normal_(field.head[2].weight, std=0.5)
        field.features.data[1:, 3:] = torch.randn(field.features.shape[0] - 1, 3, generator=g)
    else:
        from nerfgauge.nerf.grid_field import VoxelGridField
        from nerfgauge.nerf.models import CompactNeRF
        torch.manual_seed(0)
        viewdep = VoxelGridField(field.aabb, 24, 24, True, feature_channels=5)
        dense = viewdep.to_dense()
        dense[0] = field.to_dense()[0]
        dense[1:] = torch.randn(dense[1:].shape, generator=g)
        viewdep.load_dense(dense)
        model = CompactNeRF(viewdep)
        model.update_occupancy()
    origins, directions = _rays(g, aabb, 800)
    with torch.no_grad():
        rgb, opacity, _, _ = _compiled(model, origins, directions, min_transmittance=0.0, colour_min_weight=-1.0)
        full = _full_pass(model, origins, directions)
    assert full[0].abs().max() > 0.1
    torch.testing.assert_close(rgb, full[0], rtol=0, atol=1e-4)
    torch.testing.assert_close(opacity, full[1], rtol=0, atol=1e-4)


def test_the_sparse_tables_give_the_dense_tables_values(monkeypatch):
    """A grid too large for a dense copy is read through the node index and the sparse rows
    (row 0: empty): the same render."""
    g = torch.Generator().manual_seed(8)
    model, aabb = blob_model(g)
    model.field.keep_rows(node_mask(model.field.occupancy(dilate=2)))  # the rest unallocated: EMPTY_RAW
    assert model.field.allocated < np.prod(model.field.shape)
    origins, directions = _rays(g, aabb, 1500)
    with torch.no_grad():
        dense = _compiled(model, origins, directions)
        monkeypatch.setattr(march_cpu, "DENSE_RENDER_FLOATS", 0)
        grids = kernel_grids(model.field, model.occupancy, model.inference_cells())
        assert grids.index.shape[0] == int(np.prod(model.field.shape))
        sparse = render_compiled(model.field, grids, origins, directions)
    for a, b in zip(dense[:3], sparse[:3]):
        assert torch.equal(a, b)


# --------------------------------------------------------------------------------------
# which samples


def test_inference_leaves_out_only_the_margin_round_the_occupied_cells():
    """Empty air at 0.9 OCCUPANCY_ALPHA a step: the margin training grows round the blobs is
    faint, not empty. Inference samples the cells `_sampled_cells` finds (the model's own
    `inference_cells`), fewer than the occupancy; against every marched sample, a ray's
    opacity moves by at most OCCUPANCY_ALPHA for each sample left out, and rays through
    the margin do move (a cell wrongly left out, with a blob's opacity, would break the
    bound; one wrongly kept would leave the render equal). The torch windows leave out
    the same samples."""
    g = torch.Generator().manual_seed(12)
    model, aabb = blob_model(g)
    field = model.field
    grid = field.to_dense()
    faint = math.log(math.expm1(-math.log(1 - 0.9 * OCCUPANCY_ALPHA) / (DENSITY_SCALE * field.marching_step
                                                                         / field.voxel_final))) - field.shift
    grid[0] = torch.where(grid[0] < -20, torch.full_like(grid[0], faint), grid[0])
    field.load_dense(grid)
    model.update_occupancy()
    model.eval()
    cells = model.inference_cells()
    assert torch.equal(cells, _sampled_cells(model)) and 0 < cells.sum() < model.occupancy.sum()
    origins, directions = _rays(g, aabb, 1500)
    with torch.no_grad():
        every_grids = kernel_grids(field, model.occupancy)  # every marched sample
        every = render_compiled(field, every_grids, origins, directions, min_transmittance=0.0,
                                colour_min_weight=-1.0)
        sampled = _compiled(model, origins, directions, min_transmittance=0.0, colour_min_weight=-1.0)
        windows = model._render_windows(origins, directions)
        left_out = torch.tensor([  # samples left out, ray by ray (the first 300)
            render_compiled(field, every_grids, o[None], d[None], min_transmittance=0.0)[3]
            - _compiled(model, o[None], d[None], min_transmittance=0.0)[3]
            for o, d in zip(origins[:300], directions[:300])],
            dtype=torch.float64)
    moved = (every[1] - sampled[1])[:300].abs()
    assert (left_out > 0).sum() > 50 and (moved > 1e-4).sum() > 20
    assert (moved <= left_out * OCCUPANCY_ALPHA + 1e-9).all()
    assert windows.n_samples <= sampled[3] and (windows.opacity - sampled[1]).abs().max() <= 1e-3 + 1e-5


def test_skip_distances_are_the_chebyshev_distance_to_the_nearest_occupied_voxel():
    g = torch.Generator().manual_seed(1)
    occupancy = torch.rand((9, 11, 13), generator=g) > 0.985
    got = skip_distances(occupancy, cap=6)
    points = occupancy.nonzero().numpy()
    zyx = np.stack(np.meshgrid(*(np.arange(n) for n in occupancy.shape), indexing="ij"), -1).reshape(-1, 3)
    brute = np.abs(zyx[:, None, :] - points[None, :, :]).max(-1).min(1).reshape(occupancy.shape)
    assert len(points) >= 2
    assert np.array_equal(got, np.minimum(brute, 6))
    assert (skip_distances(torch.zeros((3, 4, 5), dtype=torch.bool), cap=4) == 4).all()


def test_where_rays_enter_the_box_is_ray_aabb_s():
    """Near and far as the slab method in torch has them, rays parallel to a face inside its
    slab or outside it included; a miss or a graze: both 0."""
    g = torch.Generator().manual_seed(2)
    aabb = torch.tensor([[-1.0, -0.5, -0.75], [1.0, 0.5, 0.75]])
    origins, directions = _rays(g, aabb, 500)
    directions[:40, 0] = 0.0  # parallel to the x faces: some inside the slab, some outside
    origins[20:40, 0] = 1.5
    directions = F.normalize(directions, dim=-1)
    origins[40:45] = torch.tensor([0.1, 0.2, 0.3])  # inside the box: near 0
    n = len(origins)
    near, far, key = np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
    march_cpu._enter_box(origins.numpy(), directions.numpy(), aabb[0].double().numpy(), aabb[1].double().numpy(),
                         0.1, near, far, key)
    want_near, want_far, hit = ray_aabb(origins, directions, aabb)
    assert 0 < hit.sum() < n and (want_near[40:45] == 0).all() and hit[40:45].all()
    np.testing.assert_allclose(near, want_near.double().numpy(), atol=2e-6)
    np.testing.assert_allclose(far, want_far.double().numpy(), atol=2e-6)
    assert (key[~hit.numpy()] > key[hit.numpy()].max()).all()  # misses last


def test_a_haze_below_the_threshold_everywhere_is_rendered_whole():
    """A field early in training: every node at opacity 0.9 OCCUPANCY_ALPHA a step, no cell
    hot, the occupancy still every cell. There is no margin to leave out, and the faint
    samples are the whole image (a ray through the 24-voxel box takes about 48 of them, an
    opacity near 0.2): inference renders every one, as the full pass does."""
    g = torch.Generator().manual_seed(14)
    model, aabb = blob_model(g)
    field = model.field
    grid = field.to_dense()
    grid[0] = math.log(math.expm1(-math.log(1 - 0.9 * OCCUPANCY_ALPHA) / (DENSITY_SCALE * field.marching_step
                                                                         / field.voxel_final))) - field.shift
    field.load_dense(grid)
    model.occupancy = torch.ones_like(model.occupancy)
    model.eval()
    assert torch.equal(model.inference_cells(), model.occupancy)
    origins, directions = _rays(g, aabb, 500)
    with torch.no_grad():
        got = model.render(origins, directions)
        every = render_compiled(field, kernel_grids(field, model.occupancy), origins, directions)
    assert float(got.opacity.max()) > 0.1
    assert torch.equal(got.opacity, every[1]) and torch.equal(got.rgb, every[0])


# --------------------------------------------------------------------------------------
# what must not change it


def test_the_thread_count_and_the_rays_order_do_not_change_a_ray():
    g = torch.Generator().manual_seed(10)
    model, aabb = blob_model(g)
    origins, directions = _rays(g, aabb, 3000)
    before = numba.get_num_threads(), torch.get_num_threads()
    with torch.no_grad():
        with kernel_threads(1):
            one = _compiled(model, origins, directions)
            assert numba.get_num_threads() == 1 and torch.get_num_threads() == 1
        with kernel_threads(numba.config.NUMBA_NUM_THREADS):
            many = _compiled(model, origins, directions)
        shuffled = torch.randperm(len(origins), generator=g)
        moved = _compiled(model, origins[shuffled], directions[shuffled])
    assert (numba.get_num_threads(), torch.get_num_threads()) == before
    for a, b, c in zip(one[:3], many[:3], moved[:3]):
        assert torch.equal(a, b) and torch.equal(a[shuffled], c)


def test_the_morton_order_is_numpy_s_stable_argsort_of_the_keys():
    """The radix sort against numpy's stable argsort: repeated keys (rays that enter the box
    in one cell), every bit of a 30-bit key, and the key of a ray that misses."""
    rng = np.random.default_rng(12)
    for n in (0, 1, 5000):
        key = rng.integers(0, 1 << 30, size=n, dtype=np.int64)
        key[: n // 2] = key[: n // 2] % 97  # many equal keys: their order must stay the rays' own
        key[::7] = 1 << 62  # misses: after every ray that enters
        key[1::11] = (1 << 30) - 1  # the largest key a ray that enters can have
        assert np.array_equal(march_cpu.morton_order(key), np.argsort(key, kind="stable"))


def test_the_kernel_s_grids_follow_the_field_s_tables():
    """An Adam step, or any in-place change of a table, is seen by the next render."""
    g = torch.Generator().manual_seed(11)
    model, aabb = blob_model(g)
    model.eval()
    origins, directions = _rays(g, aabb, 600)
    with torch.no_grad():
        before = model.render(origins, directions)
        model.field.features.mul_(-1)  # in place, as Adam's step: the table's version moves
        after = model.render(origins, directions)
        fresh = _compiled(model, origins, directions)
    assert not torch.equal(before.rgb, after.rgb) and torch.equal(after.rgb, fresh[0])
