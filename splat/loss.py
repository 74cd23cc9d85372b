"""The photometric loss of Kerbl et al. 2023: (1 - lambda) L1 + lambda (1 - SSIM), lambda = 0.2.

SSIM as the 3DGS code computes it for training (its utils/loss_utils.ssim): per channel, an
11 x 11 Gaussian window of sigma 1.5 (zero padding at the border), C1 = 0.01^2, C2 = 0.03^2
for data in [0, 1], the SSIM map averaged over pixels and channels:

    SSIM = mean [(2 mu_x mu_y + C1)(2 sigma_xy + C2)] / [(mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)]

(The evaluator's SSIM is scikit-image's, docs/conventions.md; this one is the training loss.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

WINDOW = 11
SIGMA = 1.5
C1 = 0.01 ** 2
C2 = 0.03 ** 2


def gaussian_window(size: int = WINDOW, sigma: float = SIGMA, dtype=torch.float32) -> torch.Tensor:
    """Normalised separable Gaussian, as an outer product. Returns [size, size]."""
    x = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] (module docstring). Returns a 0-d tensor."""
    channels = image.shape[-1]
    x, y = image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]  # [1, C, H, W]
    window = gaussian_window(dtype=image.dtype).to(image.device).expand(channels, 1, WINDOW, WINDOW)
    blur = lambda t: F.conv2d(t, window, padding=WINDOW // 2, groups=channels)  # noqa: E731
    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x * mu_x
    sigma_y = blur(y * y) - mu_y * mu_y
    sigma_xy = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + C1) * (2 * sigma_xy + C2)) / ((mu_x * mu_x + mu_y * mu_y + C1)
                                                                 * (sigma_x + sigma_y + C2))
    return ssim_map.mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    """(1 - ssim_weight) |image - target|_1 (mean) + ssim_weight (1 - SSIM). image, target: [H, W, 3]."""
    l1 = (image - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(image, target))
