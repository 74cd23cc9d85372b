"""The brute-force compositor: every Gaussian at every pixel, torch autograd. The tests' oracle
for `splat.raster` (Mitsuba keeps `prb_basic.py` beside `prb.py` the same way).

The same maths as the tiled rasteriser, written the plain way: all V drawn Gaussians sorted by
depth once for the whole image, alpha evaluated at all P pixel centres ([P, V]), and the
sequential rules of the front-to-back loop as masks:

    alpha_pi = min(0.99, o_i exp(power_pi)), set to 0 where < 1/255 or power_pi > 0
    T_pi     = prod_{j < i} (1 - alpha_pj)                     (exclusive cumulative product)
    kept_pi  = T_pi (1 - alpha_pi) >= 1e-4                     (T only falls: a prefix of the list)
    F_p = sum_i kept alpha T f_i,   A_p = sum_i kept alpha T

No tiles, no binning, no hand-written backward: gradients come from autograd. Memory is
P x V, so it is for small images and scenes only (tests: 32 x 24 pixels, a few hundred
Gaussians). `render_reference` puts it behind the same projection and colour as `splat.render`.
"""

from __future__ import annotations

import torch

from nerfgauge.splat.raster import ALPHA_MAX, T_MIN
from nerfgauge.splat.tiles import ALPHA_MIN


def composite_reference(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                        features: torch.Tensor, depths: torch.Tensor, width: int, height: int
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """F [H, W, C] and A [H, W] of V Gaussians (module docstring).

    means2d: [V, 2]; conics: [V, 3]; opacities: [V]; features: [V, C]; depths: [V] (the
    order, front first). All in one dtype; float64 for gradcheck."""
    order = torch.argsort(depths.detach(), stable=True)  # [V]
    means2d, conics, opacities, features = means2d[order], conics[order], opacities[order], features[order]
    dtype, device = means2d.dtype, means2d.device
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                            torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")  # [H, W] each
    dx = means2d[None, :, 0] - xs.reshape(-1, 1)  # [P, V]
    dy = means2d[None, :, 1] - ys.reshape(-1, 1)  # [P, V]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]  # [V] each
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy  # [P, V]
    alpha = torch.clamp(opacities * torch.exp(power), max=ALPHA_MAX)  # [P, V]
    drawn = (alpha >= ALPHA_MIN) & (power <= 0)  # [P, V]
    alpha = torch.where(drawn, alpha, torch.zeros_like(alpha))  # [P, V]
    after = torch.cumprod(1.0 - alpha, dim=1)  # [P, V]: T after each Gaussian
    before = torch.cat([torch.ones_like(after[:, :1]), after[:, :-1]], dim=1)  # [P, V]: T_pi
    kept = (after >= T_MIN).to(dtype)  # [P, V]
    weights = alpha * before * kept  # [P, V]
    out = weights @ features  # [P, C]
    return out.reshape(height, width, -1), weights.sum(dim=1).reshape(height, width)
