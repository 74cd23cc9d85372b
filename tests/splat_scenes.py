"""Small random Gaussian scenes for the splatting tests (tests/test_splat_*.py), and the
check that a scene keeps clear of the compositor's discrete rules.

A scene: N Gaussians spread over [-0.8, 0.8]^3, seen from about 3.9 units, scales 0.01-0.17
(most cover 2-10 pixels at 40 x 28 px, so they overlap and cross tile borders), random
rotations, opacities over the whole range (logits ~ N(0, 2^2)), degree-3 colour; a few placed
behind the camera, one far outside the view.

The rasteriser and its oracle both make discrete decisions (alpha >= 1/255, the 0.99 clamp,
stopping where T would drop below 1e-4). Tests that compare gradients by finite differences
(gradcheck) need every decision away from its threshold by more than the perturbation:
`margins` measures how close a scene comes, from the oracle's own [pixels, Gaussians] tables.
"""

from __future__ import annotations

import numpy as np
import torch
from nerfgauge.splat.projection import Camera, project
from nerfgauge.splat.raster import ALPHA_MAX, T_MIN
from nerfgauge.splat.tiles import ALPHA_MIN

from nerfgauge.core.camera import Intrinsics, look_at

EYE = (3.0, -2.0, 1.5)


def camera(width: int = 40, height: int = 28, dtype=torch.float64) -> Camera:
    intrinsics = Intrinsics(width, height, 0.9 * width, 0.92 * width, width / 2 + 0.3, height / 2 - 0.2)
    return Camera.from_c2w(look_at(EYE, (0.0, 0.0, 0.0)), intrinsics, dtype=dtype)


def scene(n: int = 300, seed: int = 0, dtype=torch.float64, sh_scale: float = 0.3) -> dict:
    """{means, log_scales, quats, logits, sh} tensors of one dtype (leaves, no grad)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * 0.8
    means[:3] = torch.tensor(EYE, dtype=dtype) * 1.2  # behind the camera
    means[3] = torch.tensor([0.0, 0.0, 9.0], dtype=dtype)  # far outside the view
    log_scales = torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.16 + 0.01)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    logits = torch.randn(n, generator=g, dtype=dtype) * 2
    sh = torch.randn(n, 16, 3, generator=g, dtype=dtype) * sh_scale
    return {"means": means, "log_scales": log_scales, "quats": quats, "logits": logits, "sh": sh}


def activated(params: dict) -> tuple:
    """(means, scales, quats, opacities, sh) as splat.render.render takes them."""
    return (params["means"], torch.exp(params["log_scales"]), params["quats"], torch.sigmoid(params["logits"]),
            params["sh"])


@torch.no_grad()
def margins(params: dict, cam: Camera) -> dict:
    """The smallest relative distance, over every (pixel, drawn Gaussian) pair, of alpha to
    1/255, of o exp(power) to 0.99, and of T after a Gaussian to 1e-4 (pairs where the pixel
    has not stopped). 1e-3 means every decision would survive a 0.1% change."""
    means, scales, quats, opacities, _ = (t.double() for t in activated(params))
    p = project(means, scales, quats, cam.to(torch.float64))
    keep = p.in_front
    order = torch.argsort(p.depths[keep])
    m, c, o = p.means2d[keep][order], p.conics[keep][order], opacities[keep][order]
    ys, xs = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64) + 0.5,
                            torch.arange(cam.width, dtype=torch.float64) + 0.5, indexing="ij")
    dx, dy = m[None, :, 0] - xs.reshape(-1, 1), m[None, :, 1] - ys.reshape(-1, 1)
    raw = o * torch.exp(-0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) - c[:, 1] * dx * dy)
    alpha = torch.where(torch.clamp(raw, max=ALPHA_MAX) >= ALPHA_MIN, torch.clamp(raw, max=ALPHA_MAX),
                        torch.zeros_like(raw))
    after = torch.cumprod(1 - alpha, dim=1)
    live = torch.cat([torch.ones_like(after[:, :1], dtype=torch.bool), after[:, :-1] >= T_MIN], dim=1)
    relative = lambda value, bound: ((value - bound).abs() / bound)[live].min().item() if live.any() else 1.0  # noqa: E731
    return {"alpha_min": relative(raw, ALPHA_MIN), "alpha_max": relative(raw, ALPHA_MAX),
            "t_min": relative(after, T_MIN)}


def clear_seed(n: int, dtype, cam: Camera, start: int = 0, margin: float = 1e-3, **options) -> int:
    """The first seed from `start` whose scene keeps every decision `margin` away (`margins`)."""
    for seed in range(start, start + 200):
        if min(margins(scene(n, seed, dtype, **options), cam).values()) > margin:
            return seed
    raise AssertionError(f"no seed in {start}..{start + 199} gives a scene {margin} clear of the thresholds")


def grads_of(outputs: dict, params: dict, seed: int = 7) -> dict:
    """Gradients of a fixed random linear functional of rgb, depth and opacity (every output
    and pixel weighted) with respect to every parameter."""
    g = torch.Generator().manual_seed(seed)
    total = sum((outputs[name] * torch.randn(outputs[name].shape, generator=g, dtype=torch.float64)
                 .to(outputs[name].dtype)).sum() for name in ("rgb", "depth", "opacity"))
    grads = torch.autograd.grad(total, [params[name] for name in params])
    return dict(zip(params, grads))


def as_numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().double().numpy()
