"""The brute-force oracle itself (splat.reference behind splat.render): float64 gradcheck of
the whole pipeline (projection, colour, compositing), and cases whose answer is known in
closed form, so that the oracle the rasteriser is held to is right.

gradcheck compares autograd with central differences (eps 1e-6) in float64; it is valid away
from the compositor's discrete rules, so the scene is one whose every decision is at least
1e-4 (relative) from its threshold (splat_scenes.margins): a perturbation of 1e-6 moves an
alpha by far less.
"""

from __future__ import annotations

import math

import pytest
import torch
from nerfgauge.splat.projection import Camera
from nerfgauge.splat.raster import ALPHA_MAX
from nerfgauge.splat.render import render
from nerfgauge.splat.sh import C0
from splat_scenes import activated, camera, clear_seed, scene

from nerfgauge.core.camera import Intrinsics, look_at


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_gradcheck_of_the_whole_pipeline_in_float64(backend):
    """Both compositors (the CPU one's backward is hand-written) against finite differences."""
    cam = camera(width=10, height=7)
    seed = clear_seed(8, torch.float64, cam, margin=1e-4, sh_scale=0.1)
    params = scene(8, seed, sh_scale=0.1)
    params["means"][:4] = params["means"][4:8] * 0.5  # all in view, in front
    names = list(params)
    background = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64)

    def outputs(*tensors):
        out = render(*activated(dict(zip(names, tensors))), cam, background, 3, backend=backend)
        return out.rgb, out.depth, out.opacity

    inputs = tuple(params[name].clone().requires_grad_(True) for name in names)
    rgb, depth, opacity = outputs(*inputs)
    assert float(opacity.detach().max()) > 0.5 and float((depth > 0).float().mean()) > 0.2
    assert torch.autograd.gradcheck(outputs, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def flat_camera(width: int = 16, height: int = 16, centre: float = 8.0) -> Camera:
    """Looking down -z from (0, 0, 4): world x right, world y up on the image; the world
    origin at pixel coordinates (centre, centre)."""
    return Camera.from_c2w(look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)),
                           Intrinsics(width, height, 20.0, 20.0, centre, centre), dtype=torch.float64)


def one_gaussian(mean, scale, opacity, rgb, dtype=torch.float64):
    sh = torch.zeros(1, 16, 3, dtype=dtype)
    sh[0, 0] = (torch.tensor(rgb, dtype=dtype) - 0.5) / C0
    return (torch.tensor([mean], dtype=dtype), torch.tensor([scale], dtype=dtype),
            torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype), torch.tensor([opacity], dtype=dtype), sh)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_one_gaussian_closed_form(backend):
    """One isotropic Gaussian at the image centre: alpha = o exp(-q/2) with the 2D covariance
    (f s / z)^2 + 0.3 at every pixel; colour, opacity and depth follow."""
    cam = flat_camera()
    scale, opacity, rgb, bg = 0.1, 0.7, (0.9, 0.2, 0.4), torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    out = render(*one_gaussian((0.0, 0.0, 0.0), (scale,) * 3, opacity, rgb), cam, bg, 0, backend=backend)
    variance = (20.0 * scale / 4.0) ** 2 + 0.3
    pixels = torch.arange(16, dtype=torch.float64) + 0.5
    ys, xs = torch.meshgrid(pixels, pixels, indexing="ij")
    alpha = opacity * torch.exp(-((xs - 8) ** 2 + (ys - 8) ** 2) / (2 * variance))
    alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
    torch.testing.assert_close(out.opacity, alpha, rtol=1e-12, atol=1e-12)
    expected = alpha[..., None] * torch.tensor(rgb, dtype=torch.float64) + (1 - alpha[..., None]) * bg
    torch.testing.assert_close(out.rgb, expected, rtol=1e-12, atol=1e-12)
    # depth: the camera depth 4 as ray distance along each drawn pixel's centre ray
    ray = torch.sqrt(1 + ((xs - 8) / 20) ** 2 + ((ys - 8) / 20) ** 2)
    torch.testing.assert_close(out.depth, torch.where(alpha > 0, 4 * ray, torch.zeros_like(ray)), rtol=1e-12,
                               atol=1e-12)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_clamp_and_early_termination(backend):
    """Opaque Gaussians stacked at one pixel: alpha clamps at 0.99 (so 1 - T = 1 - 0.01^k),
    and compositing stops before the Gaussian that would take T below 1e-4: two of them
    leave T = 1e-4 exactly, a third (behind) would take it to 1e-6 and is not drawn."""
    cam = flat_camera(centre=8.5)  # pixel (8, 8)'s centre on the means: exp(power) = 1 there
    means, scales, quats, opacities, sh = (torch.cat(parts) for parts in zip(
        one_gaussian((0.0, 0.0, 1.0), (0.5,) * 3, 1.0, (1.0, 0.0, 0.0)),
        one_gaussian((0.0, 0.0, 0.0), (0.5,) * 3, 1.0, (0.0, 1.0, 0.0)),
        one_gaussian((0.0, 0.0, -1.0), (0.5,) * 3, 1.0, (0.0, 0.0, 1.0))))
    means.requires_grad_(True)
    opacities.requires_grad_(True)
    out = render(means, scales, quats, opacities, sh, cam, torch.zeros(3, dtype=torch.float64), 0, backend=backend)
    centre = out.rgb[8, 8]
    assert math.isclose(float(out.opacity[8, 8]), 1 - (1 - ALPHA_MAX) ** 2, rel_tol=1e-12)
    torch.testing.assert_close(centre, torch.tensor([0.99, 0.99 * 0.01, 0.0], dtype=torch.float64))
    # clamped alphas do not move with opacity or position there; the hidden third gets nothing
    (out.rgb[8, 8].sum() + out.opacity[8, 8]).backward()
    assert float(opacities.grad.abs().max()) == 0 and float(means.grad[2].abs().max()) == 0
