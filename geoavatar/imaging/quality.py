"""Image similarity shared by the training loss (D-SSIM) and the evaluation (SSIM, PSNR), so that both
score with the same SSIM: 3DGS's, which GaussianAvatars and the paper's tables use too.
Images are channel-last, [H, W, C] or [B, H, W, C], values in [0, 1] (the renderer's layout)."""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import Tensor


@lru_cache(maxsize=8)
def _gaussian_window_1d(size: int, sigma: float) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    w = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (w / w.sum()).float()


def _as_bchw(image: Tensor, name: str) -> Tensor:
    if image.dim() == 3:
        image = image[None]
    if image.dim() != 4:
        raise ValueError(f"{name}: expected an image [H, W, C] or [B, H, W, C], got shape {tuple(image.shape)}")
    return image.permute(0, 3, 1, 2)


def ssim(image: Tensor, target: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of [H, W, C] / [B, H, W, C] images in [0, 1], as 3DGS's training loss computes it.

    Gaussian window 11x11 with sigma 1.5 (separable), zero padding of window//2 at the border (3DGS),
    C1 = 0.01^2, C2 = 0.03^2, averaged over pixels, channels and batch.
    """
    if image.shape != target.shape:
        raise ValueError(f"ssim: image {tuple(image.shape)} and target {tuple(target.shape)} differ in shape")
    x, y = _as_bchw(image, "ssim"), _as_bchw(target, "ssim")
    channels = x.shape[1]
    w1 = _gaussian_window_1d(window_size, sigma).to(x)
    pad = window_size // 2

    def blur(t: Tensor) -> Tensor:
        t = F.conv2d(t, w1.view(1, 1, 1, -1).expand(channels, 1, 1, window_size), padding=(0, pad), groups=channels)
        return F.conv2d(t, w1.view(1, 1, -1, 1).expand(channels, 1, window_size, 1), padding=(pad, 0), groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x**2
    sigma_y = blur(y * y) - mu_y**2
    sigma_xy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))
    return ssim_map.mean()


def psnr_from_mse(value: float) -> float:
    """PSNR in dB for data range 1; inf when the images are identical (the trainer's log and eval's tables)."""
    return float("inf") if value <= 0.0 else -10.0 * math.log10(value)


__all__ = ["psnr_from_mse", "ssim"]
