"""Volume rendering: the vectorised functions against the per-ray oracle, analytic cases, hard inputs.

Tolerances sit with each case. Comparisons with the oracle run in float64: the renderer
computes T_i = exp(-sum tau) and the oracle prod(1 - alpha); for S <= 32 samples each
formula carries at most ~S roundings of 1.1e-16, so agreement to 1e-10 leaves three orders
of margin while any slip in the maths (an off-by-one in the exclusive sum, delta or
midpoint) shows up at 1e-2 or larger.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from nerfgauge.nerf import rendering as R
from nerfgauge.nerf.reference import render_reference

RTOL64, ATOL64 = 1e-10, 1e-12
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)


def random_case(n_rays=6, n_samples=16, seed=0, dtype=torch.float64, sigma_scale=3.0):
    """Densities, colours and sorted perturbed edges on [near, far] from one seeded generator."""
    g = torch.Generator().manual_seed(seed)
    near = torch.rand(n_rays, generator=g, dtype=dtype)
    far = near + 0.5 + 2.0 * torch.rand(n_rays, generator=g, dtype=dtype)
    edges = R.stratified_edges(near, far, n_samples, perturb=True, generator=g)
    sigmas = sigma_scale * torch.rand(n_rays, n_samples, generator=g, dtype=dtype)
    sigmas[0] = 0.0  # one empty ray: opacity 0, depth 0
    rgbs = torch.rand(n_rays, n_samples, 3, generator=g, dtype=dtype)
    background = torch.rand(n_rays, 3, generator=g, dtype=dtype)
    return sigmas, rgbs, edges, background


def vectorised(sigmas, rgbs, edges, background=None):
    """The renderer's pure functions composed exactly as render_along_edges composes them."""
    weights, _, _ = R.weights_from_density(sigmas, R.deltas(edges))
    opacity = R.accumulate_along_rays(weights)
    rgb = R.accumulate_along_rays(weights, rgbs)
    depth = R.expected_depth(weights, R.midpoints(edges), opacity, edges[:, 0], edges[:, -1])
    if background is not None:
        rgb = R.composite(rgb, opacity, background)
    return {"rgb": rgb, "opacity": opacity, "depth": depth, "weights": weights}


# --------------------------------------------------------------------------------------
# oracle


@pytest.mark.parametrize("background_kind", ["none", "single", "per_ray"])
def test_matches_reference_loop_on_values(background_kind):
    sigmas, rgbs, edges, per_ray = random_case()
    background = {"none": None, "single": torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64),
                  "per_ray": per_ray}[background_kind]
    ours = vectorised(sigmas, rgbs, edges, background)
    oracle = render_reference(sigmas, rgbs, edges, background)
    for key in ("rgb", "opacity", "depth", "weights"):
        torch.testing.assert_close(ours[key], oracle[key], rtol=RTOL64, atol=ATOL64, msg=key)
    assert oracle["opacity"][0] == 0 and ours["depth"][0] == 0  # the empty ray
    assert (ours["opacity"][1:] > 0.5).all()  # the others are not trivially empty


def test_matches_reference_loop_on_gradients():
    sigmas, rgbs, edges, background = random_case(seed=1)
    g = torch.Generator().manual_seed(11)
    cot_rgb = torch.randn(sigmas.shape[0], 3, generator=g, dtype=torch.float64)
    cot_ray = torch.randn(2, sigmas.shape[0], generator=g, dtype=torch.float64)
    grads = []
    for render in (vectorised, render_reference):
        s, c = sigmas.clone().requires_grad_(), rgbs.clone().requires_grad_()
        out = render(s, c, edges, background)
        loss = (out["rgb"] * cot_rgb).sum() + (out["opacity"] * cot_ray[0]).sum() + (out["depth"] * cot_ray[1]).sum()
        grads.append(torch.autograd.grad(loss, (s, c)))
    (ours_s, ours_c), (ref_s, ref_c) = grads
    assert ours_s.abs().max() > 1e-3  # gradients are not trivially zero
    torch.testing.assert_close(ours_s, ref_s, rtol=RTOL64, atol=ATOL64)
    torch.testing.assert_close(ours_c, ref_c, rtol=RTOL64, atol=ATOL64)


def test_render_rays_matches_reference_with_an_analytic_field():
    # A density blob and position-dependent colour; the oracle gets the field sampled at
    # the midpoints computed by hand from o + t d, so positions and directions are checked too.
    def field(positions, directions):
        sigma = 4.0 * torch.exp(-(positions ** 2).sum(-1) / 0.3)
        rgb = torch.sigmoid(positions + 0.5 * directions)
        return sigma, rgb

    g = torch.Generator().manual_seed(3)
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.2, -0.1, -3.0], [3.0, 0.3, 0.1]], dtype=torch.float64)
    directions = torch.nn.functional.normalize(-origins + 0.1 * torch.rand(3, 3, generator=g, dtype=torch.float64), dim=-1)
    near, far, hit = R.ray_aabb(origins, directions, BOX)
    assert hit.all()
    out = R.render_rays(field, origins, directions, near, far, 24, perturb=True,
                        generator=torch.Generator().manual_seed(5), background=torch.ones(3, dtype=torch.float64))
    edges = out.t_edges
    t_mid = (edges[:, 1:] + edges[:, :-1]) / 2
    positions = origins[:, None] + t_mid[..., None] * directions[:, None]
    sigmas, rgbs = field(positions, directions[:, None].expand_as(positions))
    oracle = render_reference(sigmas, rgbs, edges, torch.ones(3, dtype=torch.float64))
    for key in ("rgb", "opacity", "depth", "weights"):
        torch.testing.assert_close(getattr(out, key), oracle[key], rtol=RTOL64, atol=ATOL64, msg=key)


# --------------------------------------------------------------------------------------
# gradcheck (float64, central differences; sigmas kept >= 0.1 so the +-1e-6 probes stay >= 0)


def test_gradcheck_weights_from_density():
    g = torch.Generator().manual_seed(0)
    sigmas = (0.1 + 3 * torch.rand(3, 8, generator=g, dtype=torch.float64)).requires_grad_()
    deltas = (0.05 + 0.3 * torch.rand(3, 8, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda s, d: R.weights_from_density(s, d), (sigmas, deltas))


def test_gradcheck_accumulation_depth_and_compositing():
    sigmas, rgbs, edges, background = random_case(n_rays=3, n_samples=8, seed=2)
    sigmas = (sigmas + 0.1).requires_grad_()
    rgbs = rgbs.requires_grad_()
    background = background.requires_grad_()

    def render(s, c, b):
        out = vectorised(s, c, edges, b)
        return out["rgb"], out["opacity"], out["depth"]

    assert torch.autograd.gradcheck(render, (sigmas, rgbs, background))


# --------------------------------------------------------------------------------------
# analytic cases


@pytest.mark.parametrize("perturb", [False, True])
@pytest.mark.parametrize("n_importance", [0, 16])
def test_constant_density_gives_exact_opacity(perturb, n_importance):
    # Piecewise-constant quadrature is exact for constant density: the exclusive sums
    # telescope to sigma * (far - near) whatever the bins, so only rounding remains (1e-12).
    sigma = 1.7
    field = lambda p, d: (torch.full(p.shape[:-1], sigma, dtype=p.dtype), torch.full_like(p, 0.25))
    origins = torch.zeros(4, 3, dtype=torch.float64)
    directions = torch.tensor([[0, 0, 1.0]] * 4, dtype=torch.float64)
    near = torch.tensor([0.0, 0.5, 1.0, 2.0], dtype=torch.float64)
    far = torch.tensor([0.1, 1.0, 3.0, 2.0], dtype=torch.float64)  # the last ray has near == far
    out = R.render_rays(field, origins, directions, near, far, 8, n_importance=n_importance, perturb=perturb,
                        generator=torch.Generator().manual_seed(0))
    expected = 1 - torch.exp(-sigma * (far - near))
    torch.testing.assert_close(out.opacity, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.rgb, 0.25 * expected[:, None].expand(4, 3), rtol=0, atol=1e-12)
    assert out.depth[3] == 0 and torch.isfinite(out.weights).all()


def test_thin_opaque_slab_depth_within_half_a_bin():
    # Slab |z - z_s| <= bin/2 (one bin thick along t, since d_z = 1); exactly the one
    # midpoint inside it takes all the weight, so depth is within half a bin of the slab.
    n_samples, near, far, z_slab = 40, 0.0, 4.0, 1.0
    bin_width = (far - near) / n_samples
    field = lambda p, d: (1e4 * ((p[..., 2] - z_slab).abs() <= bin_width / 2).to(p.dtype), torch.ones_like(p))
    # Slab at t = 1 - o_z; t mod bin stays >= 0.013 away from the midpoints' half-bin grid.
    offsets = -(0.013 + torch.arange(13, dtype=torch.float64) / 6)
    origins = torch.stack([0.3 * offsets, -0.2 * offsets, offsets], dim=-1)
    directions = torch.stack([torch.full_like(offsets, 0.3), torch.full_like(offsets, -0.5), torch.ones_like(offsets)], -1)
    out = R.render_rays(field, origins, directions, near, far, n_samples)
    t_slab = z_slab - offsets
    torch.testing.assert_close(out.opacity, torch.ones_like(out.opacity), rtol=0, atol=1e-12)
    assert ((out.depth - t_slab).abs() <= bin_width / 2 + 1e-12).all(), (out.depth - t_slab)


# --------------------------------------------------------------------------------------
# ray / box


def test_ray_aabb_hand_computed():
    cases = [  # origin, direction, (t_near, t_far) or None for a miss
        ((0, 0, -5), (0, 0, 1), (4, 6)),
        ((0, 0, 5), (0, 0, -1), (4, 6)),
        ((-5, -5, -5), (1, 1, 1), (4, 6)),
        ((0, 0, 0), (1, 0, 0), (0, 1)),  # inside: t_near clamped to 0
        ((-5, 0.5, 0), (2, 0, 0), (2, 3)),  # unnormalised: t in units of |d|
        ((1, 0, -5), (0, 0, 1), (4, 6)),  # parallel to the x = 1 face, in it
        ((0.5, -0.5, -5), (0, 0, 1), (4, 6)),  # parallel to two faces, inside both slabs
        ((2, 0, -5), (0, 0, 1), None),  # parallel, outside the x slab
        ((0, 0, 5), (0, 0, 1), None),  # box behind the origin
        ((-3, -1, 0), (1, 1, 0), None),  # touches only the edge at (-1, 1, z): zero length
        ((-3, 0, 0), (1, 0.1, 0), (2, 4)),
    ]
    origins = torch.tensor([c[0] for c in cases], dtype=torch.float64)
    directions = torch.tensor([c[1] for c in cases], dtype=torch.float64)
    t_near, t_far, hit = R.ray_aabb(origins, directions, BOX)
    for i, (_, _, expected) in enumerate(cases):
        if expected is None:
            assert not hit[i] and t_near[i] == 0 and t_far[i] == 0, i
        else:
            assert hit[i], i
            torch.testing.assert_close(torch.stack([t_near[i], t_far[i]]),
                                       torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-12)


def test_ray_aabb_tiny_direction_components_float32():
    # 1e-40 is subnormal in float32: its slab bounds overflow to -inf (miss) or +-inf (inside).
    origins = torch.tensor([[0.0, 2.0, -5.0], [0.0, 0.5, -5.0]])
    directions = torch.tensor([[0.0, 1e-40, 1.0], [1e-40, 0.0, 1.0]])
    t_near, t_far, hit = R.ray_aabb(origins, directions, BOX.float())
    assert hit.tolist() == [False, True]
    assert t_near.tolist() == [0.0, 4.0] and t_far.tolist() == [0.0, 6.0]


def test_ray_aabb_non_cube_box_and_float32():
    box = torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 4.0]])
    t_near, t_far, hit = R.ray_aabb(torch.tensor([[1.0, 0.5, -1.0]]), torch.tensor([[0.0, 0.0, 2.0]]), box)
    assert hit.item() and t_near.item() == pytest.approx(0.5) and t_far.item() == pytest.approx(2.5)
    assert t_near.dtype == torch.float32


def test_input_checks_name_what_was_received():
    with pytest.raises(ValueError, match=r"\(4, 2\)"):
        R.ray_aabb(torch.zeros(4, 2), torch.ones(4, 2), BOX)
    with pytest.raises(ValueError, match="directions must have length >= 1e-06 .* got length 0.0"):
        R.ray_aabb(torch.zeros(2, 3, dtype=torch.float64), torch.tensor([[0, 0, 1.0], [0, 0, 0]], dtype=torch.float64), BOX)
    with pytest.raises(ValueError, match=r"\(3, 5\)"):
        R.weights_from_density(torch.ones(3, 4), torch.ones(3, 5))
    with pytest.raises(ValueError, match="sigmas must be >= 0"):
        R.weights_from_density(-torch.ones(2, 2), torch.ones(2, 2))
    with pytest.raises(ValueError, match=r"\(4,\)"):
        R.composite(torch.ones(2, 3), torch.ones(2), torch.ones(4))
    with pytest.raises(ValueError, match="far must be >= near"):
        R.stratified_edges(torch.ones(2), torch.zeros(2), 4)
    bad_field = lambda p, d: (torch.ones(p.shape[:-1] + (1,)), torch.ones_like(p))
    with pytest.raises(ValueError, match=r"field_fn's sigma .* got shape \(2, 4, 1\)"):
        R.render_rays(bad_field, torch.zeros(2, 3), torch.ones(2, 3), 0.0, 1.0, 4)


# --------------------------------------------------------------------------------------
# sampling


def test_stratified_edges_deterministic_and_stratified():
    near, far = torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 3.0, 2.0])
    edges = R.stratified_edges(near, far, 4)
    expected_mid = near[:, None] + (far - near)[:, None] * (torch.arange(4) + 0.5) / 4
    torch.testing.assert_close(R.midpoints(edges), expected_mid)
    perturbed = R.stratified_edges(near, far, 4, perturb=True, generator=torch.Generator().manual_seed(7))
    again = R.stratified_edges(near, far, 4, perturb=True, generator=torch.Generator().manual_seed(7))
    assert torch.equal(perturbed, again) and not torch.equal(perturbed[:2], edges[:2])
    assert (perturbed[:, 0] == near).all() and (perturbed[:, -1] == far).all()
    assert (R.deltas(perturbed) >= 0).all()
    stratum = ((R.midpoints(perturbed) - near[:, None]) / (far - near).clamp_min(1e-9)[:, None] * 4)[:2]
    assert ((stratum >= torch.arange(4)) & (stratum <= torch.arange(4) + 1)).all()
    assert (R.deltas(perturbed)[2] == 0).all()  # near == far: finite zero-length intervals
    # Interior edge k is uniform on [k - 1/2, k + 1/2] bins: over 500 rays it reaches both ends.
    many = R.stratified_edges(torch.zeros(500), torch.full((500,), 8.0), 8, perturb=True,
                              generator=torch.Generator().manual_seed(8))
    offset = many[:, 1:-1] - torch.arange(1.0, 8.0)
    assert offset.min() < -0.45 and offset.max() > 0.45 and offset.abs().max() <= 0.5


def test_importance_sampling_all_zero_weights_falls_back_to_uniform():
    near, far = torch.tensor([0.0, 1.0]), torch.tensor([2.0, 1.0])  # the second has near == far
    edges = R.stratified_edges(near, far, 8)
    t = R.importance_samples(edges, torch.zeros(2, 8), 4)
    torch.testing.assert_close(t[0], torch.tensor([0.25, 0.75, 1.25, 1.75]))
    assert (t[1] == 1.0).all()
    t = R.importance_samples(edges, torch.zeros(2, 8), 5, perturb=True, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(t).all() and (t[1] == 1.0).all()


def test_importance_sampling_follows_the_weights():
    edges = R.stratified_edges(torch.zeros(1), torch.full((1,), 8.0), 8)  # bins [k, k + 1]
    weights = torch.zeros(1, 8, requires_grad=True)
    with torch.no_grad():
        weights[0, 5] = 0.9
        weights[0, 2] = 0.3
    t = R.importance_samples(edges, weights, 400, perturb=True, generator=torch.Generator().manual_seed(1))
    assert not t.requires_grad  # no_grad: sampling is not differentiable
    assert (t[:, 1:] >= t[:, :-1]).all()
    in_bin = lambda k: ((t >= k) & (t <= k + 1)).sum().item()
    assert in_bin(5) == 300 and in_bin(2) == 100  # stratified u: the counts are exact


def test_sample_mask_skips_the_field_and_matches_dense():
    calls = []

    def field(positions, directions):
        calls.append(positions.shape[:-1].numel())
        inside = (positions.norm(dim=-1) < 0.8).to(positions.dtype)
        return 3.0 * inside, torch.sigmoid(positions)

    origins = torch.tensor([[0.0, 0.0, -2.0], [0.5, 0.0, -2.0], [1.5, 0.0, -2.0]], dtype=torch.float64)
    directions = torch.tensor([[0, 0, 1.0]] * 3, dtype=torch.float64)
    dense = R.render_rays(field, origins, directions, 0.0, 4.0, 32)
    t_mid = R.midpoints(dense.t_edges)
    mask = (origins[:, None] + t_mid[..., None] * directions[:, None]).norm(dim=-1) < 0.8  # "occupancy grid"
    calls.clear()
    masked = R.render_rays(field, origins, directions, 0.0, 4.0, 32, sample_mask=mask)
    assert calls == [int(mask.sum())] and 0 < calls[0] < 3 * 32
    for key in ("rgb", "opacity", "depth", "weights"):
        torch.testing.assert_close(getattr(masked, key), getattr(dense, key), rtol=RTOL64, atol=ATOL64)


def test_coarse_and_fine_passes():
    coarse_field = lambda p, d: (2.0 * (p[..., 2].abs() < 0.3).to(p.dtype), torch.zeros_like(p))
    fine_field = lambda p, d: (2.0 * (p[..., 2].abs() < 0.3).to(p.dtype), torch.ones_like(p))
    origins = torch.tensor([[0.0, 0.0, -2.0]] * 2, dtype=torch.float64)
    directions = torch.tensor([[0, 0, 1.0]] * 2, dtype=torch.float64)
    out = R.render_rays(coarse_field, origins, directions, 0.0, 4.0, 16, n_importance=32, fine_field_fn=fine_field,
                        background=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert out.weights.shape == (2, 48) and out.coarse.weights.shape == (2, 16)
    # The fine pass put most of its samples in the slab: t in [1.7, 2.3].
    t_mid = R.midpoints(out.t_edges)
    assert ((t_mid > 1.7) & (t_mid < 2.3)).sum(-1).min() >= 30
    opacity = out.opacity[:, None]
    torch.testing.assert_close(out.rgb, torch.cat([opacity, opacity, torch.ones_like(opacity)], -1))  # fine field: white
    torch.testing.assert_close(out.coarse.rgb[:, :2], torch.zeros(2, 2, dtype=torch.float64))  # coarse: black
    with pytest.raises(ValueError, match="sample_mask cannot be combined"):
        R.render_rays(coarse_field, origins, directions, 0.0, 4.0, 16, n_importance=8,
                      sample_mask=torch.ones(2, 16, dtype=torch.bool))


# --------------------------------------------------------------------------------------
# hard inputs are finite


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [1e6, 1e8])
def test_huge_density_and_zero_delta_are_finite(dtype, sigma):
    sigmas = torch.tensor([[sigma, sigma, 0.0, sigma], [0.0, sigma, sigma, 1.0], [sigma] * 4], dtype=dtype)
    deltas = torch.tensor([[0.0, 1e3, 0.5, 0.0], [0.1, 0.0, 1e-3, 0.2], [1e3, 1e3, 1e3, 1e3]], dtype=dtype)
    edges = torch.cat([torch.zeros(3, 1, dtype=dtype), torch.cumsum(deltas, -1)], -1)
    sigmas.requires_grad_()
    rgbs = torch.rand(3, 4, 3, generator=torch.Generator().manual_seed(0), dtype=dtype).requires_grad_()
    out = vectorised(sigmas, rgbs, edges, torch.ones(3, dtype=dtype))
    loss = sum(v.sum() for v in out.values())
    grad_s, grad_c = torch.autograd.grad(loss, (sigmas, rgbs))
    for tensor in (*out.values(), grad_s, grad_c):
        assert torch.isfinite(tensor).all()
    # The first opaque interval of positive length takes all the weight.
    assert out["weights"][0, 1] == 1 and out["weights"][2, 0] == 1
    assert out["weights"][1, 2].item() == pytest.approx(1.0, abs=1e-6)  # tau = 1e3 or 1e5: alpha = 1


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_infinite_density_from_an_overflowed_activation_is_finite(dtype):
    # sigma = inf on a zero-length interval would be inf * 0 = nan without the delta > 0 test.
    # (The gradient is checked w.r.t. sigma: exp's own backward at inf is inf * 0, which is
    # why fields use a truncated exp or softplus; that is the field's business, not ours.)
    sigmas = torch.exp(torch.tensor([[10.0, 1e3, 1e3, 0.0]], dtype=dtype)).requires_grad_()  # inf for 1e3
    deltas = torch.tensor([[0.1, 0.0, 0.2, 0.3]], dtype=dtype)
    weights, transmittance, alphas = R.weights_from_density(sigmas, deltas)
    assert torch.isinf(sigmas).any()
    for tensor in (weights, transmittance, alphas):
        assert torch.isfinite(tensor).all()
    assert weights[0, 1] == 0 and weights[0, 3] == 0  # zero length, then fully occluded
    assert weights[0, 0].item() == pytest.approx(1 - math.exp(-math.exp(10.0) * 0.1), abs=1e-6)
    (grad,) = torch.autograd.grad((weights * torch.arange(1.0, 5.0, dtype=dtype)).sum(), sigmas)
    assert torch.isfinite(grad).all()
    with pytest.raises(ValueError, match="nan present: True"):
        R.weights_from_density(torch.tensor([[float("nan")]]), torch.ones(1, 1))


def test_nearly_empty_ray_depth_stays_in_near_far():
    # Opacity 1e-12 < DEPTH_EPS: sum(w t) / eps = 0.06 would lie far before near = 5.
    edges = torch.tensor([[5.0, 5.5, 6.0]], dtype=torch.float64)
    out = vectorised(torch.full((1, 2), 1e-12, dtype=torch.float64), torch.ones(1, 2, 3, dtype=torch.float64), edges)
    assert 0 < out["opacity"].item() < R.DEPTH_EPS
    assert 5.0 <= out["depth"].item() <= 6.0


def test_rays_missing_the_box_render_background():
    field = lambda p, d: (torch.full(p.shape[:-1], 5.0, dtype=p.dtype), torch.zeros_like(p))
    origins = torch.tensor([[2.0, 0.0, -5.0], [0.0, 0.0, -5.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    near, far, hit = R.ray_aabb(origins, directions, BOX.float())
    out = R.render_rays(field, origins, directions, near, far, 8, n_importance=8, background=torch.ones(3))
    assert hit.tolist() == [False, True]
    assert out.opacity[0] == 0 and out.depth[0] == 0 and (out.rgb[0] == 1).all()
    assert torch.isfinite(out.t_edges).all() and torch.isfinite(out.weights).all()


# --------------------------------------------------------------------------------------
# properties

DTYPES = st.sampled_from([torch.float32, torch.float64])
N_SAMPLES = 8


@st.composite
def density_case(draw):
    dtype = draw(DTYPES)
    n_rays = draw(st.integers(1, 3))
    sigma = st.one_of(st.just(0.0), st.just(1e8), st.floats(0.0, 1e8, allow_nan=False), st.floats(0.0, 1e-9))
    delta = st.one_of(st.just(0.0), st.just(1e3), st.floats(0.0, 1e3, allow_nan=False))
    sigmas = draw(st.lists(sigma, min_size=n_rays * N_SAMPLES, max_size=n_rays * N_SAMPLES))
    deltas = draw(st.lists(delta, min_size=n_rays * N_SAMPLES, max_size=n_rays * N_SAMPLES))
    near = draw(st.lists(st.floats(0.0, 100.0), min_size=n_rays, max_size=n_rays))
    return (torch.tensor(sigmas, dtype=dtype).reshape(n_rays, N_SAMPLES),
            torch.tensor(deltas, dtype=dtype).reshape(n_rays, N_SAMPLES), torch.tensor(near, dtype=dtype))


@settings(max_examples=60, deadline=None)
@given(density_case())
def test_property_weights_depth_and_gradients(case):
    sigmas, deltas, near = case
    dtype = sigmas.dtype
    edges = torch.cat([near[:, None], near[:, None] + torch.cumsum(deltas, -1)], -1)
    sigmas.requires_grad_()
    rgbs = torch.full(sigmas.shape + (3,), 0.5, dtype=dtype, requires_grad=True)
    out = vectorised(sigmas, rgbs, edges, torch.ones(3, dtype=dtype))
    weights, opacity, depth = out["weights"], out["opacity"], out["depth"]
    for tensor in out.values():
        assert torch.isfinite(tensor).all()
    # Each w_i carries a few roundings and the sum adds S more: 4 S eps bounds the excess.
    tolerance = 4 * N_SAMPLES * torch.finfo(dtype).eps
    assert ((weights >= 0) & (weights <= 1)).all()
    assert (opacity <= 1 + tolerance).all()
    seen = opacity > 0
    assert ((depth[seen] >= edges[seen, 0]) & (depth[seen] <= edges[seen, -1])).all()
    assert (depth[~seen] == 0).all()
    grads = torch.autograd.grad(out["rgb"].sum() + depth.sum() + opacity.sum(), (sigmas, rgbs))
    assert all(torch.isfinite(g).all() for g in grads)


COMPONENT = st.one_of(st.just(0.0), st.floats(-3.0, 3.0, allow_nan=False))


@settings(max_examples=80, deadline=None)
@given(dtype=DTYPES, origin=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
       direction=st.tuples(COMPONENT, COMPONENT, COMPONENT).filter(lambda d: math.hypot(*d) >= 1e-3),
       n_samples=st.integers(1, 6))
def test_property_ray_aabb_and_render_are_finite(dtype, origin, direction, n_samples):
    origins = torch.tensor([origin], dtype=dtype)
    directions = torch.tensor([direction], dtype=dtype)
    t_near, t_far, hit = R.ray_aabb(origins, directions, BOX.to(dtype))
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
    assert (t_near >= 0).all() and (t_near <= t_far).all()
    if hit.item():
        # The middle of the clipped segment lies in the box (up to rounding of o + t d).
        middle = origins + 0.5 * (t_near + t_far)[:, None] * directions
        slack = 1e-4 if dtype == torch.float32 else 1e-10
        assert (middle.abs() <= 1 + slack).all(), middle
    else:
        assert t_near.item() == 0 and t_far.item() == 0
    field = lambda p, d: (torch.full(p.shape[:-1], 1e8, dtype=p.dtype), 0.5 + 0 * p)
    out = R.render_rays(field, origins, directions, t_near, t_far, n_samples, n_importance=2)
    for tensor in (out.rgb, out.depth, out.opacity, out.weights, out.t_edges):
        assert torch.isfinite(tensor).all()
    assert 0 <= out.opacity.item() <= 1 and (hit.item() or out.opacity.item() == 0)


@settings(max_examples=40, deadline=None)
@given(dtype=DTYPES, near=st.floats(0.0, 50.0), length=st.one_of(st.just(0.0), st.floats(0.0, 10.0)),
       seed=st.integers(0, 2 ** 16), weights=st.lists(st.one_of(st.just(0.0), st.floats(0.0, 1.0)), min_size=6, max_size=6))
def test_property_sampling_stays_in_range(dtype, near, length, seed, weights):
    g = torch.Generator().manual_seed(seed)
    near_t = torch.tensor([near], dtype=dtype)
    far_t = near_t + length
    edges = R.stratified_edges(near_t, far_t, 6, perturb=True, generator=g)
    t = R.importance_samples(edges, torch.tensor([weights], dtype=dtype), 7, perturb=True, generator=g)
    for tensor in (edges, t):
        assert torch.isfinite(tensor).all()
        assert ((tensor >= near_t) & (tensor <= far_t)).all()
    assert (R.deltas(edges) >= 0).all() and (t[:, 1:] >= t[:, :-1]).all()
    if length == 0:
        assert (t == near_t).all()



# --------------------------------------------------------------------------------------
# the pixel filter in linear light


def test_srgb_transfer_functions_match_numpy_and_invert():
    """Against the numpy transfer functions the dataset writer and the asset reader use
    (independent code), and each other's inverse on [0, 1] to float64 rounding."""
    import numpy as np

    from nerfgauge.core.images import linear_to_srgb, srgb_to_linear

    x = torch.linspace(0, 1, 10001, dtype=torch.float64)
    assert torch.allclose(R.linear_to_srgb(x), torch.from_numpy(linear_to_srgb(x.numpy())), rtol=0, atol=1e-12)
    assert torch.allclose(R.srgb_to_linear(x), torch.from_numpy(np.asarray(srgb_to_linear(x.numpy()))), rtol=0, atol=1e-12)
    # the two segments meet at 0.04045 / 0.0031308 to 1e-7 (the standard's rounded constants)
    assert torch.allclose(R.linear_to_srgb(R.srgb_to_linear(x)), x, rtol=0, atol=1e-7)


def test_pixel_mean_is_the_ground_truths_box_filter():
    """Half black, half white opaque rays: the ground truth stores sRGB(0.5) = 0.7354 (a
    mean of radiance), not 0.5; one ray is itself; alpha averages as coverage; empty rays
    weigh nothing in the colour (a half-covered red pixel stays red, at alpha 0.5)."""
    rgb = torch.tensor([[[0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]]], dtype=torch.float64)  # [S=2, P=1, 3]
    out_rgb, out_opacity = R.pixel_mean(rgb, torch.ones(2, 1, dtype=torch.float64))
    assert torch.allclose(out_rgb, torch.full((1, 3), 1.055 * 0.5 ** (1 / 2.4) - 0.055, dtype=torch.float64), atol=1e-12)
    assert torch.equal(out_opacity, torch.ones(1, dtype=torch.float64))
    generator = torch.Generator().manual_seed(0)
    colour = torch.rand(1, 50, 3, generator=generator, dtype=torch.float64)
    opacity = torch.rand(1, 50, generator=generator, dtype=torch.float64)
    one_rgb, one_opacity = R.pixel_mean(colour * opacity[..., None], opacity)
    assert torch.allclose(one_rgb, colour[0] * opacity[0, :, None], atol=1e-7) and torch.equal(one_opacity, opacity[0])
    red = torch.tensor([[[0.8, 0.1, 0.1]], [[0.0, 0.0, 0.0]]], dtype=torch.float64)  # a covered ray and an empty one
    half_rgb, half_opacity = R.pixel_mean(red, torch.tensor([[1.0], [0.0]], dtype=torch.float64))
    assert torch.allclose(half_opacity, torch.tensor([0.5], dtype=torch.float64))
    assert torch.allclose(half_rgb / half_opacity[:, None], red[0], atol=1e-7)  # straight colour: the red


def test_pixel_mean_gradients_are_finite_at_black_and_empty():
    """Black rays (sRGB 0) and empty ones (alpha 0) sit where x^(1/2.4) has an infinite
    slope and rgb / alpha divides by zero: the gradient must stay finite, and match finite
    differences where the function is smooth."""
    rgb = torch.zeros(4, 3, 3, dtype=torch.float64, requires_grad=True)
    opacity = torch.tensor([[0.0, 1.0, 0.5]] * 4, dtype=torch.float64, requires_grad=True)
    out_rgb, out_opacity = R.pixel_mean(rgb, opacity)
    (out_rgb.sum() + out_opacity.sum()).backward()
    assert torch.isfinite(rgb.grad).all() and torch.isfinite(opacity.grad).all()
    generator = torch.Generator().manual_seed(1)
    colour = torch.rand(4, 5, 3, generator=generator, dtype=torch.float64) * 0.8 + 0.1
    alpha = torch.rand(4, 5, generator=generator, dtype=torch.float64) * 0.8 + 0.1
    assert torch.autograd.gradcheck(lambda c, a: R.pixel_mean(c * a[..., None], a),
                                    (colour.requires_grad_(), alpha.requires_grad_()))
