"""The compact field's sparse storage: lookups equal the dense grid's trilinear
interpolation, storage and optimizer state follow the occupied cells, and masks survive
the saved model."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfgauge.nerf.checkpoint import pack_mask, unpack_mask
from nerfgauge.nerf.grid_field import EMPTY_RAW, SHARPEN_ALPHA, VoxelGridField, node_mask
from nerfgauge.nerf.models import CompactNeRF
from nerfgauge.nerf.train import free_unoccupied

AABB = torch.tensor([[-1.0, -0.5, -0.75], [1.0, 0.5, 0.75]])


def random_field(resolution=12, view_dependent=False, seed=0) -> VoxelGridField:
    field = VoxelGridField(AABB, resolution, resolution, view_dependent)
    field.load_dense(field.to_dense().normal_(generator=torch.Generator().manual_seed(seed)))
    return field


def dense_lookup(field: VoxelGridField, positions: torch.Tensor) -> torch.Tensor:
    """grid_sample on the dense grid (the field before sparse storage): [M, 1 + C]."""
    grid = field.to_dense()[None]
    normalised = 2 * (positions - AABB[0]) / (AABB[1] - AABB[0]) - 1
    values = F.grid_sample(grid, normalised.view(1, 1, 1, -1, 3), mode="bilinear", align_corners=True,
                           padding_mode="border")
    return values.view(grid.shape[1], -1).t()


def test_lookup_equals_dense_trilinear_interpolation_inside_and_beyond_the_box():
    field = random_field()
    generator = torch.Generator().manual_seed(1)
    positions = (torch.rand((4000, 3), generator=generator) * 1.4 - 0.2) * (AABB[1] - AABB[0]) + AABB[0]
    rows, weights = field.corners(positions)
    sparse = torch.cat([field._blend(field.density_table, rows, weights),
                        field._blend(field.features, rows, weights)], dim=1)
    # float32 trilinear of values ~N(0, 1): rounding of a few ulps
    assert torch.allclose(sparse, dense_lookup(field, positions), atol=1e-5)
    assert torch.allclose(weights.sum(dim=1), torch.ones(len(positions)), atol=1e-6)


def test_rendering_without_gradients_reads_the_same_values_and_follows_updates():
    """No-grad calls read a cached dense copy through grid_sample: the same sigma and
    colour as the sparse gather, and a changed table (an Adam step, in place) is seen."""
    field = random_field(10, view_dependent=True)
    generator = torch.Generator().manual_seed(5)
    positions = torch.rand((3000, 3), generator=generator) * (AABB[1] - AABB[0]) + AABB[0]
    directions = F.normalize(torch.randn((3000, 3), generator=generator), dim=-1)
    for _ in range(2):
        with torch.no_grad():
            fast = field(positions, directions)
        slow = [t.detach() for t in field(positions, directions)]
        assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-5) for a, b in zip(fast, slow))
        with torch.no_grad():
            field.density_table.add_(0.5)  # in place, as Adam updates
            field.features.mul_(0.5)
    field.keep_rows(field.index > 0)  # new tables: the copy is rebuilt, not reused
    with torch.no_grad():
        fast = field(positions, directions)
    slow = [t.detach() for t in field(positions, directions)]
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-5) for a, b in zip(fast, slow))


def test_blend_gradients_match_autograd_of_the_gather_and_skip_row_zero():
    field = random_field(6)
    generator = torch.Generator().manual_seed(2)
    positions = (torch.rand((500, 3), generator=generator) * (AABB[1] - AABB[0]) + AABB[0]).requires_grad_()
    rows, weights = field.corners(positions)
    rows = torch.where(torch.arange(rows.numel()).view(rows.shape) % 5 == 0, torch.zeros_like(rows), rows)
    upstream = torch.randn((500, field.channels), generator=generator)
    (field._blend(field.features, rows, weights) * upstream).sum().backward()
    ours_table, ours_positions = field.features.grad.clone(), positions.grad.clone()
    field.features.grad, positions.grad = None, None
    rows_again, weights_again = field.corners(positions)
    reference = (weights_again[:, :, None] * field.features[rows]).sum(dim=1)
    (reference * upstream).sum().backward()
    expected_table = field.features.grad.clone()
    expected_table[0] = 0  # row 0 is every unallocated node: never trained
    assert torch.allclose(ours_table, expected_table, atol=1e-5)
    assert torch.allclose(ours_positions, positions.grad, atol=1e-4)


def test_upsample_allocates_only_the_kept_cells_and_resamples_them():
    field = random_field(8)
    before = [field.to_dense(), field.shape]
    keep = torch.zeros(tuple(n - 1 for n in field.shape), dtype=torch.bool)
    keep[1:3, 2:4, 3:5] = True
    field.upsample(24, keep, sharpen=False)
    allocated = field.index > 0
    assert 0 < int(allocated.sum()) < allocated.numel() / 4
    # every allocated node holds the old field's trilinear value at its position
    nodes = allocated.nonzero()
    last = torch.tensor([field.shape[2] - 1, field.shape[1] - 1, field.shape[0] - 1])
    positions = AABB[0] + nodes.flip(-1).float() / last * (AABB[1] - AABB[0])
    old = VoxelGridField(AABB, 8, 8, False)
    old.load_dense(before[0])
    assert torch.allclose(field.node_values(allocated), dense_lookup(old, positions), atol=1e-5)
    # a corner far from the kept cells has no allocated node around it: empty space
    with torch.no_grad():
        far_corner = field.density(AABB[1:2] - 1e-4)
    assert torch.allclose(far_corner, field.density_from_raw(torch.tensor([EMPTY_RAW])))


def test_upsample_sharpens_density_above_the_anchor_level_only():
    """sharpen_raw: raw values above the level where a step of the finer grid reaches
    opacity SHARPEN_ALPHA are steepened by the resolution ratio about it; values below
    stay; features are resampled as without sharpening."""
    plain, sharp = random_field(8), random_field(8)
    for field in (plain, sharp):  # raw densities spread over empty, faint and solid (the level is ~5)
        dense = field.to_dense()
        dense[0] = dense[0] * 6 + 4
        field.load_dense(dense)
    plain.upsample(12, sharpen=False)
    sharp.upsample(12)
    everything = torch.ones(plain.shape, dtype=torch.bool)
    before, after = plain.node_values(everything), sharp.node_values(everything)
    raw_before, raw_after = before[:, 0], after[:, 0]
    # the anchor level, from its definition: a step of the 12-voxel grid reaches SHARPEN_ALPHA
    step = plain.step_ratio * float((AABB[1] - AABB[0]).max()) / 12
    levels = torch.linspace(-20, 20, 400001)
    alphas = -torch.expm1(-plain.density_from_raw(levels) * step)
    level = float(levels[(alphas - SHARPEN_ALPHA).abs().argmin()])
    below = raw_before < level - 1e-3
    above = raw_before > level + 1e-3
    assert bool(below.any()) and bool(above.any())
    assert torch.equal(raw_after[below], raw_before[below])
    assert torch.allclose(raw_after[above], level + 1.5 * (raw_before[above] - level), atol=2e-3)
    assert torch.equal(after[:, 1:], before[:, 1:])


def test_upsample_sharpens_in_bounded_space_only():
    """In a contracted or forward grid (field.space set) coarse to fine resamples plainly:
    sharpening was measured to cost there (nerf.grid_field.SHARPEN_ALPHA)."""
    from types import SimpleNamespace

    plain, unbounded = random_field(8), random_field(8)
    for field in (plain, unbounded):
        dense = field.to_dense()
        dense[0] = dense[0] * 6 + 4
        field.load_dense(dense)
    unbounded.space = SimpleNamespace(kind="forward")  # only its presence matters to upsample
    plain.upsample(12, sharpen=False)
    unbounded.upsample(12)
    everything = torch.ones(plain.shape, dtype=torch.bool)
    assert torch.equal(unbounded.node_values(everything), plain.node_values(everything))


def test_keep_rows_frees_nodes_and_keeps_values():
    field = random_field(10)
    keep = torch.zeros(field.shape, dtype=torch.bool)
    keep[2:6, 3:7, 1:5] = True
    values = field.node_values(keep)
    rows = field.keep_rows(keep)
    assert field.allocated == int(keep.sum()) and rows.shape == (field.allocated + 1,)
    assert torch.equal(field.node_values(keep), values)
    assert bool((field.index[~keep] == 0).all())


def test_free_unoccupied_moves_adam_moments_with_their_rows():
    field = random_field(10)
    model = CompactNeRF(field)
    optimizer = torch.optim.Adam([{"params": field.grid_parameters(), "lr": 0.1}])
    positions = torch.rand((2000, 3), generator=torch.Generator().manual_seed(4)) * (AABB[1] - AABB[0]) + AABB[0]
    sigma, rgb = field(positions, F.normalize(torch.ones_like(positions), dim=-1))
    (sigma.sum() + rgb.sum()).backward()
    optimizer.step()
    occupancy = torch.zeros(tuple(n - 1 for n in field.shape), dtype=torch.bool)
    occupancy[2:5, 1:4, 3:8] = True
    model.occupancy = occupancy
    keep = node_mask(occupancy) & (field.index > 0)
    moment_before = optimizer.state[field.density_table]["exp_avg"][field.index[keep].long()].clone()
    free_unoccupied(model, optimizer)
    assert field.allocated == int(keep.sum())
    assert optimizer.param_groups[0]["params"][0] is field.density_table
    state = optimizer.state[field.density_table]
    assert torch.equal(state["exp_avg"][field.index[keep].long()], moment_before)
    assert state["exp_avg"].shape == field.density_table.shape


@settings(max_examples=60, deadline=None)
@given(st.tuples(*[st.integers(1, 7)] * 3), st.integers(0, 2), st.integers(0, 2), st.integers(0, 2**31 - 1))
def test_any_within_is_a_box_max_and_node_mask_is_its_transpose(shape, low, high, seed):
    """The separable boolean box max equals max_pool3d over the same window (out of range
    counting as empty); a cell touches a set node exactly when the node is a corner of it."""
    from nerfgauge.nerf.grid_field import any_within, cells_touching

    mask = torch.rand(shape, generator=torch.Generator().manual_seed(seed)) < 0.2
    padded = F.pad(mask[None, None].float(), (low, high) * 3)  # window i - low .. i + high
    expected = F.max_pool3d(padded, low + high + 1, stride=1)[0, 0] > 0
    assert torch.equal(any_within(mask, low, high), expected)
    if min(shape) > 1:
        cells = mask[:-1, :-1, :-1]
        corners = F.max_pool3d(mask[None, None].float(), 2, stride=1)[0, 0] > 0
        assert torch.equal(cells_touching(mask), corners)
        nodes = node_mask(cells)
        touched = F.max_pool3d(F.pad(cells[None, None].float(), (1, 1) * 3), 2, stride=1)[0, 0] > 0
        assert torch.equal(nodes, touched)


def two_walls_model(resolution=16) -> CompactNeRF:
    """A unit box with two opaque slabs, 0.25 <= z < 0.35 and 0.7 <= z < 0.8; empty elsewhere."""
    field = VoxelGridField(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), resolution, resolution, False)
    grid = field.to_dense()
    z = torch.linspace(0, 1, field.shape[0])
    grid[0] = EMPTY_RAW
    grid[0, ((z >= 0.25) & (z < 0.35)) | ((z >= 0.7) & (z < 0.8))] = 10.0
    field.load_dense(grid)
    model = CompactNeRF(field)
    model.update_occupancy()
    return model


def test_visibility_hides_what_an_opaque_wall_covers_and_blocks_only_loosen_it():
    """Rays from z < 0 looking along +z see the front wall's near face; the back wall is
    hidden (empty cells are never marched, so visibility is about occupied ones). Measured
    per block of 2^3 cells, the visible set contains the per-cell one and still hides the
    back wall."""
    generator = torch.Generator().manual_seed(0)
    n = 4000
    origins = torch.cat([torch.rand(n, 2, generator=generator), torch.full((n, 1), -0.5)], dim=1)
    directions = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3).contiguous()
    per_cell = two_walls_model()
    occupied = per_cell.occupancy.clone()
    cells_z = (torch.arange(occupied.shape[0]) + 0.5) / occupied.shape[0]  # cell centres
    front = occupied.any(dim=(1, 2)).nonzero()[0, 0]  # first occupied layer
    per_cell.measure_visibility(origins, directions)
    assert per_cell.visible[front].all() and per_cell.occupancy[front].all()
    back = cells_z > 0.6
    assert occupied[back].any() and not per_cell.visible[back].any() and not per_cell.occupancy[back].any()
    blocked = two_walls_model()
    blocked.measure_visibility(origins, directions, block=2)
    assert (blocked.visible | ~per_cell.visible).all()  # per-cell visible => block visible
    assert blocked.visible.sum() > per_cell.visible.sum()
    assert not blocked.occupancy[back].any()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 9), min_size=1, max_size=4), st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_packed_masks_round_trip(shape, density, seed):
    generator = torch.Generator().manual_seed(seed)
    mask = torch.rand(shape, generator=generator) < density
    packed = pack_mask(mask)
    assert torch.equal(unpack_mask(packed, shape), mask)


def test_damaged_packed_masks_are_refused():
    packed = pack_mask(torch.ones((4, 5, 6), dtype=torch.bool))
    with pytest.raises(ValueError):
        unpack_mask(packed, (4, 5, 7))
    with pytest.raises(ValueError):
        unpack_mask({"shape": [4, 5, 6], "bits": torch.tensor([1, 2, 3], dtype=torch.uint8)}, (4, 5, 6))
    short = pack_mask(torch.ones((4, 5, 5), dtype=torch.bool))
    with pytest.raises(ValueError):
        unpack_mask({"shape": [4, 5, 6], "bits": short["bits"]}, (4, 5, 6))


@pytest.mark.slow
def test_training_at_256_px_stores_a_fraction_of_the_dense_grid(tmp_path):
    """A 256 px run: the final grid allocates a minority of its nodes (a dense grid
    allocates all of them; primitives fill a small part of their box, and a 320-step run's
    remaining low-density fog keeps about 0.4 with 6 views of 1024 rays a step, about a
    third with 12 of 4096), and the saved model renders finite images. The pixel footprint
    at 256 px sets the 218-voxel final grid; 320 steps are the fewest that reach it (three
    growths, each after MIN_STAGE_STEPS = 100 steps)."""
    from nerfgauge.api import generate_dataset, train
    from nerfgauge.nerf.checkpoint import load_model

    dataset = tmp_path / "d"
    generate_dataset("primitives", dataset, width=256, height=256, views=6, test_views=1, val_views=0, spp=1)
    run = tmp_path / "run"
    train(dataset, run, steps=320, batch_rays=1024, eval_views=1, eval_rays=1024)
    model, config = load_model(run / "model.pt")
    nodes = math.prod(model.field.shape)
    assert config.final_resolution >= 128
    assert model.field.allocated < 0.5 * nodes
    with torch.no_grad():
        out = model.render(torch.tensor([[0.0, -4.0, 0.5]]), F.normalize(torch.tensor([[0.0, 1.0, -0.1]]), dim=-1))
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()


def test_visibility_sampling_keeps_its_ray_and_sample_budgets():
    """Small captures use every 4th ray per cell; past 409,600 rays or 16 x that many
    marched samples the stride grows (odd) and blocks grow so that block^2 ~ stride / 4."""
    from nerfgauge.nerf.train import VISIBILITY_RAYS, VISIBILITY_SAMPLES, visibility_sampling

    assert visibility_sampling(100 * 128 * 128, 12.0) == (4, 1)
    for n_rays, samples in [(100 * 256 * 256, 20.0), (100 * 128 * 128, 126.0), (100 * 512 * 512, 8.0)]:
        stride, block = visibility_sampling(n_rays, samples)
        assert stride % 2 == 1 and stride > 4
        assert -(-n_rays // stride) <= VISIBILITY_RAYS
        assert -(-n_rays // stride) * samples <= VISIBILITY_SAMPLES * 1.01
        assert block == max(1, round(math.sqrt(stride / 4)))


def sparse_random_field(seed: int) -> tuple[VoxelGridField, torch.Tensor]:
    """A 14-voxel random field with a random half of its nodes freed. Returns (field, the
    kept node mask [nz, ny, nx])."""
    field = random_field(14, seed=seed)
    keep = torch.rand(field.shape, generator=torch.Generator().manual_seed(seed + 1)) < 0.5
    field.keep_rows(keep)
    return field, keep


def exact_total_variation(raw: torch.Tensor, keep: torch.Tensor) -> float:
    """Sum over the axes of the mean squared difference of neighbouring kept nodes'
    values raw [C, nz, ny, nx] (over the pairs and the channels), by plain slicing of the
    dense grid; raw [nz, ny, nx] is one channel."""
    raw = raw[None] if raw.dim() == 3 else raw
    total = 0.0
    for dim in range(3):
        n = raw.shape[dim + 1]
        both = keep.narrow(dim, 1, n - 1) & keep.narrow(dim, 0, n - 1)
        difference = raw.narrow(dim + 1, 1, n - 1) - raw.narrow(dim + 1, 0, n - 1)
        total += float((difference[:, both] ** 2).mean())
    return total


@pytest.mark.parametrize("seed", [0, 1])
def test_total_variation_is_the_mean_over_allocated_neighbour_pairs(seed):
    """`--tv-weight`'s prior: along each axis the mean squared difference of raw density
    over the neighbour pairs whose nodes are both allocated (freed nodes read EMPTY_RAW
    and must not count), summed over the axes; and its gradient never reaches row 0."""
    field, keep = sparse_random_field(seed)
    exact = exact_total_variation(field.to_dense()[0], keep)
    total = field.total_variation()
    assert float(total.detach()) == pytest.approx(exact, rel=1e-5)
    total.backward()
    assert field.density_table.grad[0] == 0 and int((field.density_table.grad != 0).sum()) > 100


@pytest.mark.parametrize("seed", [0, 1])
def test_total_variation_of_the_colour_features_is_the_mean_over_pairs_and_channels(seed):
    """The sparse-capture priors' colour smoothness (nerf.sparse_priors): the same rule on
    the feature channels; its gradient reaches the features only, never row 0."""
    field, keep = sparse_random_field(seed)
    with torch.no_grad():
        field.features.normal_(generator=torch.Generator().manual_seed(seed))
    exact = exact_total_variation(field.to_dense()[1:], keep)
    total = field.total_variation("features")
    assert float(total.detach()) == pytest.approx(exact, rel=1e-5)
    total.backward()
    assert field.density_table.grad is None and bool((field.features.grad[0] == 0).all())
    assert int((field.features.grad != 0).sum()) > 100
