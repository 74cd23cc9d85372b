"""A plain per-ray loop of the volume-rendering maths: the test oracle for `nerf.rendering`.

Kept beside the vectorised renderer the way Mitsuba keeps `prb_basic.py` beside `prb.py`:
one ray at a time, one sample at a time, in NeRF's product form (Mildenhall et al. 2020)

    alpha_i = 1 - exp(-sigma_i delta_i),   T_i = prod_{j<i} (1 - alpha_j),   w_i = T_i alpha_i,

instead of the renderer's exp(-exclusive cumulative sum). It works on 0-d torch tensors so
autograd gives gradients to compare. Slow by design; use it on small inputs only, with
moderate sigma * delta (it has none of the renderer's guards against overflow).
"""

from __future__ import annotations

import torch

DEPTH_EPS = 1e-10


def render_reference(sigmas: torch.Tensor, rgbs: torch.Tensor, t_edges: torch.Tensor,
                     background: torch.Tensor | None = None, eps: float = DEPTH_EPS) -> dict[str, torch.Tensor]:
    """Render every ray with Python loops.

    sigmas: [n_rays, n_samples]; rgbs: [n_rays, n_samples, 3]; t_edges: [n_rays, n_samples + 1]
    (interval i is [t_edges[r, i], t_edges[r, i + 1]], its sample at the midpoint);
    background: None, [3] or [n_rays, 3].
    Returns a dict of rgb [n_rays, 3], opacity [n_rays], depth [n_rays], weights
    [n_rays, n_samples]: the same definitions as `nerf.rendering` (depth is the
    opacity-normalised expected midpoint, clamped into [near, far], 0 where opacity is 0).
    """
    n_rays, n_samples = sigmas.shape
    if rgbs.shape != (n_rays, n_samples, 3) or t_edges.shape != (n_rays, n_samples + 1):
        raise ValueError(f"shapes do not match: sigmas {tuple(sigmas.shape)}, rgbs {tuple(rgbs.shape)}, "
                         f"t_edges {tuple(t_edges.shape)}")
    rgb_rows, opacity_rows, depth_rows, weight_rows = [], [], [], []
    for r in range(n_rays):
        near, far = t_edges[r, 0], t_edges[r, n_samples]
        transmittance = torch.ones((), dtype=sigmas.dtype)
        colour = [torch.zeros((), dtype=sigmas.dtype) for _ in range(3)]
        opacity = torch.zeros((), dtype=sigmas.dtype)
        weighted_t = torch.zeros((), dtype=sigmas.dtype)
        weights = []
        for i in range(n_samples):
            t0, t1 = t_edges[r, i], t_edges[r, i + 1]
            delta = t1 - t0
            t_mid = (t0 + t1) / 2
            alpha = 1 - torch.exp(-sigmas[r, i] * delta)
            weight = transmittance * alpha
            for c in range(3):
                colour[c] = colour[c] + weight * rgbs[r, i, c]
            opacity = opacity + weight
            weighted_t = weighted_t + weight * t_mid
            weights.append(weight)
            transmittance = transmittance * (1 - alpha)
        if opacity > 0:
            depth = weighted_t / torch.clamp(opacity, min=eps)
            depth = torch.clamp(depth, min=near, max=far)
        else:
            depth = torch.zeros((), dtype=sigmas.dtype)
        if background is not None:
            bg = background if background.ndim == 1 else background[r]
            colour = [colour[c] + (1 - opacity) * bg[c] for c in range(3)]
        rgb_rows.append(torch.stack(colour))
        opacity_rows.append(opacity)
        depth_rows.append(depth)
        weight_rows.append(torch.stack(weights))
    return {
        "rgb": torch.stack(rgb_rows),
        "opacity": torch.stack(opacity_rows),
        "depth": torch.stack(depth_rows),
        "weights": torch.stack(weight_rows),
    }
