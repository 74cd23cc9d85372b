"""Numerical stability of volume rendering and sampling on extreme inputs.

For float32 and float64, sigma in [0, 1e8] and delta in [0, 1e3] (both endpoints drawn
exactly), rays with near == far and directions with zero components:

- outputs are finite;
- weights lie in [0, 1] and sum to at most 1 per ray;
- depth lies in [near, far] where opacity > 0, and is 0 where opacity is 0;
- gradients of a scalar loss w.r.t. sigma and rgb are finite.

tests/test_rendering.py already has properties for dense weights with 8 samples and a
constant colour, ray_aabb + render_rays at one density, and stratified + importance
sampling from uniform random weights. This file covers the rest: dense transmittance and
alphas with any sample count, rays forced to near == far, random colours and backgrounds;
render_rays end to end with gradients through both passes; importance sampling from the
one-hot and zero-length-bin weights that extreme densities give; and every packed function
(exclusive sums, transmittance, weights, render, distortion, early stop), on its own and
after ray_aabb + march.

Tolerances, eps being the dtype's machine epsilon:
- A weight w_i = T_i alpha_i carries a few roundings (exp, expm1, the product), and
  T_i = exp(-E_i) inherits the rounding of the cumulative sum E_i, an absolute error of at
  most E_i eps exp(-E_i) <= eps / e per cumulative step. A sum over S samples adds S more
  roundings, so sum_i w_i <= 1 + 4 (S + 1) eps (`sum_slack`).
- Depth is a weighted mean of midpoints that lie in [near, far]; the quotient may round
  past either end by eps * max(|near|, |far|) (`assert_depth_in_range`).
- Packed samples take a ray's exclusive sum E_i as a float64 cumulative sum over the whole
  batch minus its value where the ray starts (nerf/packed.py), so E_i is also off by the
  rounding of that running total: at most 2 (n + 2) eps64 G for n samples of total optical
  depth G (each prefix of n terms is within n eps64 G, whatever the summation order). That
  moves each T_i <= 1 by as much, once per sample of the ray (`packed_slack`). It is far
  below float32's eps here; in float64 it is what the design trades for one cumulative sum.
"""

from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from nerfgauge.nerf import rendering as R
from nerfgauge.nerf.marching import march, occupancy_pyramid
from nerfgauge.nerf.packed import (
    TAU_MAX_PACKED,
    packed_distortion,
    packed_exclusive_cumsum,
    packed_render,
    packed_render_early_stop,
    packed_transmittance,
    packed_weights,
)

DTYPES = st.sampled_from([torch.float32, torch.float64])
# The ranges, endpoints included exactly, plus a moderate band where alphas are
# neither 0 nor 1 (with delta <= 0.1, sigma <= 10 gives tau <= 1).
SIGMA = st.one_of(st.sampled_from([0.0, 1e8]), st.floats(0.0, 1e8), st.floats(0.0, 10.0))
DELTA = st.one_of(st.sampled_from([0.0, 1e3]), st.floats(0.0, 1e3), st.floats(0.0, 0.1))
NEAR = st.one_of(st.just(0.0), st.floats(0.0, 1e3))
SEED = st.integers(0, 2 ** 32 - 1)
EPS64 = torch.finfo(torch.float64).eps


def eps(dtype: torch.dtype) -> float:
    return torch.finfo(dtype).eps


def sum_slack(dtype: torch.dtype, n_samples) -> float | torch.Tensor:
    """How far a sum of n_samples weights may exceed 1 by rounding (module docstring).
    n_samples: a number, or a tensor of counts per ray (then a float64 tensor)."""
    if isinstance(n_samples, torch.Tensor):
        n_samples = n_samples.double()
    return 4 * (n_samples + 1) * eps(dtype)


def global_sum_error(tau: torch.Tensor) -> float:
    """Bound on the error of a packed exclusive sum from the batch-wide float64 running total
    (module docstring): 2 (n + 2) eps64 G, tau [n] the clamped optical depths."""
    return 2 * (len(tau) + 2) * EPS64 * float(tau.detach().double().sum())


def packed_slack(dtype: torch.dtype, counts: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """`sum_slack` per ray [n_rays] plus each sample's share of `global_sum_error`."""
    return sum_slack(dtype, counts) + counts.double() * global_sum_error(tau)


def assert_finite(*tensors: torch.Tensor) -> None:
    for tensor in tensors:
        assert torch.isfinite(tensor).all(), tensor


def assert_depth_in_range(depth, opacity, near, far) -> None:
    """Depth in [near - s, far + s] with s = eps max(|near|, |far|) where opacity > 0; 0 elsewhere."""
    assert_finite(depth)
    slack = eps(depth.dtype) * torch.maximum(near.abs(), far.abs())  # [n_rays]
    seen = opacity > 0
    inside = (depth >= near - slack) & (depth <= far + slack)
    assert inside[seen].all(), (depth[seen], near[seen], far[seen])
    assert (depth[~seen] == 0).all(), depth[~seen]


def assert_grads_finite(loss: torch.Tensor, inputs: tuple) -> None:
    grads = torch.autograd.grad(loss, inputs, allow_unused=True)
    for grad in grads:
        assert grad is None or torch.isfinite(grad).all(), grad


def random_cotangents(n_rays: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    """[n_rays, 6] signed weights for a scalar loss over rgb, opacity, depth and distortion."""
    return torch.randn((n_rays, 6), generator=torch.Generator().manual_seed(seed), dtype=dtype)


def first_of_ray(ray_index: torch.Tensor) -> torch.Tensor:
    """[n_samples] bool: the sample starts its ray (packed samples are sorted by ray)."""
    first = torch.ones_like(ray_index, dtype=torch.bool)
    first[1:] = ray_index[1:] != ray_index[:-1]
    return first


# --------------------------------------------------------------------------------------
# dense [n_rays, n_samples]


@st.composite
def dense_case(draw):
    """sigmas [n_rays, S], sorted edges [n_rays, S + 1] built from deltas on [near, far],
    colours [n_rays, S, 3] and a background [3] in [0, 1], and which rays have near == far."""
    dtype = draw(DTYPES)
    n_rays, n_samples = draw(st.integers(1, 4)), draw(st.integers(1, 12))
    n = n_rays * n_samples
    sigmas = torch.tensor(draw(st.lists(SIGMA, min_size=n, max_size=n)), dtype=dtype).reshape(n_rays, n_samples)
    deltas = torch.tensor(draw(st.lists(DELTA, min_size=n, max_size=n)), dtype=dtype).reshape(n_rays, n_samples)
    near = torch.tensor(draw(st.lists(NEAR, min_size=n_rays, max_size=n_rays)), dtype=dtype)
    collapsed = torch.tensor(draw(st.lists(st.booleans(), min_size=n_rays, max_size=n_rays)))
    deltas[collapsed] = 0.0  # near == far
    edges = torch.cat([near[:, None], near[:, None] + torch.cumsum(deltas, -1)], -1)  # [n_rays, S + 1]
    g = torch.Generator().manual_seed(draw(SEED))
    rgbs = torch.rand((n_rays, n_samples, 3), generator=g, dtype=dtype)
    background = torch.rand(3, generator=g, dtype=dtype)
    return sigmas, edges, rgbs, background, collapsed


@settings(max_examples=80, deadline=None)
@given(case=dense_case(), seed=SEED)
def test_dense_weights_transmittance_rendering_and_gradients(case, seed):
    sigmas, edges, rgbs, background, collapsed = case
    dtype, (n_rays, n_samples) = sigmas.dtype, sigmas.shape
    sigmas.requires_grad_(), rgbs.requires_grad_()
    near, far = edges[:, 0], edges[:, -1]
    deltas = R.deltas(edges)
    weights, transmittance, alphas = R.weights_from_density(sigmas, deltas)
    for tensor in (weights, transmittance, alphas):
        assert_finite(tensor)
        assert ((tensor >= 0) & (tensor <= 1)).all(), tensor
    assert (transmittance[:, 0] == 1).all()
    assert (transmittance[:, 1:] <= transmittance[:, :-1]).all()  # light only gets absorbed
    assert (weights <= transmittance).all()  # w = T alpha with alpha <= 1 (rounding is monotone)
    assert (weights[deltas == 0] == 0).all()  # a zero-length interval holds nothing, whatever sigma

    opacity = R.accumulate_along_rays(weights)  # [n_rays]
    rgb = R.accumulate_along_rays(weights, rgbs)  # [n_rays, 3]
    depth = R.expected_depth(weights, R.midpoints(edges), opacity, near, far)
    composited = R.composite(rgb, opacity, background)
    slack = sum_slack(dtype, n_samples)
    assert_finite(opacity, rgb, composited)
    assert ((opacity >= 0) & (opacity <= 1 + slack)).all(), opacity
    # colours in [0, 1]: premultiplied colour is at most the opacity, composited stays in [0, 1]
    assert ((rgb >= 0) & (rgb <= opacity[:, None] + slack)).all(), (rgb, opacity)
    assert ((composited >= -slack) & (composited <= 1 + 2 * slack)).all(), composited
    assert_depth_in_range(depth, opacity, near, far)
    # near == far: nothing is seen, the background shows unchanged
    assert (opacity[collapsed] == 0).all() and (depth[collapsed] == 0).all()
    assert (composited[collapsed] == background).all()

    cot = random_cotangents(n_rays, dtype, seed)
    loss = (composited * cot[:, :3]).sum() + (opacity * cot[:, 3]).sum() + (depth * cot[:, 4]).sum()
    grad_sigma, grad_rgb = torch.autograd.grad(loss, (sigmas, rgbs))
    assert_finite(grad_sigma, grad_rgb)
    # d loss / d rgb_i = w_i cot exactly: bounded by |cot| since w_i <= 1
    assert (grad_rgb.abs() <= cot[:, None, :3].abs()).all()


COMPONENT = st.one_of(st.sampled_from([0.0, 0.0, -1.0, 1.0]), st.floats(-1.0, 1.0))
# Face and edge coordinates of the boxes used below, points inside them and outside.
COORD = st.one_of(st.sampled_from([-3.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0]), st.floats(-1.0, 1.0),
                  st.floats(-3.0, 3.0))
DIRECTION = st.tuples(COMPONENT, COMPONENT, COMPONENT).filter(lambda d: math.hypot(*d) >= 1e-3)
BOXES = [((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), ((-1.0, -0.5, 0.0), (1.0, 0.5, 2.0))]


@st.composite
def ray_case(draw, max_rays=4):
    """Origins [n, 3], unit directions [n, 3] with zero components, a box [2, 3]."""
    dtype = draw(DTYPES)
    n_rays = draw(st.integers(1, max_rays))
    origins = torch.tensor(draw(st.lists(st.tuples(COORD, COORD, COORD), min_size=n_rays, max_size=n_rays)),
                           dtype=dtype)
    directions = torch.tensor(draw(st.lists(DIRECTION, min_size=n_rays, max_size=n_rays)), dtype=dtype)
    directions = torch.nn.functional.normalize(directions, dim=-1)  # a zero component stays exactly 0
    box = torch.tensor(draw(st.sampled_from(BOXES)), dtype=dtype)
    return origins, directions, box


@st.composite
def render_rays_case(draw):
    origins, directions, box = draw(ray_case())
    n_rays, dtype = origins.shape[0], origins.dtype
    n_samples, n_importance = draw(st.integers(1, 6)), draw(st.integers(0, 4))
    n_coarse, n_fine = n_rays * n_samples, n_rays * (n_samples + n_importance)
    coarse = draw(st.lists(SIGMA, min_size=n_coarse, max_size=n_coarse))
    fine = draw(st.lists(SIGMA, min_size=n_fine, max_size=n_fine))
    collapse = torch.tensor(draw(st.lists(st.booleans(), min_size=n_rays, max_size=n_rays)))
    return (origins, directions, box, torch.tensor(coarse, dtype=dtype).reshape(n_rays, n_samples),
            torch.tensor(fine, dtype=dtype).reshape(n_rays, n_samples + n_importance), collapse,
            draw(st.booleans()), draw(SEED))


@settings(max_examples=60, deadline=None)
@given(render_rays_case())
def test_render_rays_through_ray_aabb_with_gradients(case):
    """ray_aabb + render_rays, coarse and fine, with the field's sigma and rgb as leaves."""
    origins, directions, box, sigma_coarse, sigma_fine, collapse, perturb, seed = case
    dtype, n_rays = origins.dtype, origins.shape[0]
    near, far, hit = R.ray_aabb(origins, directions, box)
    assert_finite(near, far)
    far = torch.where(collapse, near, far)  # and some rays forced to near == far (misses have 0 == 0)
    g = torch.Generator().manual_seed(seed)
    rgb_coarse = torch.rand(sigma_coarse.shape + (3,), generator=g, dtype=dtype).requires_grad_()
    rgb_fine = torch.rand(sigma_fine.shape + (3,), generator=g, dtype=dtype).requires_grad_()
    sigma_coarse.requires_grad_(), sigma_fine.requires_grad_()

    def leaf_field(sigma, rgb):
        def field(positions, view_dirs):
            assert_finite(positions, view_dirs)
            assert positions.shape[:-1] == sigma.shape
            return sigma, rgb
        return field

    n_samples, n_importance = sigma_coarse.shape[1], sigma_fine.shape[1] - sigma_coarse.shape[1]
    background = torch.rand(3, generator=g, dtype=dtype)
    out = R.render_rays(leaf_field(sigma_coarse, rgb_coarse), origins, directions, near, far, n_samples,
                        n_importance=n_importance, fine_field_fn=leaf_field(sigma_fine, rgb_fine),
                        perturb=perturb, generator=g, background=background)
    passes = [out] if out.coarse is None else [out, out.coarse]
    cot = random_cotangents(n_rays, dtype, seed)
    loss = 0
    for rendered in passes:
        edges, weights = rendered.t_edges, rendered.weights
        assert_finite(edges, weights, rendered.rgb, rendered.opacity)
        # sampling clamps to [near, far] and sorts: exact, no slack
        assert ((edges >= near[:, None]) & (edges <= far[:, None])).all()
        assert (edges[:, 1:] >= edges[:, :-1]).all()
        assert ((weights >= 0) & (weights <= 1)).all()
        slack = sum_slack(dtype, weights.shape[1])
        assert ((rendered.opacity >= 0) & (rendered.opacity <= 1 + slack)).all()
        assert ((rendered.rgb >= -slack) & (rendered.rgb <= 1 + 2 * slack)).all()
        assert_depth_in_range(rendered.depth, rendered.opacity, near, far)
        empty = ~hit | collapse
        assert (rendered.opacity[empty] == 0).all() and (rendered.rgb[empty] == background).all()
        loss = loss + (rendered.rgb * cot[:, :3]).sum() + (rendered.opacity * cot[:, 3]).sum() \
            + (rendered.depth * cot[:, 4]).sum()
    assert_grads_finite(loss, (sigma_coarse, rgb_coarse, sigma_fine, rgb_fine))


@settings(max_examples=60, deadline=None)
@given(case=dense_case(), n_fine=st.integers(1, 9), perturb=st.booleans(), seed=SEED)
def test_importance_sampling_from_extreme_weights(case, n_fine, perturb, seed):
    """Weights from extreme densities are one-hot, zero on zero-length bins, or tiny."""
    sigmas, edges, _, _, collapsed = case
    weights, _, _ = R.weights_from_density(sigmas, R.deltas(edges))
    t = R.importance_samples(edges, weights, n_fine, perturb=perturb, generator=torch.Generator().manual_seed(seed))
    near, far = edges[:, :1], edges[:, -1:]
    assert_finite(t)
    assert ((t >= near) & (t <= far)).all()
    assert (t[:, 1:] >= t[:, :-1]).all()
    assert (t[collapsed] == near[collapsed]).all()
    merged = R.merge_edges(edges, t)
    assert merged.shape == (edges.shape[0], edges.shape[1] + n_fine)
    assert (merged[:, 1:] >= merged[:, :-1]).all() and (merged[:, :1] == near).all() and (merged[:, -1:] == far).all()
    if not perturb:
        # Samples land only in bins of positive weight (up to the rounding of t_lo + f (t_hi - t_lo),
        # one ulp of the largest t). With deterministic u <= 1 - 1/(2 n_fine), the CDF's rounding
        # deficit (<= S eps < 1/(2 n_fine) here) cannot reach a trailing zero-weight bin.
        slack = eps(t.dtype) * edges.abs().amax(dim=-1, keepdim=True)[:, :, None]  # [n_rays, 1, 1]
        in_bin = (t[:, :, None] >= edges[:, None, :-1] - slack) & (t[:, :, None] <= edges[:, None, 1:] + slack)
        supported = (in_bin & (weights[:, None, :] > 0)).any(-1)  # [n_rays, n_fine]
        has_weight = weights.sum(-1) > 0
        assert supported[has_weight].all(), (t, edges, weights)


# --------------------------------------------------------------------------------------
# packed (ragged) samples


@st.composite
def packed_case(draw, constant_step=False):
    """Rays with 0..10 samples each: sigmas, deltas, t_mid, ray_index [n_samples], near and
    far [n_rays], counts [n_rays]. Each ray's intervals tile [near, far] from its deltas;
    rays with no samples or only zero-length ones have near == far. constant_step: every
    delta is the same drawn value (as march and early stopping make them)."""
    dtype = draw(DTYPES)
    n_rays = draw(st.integers(1, 5))
    counts = draw(st.lists(st.integers(0, 10), min_size=n_rays, max_size=n_rays))
    n = sum(counts)
    sigmas = draw(st.lists(SIGMA, min_size=n, max_size=n))
    if constant_step:
        deltas = [draw(DELTA)] * n
    else:
        deltas = draw(st.lists(DELTA, min_size=n, max_size=n))
    near = torch.tensor(draw(st.lists(NEAR, min_size=n_rays, max_size=n_rays)), dtype=dtype)
    collapsed = draw(st.lists(st.booleans(), min_size=n_rays, max_size=n_rays))
    t_mid, delta, far, start = [], [], [], 0
    for r, count in enumerate(counts):
        d = torch.tensor(deltas[start:start + count], dtype=dtype)
        if collapsed[r] and not constant_step:
            d = torch.zeros_like(d)
        edges = torch.cat([near[r:r + 1], near[r] + torch.cumsum(d, 0)])  # [count + 1]
        t_mid.append(0.5 * (edges[1:] + edges[:-1]))
        delta.append(d if constant_step else edges[1:] - edges[:-1])
        far.append(edges[-1])
        start += count
    ray_index = torch.repeat_interleave(torch.arange(n_rays), torch.tensor(counts, dtype=torch.long))
    rgbs = torch.rand((n, 3), generator=torch.Generator().manual_seed(draw(SEED)), dtype=dtype)
    return (torch.tensor(sigmas, dtype=dtype), rgbs, torch.cat(delta), torch.cat(t_mid), ray_index,
            near, torch.stack(far), torch.tensor(counts))


def dense_from_packed(values: torch.Tensor, ray_index: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Packed [n_samples] -> [n_rays, max(count, 1)], padded with 0 (sigma = delta = 0 adds nothing)."""
    dense = values.new_zeros((len(counts), max(int(counts.max()), 1)))
    rank = torch.arange(len(ray_index)) - (torch.cumsum(counts, 0) - counts)[ray_index]
    dense[ray_index, rank] = values
    return dense


@settings(max_examples=80, deadline=None)
@given(case=packed_case(), seed=SEED)
def test_packed_rendering_distortion_and_gradients(case, seed):
    sigmas, rgbs, deltas, t_mid, ray_index, near, far, counts = case
    dtype, n_rays, n = sigmas.dtype, len(counts), len(sigmas)
    first, same_ray = first_of_ray(ray_index), ray_index[1:] == ray_index[:-1]
    sigmas.requires_grad_(), rgbs.requires_grad_()

    transmittance, tau = packed_transmittance(sigmas, deltas, ray_index, n_rays)
    assert_finite(transmittance, tau)
    assert ((tau >= 0) & (tau <= TAU_MAX_PACKED)).all()
    assert ((transmittance >= 0) & (transmittance <= 1)).all()
    assert (transmittance[first] == 1).all()
    cross = global_sum_error(tau)  # how far each E_i, hence each T_i <= 1, may be off
    assert (transmittance[1:][same_ray] <= transmittance[:-1][same_ray] + 2 * cross).all()

    # Exclusive sums against a per-ray float64 loop: off by `global_sum_error`, then one
    # rounding to the dtype.
    optical_depth = packed_exclusive_cumsum(tau, ray_index, n_rays)
    assert_finite(optical_depth)
    assert (optical_depth[first] == 0).all()
    expected = torch.cat([torch.cumsum(tau.detach().double()[ray_index == r], 0) - tau.detach().double()[ray_index == r]
                          for r in range(n_rays)])
    tolerance = cross + eps(dtype) * expected
    assert ((optical_depth.double() - expected).abs() <= tolerance).all()

    weights = packed_weights(sigmas, deltas, ray_index, n_rays)
    assert_finite(weights)
    assert ((weights >= 0) & (weights <= 1)).all()
    slack = packed_slack(dtype, counts, tau)  # [n_rays]
    sums = torch.zeros(n_rays, dtype=dtype).index_add(0, ray_index, weights.detach())
    assert (sums <= 1 + slack).all(), sums - 1
    assert (weights[deltas == 0] == 0).all()
    # The dense renderer agrees up to rounding and the packed clamp tau <= TAU_MAX_PACKED,
    # which leaves at most exp(-TAU_MAX_PACKED) of transmittance behind an opaque sample.
    dense_weights, _, _ = R.weights_from_density(dense_from_packed(sigmas.detach(), ray_index, counts),
                                                 dense_from_packed(deltas, ray_index, counts))
    gap = (dense_from_packed(weights.detach(), ray_index, counts) - dense_weights).abs()
    assert (gap <= slack[:, None] + math.exp(-TAU_MAX_PACKED)).all(), gap

    rgb, opacity, depth, render_weights = packed_render(sigmas, rgbs, deltas, t_mid, ray_index, near, far)
    assert_finite(rgb, opacity, render_weights)
    assert ((opacity >= 0) & (opacity <= 1 + slack)).all()
    assert ((rgb >= 0) & (rgb <= opacity[:, None] + slack[:, None])).all()  # colours in [0, 1]
    assert_depth_in_range(depth, opacity, near, far)
    nothing = (counts == 0) | (far == near)  # no samples, or only zero-length ones
    assert (opacity[nothing] == 0).all() and (rgb[nothing] == 0).all()

    # Distortion: 0 <= L <= A^2 (far - near) + A max(delta) / 3 (t sorted in [near, far]).
    # The O(n) form subtracts t W_<i - S_<i: ~4 roundings of t_max A per sample, times 2 w_i,
    # and S more in the sum; the float64 global sums add (n + 2) eps64 of all rays' totals.
    distortion = packed_distortion(render_weights, t_mid, deltas, ray_index, n_rays)
    assert_finite(distortion)
    w, t = render_weights.detach(), t_mid
    max_delta = torch.zeros(n_rays, dtype=dtype).scatter_reduce(0, ray_index, deltas, "amax")
    cross = 2 * (n + 2) * EPS64 * (far.abs() * float(w.sum()) + float((w * t.abs()).sum()))
    tolerance = 4 * (counts + 3) * eps(dtype) * (far.abs() + max_delta) + cross
    a = opacity.detach()
    assert (distortion >= -tolerance).all(), distortion
    assert (distortion <= a ** 2 * (far - near) + a * max_delta / 3 + tolerance).all(), distortion

    cot = random_cotangents(n_rays, dtype, seed)
    loss = (rgb * cot[:, :3]).sum() + (opacity * cot[:, 3]).sum() + (depth * cot[:, 4]).sum() \
        + (distortion * cot[:, 5]).sum()
    assert_grads_finite(loss, (sigmas, rgbs))


@settings(max_examples=60, deadline=None)
@given(case=packed_case(constant_step=True), window=st.integers(1, 6),
       min_transmittance=st.sampled_from([0.0, 1e-3, 0.1]))
def test_packed_early_stop_matches_packed_render_within_the_stop_threshold(case, window, min_transmittance):
    sigmas, rgbs, deltas, t_mid, ray_index, near, far, counts = case
    dtype = sigmas.dtype
    step = float(deltas[0]) if len(deltas) else 0.0
    calls = []

    def field_at(index):
        calls.append(index)
        return sigmas[index], rgbs[index]

    rgb, opacity, depth, evaluated = packed_render_early_stop(field_at, t_mid, ray_index, step, near, far,
                                                              window=window, min_transmittance=min_transmittance)
    assert_finite(rgb, opacity)
    assert evaluated <= len(sigmas) and evaluated == sum(len(i) for i in calls)
    assert ((opacity >= 0) & (opacity <= 1)).all()  # 1 - T with T in [0, 1]
    slack = packed_slack(dtype, counts, (sigmas * deltas).clamp(0.0, TAU_MAX_PACKED))  # [n_rays]
    assert ((rgb >= 0) & (rgb <= opacity[:, None] + slack[:, None])).all(), (rgb, opacity)
    assert_depth_in_range(depth, opacity, near, far)
    # What a stopped ray leaves out lies behind transmittance < min_transmittance.
    full_rgb, full_opacity, _, _ = packed_render(sigmas, rgbs, deltas, t_mid, ray_index, near, far)
    assert ((opacity - full_opacity).abs() <= min_transmittance + 2 * slack).all()
    assert ((rgb - full_rgb).abs() <= min_transmittance + 2 * slack[:, None]).all()


# --------------------------------------------------------------------------------------
# ray_aabb + march + packed rendering


@st.composite
def march_case(draw):
    origins, directions, box = draw(ray_case(max_rays=6))
    shape = draw(st.tuples(*[st.integers(1, 6)] * 3))  # [nz, ny, nx]
    fill = draw(st.sampled_from([0.0, 0.3, 1.0]))
    occupancy = torch.rand(shape, generator=torch.Generator().manual_seed(draw(SEED))) < fill
    step_ratio = draw(st.sampled_from([1.0, 0.5, 0.3]))  # marching step in voxels
    jitter = draw(st.none() | st.lists(st.one_of(st.sampled_from([0.0, 0.999]), st.floats(0.0, 0.999)),
                                       min_size=len(origins), max_size=len(origins)))
    sigma_values = draw(st.lists(SIGMA, min_size=1, max_size=8))  # cycled over the samples
    return origins, directions, box, occupancy, step_ratio, jitter, sigma_values, draw(SEED)


@settings(max_examples=60, deadline=None)
@given(march_case())
def test_march_then_packed_render_on_axis_parallel_and_grazing_rays(case):
    origins, directions, box, occupancy, step_ratio, jitter, sigma_values, seed = case
    dtype, n_rays = origins.dtype, origins.shape[0]
    nz, ny, nx = occupancy.shape
    voxel = (box[1] - box[0]) / torch.tensor([nx, ny, nz], dtype=dtype)
    step = float(voxel.max()) * step_ratio
    jitter = None if jitter is None else torch.tensor(jitter, dtype=dtype)
    near, far, hit = R.ray_aabb(origins, directions, box)
    samples = march(origins, directions, box, occupancy, step, jitter=jitter, levels=occupancy_pyramid(occupancy))
    t, rays = samples.t_mid, samples.ray_index
    assert torch.equal(samples.near, near) and torch.equal(samples.far, far)
    assert_finite(t)
    assert (rays[1:] >= rays[:-1]).all()  # sorted by ray
    assert hit[rays].all()  # rays that miss (near == far == 0) get no samples
    assert ((t >= near[rays]) & (t < far[rays])).all()
    same_ray = rays[1:] == rays[:-1]
    assert (t[1:][same_ray] > t[:-1][same_ray]).all()  # then by distance
    # Samples lie in the box, up to the rounding of o + t d.
    positions = origins[rays] + t[:, None] * directions[rays]
    slack = 4 * eps(dtype) * (origins[rays].abs() + t[:, None].abs() + box.abs().amax(0))
    assert ((positions >= box[0] - slack) & (positions <= box[1] + slack)).all()

    n = len(t)
    sigmas = torch.tensor(sigma_values, dtype=dtype)[torch.arange(n) % len(sigma_values)].requires_grad_()
    rgbs = torch.rand((n, 3), generator=torch.Generator().manual_seed(seed), dtype=dtype).requires_grad_()
    deltas = torch.full_like(t, samples.step)
    rgb, opacity, depth, weights = packed_render(sigmas, rgbs, deltas, t, rays, near, far)
    counts = torch.bincount(rays, minlength=n_rays)
    slack = packed_slack(dtype, counts, (sigmas * deltas).clamp(0.0, TAU_MAX_PACKED))
    assert_finite(rgb, opacity, weights)
    assert ((weights >= 0) & (weights <= 1)).all()
    assert ((opacity >= 0) & (opacity <= 1 + slack)).all()
    assert ((rgb >= 0) & (rgb <= opacity[:, None] + slack[:, None])).all()
    assert_depth_in_range(depth, opacity, near, far)
    assert (opacity[~hit] == 0).all() and (depth[~hit] == 0).all()
    distortion = packed_distortion(weights, t, deltas, rays, n_rays)
    assert_finite(distortion)
    cot = random_cotangents(n_rays, dtype, seed)
    loss = (rgb * cot[:, :3]).sum() + (opacity * cot[:, 3]).sum() + (depth * cot[:, 4]).sum() \
        + (distortion * cot[:, 5]).sum()
    assert_grads_finite(loss, (sigmas, rgbs))

    early = packed_render_early_stop(lambda i: (sigmas.detach()[i], rgbs.detach()[i]), t, rays, samples.step,
                                     near, far, window=4)
    assert_finite(*early[:2])
    assert ((early[1] >= 0) & (early[1] <= 1)).all()
    assert_depth_in_range(early[2], early[1], near, far)
