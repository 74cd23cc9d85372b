"""Degenerate Gaussians among ordinary ones: zero scale, behind the camera, covering the whole
image, a zero quaternion, huge coordinates, NaN from an upstream step. The render stays
finite (and for every finite input, so do the gradients, equal to the oracle's); NaN
parameters in training stop it with NumericalError (exit 3 at the command line)."""

from __future__ import annotations

import math

import pytest
import torch
from nerfgauge.splat.render import render
from nerfgauge.splat.train import _check_finite
from splat_scenes import activated, camera, grads_of, scene

from nerfgauge.core.errors import NumericalError


def degenerate_scene(dtype=torch.float64) -> dict:
    params = scene(60, seed=21, dtype=dtype)
    params["log_scales"][10] = -math.inf  # zero scale: the low-pass still draws it
    params["log_scales"][11] = torch.tensor([-200.0, 0.0, -1.0])  # flat
    params["means"][12] = torch.tensor([0.0, 0.0, 0.0])
    params["log_scales"][12] = math.log(30.0)  # covers the whole image, and the camera
    params["logits"][12] = -1.0
    params["quats"][13] = 0.0  # no rotation at all
    params["means"][14] = torch.tensor([1e30, -1e30, 1e30])  # overflows the projection
    params["means"][15] = torch.tensor([3.0, -2.0, 1.5])  # at the camera centre
    return params


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_degenerate_gaussians_render_finite_with_finite_gradients(backend):
    cam = camera()
    params = {k: v.clone().requires_grad_(True) for k, v in degenerate_scene().items()}
    out = render(*activated(params), cam, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64), 3, backend=backend)
    for name in ("rgb", "depth", "opacity"):
        assert bool(torch.isfinite(getattr(out, name)).all()), name
    assert float(out.opacity.min()) > 0.05  # the whole-image Gaussian is drawn everywhere
    grads = grads_of({"rgb": out.rgb, "depth": out.depth, "opacity": out.opacity}, params)
    for name, grad in grads.items():
        assert bool(torch.isfinite(grad).all()), name
    assert not bool(out.visible[[0, 1, 2, 13, 14, 15]].any())  # behind, no rotation, overflowed, at the centre


def test_degenerate_gaussians_match_the_oracle():
    cam = camera()
    outputs = []
    for backend in ("cpu", "reference"):
        params = {k: v.clone().requires_grad_(True) for k, v in degenerate_scene().items()}
        out = render(*activated(params), cam, torch.zeros(3, dtype=torch.float64), 3, backend=backend)
        outputs.append([out.rgb, out.depth, out.opacity,
                        *grads_of({"rgb": out.rgb, "depth": out.depth, "opacity": out.opacity}, params).values()])
    for a, b in zip(*outputs):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * max(float(b.abs().max()), 1e-30))


@pytest.mark.parametrize("name,index", [("means", (20, 1)), ("log_scales", (21, 0)), ("quats", (22, 2)),
                                        ("logits", (23,)), ("sh", (24, 0, 1)), ("sh", (25, 9, 2))])
def test_nan_from_upstream_leaves_the_image_finite(name, index):
    """A NaN parameter makes its Gaussian undrawn, in the render (the others unchanged)."""
    cam = camera(dtype=torch.float32)
    params = scene(60, seed=22, dtype=torch.float32)
    clean = render(*activated(params), cam, torch.ones(3), 3)
    params[name][index] = math.nan
    out = render(*activated(params), cam, torch.ones(3), 3)
    for image in (out.rgb, out.depth, out.opacity):
        assert bool(torch.isfinite(image).all())
    assert not bool(out.visible[index[0]]) and bool(clean.visible[index[0]])


def test_nan_in_a_parameter_or_gradient_is_a_numerical_error():
    from nerfgauge.splat.gaussians import GaussianAdam, Gaussians  # the training's own check

    params = scene(10, seed=23, dtype=torch.float32)
    gaussians = Gaussians(params["means"].clone(), params["log_scales"].clone(), params["quats"].clone(),
                          params["logits"].clone(), params["sh"][:, :1].clone(), params["sh"][:, 1:].clone())
    adam = GaussianAdam(gaussians, dict.fromkeys(("means", "log_scales", "quats", "opacity_logits", "sh_dc",
                                                  "sh_rest"), 1e-3))
    loss = torch.tensor(1.0)
    _check_finite(loss, adam, 5, "parameter")  # all finite: no error
    with torch.no_grad():
        gaussians.sh_rest[3, 4, 1] = math.nan
    with pytest.raises(NumericalError, match="step 5.*parameter after the step"):
        _check_finite(loss, adam, 5, "parameter")
    with pytest.raises(NumericalError, match="step 7"):
        _check_finite(torch.tensor(math.inf), adam, 7, "gradient")
