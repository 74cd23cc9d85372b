"""Projection and spherical harmonics against independent implementations.

- gsplat's pure-PyTorch reference (gsplat/cuda/_torch_impl.py: `_fully_fused_projection`,
  `_spherical_harmonics`, Sloan's recurrence), written for gsplat's CUDA kernels, not for
  ours: same means2d, conics and depths for our cameras once turned into its world-to-camera
  OpenCV view matrix; same colours for every degree. float64: 1e-10.
- The project's one camera (core.camera.project): the projected means are its pixel
  coordinates, so the conventions (OpenGL camera-to-world, pixel centres at i + 0.5) agree.
- The EWA linearisation itself, by Monte Carlo: points drawn from a small 3D Gaussian,
  projected with core.camera.project, have the 2D covariance J W Sigma W^T J^T (the conic
  minus the 0.3 low-pass) up to the sampling error and the second-order term of the projection.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfgauge.splat.project_cpu import project_and_colour
from nerfgauge.splat.projection import GL_TO_CV, LOW_PASS, Camera, covariance_3d, project
from nerfgauge.splat.sh import sh_colour
from splat_scenes import camera, scene

from nerfgauge.core.camera import Intrinsics, look_at
from nerfgauge.core.camera import project as camera_project

gsplat_reference = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (the test extra) is not installed")


def gsplat_view(cam: Camera, c2w_gl: np.ndarray, dtype=torch.float64):
    view = torch.tensor(np.linalg.inv(np.asarray(c2w_gl) @ GL_TO_CV), dtype=dtype)[None]  # [1, 4, 4] world to camera
    K = torch.tensor([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]], dtype=dtype)[None]
    return view, K


def test_projection_matches_gsplat():
    params = scene(400, seed=11)
    means, scales, quats = params["means"], torch.exp(params["log_scales"]), params["quats"]
    c2w = look_at((3.0, -2.0, 1.5), (0.0, 0.0, 0.0))
    cam = Camera.from_c2w(c2w, Intrinsics(40, 28, 36.0, 36.8, 20.3, 13.8), dtype=torch.float64)
    ours = project(means, scales, quats, cam)
    covars, _ = gsplat_reference._quat_scale_to_covar_preci(quats, scales, True, False)
    view, K = gsplat_view(cam, c2w)
    radii, means2d, depths, conics, _ = gsplat_reference._fully_fused_projection(means, covars, view, K, 40, 28,
                                                                                 eps2d=LOW_PASS)
    front = ours.in_front
    assert 300 < int(front.sum()) < 400  # the scene's few behind the camera are out
    torch.testing.assert_close(ours.depths, depths[0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.means2d[front], means2d[0][front], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ours.conics[front], conics[0][front], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(covariance_3d(scales, quats), covars, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_match_gsplat(degree):
    g = torch.Generator().manual_seed(degree)
    coefficients = torch.randn(500, 16, 3, generator=g, dtype=torch.float64)
    directions = torch.randn(500, 3, generator=g, dtype=torch.float64)
    theirs = torch.clamp_min(gsplat_reference._spherical_harmonics(degree, directions, coefficients) + 0.5, 0.0)
    torch.testing.assert_close(sh_colour(coefficients, directions, degree), theirs, rtol=1e-12, atol=1e-12)


def test_projected_means_are_the_cameras_pixel_coordinates():
    params = scene(200, seed=12)
    cam = camera()
    c2w = look_at((3.0, -2.0, 1.5), (0.0, 0.0, 0.0))
    intrinsics = Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    ours = project(params["means"], torch.exp(params["log_scales"]), params["quats"], cam)
    u, v, _ = camera_project(params["means"].numpy(), c2w, intrinsics)
    front = ours.in_front.numpy()
    np.testing.assert_allclose(ours.means2d[front].numpy(), np.stack([u, v], axis=1)[front], rtol=0, atol=1e-10)
    assert np.isnan(u[~front]).all()  # behind the camera: core.camera says so too


def test_ewa_covariance_is_that_of_projected_samples():
    """For a Gaussian of std s at distance d, the projection's second-order term is
    O((s/d)^2) relative: with s/d = 0.5% the linearised covariance should match the samples'
    to the Monte Carlo error (2 sqrt(2/n) relative for n samples: 0.6% at 200,000) plus ~0.1%."""
    c2w = look_at((0.4, -3.0, 1.2), (0.0, 0.0, 0.0))
    cam = Camera.from_c2w(c2w, Intrinsics(64, 48, 60.0, 62.0, 31.0, 25.0), dtype=torch.float64)
    rng = np.random.default_rng(0)
    for mean, scale in (((0.2, 0.1, -0.1), (0.012, 0.004, 0.008)), ((-0.4, 0.3, 0.2), (0.002, 0.015, 0.006))):
        quat = torch.tensor([[0.8, 0.3, -0.4, 0.2]], dtype=torch.float64)
        projected = project(torch.tensor([mean], dtype=torch.float64), torch.tensor([scale], dtype=torch.float64),
                            quat, cam)
        a, b, c = projected.conics[0].tolist()
        linear = np.linalg.inv([[a, b], [b, c]]) - LOW_PASS * np.eye(2)
        sigma = covariance_3d(torch.tensor([scale], dtype=torch.float64), quat)[0].numpy()
        samples = rng.multivariate_normal(mean, sigma, size=200_000)
        u, v, _ = camera_project(samples, c2w, Intrinsics(64, 48, 60.0, 62.0, 31.0, 25.0))
        empirical = np.cov(np.stack([u, v]))
        assert np.abs(empirical - linear).max() <= 0.008 * np.abs(linear).max(), (empirical, linear)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_fused_projection_and_colour_match_the_torch_definitions(degree):
    """splat.project_cpu (compiled, hand-written backward) against splat.projection and
    splat.sh (torch, autograd) in float64: values and every gradient to 1e-12 of each
    tensor's largest magnitude (measured ~1e-15), on a scene with Gaussians behind the
    camera, one far outside the view (its Jacobian clamped) and a zero quaternion."""
    params = scene(300, seed=13)
    params["quats"][5] = 0.0
    results = []
    for fused in (True, False):
        leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
        means, scales, quats, sh = leaves["means"], torch.exp(leaves["log_scales"]), leaves["quats"], leaves["sh"]
        cam = camera()
        if fused:
            projected, colours = project_and_colour(means, scales, quats, sh, degree, cam)
        else:
            projected, colours = project(means, scales, quats, cam), sh_colour(sh, means - cam.centre, degree)
        drawn = projected.in_front
        g = torch.Generator().manual_seed(degree)
        outputs = [projected.means2d[drawn], projected.conics[drawn], projected.depths[drawn], colours[drawn]]
        total = sum((t * torch.randn(t.shape, generator=g, dtype=torch.float64)).sum() for t in outputs)
        grads = torch.autograd.grad(total, [leaves["means"], leaves["log_scales"], leaves["quats"], leaves["sh"]])
        results.append([drawn, projected.cov2d_diagonal[drawn], *outputs, *grads])
    assert bool(results[0][0][3]) and not bool(results[0][0][5])  # far outside the view: drawn; no rotation: not
    for a, b in zip(*results):
        a, b = a.detach().double(), b.detach().double()
        assert float((a - b).abs().max()) <= 1e-12 * max(float(b.abs().max()), 1e-30)
