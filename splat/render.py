"""One view of a set of Gaussians: projection, colour, binning, compositing, background.

    project (splat.projection)  ->  means2d [N, 2], conics [N, 3], camera depths t_z [N]
    colour  (splat.sh)          ->  c_i = SH(mu_i - camera centre) [V, 3] for the V drawn Gaussians
    composite                   ->  F = sum_i alpha_i T_i (c_i, t_z,i),  A = sum_i alpha_i T_i
    rgb   = F_rgb + (1 - A) background
    depth = (F_z / A) |(x, y, 1)|        expected camera depth, turned into ray distance along each
                                          pixel's centre ray (docs/conventions.md: depth ground truth
                                          is ray distance); 0 where A = 0
    opacity = A

A Gaussian's depth enters as its mean's camera depth t_z; along the pixel's ray the plane
t_z = const lies at ray distance t_z |(x, y, 1)| (x, y the pixel's normalised coordinates), so
the expected depth converts per pixel exactly as core.camera.z_depth_from_distance converts
the ground truth the other way.

Backends: "cpu", projection and colour fused in compiled loops (`splat.project_cpu`) and the
tiled numba rasteriser (`splat.raster`), both with hand-written backwards; "reference", the
torch projection and colour (`splat.projection`, `splat.sh`) and the brute-force compositor
(`splat.reference`), all autograd: the oracle, sharing no code with "cpu" but the
visibility rule; "gsplat",
gsplat's CUDA `rasterization` (on a CUDA device when gsplat imports: `backend_for`). The
gsplat path is not exercised by the tests here (no GPU on the machines they ran on); it clamps
alpha at 0.999 where ours clamps at 0.99, which is its own rasteriser's rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerfgauge.splat.project_cpu import project_and_colour
from nerfgauge.splat.projection import NEAR, Camera, project
from nerfgauge.splat.raster import rasterise
from nerfgauge.splat.reference import composite_reference
from nerfgauge.splat.sh import sh_colour
from nerfgauge.splat.tiles import bin_gaussians, footprint_box

BACKENDS = ("cpu", "reference", "gsplat")
DEPTH_EPS = 1e-10  # A below this renders depth 0: nothing was hit


@dataclass
class Rendered:
    """rgb [H, W, 3] (composited on the background), depth [H, W] (ray distance, 0 where
    opacity is 0), opacity [H, W]; means2d [N, 2] ([1, N, 2] from gsplat: the projected means,
    a non-leaf tensor whose .grad the densification reads after backward when asked for),
    radii [N] (the largest footprint half extent in pixels, 0 when not drawn), visible [N] bool."""

    rgb: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor


def backend_for(device: torch.device) -> str:
    """The compositor for a device: gsplat's CUDA rasteriser on a CUDA device, the tiled CPU
    rasteriser otherwise (its kernels read numpy arrays, so it runs on CPU tensors only)."""
    return "gsplat" if device.type == "cuda" else "cpu"


def render(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, opacities: torch.Tensor,
           sh: torch.Tensor, camera: Camera, background: torch.Tensor, sh_degree: int, *, backend: str = "cpu",
           retain_means2d_grad: bool = False) -> Rendered:
    """Render N Gaussians into `camera` (module docstring).

    means: [N, 3]; scales: [N, 3] (> 0); quats: [N, 4] (w, x, y, z); opacities: [N] in (0, 1);
    sh: [N, K, 3] spherical-harmonic coefficients (splat.sh), of which the first
    (sh_degree + 1)^2 are used; background: [3] or [H, W, 3]."""
    if backend == "gsplat":
        return _render_gsplat(means, scales, quats, opacities, sh, camera, background, sh_degree, retain_means2d_grad)
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    width, height = camera.width, camera.height
    if backend == "cpu":  # the same maths compiled, one pass each way (splat.project_cpu)
        projected, all_colours = project_and_colour(means, scales, quats, sh, sh_degree, camera)
    else:
        projected, all_colours = project(means, scales, quats, camera), None
    means2d = projected.means2d  # [N, 2]
    if retain_means2d_grad and means2d.requires_grad:
        means2d.retain_grad()
    half = footprint_box(projected.cov2d_diagonal, opacities.detach())  # [N, 2]
    u, v = means2d[:, 0].detach(), means2d[:, 1].detach()  # [N] each
    on_screen = (u + half[:, 0] > 0) & (u - half[:, 0] < width) & (v + half[:, 1] > 0) & (v - half[:, 1] < height)
    finite = torch.isfinite(opacities.detach())  # [N]; NaN in a colour: project_and_colour says not in front
    if backend == "reference":
        finite &= torch.isfinite(sh.detach()[:, :(sh_degree + 1) ** 2]).flatten(1).all(1)
    visible = projected.in_front & finite & (half[:, 0] > 0) & on_screen  # [N]
    # the reference composites every Gaussian in front of the camera, the tiles the visible ones
    drawn = ((projected.in_front & finite) if backend == "reference" else visible).nonzero().squeeze(1)  # [V]
    if backend == "reference":
        colours = sh_colour(sh[drawn], means[drawn] - camera.centre, sh_degree)  # [V, 3]
        depths = projected.depths[drawn]  # [V]
        features = torch.cat([colours, depths[:, None]], dim=1)  # [V, 4]
        out, alpha = composite_reference(means2d[drawn], projected.conics[drawn], opacities[drawn], features, depths,
                                         width, height)
    else:  # the tiles index all N Gaussians: no gather here, no scatter in the backward
        features = torch.cat([all_colours, projected.depths[:, None]], dim=1)  # [N, 4]
        binning = bin_gaussians(means2d, half, projected.depths, width, height, drawn)
        out, alpha = rasterise(means2d, projected.conics, opacities, features, binning, width, height)
    radii = torch.where(visible, half.max(dim=1).values, torch.zeros_like(half[:, 0]))  # [N]
    return _finish(out[..., :3], out[..., 3], alpha, camera, background, means2d, radii, visible)


def _finish(colour, depth_sum, alpha, camera: Camera, background, means2d, radii, visible) -> Rendered:
    """rgb on the background, expected camera depth as ray distance (module docstring)."""
    rgb = colour + (1.0 - alpha)[..., None] * background  # [H, W, 3]
    hit = alpha > DEPTH_EPS  # [H, W]
    expected_z = depth_sum / torch.where(hit, alpha, torch.ones_like(alpha))  # [H, W]
    depth = torch.where(hit, expected_z * camera.ray_length_per_depth().to(alpha.dtype), torch.zeros_like(alpha))
    return Rendered(rgb, depth, alpha, means2d, radii, visible)


def _render_gsplat(means, scales, quats, opacities, sh, camera: Camera, background, sh_degree: int,
                   retain_means2d_grad: bool) -> Rendered:
    """gsplat's `rasterization` (CUDA), same conventions: OpenCV world-to-camera view
    matrix, pixel centres at i + 0.5, 0.3 low-pass, RGB plus expected camera depth ("ED").
    Untested here: no CUDA device on the machines these tests ran on."""
    from gsplat import rasterization  # gsplat: optional, CUDA only; imported only on this path

    view = torch.eye(4, dtype=means.dtype, device=means.device)
    view[:3, :3], view[:3, 3] = camera.rotation, camera.translation
    K = torch.tensor([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
                     dtype=means.dtype, device=means.device)
    colours, alphas, meta = rasterization(means, quats, scales, opacities, sh[:, :(sh_degree + 1) ** 2],
                                          view[None], K[None], camera.width, camera.height, near_plane=NEAR,
                                          eps2d=0.3, sh_degree=sh_degree, packed=False, render_mode="RGB+ED",
                                          rasterize_mode="classic")
    means2d = meta["means2d"]  # [1, N, 2]: the tensor in the graph (a view of it would get no .grad)
    if retain_means2d_grad and means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0].float()  # [N, 2] or [N]
    radii = radii.max(dim=-1).values if radii.ndim == 2 else radii
    alpha = alphas[0, ..., 0]  # [H, W]
    depth_sum = colours[0, ..., 3] * alpha  # gsplat's ED is normalised by alpha already
    return _finish(colours[0, ..., :3], depth_sum, alpha, camera, background, means2d, radii, radii > 0)
