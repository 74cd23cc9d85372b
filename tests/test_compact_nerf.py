"""The compact NeRF's own maths: packed rendering against the per-ray oracle, the
distortion loss against its O(n^2) definition, and marching that never skips occupied space."""

from __future__ import annotations

import pytest
import torch
from nerfgauge.nerf.marching import march, occupancy_pyramid
from nerfgauge.nerf.packed import packed_distortion, packed_render, packed_weights
from nerfgauge.nerf.reference import render_reference


def ragged_case(seed=0, n_rays=5, max_samples=12, dtype=torch.float64):
    """Rays with different sample counts, as dense padded tensors and as packed ones."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(1, max_samples + 1, (n_rays,), generator=g)
    dense_sigma = torch.rand((n_rays, max_samples), generator=g, dtype=dtype) * 4
    dense_rgb = torch.rand((n_rays, max_samples, 3), generator=g, dtype=dtype)
    steps = torch.rand((n_rays, max_samples), generator=g, dtype=dtype) * 0.3 + 0.05
    edges = torch.cat([torch.rand((n_rays, 1), generator=g, dtype=dtype), steps], 1).cumsum(1)
    keep = torch.arange(max_samples)[None, :] < counts[:, None]
    return counts, dense_sigma, dense_rgb, edges, keep


def test_packed_render_matches_the_reference_loop_on_values_and_gradients():
    counts, sigma, rgb, edges, keep = ragged_case()
    sigma.requires_grad_(True), rgb.requires_grad_(True)
    rays = torch.arange(len(counts))[:, None].expand_as(keep)[keep]
    t_mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    delta = edges[:, 1:] - edges[:, :-1]
    near = edges[:, 0]
    far = torch.stack([edges[r, c] for r, c in enumerate(counts)])
    colour, opacity, depth, _ = packed_render(sigma[keep], rgb[keep], delta[keep], t_mid[keep], rays, near, far)
    loss = colour.sum() + opacity.sum() + 0.1 * depth.sum()
    grads = torch.autograd.grad(loss, (sigma, rgb))
    # The oracle renders each ray's own samples only (padding is not part of the ray).
    ref_loss = 0
    ref_colour, ref_opacity, ref_depth = [], [], []
    for r, c in enumerate(counts.tolist()):
        out = render_reference(sigma[r:r + 1, :c], rgb[r:r + 1, :c], edges[r:r + 1, :c + 1])
        ref_colour.append(out["rgb"]), ref_opacity.append(out["opacity"]), ref_depth.append(out["depth"])
        ref_loss = ref_loss + out["rgb"].sum() + out["opacity"].sum() + 0.1 * out["depth"].sum()
    ref_grads = torch.autograd.grad(ref_loss, (sigma, rgb))
    # float64, at most 12 factors per ray: agreement to ~1e-14; 1e-10 leaves room for the
    # float64 cumulative sum, while any slip in the maths shows at 1e-3.
    torch.testing.assert_close(colour, torch.cat(ref_colour), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(opacity, torch.cat(ref_opacity), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(depth, torch.cat(ref_depth), rtol=1e-10, atol=1e-10)
    for mine, theirs in zip(grads, ref_grads):
        torch.testing.assert_close(mine, theirs, rtol=1e-9, atol=1e-10)


def test_packed_weights_gradcheck():
    counts, sigma, _, edges, keep = ragged_case(seed=3, n_rays=3, max_samples=5)
    rays = torch.arange(len(counts))[:, None].expand_as(keep)[keep]
    delta = (edges[:, 1:] - edges[:, :-1])[keep]
    s = sigma[keep].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: packed_weights(x, delta, rays, len(counts)), (s,))


def test_distortion_equals_its_quadratic_definition():
    counts, sigma, _, edges, keep = ragged_case(seed=1)
    rays = torch.arange(len(counts))[:, None].expand_as(keep)[keep]
    t_mid = (0.5 * (edges[:, 1:] + edges[:, :-1]))[keep]
    delta = (edges[:, 1:] - edges[:, :-1])[keep]
    w = packed_weights(sigma[keep], delta, rays, len(counts))
    fast = packed_distortion(w, t_mid, delta, rays, len(counts))
    for r in range(len(counts)):
        wr, tr, dr = w[rays == r], t_mid[rays == r], delta[rays == r]
        slow = (wr[:, None] * wr[None, :] * (tr[:, None] - tr[None, :]).abs()).sum() + (wr ** 2 * dr).sum() / 3
        torch.testing.assert_close(fast[r], slow, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma_value", [0.0, 1e6, 1e8])
def test_packed_rendering_stays_finite_on_hard_inputs(dtype, sigma_value):
    rays = torch.tensor([0, 0, 0, 1, 1, 2])
    sigma = torch.full((6,), sigma_value, dtype=dtype, requires_grad=True)
    delta = torch.tensor([0.0, 0.1, 1e3, 0.0, 0.2, 0.1], dtype=dtype)
    t_mid = torch.tensor([1.0, 1.1, 1.2, 2.0, 2.1, 3.0], dtype=dtype)
    rgb = torch.rand((6, 3), dtype=dtype)
    near, far = torch.tensor([1.0, 2.0, 3.0, 0.0], dtype=dtype), torch.tensor([2.0, 3.0, 3.5, 0.0], dtype=dtype)
    colour, opacity, depth, w = packed_render(sigma, rgb, delta, t_mid, rays, near, far)
    (colour.sum() + depth.sum()).backward()
    for value in (colour, opacity, depth, w, sigma.grad):
        assert torch.isfinite(value).all()
    eps = torch.finfo(dtype).eps
    assert (w >= 0).all() and (opacity <= 1 + 8 * eps).all()
    assert opacity[3] == 0 and depth[3] == 0  # a ray with no samples renders nothing
    hit = opacity > 0
    assert ((depth[hit] >= near[hit] - eps * 10) & (depth[hit] <= far[hit] + eps * 10)).all()


def dilate(grid):
    return torch.nn.functional.max_pool3d(grid[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0


def test_marching_never_skips_an_occupied_voxel():
    """Dense marching at the same step, kept where the (undilated) voxel is occupied, must
    be a subset of what the hierarchical march returns from the dilated grid."""
    g = torch.Generator().manual_seed(0)
    occupied = torch.rand((20, 24, 28), generator=g) > 0.985  # sparse specks: the hard case
    aabb = torch.tensor([[-1.0, -1.2, -0.8], [1.8, 1.2, 1.2]])
    cell = (aabb[1] - aabb[0]) / torch.tensor([28, 24, 20])
    step = float(cell.max()) / 2
    n = 400
    origins = torch.rand((n, 3), generator=g) * 6 - 3
    targets = aabb[0] + torch.rand((n, 3), generator=g) * (aabb[1] - aabb[0])
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    samples = march(origins, directions, aabb, dilate(occupied), step, levels=occupancy_pyramid(dilate(occupied)))
    from nerfgauge.nerf.rendering import ray_aabb
    near, far, hit = ray_aabb(origins, directions, aabb)
    missed = 0
    for r in torch.nonzero(hit).flatten().tolist():
        t = near[r] + (torch.arange(int((far[r] - near[r]) / step) + 1) + 0.5) * step
        t = t[t < far[r]]
        index = ((origins[r] + t[:, None] * directions[r] - aabb[0]) / cell).floor().long()
        index = torch.minimum(index.clamp_min(0), torch.tensor([27, 23, 19]))
        inside = occupied[index[:, 2], index[:, 1], index[:, 0]]
        mine = samples.t_mid[samples.ray_index == r]
        if inside.any():
            # the same lattice of t, up to float32 rounding of the sums that build it
            gap = (t[inside][:, None] - mine[None, :]).abs().min(dim=1).values if mine.numel() else torch.full((1,), 1.0)
            missed += int((gap > 1e-4).sum())
    assert missed == 0
    assert samples.t_mid.numel() < 0.5 * sum(int((far[r] - near[r]) / step) for r in range(n))  # and it does skip


def test_marching_an_empty_grid_and_rays_that_miss():
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    origins = torch.tensor([[0.5, 0.5, -1.0], [5.0, 5.0, 5.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    empty = march(origins, directions, aabb, torch.zeros((8, 8, 8), dtype=torch.bool), 1 / 16)
    assert empty.t_mid.numel() == 0
    full = march(origins, directions, aabb, torch.ones((8, 8, 8), dtype=torch.bool), 1 / 16)
    assert (full.ray_index == 0).all() and full.t_mid.numel() == 16  # 1 unit at 1/16 steps
    torch.testing.assert_close(full.t_mid, 1.0 + (torch.arange(16) + 0.5) / 16)


def test_transmittance_with_early_stop_equals_the_full_pass_where_rays_still_see():
    """Visibility's front-to-back pass returns every sample whose transmittance is at least
    the threshold, with the full pass's value (exact up to float64 rounding across windows),
    and skips only samples the full pass puts below the threshold."""
    from nerfgauge.nerf.packed import packed_transmittance, packed_transmittance_early_stop

    counts, sigma, _, _, keep = ragged_case(seed=5, n_rays=50, max_samples=70, dtype=torch.float64)
    sigma = sigma * 10
    sigma[::4] = 0.01
    rays = torch.arange(len(counts))[:, None].expand_as(keep)[keep]
    s = sigma[keep]
    step = torch.rand(s.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(6)) * 0.2
    full, _ = packed_transmittance(s, step, rays, len(counts))
    index, early = packed_transmittance_early_stop(lambda i: s[i], rays, step, len(counts), window=4,
                                                   min_transmittance=1e-3)
    assert index.numel() < s.numel()  # it did stop rays
    assert len(set(index.tolist())) == index.numel()
    torch.testing.assert_close(early.double(), full[index], rtol=1e-6, atol=1e-9)
    skipped = torch.ones(s.numel(), dtype=torch.bool)
    skipped[index] = False
    assert (full[skipped] < 1e-3).all()
    assert torch.equal(index[early >= 1e-3].sort().values, (full >= 1e-3).nonzero()[:, 0])


def _packed_case(seed: int, step: float = 0.1):
    """A ragged float64 case laid out as packed samples at a constant `step`: (sigma [n_rays,
    max_samples], rgb, keep mask, each kept sample's ray index and t_mid, near, far, step).
    Index sigma and rgb with `keep` after editing them."""
    counts, sigma, rgb, _, keep = ragged_case(seed=seed, n_rays=40, max_samples=60, dtype=torch.float64)
    rays = torch.arange(len(counts))[:, None].expand_as(keep)[keep]
    t_mid = (torch.arange(keep.shape[1], dtype=torch.float64) * step + 0.05)[None, :].expand_as(keep)[keep]
    near = torch.zeros(len(counts), dtype=torch.float64)
    far = torch.full((len(counts),), keep.shape[1] * step, dtype=torch.float64)
    return sigma, rgb, keep, rays, t_mid, near, far, step


def test_early_termination_leaves_out_at_most_the_remaining_transmittance():
    """Stopping a ray once T < 1e-3 drops only what lies behind: colour and opacity change
    by at most T_stop (colours are in [0, 1]); rays that never get opaque are untouched."""
    from nerfgauge.nerf.packed import packed_render_early_stop

    sigma, rgb, keep, rays, t_mid, near, far, step = _packed_case(seed=4)
    sigma = sigma * 10  # opaque within a few samples on most rays
    sigma[::5] = 0.01  # and some rays that stay nearly transparent
    s, c = sigma[keep], rgb[keep]
    full = packed_render(s, c, torch.full_like(s, step), t_mid, rays, near, far)
    early = packed_render_early_stop(lambda i: (s[i], c[i]), t_mid, rays, step, near, far, window=4,
                                     min_transmittance=1e-3)
    assert early[3] < len(s)  # it did skip samples
    assert (early[0] - full[0]).abs().max() <= 1e-3 + 1e-12
    assert (early[1] - full[1]).abs().max() <= 1e-3 + 1e-12
    transparent = full[1] < 0.5
    torch.testing.assert_close(early[0][transparent], full[0][transparent], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("min_weight", [1e-5, 1e-3])
def test_a_lazy_colour_is_asked_only_where_samples_weigh_and_moves_a_ray_by_at_most_what_it_leaves_out(
        min_weight, monkeypatch):
    """render_front_to_back with colour_at: colour is evaluated only for samples whose
    weight exceeds COLOUR_MIN_WEIGHT; the others' weight times a colour in [0, 1] is left
    out, so each ray's colour differs from the eager render by at most the sum of the
    weights left out, and opacity and depth not at all."""
    from nerfgauge.nerf import packed

    sigma, rgb, keep, rays, t_mid, near, far, step = _packed_case(seed=7)
    sigma[::3] = 0.05  # faint rays, whose samples mostly weigh little
    s, c = sigma[keep], rgb[keep]
    asked = []

    def eager(chosen):
        return rays[chosen], t_mid[chosen], torch.full_like(s[chosen], step), s[chosen], c[chosen]

    def lazy(chosen):
        def colour_at(index):
            asked.append(chosen[index])
            return c[chosen[index]]
        return rays[chosen], t_mid[chosen], torch.full_like(s[chosen], step), s[chosen], colour_at

    monkeypatch.setattr(packed, "COLOUR_MIN_WEIGHT", min_weight)
    full = packed.render_front_to_back(eager, rays, near, far, window=4)
    got = packed.render_front_to_back(lazy, rays, near, far, window=4)
    weights = packed_render(s, c, torch.full_like(s, step), t_mid, rays, near, far)[3]  # [n_samples]
    asked = torch.cat(asked)
    left_out = torch.ones(len(s), dtype=torch.bool)
    left_out[asked] = False
    assert (weights[asked] > min_weight * (1 - 1e-9)).all() and len(asked) < len(s)
    bound = torch.zeros(len(near), dtype=torch.float64).index_add_(0, rays, weights * left_out)
    assert ((got[0] - full[0]).abs().amax(dim=1) <= bound + 1e-12).all()
    assert torch.equal(got[1], full[1]) and torch.equal(got[2], full[2])


def blob_model(g: torch.Generator, step_ratio: float = 0.5):
    """A CompactNeRF on a 24-voxel grid of blobs in empty air, denser towards their cores
    (softplus(raw + shift), shift ~ -9.2), occupancy updated. Returns (model, aabb)."""
    import torch.nn.functional as F
    from nerfgauge.nerf.grid_field import VoxelGridField
    from nerfgauge.nerf.models import CompactNeRF

    aabb = torch.tensor([[-1.0, -0.5, -0.75], [1.0, 0.5, 0.75]])
    field = VoxelGridField(aabb, 24, 24, False)
    grid = field.to_dense().normal_(generator=g)
    blobs = F.avg_pool3d(torch.rand(grid.shape[1:], generator=g)[None, None], 5, stride=1, padding=2)[0, 0]
    grid[0] = torch.where(blobs > 0.50, 6.0 + 200.0 * (blobs - 0.50) + grid[0], -30.0)
    field.load_dense(grid)
    field.step_ratio = step_ratio
    model = CompactNeRF(field)
    model.update_occupancy()
    return model, aabb


@pytest.mark.parametrize("step_ratio", [0.5, 1.0])
def test_inference_cuts_only_the_segments_rays_reach_and_matches_the_full_pass(step_ratio, monkeypatch):
    """Rendering without gradients marches a level above the voxel grid and cuts segments
    into samples only until a ray is opaque: its colour and opacity stay within the early
    stop's min_transmittance (1e-3) of the full pass over every marched sample, and its
    depth within what that missing weight can move it (1e-3 (far - near) / opacity).
    (One 4-voxel segment per window, so this 24-voxel box takes several.)"""
    import nerfgauge.nerf.models as models_module
    monkeypatch.setattr(models_module, "EARLY_STOP_SEGMENTS", 1)
    import torch.nn.functional as F
    from nerfgauge.nerf.rendering import ray_aabb

    g = torch.Generator().manual_seed(3)
    model, aabb = blob_model(g, step_ratio)
    model.eval()
    n = 3000
    origins = torch.randn((n, 3), generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])
    targets = aabb[0] + torch.rand((n, 3), generator=g) * (aabb[1] - aabb[0]) * 1.3 - 0.15 * (aabb[1] - aabb[0])
    directions = F.normalize(targets - origins, dim=-1)
    with torch.no_grad():
        fast = model.render(origins, directions)
    with torch.enable_grad():  # training=False with gradients: the full pass, every sample
        full = model.render(origins, directions)
    near, far, hit = ray_aabb(origins, directions, aabb)
    assert (full.opacity > 0.999).sum() > 100 and ((full.opacity > 0.05) & (full.opacity < 0.9)).sum() > 20
    assert not hit.all() and fast.n_samples < full.n_samples
    assert (fast.rgb - full.rgb.detach()).abs().max() <= 1e-3 + 1e-5
    assert (fast.opacity - full.opacity.detach()).abs().max() <= 1e-3 + 1e-5
    seen = full.opacity.detach() > 0.5
    bound = 1e-3 * (far - near)[seen] / (full.opacity.detach()[seen] - 1e-3) + 1e-4
    assert ((fast.depth - full.depth.detach())[seen].abs() <= bound).all()


def test_training_differentiates_only_what_rays_reach_and_matches_the_full_pass(monkeypatch):
    """Training renders every marched sample's density without gradients, then the full
    differentiable pass only in front of where transmittance falls below
    TRAIN_MIN_TRANSMITTANCE (1e-4). Colour and opacity stay within 1e-4 of the pass over
    every sample (what is dropped weighs T < 1e-4 in all, colours in [0, 1]); the loss
    gradient on the density table moves by at most what the dropped samples carry:
    each a factor T < 1e-4 of its ray, so by at most 1e-4 x samples-per-ray x the full
    gradient's largest entry."""
    import nerfgauge.nerf.models as models_module
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(5)
    model, aabb = blob_model(g)
    field = model.field
    n = 2000
    origins = torch.randn((n, 3), generator=g) * 0.2 + torch.tensor([0.0, 0.0, 3.0])
    targets = aabb[0] + torch.rand((n, 3), generator=g) * (aabb[1] - aabb[0])
    directions = F.normalize(targets - origins, dim=-1)

    def pass_with(threshold):
        monkeypatch.setattr(models_module, "TRAIN_MIN_TRANSMITTANCE", threshold)
        field.density_table.grad = None
        out = model.render(origins, directions, generator=torch.Generator().manual_seed(0), training=True)
        (out.rgb.sum() + out.opacity.sum()).backward()
        return out, field.density_table.grad.clone()

    full, full_grad = pass_with(-1.0)  # every sample
    front, front_grad = pass_with(1e-4)
    assert (full.opacity > 0.9999).sum() > 200  # rays that do turn opaque, so samples are dropped
    assert front.n_samples < 0.8 * full.n_samples
    assert (front.rgb - full.rgb).abs().max() <= 1e-4 + 1e-6
    assert (front.opacity - full.opacity).abs().max() <= 1e-4 + 1e-6
    samples_per_ray = full.n_samples / n
    assert (front_grad - full_grad).abs().max() <= 1e-4 * samples_per_ray * full_grad.abs().max()
    assert torch.isfinite(front.distortion).all()


def test_a_non_finite_field_reaches_the_training_loss():
    """Dropping samples behind surfaces must not hide a NaN: a ray whose field turns NaN
    keeps its samples in the differentiable pass, so the loss is NaN and training stops
    with its one-line error instead of going on with a broken table."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(6)
    model, aabb = blob_model(g)
    with torch.no_grad():
        model.field.density_table[1:] = float("nan")  # every allocated node
    n = 64
    origins = torch.zeros((n, 3)) + torch.tensor([0.0, 0.0, 3.0])
    directions = F.normalize(aabb[0] + torch.rand((n, 3), generator=g) * (aabb[1] - aabb[0]) - origins, dim=-1)
    out = model.render(origins, directions, generator=torch.Generator().manual_seed(0), training=True)
    assert not torch.isfinite(out.rgb).all()
