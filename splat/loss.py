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
    """The normalised 1D Gaussian; the 2D window is its outer product. Returns [size]."""
    x = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def blur(images: torch.Tensor) -> torch.Tensor:
    """Each channel of [1, C, H, W] convolved with the 11 x 11 window (zero padding), as two
    1D passes (the window is separable: the same sums as the 2D convolution, 22 taps a pixel
    instead of 121)."""
    channels = images.shape[1]
    g = gaussian_window(dtype=images.dtype).to(images.device)
    rows = F.conv2d(images, g.view(1, 1, 1, WINDOW).expand(channels, 1, 1, WINDOW), padding=(0, WINDOW // 2),
                    groups=channels)
    return F.conv2d(rows, g.view(1, 1, WINDOW, 1).expand(channels, 1, WINDOW, 1), padding=(WINDOW // 2, 0),
                    groups=channels)


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] (module docstring). Returns a 0-d tensor."""
    return ssim_map(image, target).mean()


def ssim_map(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of two [H, W, C] images. Returns [1, C, H, W]."""
    channels = image.shape[-1]
    x, y = image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]  # [1, C, H, W]
    blurred = blur(torch.cat([x, y, x * x, y * y, x * y], dim=1))  # [1, 5C, H, W]: the five local means at once
    mu_x, mu_y, xx, yy, xy = blurred.split(channels, dim=1)
    sigma_x = xx - mu_x * mu_x
    sigma_y = yy - mu_y * mu_y
    sigma_xy = xy - mu_x * mu_y
    return ((2 * mu_x * mu_y + C1) * (2 * sigma_xy + C2)) / ((mu_x * mu_x + mu_y * mu_y + C1)
                                                             * (sigma_x + sigma_y + C2))


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    """(1 - ssim_weight) |image - target|_1 (mean) + ssim_weight (1 - SSIM). image, target: [H, W, 3]."""
    l1 = (image - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(image, target))
