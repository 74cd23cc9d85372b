"""View-dependent colour from real spherical harmonics up to degree 3, as 3DGS evaluates it.

A Gaussian carries K = (degree_max + 1)^2 coefficients per colour channel, k_0 the constant
(DC) term. Seen along the unit direction d = (x, y, z) = (mu - camera centre) / |...| (world
axes), its colour is

    c(d) = max(0, 0.5 + sum_{l <= degree} sum_m Y_lm(d) k_lm)

with 3DGS's basis and signs (its computeColorFromSH; the training raises `degree` over
time, so the higher coefficients start at zero and join one degree at a time):

    l = 0:  C0
    l = 1:  -C1 y, C1 z, -C1 x
    l = 2:  C2_0 xy, C2_1 yz, C2_2 (2z^2 - x^2 - y^2), C2_3 xz, C2_4 (x^2 - y^2)
    l = 3:  C3_0 y (3x^2 - y^2), C3_1 xyz, C3_2 y (4z^2 - x^2 - y^2), C3_3 z (2z^2 - 3x^2 - 3y^2),
            C3_4 x (4z^2 - x^2 - y^2), C3_5 z (x^2 - y^2), C3_6 x (x^2 - 3y^2)

The same basis is what the 3DGS PLY layout stores (splat/ply.py), so a PLY from another tool
renders with its own colours. The 0.5 offset makes zero coefficients mid-grey; the DC term of
a colour c is (c - 0.5) / C0 (`rgb_to_dc`).
"""

from __future__ import annotations

import torch

MAX_DEGREE = 3
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def coefficient_count(degree: int) -> int:
    """(degree + 1)^2: coefficients per channel up to `degree`."""
    return (degree + 1) ** 2


def sh_basis(directions: torch.Tensor, degree: int) -> torch.Tensor:
    """The basis functions Y_k(d), k < (degree + 1)^2, in 3DGS's order and signs.
    directions: [N, 3] unit vectors. Returns [N, (degree + 1)^2]."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"spherical-harmonic degree must be 0 to {MAX_DEGREE}, got {degree}")
    x, y, z = directions.unbind(-1)  # [N] each
    basis = [torch.full_like(x, C0)]
    if degree >= 1:
        basis += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                  C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy),
                  C3[6] * x * (xx - 3 * yy)]
    return torch.stack(basis, dim=-1)  # [N, K]


def sh_colour(coefficients: torch.Tensor, directions: torch.Tensor, degree: int) -> torch.Tensor:
    """c(d) = max(0, 0.5 + sum_k Y_k(d) k_k) over the first (degree + 1)^2 coefficients.

    coefficients: [N, K, 3] with K >= (degree + 1)^2; directions: [N, 3], any non-zero length
    (normalised here). Returns [N, 3]; the gradient is zero where the colour is clamped at 0."""
    count = coefficient_count(degree)
    if coefficients.shape[1] < count:
        raise ValueError(f"degree {degree} needs {count} coefficients per channel, got {coefficients.shape[1]}")
    unit = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # [N, 3]
    basis = sh_basis(unit, degree)  # [N, count]
    colour = (basis[:, :, None] * coefficients[:, :count, :]).sum(dim=1)  # [N, 3]
    return torch.clamp_min(colour + 0.5, 0.0)


def rgb_to_dc(rgb: torch.Tensor) -> torch.Tensor:
    """The DC coefficient that shows colour `rgb` from every direction: (rgb - 0.5) / C0. [N, 3]."""
    return (rgb - 0.5) / C0
