"""Volume rendering as pure functions (NeRF's quadrature, Mildenhall et al. 2020, vectorised over rays).

A ray r(t) = o + t d is cut into intervals [t_k, t_{k+1}] by bin edges, the density and
colour are taken as constant on each interval (the value at its midpoint), and

    tau_i   = sigma_i * delta_i,                 delta_i = t_{i+1} - t_i
    alpha_i = 1 - exp(-tau_i)                    (opacity of interval i)
    T_i     = exp(-sum_{j<i} tau_j)              (= prod_{j<i} (1 - alpha_j), transmittance)
    w_i     = T_i * alpha_i                      (weights)
    C       = sum_i w_i c_i,   A = sum_i w_i,    D = sum_i w_i t_mid_i / max(A, eps)

This quadrature is exact for piecewise-constant density and colour. Rendering never
imports a model: `render_rays` takes the field as a callback. Sampling steps (stratified
and importance sampling, ray/box clipping) are not differentiable and run under
`torch.no_grad()`; weights, accumulation, depth and compositing are differentiable.

Shapes: N rays, S intervals (samples) per ray. Every t is a distance along the ray in
units of |d| (ray distance when directions are unit length, as `nerfgauge.core.camera` makes
them). Opacity and depth are [N], colours [N, 3].
`nerf/reference.py` holds a per-ray loop of the same maths, the tests' oracle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

# sigma * delta is clamped to [0, TAU_MAX]: exp(-TAU_MAX) is 0 in both dtypes (alpha == 1
# exactly), and tau and its running sums stay finite even for sigma = inf. (An infinite tau
# would also pass through exp harmlessly; the clamp guards the intermediates, while the
# zero-length test in `weights_from_density` is what prevents inf * 0 = nan.)
TAU_MAX = 1e4
DEPTH_EPS = 1e-10
# t is measured in units of |d|: shorter directions would push t past float32's range.
MIN_DIRECTION_LENGTH = 1e-6

FieldFn = Callable[[torch.Tensor, torch.Tensor], "tuple[torch.Tensor, torch.Tensor]"]


# --------------------------------------------------------------------------------------
# shape checks where data enters


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _check_rays(origins: torch.Tensor, directions: torch.Tensor) -> None:
    _check(origins.ndim == 2 and origins.shape[-1] == 3,
           f"origins must be [n_rays, 3], got shape {tuple(origins.shape)}")
    _check(directions.shape == origins.shape,
           f"directions must be [n_rays, 3] like origins {tuple(origins.shape)}, got shape {tuple(directions.shape)}")
    _check(origins.is_floating_point() and directions.dtype == origins.dtype,
           f"origins and directions must share a floating dtype, got {origins.dtype} and {directions.dtype}")


def _as_per_ray(value, n_rays: int, like: torch.Tensor, name: str) -> torch.Tensor:
    """A float or a [n_rays] tensor -> [n_rays] tensor in `like`'s dtype and device."""
    value = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if value.ndim == 0:
        return value.expand(n_rays)
    _check(value.shape == (n_rays,), f"{name} must be a number or [n_rays] = [{n_rays}], got shape {tuple(value.shape)}")
    return value


def _check_edges(t_edges: torch.Tensor) -> None:
    _check(t_edges.ndim == 2 and t_edges.shape[-1] >= 2,
           f"t_edges must be [n_rays, n_samples + 1] with n_samples >= 1, got shape {tuple(t_edges.shape)}")


def _check_samples(name: str, tensor: torch.Tensor, n_rays: int, n_samples: int, trailing: tuple = ()) -> None:
    expected = (n_rays, n_samples, *trailing)
    _check(tuple(tensor.shape) == expected,
           f"{name} must be [n_rays, n_samples{', ' + ', '.join(map(str, trailing)) if trailing else ''}]"
           f" = {list(expected)}, got shape {tuple(tensor.shape)}")


# --------------------------------------------------------------------------------------
# rays and samples (not differentiable)


@torch.no_grad()
def ray_aabb(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Clip rays to an axis-aligned box by the slab method. Not differentiable (no_grad).

    For each axis a with d_a != 0 the ray is inside the slab for t between
    (lo_a - o_a) / d_a and (hi_a - o_a) / d_a; the ray is in the box on the intersection of
    the three slab intervals and of t >= 0. An axis with d_a == 0 is handled without
    dividing: the slab holds every t if lo_a <= o_a <= hi_a (a ray parallel to a face inside
    the slab, faces included) and no t otherwise, so no 0 * inf or 0 / 0 arises.

    origins: [n_rays, 3], directions: [n_rays, 3] (length >= MIN_DIRECTION_LENGTH, not
    necessarily 1; t is in units of |d|), aabb: [2, 3] rows (min corner, max corner).
    Components may be tiny or zero: a slab bound that overflows to +-inf is still ordered.
    Returns t_near [n_rays], t_far [n_rays] and hit [n_rays] (bool). t_near >= 0 (clamped
    when the origin is inside the box). hit means the ray runs through the box for a
    positive length t_far > t_near; rays that miss (including ones that only graze an edge
    or corner, or start behind the box) get hit = False and t_near = t_far = 0.
    """
    _check_rays(origins, directions)
    aabb = torch.as_tensor(aabb, dtype=origins.dtype, device=origins.device)
    _check(aabb.shape == (2, 3), f"aabb must be [2, 3] (min corner, max corner), got shape {tuple(aabb.shape)}")
    _check(bool((aabb[0] <= aabb[1]).all()), f"aabb min corner must not exceed max corner, got {aabb.tolist()}")
    shortest = directions.norm(dim=-1).min().item() if len(directions) else 1.0
    _check(shortest >= MIN_DIRECTION_LENGTH,
           f"directions must have length >= {MIN_DIRECTION_LENGTH} (t is in units of |d|), got length {shortest}")

    lo, hi = aabb[0], aabb[1]  # [3]
    parallel = directions == 0  # [n_rays, 3]
    safe_d = torch.where(parallel, torch.ones_like(directions), directions)  # [n_rays, 3]
    t_lo = (lo - origins) / safe_d  # [n_rays, 3]
    t_hi = (hi - origins) / safe_d  # [n_rays, 3]
    t_enter = torch.minimum(t_lo, t_hi)  # [n_rays, 3]
    t_exit = torch.maximum(t_lo, t_hi)  # [n_rays, 3]
    inside_slab = (origins >= lo) & (origins <= hi)  # [n_rays, 3]
    inf = torch.full_like(t_enter, float("inf"))
    t_enter = torch.where(parallel, torch.where(inside_slab, -inf, inf), t_enter)
    t_exit = torch.where(parallel, torch.where(inside_slab, inf, -inf), t_exit)
    t_near = t_enter.amax(dim=-1).clamp_min(0.0)  # [n_rays]
    t_far = t_exit.amin(dim=-1)  # [n_rays]
    hit = t_far > t_near  # [n_rays]
    zero = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zero), torch.where(hit, t_far, zero), hit


@torch.no_grad()
def stratified_edges(near: torch.Tensor, far: torch.Tensor, n_samples: int, perturb: bool = False,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Bin edges for stratified sampling on [near, far]. Not differentiable (no_grad).

    [near, far] is split into n_samples equal strata; edge k (0 < k < n_samples) is drawn
    uniformly in [(k - 1/2), (k + 1/2)] * (far - near) / n_samples + near, so the edges stay
    sorted, the first is near and the last is far, and the midpoint of interval i (where
    the field is evaluated, see `midpoints`) always lies in stratum i. With perturb=False
    every interior edge sits at the centre of its range: equal bins, deterministic
    midpoints. near == far gives finite, zero-length intervals.

    near, far: [n_rays] with far >= near. generator: the random source when perturb=True
    (None uses torch's default generator).
    Returns t_edges [n_rays, n_samples + 1], sorted along each ray.
    """
    _check(isinstance(n_samples, int) and n_samples >= 1, f"n_samples must be an integer >= 1, got {n_samples!r}")
    _check(near.ndim == 1 and far.shape == near.shape,
           f"near and far must both be [n_rays], got shapes {tuple(near.shape)} and {tuple(far.shape)}")
    _check(bool((far >= near).all()), f"far must be >= near on every ray; smallest far - near is {(far - near).min().item()}")
    n_rays = near.shape[0]
    steps = torch.arange(n_samples + 1, dtype=near.dtype, device=near.device)  # [n_samples + 1]
    if perturb:
        jitter = torch.rand((n_rays, n_samples - 1), dtype=near.dtype, device=near.device, generator=generator) - 0.5
        interior = steps[1:-1] + jitter  # [n_rays, n_samples - 1]
        steps = torch.cat([steps[:1].expand(n_rays, 1), interior, steps[-1:].expand(n_rays, 1)], dim=-1)
    fraction = steps / n_samples  # [n_rays or 1, n_samples + 1]
    t_edges = near[:, None] + (far - near)[:, None] * fraction  # [n_rays, n_samples + 1]
    # Rounding can put the last edge a hair beyond far: pin both ends exactly.
    t_edges = torch.cat([near[:, None], t_edges[:, 1:-1].clamp(near[:, None], far[:, None]), far[:, None]], dim=-1)
    return t_edges


def midpoints(t_edges: torch.Tensor) -> torch.Tensor:
    """Interval midpoints: t_edges [n_rays, n_samples + 1] -> t_mid [n_rays, n_samples]."""
    _check_edges(t_edges)
    return 0.5 * (t_edges[:, 1:] + t_edges[:, :-1])


def deltas(t_edges: torch.Tensor) -> torch.Tensor:
    """Interval lengths: t_edges [n_rays, n_samples + 1] -> delta [n_rays, n_samples] (>= 0 if sorted)."""
    _check_edges(t_edges)
    return t_edges[:, 1:] - t_edges[:, :-1]


@torch.no_grad()
def importance_samples(t_edges: torch.Tensor, weights: torch.Tensor, n_samples: int, perturb: bool = False,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """Hierarchical (coarse-to-fine) sampling by inverting the weights' CDF. Not differentiable (no_grad).

    The coarse weights define a piecewise-constant pdf over the coarse intervals,
        pdf_i = w_i / sum_j w_j,   CDF(t_edges_k) = sum_{i<k} pdf_i,
    and n_samples values u in [0, 1) are mapped through the inverse CDF (linear within an
    interval, found with torch.searchsorted). With perturb=False, u_k = (k + 1/2) / n_samples
    (deterministic); with perturb=True, u_k = (k + U[0,1)) / n_samples (stratified in u).
    A ray whose weights are all zero (or whose sum is not positive) falls back to the
    uniform pdf over its coarse intervals, so the result is always finite. Zero-length
    intervals (near == far) give samples at that single t.

    t_edges: [n_rays, n_coarse + 1] sorted; weights: [n_rays, n_coarse] >= 0.
    Returns t [n_rays, n_samples], sorted along each ray, within [t_edges[:, 0], t_edges[:, -1]].
    The fine pass uses the union of coarse edges and these t as its bin edges (`merge_edges`).
    """
    _check_edges(t_edges)
    n_rays, n_coarse = t_edges.shape[0], t_edges.shape[1] - 1
    _check_samples("weights", weights, n_rays, n_coarse)
    _check(isinstance(n_samples, int) and n_samples >= 1, f"n_samples must be an integer >= 1, got {n_samples!r}")
    weights = weights.detach().to(t_edges.dtype).clamp_min(0.0)  # [n_rays, n_coarse]
    total = weights.sum(dim=-1, keepdim=True)  # [n_rays, 1]
    uniform = torch.full_like(weights, 1.0 / n_coarse)
    pdf = torch.where(total > 0, weights / torch.where(total > 0, total, torch.ones_like(total)), uniform)
    cdf = torch.cumsum(pdf, dim=-1).clamp_max(1.0)  # [n_rays, n_coarse]
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf[:, :-1], torch.ones_like(cdf[:, :1])], dim=-1)  # [n_rays, n_coarse + 1]

    offsets = torch.arange(n_samples, dtype=t_edges.dtype, device=t_edges.device)  # [n_samples]
    if perturb:
        u = (offsets + torch.rand((n_rays, n_samples), dtype=t_edges.dtype, device=t_edges.device,
                                  generator=generator)) / n_samples  # [n_rays, n_samples]
    else:
        u = ((offsets + 0.5) / n_samples).expand(n_rays, n_samples)  # [n_rays, n_samples]
    u = u.contiguous()

    # Interval k with cdf[k] <= u < cdf[k + 1]; intervals of zero probability are never chosen.
    upper = torch.searchsorted(cdf, u, right=True).clamp(1, n_coarse)  # [n_rays, n_samples]
    lower = upper - 1
    cdf_lo, cdf_hi = cdf.gather(-1, lower), cdf.gather(-1, upper)  # [n_rays, n_samples]
    t_lo, t_hi = t_edges.gather(-1, lower), t_edges.gather(-1, upper)  # [n_rays, n_samples]
    span = cdf_hi - cdf_lo
    fraction = torch.where(span > 0, (u - cdf_lo) / torch.where(span > 0, span, torch.ones_like(span)),
                           torch.zeros_like(span)).clamp(0.0, 1.0)
    t = t_lo + fraction * (t_hi - t_lo)  # [n_rays, n_samples]
    return t.clamp(t_edges[:, :1], t_edges[:, -1:])


@torch.no_grad()
def merge_edges(t_edges: torch.Tensor, t_new: torch.Tensor) -> torch.Tensor:
    """Union of bin edges [n_rays, S + 1] and new t values [n_rays, K], sorted: [n_rays, S + K + 1]. No grad."""
    _check_edges(t_edges)
    _check(t_new.ndim == 2 and t_new.shape[0] == t_edges.shape[0],
           f"t_new must be [n_rays = {t_edges.shape[0]}, k], got shape {tuple(t_new.shape)}")
    return torch.sort(torch.cat([t_edges, t_new.to(t_edges.dtype)], dim=-1), dim=-1).values


# --------------------------------------------------------------------------------------
# weights, accumulation, depth, compositing (differentiable)


def weights_from_density(sigmas: torch.Tensor, deltas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Volume-rendering weights from densities on intervals.

        tau_i = clamp(sigma_i * delta_i, 0, TAU_MAX),  tau_i = 0 where delta_i = 0
        alpha_i = 1 - exp(-tau_i)                   (computed as -expm1(-tau_i))
        T_i = exp(-sum_{j<i} tau_j)                 (exclusive cumulative sum, never cumsum - tau)
        w_i = T_i * alpha_i

    Every factor lies in [0, 1] and nothing overflows, so values and gradients w.r.t. sigma
    are finite for any sigma in [0, inf] (an exp activation that overflowed included) and
    delta >= 0: a zero-length interval contributes tau = 0 rather than inf * 0, and the
    clamp zeroes the gradient only where exp(-tau) is already 0 in float64.

    sigmas: [n_rays, n_samples] in [0, inf], deltas: [n_rays, n_samples] >= 0 (same dtype).
    Returns weights, transmittance, alphas, each [n_rays, n_samples].
    """
    _check(sigmas.ndim == 2, f"sigmas must be [n_rays, n_samples], got shape {tuple(sigmas.shape)}")
    _check(deltas.shape == sigmas.shape, f"deltas must be [n_rays, n_samples] like sigmas {tuple(sigmas.shape)}, got shape {tuple(deltas.shape)}")
    _check(bool((sigmas >= 0).all()), f"sigmas must be >= 0 (inf is allowed, nan is not); got min {sigmas.min().item()}, nan present: {bool(sigmas.isnan().any())}")
    _check(bool((deltas >= 0).all()), f"deltas must be >= 0 (sorted edges); smallest is {deltas.min().item()}")
    tau = torch.where(deltas > 0, sigmas * deltas, torch.zeros_like(sigmas)).clamp(0.0, TAU_MAX)  # [n_rays, n_samples]
    alphas = -torch.expm1(-tau)  # [n_rays, n_samples]
    optical_depth = torch.cumsum(tau, dim=-1)  # [n_rays, n_samples]
    exclusive = torch.cat([torch.zeros_like(tau[:, :1]), optical_depth[:, :-1]], dim=-1)  # [n_rays, n_samples]
    transmittance = torch.exp(-exclusive)  # [n_rays, n_samples]
    weights = transmittance * alphas  # [n_rays, n_samples]
    return weights, transmittance, alphas


def accumulate_along_rays(weights: torch.Tensor, values: torch.Tensor | None = None) -> torch.Tensor:
    """sum_i w_i v_i along each ray.

    weights: [n_rays, n_samples]; values: [n_rays, n_samples, C], or None to sum the weights
    themselves (opacity). Returns [n_rays, C], or [n_rays] when values is None.
    """
    _check(weights.ndim == 2, f"weights must be [n_rays, n_samples], got shape {tuple(weights.shape)}")
    if values is None:
        return weights.sum(dim=-1)  # [n_rays]
    _check(values.ndim == 3 and values.shape[:2] == weights.shape,
           f"values must be [n_rays, n_samples, C] with [n_rays, n_samples] = {list(weights.shape)}, got shape {tuple(values.shape)}")
    return (weights[..., None] * values).sum(dim=-2)  # [n_rays, C]


def expected_depth(weights: torch.Tensor, t_mid: torch.Tensor, opacity: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor, eps: float = DEPTH_EPS) -> torch.Tensor:
    """Expected ray distance of the visible surface, normalised by opacity.

        D = sum_i w_i t_mid_i / max(A, eps),   then clamped into [near, far] where A > 0

    A = sum_i w_i (`opacity`). The weighted mean of midpoints lies in [near, far]; the clamp
    only catches A < eps and rounding. Rays with A == 0 get D = 0, the dataset's value for
    pixels that hit nothing.

    weights, t_mid: [n_rays, n_samples]; opacity, near, far: [n_rays]. Returns [n_rays].
    """
    _check(t_mid.shape == weights.shape, f"t_mid must be [n_rays, n_samples] like weights {tuple(weights.shape)}, got shape {tuple(t_mid.shape)}")
    n_rays = weights.shape[0]
    for name, tensor in (("opacity", opacity), ("near", near), ("far", far)):
        _check(tensor.shape == (n_rays,), f"{name} must be [n_rays] = [{n_rays}], got shape {tuple(tensor.shape)}")
    depth = (weights * t_mid).sum(dim=-1) / opacity.clamp_min(eps)  # [n_rays]
    depth = torch.minimum(torch.maximum(depth, near), far)  # [n_rays]
    return torch.where(opacity > 0, depth, torch.zeros_like(depth))


def composite(rgb: torch.Tensor, opacity: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Composite premultiplied colour over a background: rgb + (1 - A) * background.

    rgb: [n_rays, 3]; opacity: [n_rays]; background: [3] (one colour, e.g. white for
    metrics) or [n_rays, 3] (e.g. random per ray during training). Returns [n_rays, 3].
    """
    _check(rgb.ndim == 2 and rgb.shape[-1] == 3, f"rgb must be [n_rays, 3], got shape {tuple(rgb.shape)}")
    _check(opacity.shape == rgb.shape[:1], f"opacity must be [n_rays] = [{rgb.shape[0]}], got shape {tuple(opacity.shape)}")
    background = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
    _check(background.shape in ((3,), tuple(rgb.shape)),
           f"background must be [3] or [n_rays, 3] = {list(rgb.shape)}, got shape {tuple(background.shape)}")
    return rgb + (1.0 - opacity)[:, None] * background  # [n_rays, 3]


# --------------------------------------------------------------------------------------
# rays into pixels: the pixel filter in linear light

# A ray's opacity below this counts as empty when its straight colour is taken (rgb / A).
STRAIGHT_EPS = 1e-6


def srgb_to_linear(encoded: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 decoding, elementwise, of values on [0, 1] (clamped first). Any shape."""
    x = encoded.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 encoding, elementwise, of values on [0, 1] (clamped first). Any shape.
    The power branch reads its input clamped to its own domain, so the gradient stays finite
    at 0 (x^(1/2.4) has an infinite slope there; the linear segment is what is taken)."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def pixel_mean(rgb: torch.Tensor, opacity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean of S rays through each of P pixels, taken as the ground truth's pixel filter
    takes it: in linear light. The renderer (Mitsuba, a camera) averages radiance over the
    pixel, and the image stores the straight colour of that mean in sRGB; the model's
    colours are sRGB. The mean of sRGB values is not the sRGB of the mean: a pixel half
    black, half white is 0.735 in the ground truth and 0.5 as a mean of sRGB rays, so a
    texture edge or a defocused one cannot be fit by the right colours on both sides.
    Alpha is a coverage and averages as it is.

        A = mean_s a_s,  L = mean_s lin(c_s) a_s,  c_s = rgb_s / a_s (straight sRGB)
        pixel rgb = srgb(L / A) * A  (premultiplied sRGB, as a ray's)

    One ray (S = 1) returns its own values (to rounding). rgb: [S, P, 3] premultiplied
    sRGB; opacity: [S, P]. Returns rgb [P, 3], opacity [P]."""
    _check(rgb.ndim == 3 and rgb.shape[-1] == 3, f"rgb must be [S, P, 3], got shape {tuple(rgb.shape)}")
    _check(opacity.shape == rgb.shape[:2], f"opacity must be [S, P] = {list(rgb.shape[:2])}, got {tuple(opacity.shape)}")
    straight = rgb / opacity.clamp_min(STRAIGHT_EPS)[..., None]  # [S, P, 3]
    linear = (srgb_to_linear(straight) * opacity[..., None]).mean(dim=0)  # [P, 3] premultiplied
    mean_opacity = opacity.mean(dim=0)  # [P]
    return linear_to_srgb(linear / mean_opacity.clamp_min(STRAIGHT_EPS)[:, None]) * mean_opacity[:, None], mean_opacity


# --------------------------------------------------------------------------------------
# the whole ray


@dataclass
class RenderOutput:
    """What `render_rays` returns. `coarse` holds the coarse pass when importance sampling ran."""

    rgb: torch.Tensor  # [n_rays, 3], composited if a background was given, else premultiplied
    depth: torch.Tensor  # [n_rays], expected ray distance (0 where opacity == 0)
    opacity: torch.Tensor  # [n_rays]
    weights: torch.Tensor  # [n_rays, n_samples]
    t_edges: torch.Tensor  # [n_rays, n_samples + 1]
    coarse: "RenderOutput | None" = None


def _evaluate_field(field_fn: FieldFn, positions: torch.Tensor, directions: torch.Tensor,
                    sample_mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Call the field on every sample, or only on masked ones (scattered back with sigma = 0)."""
    n_rays, n_samples = positions.shape[:2]
    if sample_mask is None:
        sigmas, rgbs = field_fn(positions, directions)
        _check_samples("field_fn's sigma", sigmas, n_rays, n_samples)
        _check_samples("field_fn's rgb", rgbs, n_rays, n_samples, (3,))
        return sigmas, rgbs
    kept = int(sample_mask.sum())
    sigmas_kept, rgbs_kept = field_fn(positions[sample_mask], directions[sample_mask])  # [kept], [kept, 3]
    _check(tuple(sigmas_kept.shape) == (kept,), f"field_fn's sigma on masked samples must be [{kept}], got shape {tuple(sigmas_kept.shape)}")
    _check(tuple(rgbs_kept.shape) == (kept, 3), f"field_fn's rgb on masked samples must be [{kept}, 3], got shape {tuple(rgbs_kept.shape)}")
    sigmas = sigmas_kept.new_zeros((n_rays, n_samples)).index_put((sample_mask,), sigmas_kept)  # [n_rays, n_samples]
    rgbs = rgbs_kept.new_zeros((n_rays, n_samples, 3)).index_put((sample_mask,), rgbs_kept)  # [n_rays, n_samples, 3]
    return sigmas, rgbs


def render_along_edges(field_fn: FieldFn, origins: torch.Tensor, directions: torch.Tensor, t_edges: torch.Tensor,
                       sample_mask: torch.Tensor | None = None) -> RenderOutput:
    """One pass: evaluate the field at interval midpoints and integrate (no background).

    origins, directions: [n_rays, 3]; t_edges: [n_rays, n_samples + 1] sorted;
    sample_mask: optional [n_rays, n_samples] bool, samples to evaluate (others get sigma = 0
    and are never passed to field_fn). Returns premultiplied rgb.
    """
    n_rays, n_samples = t_edges.shape[0], t_edges.shape[1] - 1
    t_mid = midpoints(t_edges)  # [n_rays, n_samples]
    positions = origins[:, None, :] + t_mid[..., None] * directions[:, None, :]  # [n_rays, n_samples, 3]
    view_dirs = directions[:, None, :].expand(n_rays, n_samples, 3)  # [n_rays, n_samples, 3]
    sigmas, rgbs = _evaluate_field(field_fn, positions, view_dirs, sample_mask)
    weights, _, _ = weights_from_density(sigmas, deltas(t_edges))  # [n_rays, n_samples]
    opacity = accumulate_along_rays(weights)  # [n_rays]
    rgb = accumulate_along_rays(weights, rgbs)  # [n_rays, 3]
    depth = expected_depth(weights, t_mid, opacity, t_edges[:, 0], t_edges[:, -1])  # [n_rays]
    return RenderOutput(rgb=rgb, depth=depth, opacity=opacity, weights=weights, t_edges=t_edges)


def render_rays(field_fn: FieldFn, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor | float,
                far: torch.Tensor | float, n_samples: int, *, n_importance: int = 0,
                fine_field_fn: FieldFn | None = None, perturb: bool = False,
                generator: torch.Generator | None = None, background: torch.Tensor | None = None,
                sample_mask: torch.Tensor | None = None) -> RenderOutput:
    """Render rays through a radiance field given as a callback.

        field_fn(positions [..., 3], directions [..., 3]) -> (sigma [...] in [0, inf], rgb [..., 3])

    is called with [n_rays, n_samples, 3] tensors, or with [n_kept, 3] when sample_mask is
    given (only the kept samples: empty-space skipping skips the work, not just the result).
    Directions are the ray directions as given (normalise them for unit ray distance).

    Stratified samples (`stratified_edges`) on [near, far]; if n_importance > 0, a fine pass
    evaluates `fine_field_fn` (default: field_fn) on the union of the coarse edges and
    n_importance samples drawn from the coarse weights (`importance_samples`), as NeRF does.

    origins, directions: [n_rays, 3]; near, far: [n_rays] or numbers, far >= near;
    background: None (premultiplied rgb), [3] or [n_rays, 3] (see `composite`);
    sample_mask: [n_rays, n_samples] bool for the stratified samples, e.g. from an occupancy
    grid; it cannot be combined with importance sampling.
    Returns a RenderOutput (the fine pass, with `.coarse` set when n_importance > 0).
    """
    _check_rays(origins, directions)
    n_rays = origins.shape[0]
    near = _as_per_ray(near, n_rays, origins, "near")
    far = _as_per_ray(far, n_rays, origins, "far")
    _check(isinstance(n_importance, int) and n_importance >= 0, f"n_importance must be an integer >= 0, got {n_importance!r}")
    if sample_mask is not None:
        _check(n_importance == 0, "sample_mask cannot be combined with importance sampling (n_importance > 0)")
        _check(sample_mask.dtype == torch.bool and tuple(sample_mask.shape) == (n_rays, n_samples),
               f"sample_mask must be bool [n_rays, n_samples] = [{n_rays}, {n_samples}], "
               f"got {sample_mask.dtype} shape {tuple(sample_mask.shape)}")
    t_edges = stratified_edges(near, far, n_samples, perturb=perturb, generator=generator)  # [n_rays, n_samples + 1]
    output = render_along_edges(field_fn, origins, directions, t_edges, sample_mask)
    if n_importance > 0:
        t_fine = importance_samples(t_edges, output.weights, n_importance, perturb=perturb, generator=generator)
        fine_edges = merge_edges(t_edges, t_fine)  # [n_rays, n_samples + n_importance + 1]
        coarse = output
        fine_fn = field_fn if fine_field_fn is None else fine_field_fn
        output = render_along_edges(fine_fn, origins, directions, fine_edges)
        output.coarse = coarse
    if background is not None:
        for out in (output, output.coarse) if output.coarse is not None else (output,):
            out.rgb = composite(out.rgb, out.opacity, background)
    return output


@torch.no_grad()
def render_rays_chunked(model, origins, directions, chunk: int = 16384):
    """Render many rays in chunks through `model.render(origins, directions)` (a field's
    renderer: anything returning `.rgb`, `.opacity`, `.depth`). Returns premultiplied
    rgb [n, 3], opacity [n], depth [n]; no gradients (inference only)."""
    rgb, opacity, depth = [], [], []
    for start in range(0, origins.shape[0], chunk):
        out = model.render(origins[start:start + chunk], directions[start:start + chunk])
        rgb.append(out.rgb), opacity.append(out.opacity), depth.append(out.depth)
    return torch.cat(rgb), torch.cat(opacity), torch.cat(depth)
