"""The fit's losses and image metrics: L1 + D-SSIM, PSNR, and the needle penalty on surfels."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two (H, W, 3) images in [0, 1] (Gaussian window, the usual constants)."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    g = torch.exp(-((torch.arange(window, device=a.device) - window // 2) ** 2) / (2 * sigma**2))
    g = (g / g.sum()).to(a.dtype)
    k = (g[:, None] * g[None, :]).expand(3, 1, window, window)
    pad = window // 2

    def blur(t):
        return F.conv2d(t, k, padding=pad, groups=3)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return s.mean()


def psnr_from_mse(mse: float) -> float:
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return psnr_from_mse(float(((a - b) ** 2).mean()))


def photometric_loss(rgb: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of two (H, W, 3) images."""
    l1 = (rgb - gt).abs().mean()
    return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(rgb, gt))


def anisotropy_penalty(log_scales: torch.Tensor, max_aspect: float) -> torch.Tensor:
    """Mean excess of each Gaussian's axis ratio over `max_aspect` (0 when none exceeds it):
    keeps surfels from turning into needles that look right only edge-on. log_scales: (N, 2|3)."""
    log_ratio = log_scales.max(dim=1).values - log_scales.min(dim=1).values
    return F.relu(torch.exp(log_ratio) - max_aspect).mean()
