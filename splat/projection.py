"""EWA projection of 3D Gaussians into 2D conics (Zwicker et al. 2001, as 3DGS uses it).

A Gaussian has a mean mu, per-axis scales s and a rotation quaternion q = (w, x, y, z)
(normalised here; any non-zero length). Its covariance in the world is

    Sigma = R(q) S S^T R(q)^T,                   S = diag(s)

A camera (nerfgauge.core.camera: OpenGL camera-to-world, pixel (row i, col j) centred at
(j + 0.5, i + 0.5)) is turned into OpenCV axes for the projection (+X right, +Y down,
looking along +Z: c2w_cv = c2w_gl @ diag(1, -1, -1, 1), docs/conventions.md), so that

    t = W mu + w                                 (camera coordinates, W = R_cv^T, w = -W c)
    u = fx t_x / t_z + cx,   v = fy t_y / t_z + cy        (pixel coordinates of the mean)
    J = [[fx / t_z, 0, -fx t_x / t_z^2],
         [0, fy / t_z, -fy t_y / t_z^2]]         (the projection's Jacobian at t)
    Sigma' = J W Sigma W^T J^T + 0.3 I           (2D covariance, pixels^2)
    conic  = Sigma'^{-1} = (a, b, c):  q(d) = a d_x^2 + 2 b d_x d_y + c d_y^2

The 0.3 added to the diagonal is 3DGS's low-pass filter: every splat covers at least about
a pixel, so a Gaussian smaller than a pixel cannot fall between pixel centres. In J, t_x / t_z
and t_y / t_z are clamped to 1.3 times the half field of view (3DGS and gsplat do the same),
so a Gaussian far outside the image does not get an unbounded footprint; the mean's pixel
coordinates (u, v) are not clamped.

A Gaussian is drawn only when t_z > NEAR (in front of the camera), everything about it is
finite, and its footprint box (`tiles.footprint_box`) meets the image. Everything here is a
pure torch function, differentiable by autograd (the validity mask and the footprint's
extent are not: they are decisions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nerfgauge.core.camera import Intrinsics

LOW_PASS = 0.3  # pixels^2 added to the projected covariance's diagonal (3DGS's dilation)
NEAR = 0.01  # scene units: Gaussians nearer the camera plane than this are not drawn (gsplat's)
FOV_CLAMP = 1.3  # the Jacobian sees t_x/t_z, t_y/t_z within 1.3x the half field of view
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # c2w_cv = c2w_gl @ GL_TO_CV (its own inverse)


@dataclass(frozen=True)
class Camera:
    """One pinhole view, as tensors the projection reads.

    rotation: [3, 3] world-to-camera rotation W (OpenCV axes); translation: [3] w; centre: [3]
    camera centre in the world; fx, fy, cx, cy in pixels; width, height in pixels."""

    rotation: torch.Tensor
    translation: torch.Tensor
    centre: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_c2w(cls, c2w_gl, intrinsics: Intrinsics, dtype=torch.float32, device="cpu") -> "Camera":
        """From a [4, 4] OpenGL camera-to-world matrix (core.camera's convention)."""
        c2w = np.array(c2w_gl, np.float64)  # a copy: the dataset's poses are read-only arrays
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise ValueError(f"c2w must be a finite [4, 4] matrix, got {c2w.shape}")
        c2w_cv = c2w @ GL_TO_CV
        rotation = c2w_cv[:3, :3].T  # [3, 3] world to camera (rotation matrices are orthonormal)
        translation = -rotation @ c2w_cv[:3, 3]  # [3]
        as_tensor = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        return cls(as_tensor(rotation), as_tensor(translation), as_tensor(c2w[:3, 3]), float(intrinsics.fx),
                   float(intrinsics.fy), float(intrinsics.cx), float(intrinsics.cy), int(intrinsics.width),
                   int(intrinsics.height))

    def to(self, dtype=None, device=None) -> "Camera":
        move = lambda t: t.to(dtype=dtype or t.dtype, device=device or t.device)  # noqa: E731
        return Camera(move(self.rotation), move(self.translation), move(self.centre), self.fx, self.fy, self.cx,
                      self.cy, self.width, self.height)

    def ray_length_per_depth(self) -> torch.Tensor:
        """|(x, y, 1)| at each pixel centre, x = (j + 0.5 - cx) / fx, y = (i + 0.5 - cy) / fy:
        the ray distance per unit of camera depth t_z along each pixel's centre ray.
        Returns [height, width]."""
        dtype, device = self.rotation.dtype, self.rotation.device
        x = (torch.arange(self.width, dtype=dtype, device=device) + 0.5 - self.cx) / self.fx  # [W]
        y = (torch.arange(self.height, dtype=dtype, device=device) + 0.5 - self.cy) / self.fy  # [H]
        return torch.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)  # [H, W]


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of quaternions (w, x, y, z), normalised first.

        R = [[1 - 2(y^2 + z^2), 2(xy - wz),       2(xz + wy)],
             [2(xy + wz),       1 - 2(x^2 + z^2), 2(yz - wx)],
             [2(xz - wy),       2(yz + wx),       1 - 2(x^2 + y^2)]]

    quats: [N, 4]. Returns [N, 3, 3]. A zero quaternion gives NaN (it names no rotation);
    the model's quaternions are never zero (they start at (1, 0, 0, 0) and Adam moves them)."""
    q = quats / quats.norm(dim=-1, keepdim=True)  # [N, 4]
    w, x, y, z = q.unbind(-1)  # [N] each
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))  # [N, 3, 3]


def covariance_3d(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T = M M^T with M = R S. scales: [N, 3] (> 0), quats: [N, 4].
    Returns [N, 3, 3]."""
    m = quaternion_to_rotation(quats) * scales[:, None, :]  # [N, 3, 3]: column k of R times s_k
    return m @ m.transpose(1, 2)  # [N, 3, 3]


@dataclass
class Projected:
    """The 2D Gaussians of one view. means2d: [N, 2] pixel coordinates (u, v) of the means;
    conics: [N, 3] (a, b, c) of Sigma'^{-1}; depths: [N] camera depth t_z; cov2d_diagonal: [N, 2]
    Sigma'_xx, Sigma'_yy (for the footprint, not differentiable); in_front: [N] bool, t_z >
    NEAR and everything finite."""

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    cov2d_diagonal: torch.Tensor
    in_front: torch.Tensor


def project(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, camera: Camera) -> Projected:
    """EWA projection of N Gaussians into `camera` (the module docstring's equations).

    means: [N, 3] world positions; scales: [N, 3] standard deviations along the Gaussian's
    axes (>= 0; 0 is a flat or point Gaussian, which the low-pass still draws); quats: [N, 4]
    (w, x, y, z). A Gaussian behind the camera (t_z <= NEAR), or with a non-finite value or a
    zero quaternion, gets in_front = False and finite stand-ins in every division (depth 1,
    scale 0, rotation identity), so neither its values nor its gradients are NaN."""
    t = means @ camera.rotation.T + camera.translation  # [N, 3] camera coordinates (OpenCV axes)
    in_front = (t[:, 2] > NEAR) & torch.isfinite(t).all(-1) & torch.isfinite(scales).all(-1) \
        & torch.isfinite(quats).all(-1) & (quats.detach().abs().sum(-1) > 0)  # [N]: a zero quaternion is no rotation
    tz = torch.where(in_front, t[:, 2], torch.full_like(t[:, 2], 1.0))  # [N]: finite divisions for the rest
    tx = torch.where(in_front, t[:, 0], torch.zeros_like(tz))  # [N]
    ty = torch.where(in_front, t[:, 1], torch.zeros_like(tz))  # [N]
    u = camera.fx * tx / tz + camera.cx  # [N]
    v = camera.fy * ty / tz + camera.cy  # [N]
    # the Jacobian at a point clamped into 1.3x the field of view (tx, ty themselves stay)
    margin_x = (FOV_CLAMP - 1) * 0.5 * camera.width / camera.fx  # 0.3 x tan(half fov), gsplat's rule
    margin_y = (FOV_CLAMP - 1) * 0.5 * camera.height / camera.fy
    lim_x_pos = (camera.width - camera.cx) / camera.fx + margin_x
    lim_x_neg = camera.cx / camera.fx + margin_x
    lim_y_pos = (camera.height - camera.cy) / camera.fy + margin_y
    lim_y_neg = camera.cy / camera.fy + margin_y
    jx = tz * torch.clamp(tx / tz, -lim_x_neg, lim_x_pos)  # [N]
    jy = tz * torch.clamp(ty / tz, -lim_y_neg, lim_y_pos)  # [N]
    zero = torch.zeros_like(tz)
    jacobian = torch.stack([camera.fx / tz, zero, -camera.fx * jx / (tz * tz),
                            zero, camera.fy / tz, -camera.fy * jy / (tz * tz)], dim=-1).reshape(-1, 2, 3)  # [N, 2, 3]
    safe_scales = torch.where(in_front[:, None], scales, torch.zeros_like(scales))  # [N, 3]
    safe_quats = torch.where(in_front[:, None], quats, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype,
                                                                       device=quats.device))  # [N, 4]
    sigma = covariance_3d(safe_scales, safe_quats)  # [N, 3, 3]
    jw = jacobian @ camera.rotation  # [N, 2, 3]: J W
    cov2d = jw @ sigma @ jw.transpose(1, 2)  # [N, 2, 2]
    sxx = cov2d[:, 0, 0] + LOW_PASS  # [N]
    syy = cov2d[:, 1, 1] + LOW_PASS  # [N]
    sxy = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])  # [N]
    det = sxx * syy - sxy * sxy  # [N] >= 0.09 for a positive semi-definite cov2d
    conics = torch.stack([syy / det, -sxy / det, sxx / det], dim=-1)  # [N, 3]
    in_front = in_front & torch.isfinite(conics).all(-1) & (det > 0)
    means2d = torch.stack([u, v], dim=-1)  # [N, 2]
    return Projected(means2d, conics, t[:, 2], torch.stack([sxx, syy], dim=-1).detach(), in_front)
