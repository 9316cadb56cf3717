"""Image similarity shared by the training loss (D-SSIM) and the evaluation (SSIM, PSNR), so that both
score with the same SSIM: 3DGS's, which GaussianAvatars and the paper's tables use too.
Images are channel-last, [H, W, C] or [B, H, W, C], values in [0, 1] (the renderer's layout).

On CPU the SSIM and its gradient run as this layer's native extension (csrc/ssim_cpu.cpp: the moments blurred
and the map's terms fused, ~7 ms fwd+bwd at 256 px against the convolutions' 16-19), when it builds; the PyTorch
convolutions serve CUDA, a target that needs a gradient, and machines without a compiler. tests/test_losses.py
checks the two against each other and the native gradient with gradcheck."""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from geoavatar.native import ExtensionSpec, load_extension as load_native_extension, new_state

_EXTENSION = ExtensionSpec(
    name="ssim_cpu", source=Path(__file__).with_name("csrc") / "ssim_cpu.cpp", what="the native CPU SSIM",
    instead="SSIM on CPU runs as PyTorch convolutions (slower)")
_state = new_state()


def load_extension():
    """The compiled module of csrc/ssim_cpu.cpp (built on first use), or None with one warning."""
    return load_native_extension(_EXTENSION, _state)


@lru_cache(maxsize=8)
def _gaussian_window_1d(size: int, sigma: float) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    w = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (w / w.sum()).float()


def _as_bhwc(image: Tensor, name: str) -> Tensor:
    """[H, W, C] or [B, H, W, C] -> [B, H, W, C]; anything else is a ValueError naming `name`."""
    if image.dim() == 3:
        image = image[None]
    if image.dim() != 4:
        raise ValueError(f"{name}: expected an image [H, W, C] or [B, H, W, C], got shape {tuple(image.shape)}")
    return image


class _NativeSSIM(torch.autograd.Function):
    """Mean SSIM of [B, H, W, C] images by the native kernels; the gradient reaches `image` only."""

    @staticmethod
    def forward(ctx, image: Tensor, target: Tensor, window: Tensor) -> Tensor:
        value, coefficients = load_extension().ssim_forward(image, target, window, ctx.needs_input_grad[0])
        ctx.save_for_backward(image, target, window, coefficients)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        image, target, window, coefficients = ctx.saved_tensors
        return load_extension().ssim_backward(float(grad), image, target, window, coefficients), None, None


def ssim(image: Tensor, target: Tensor, window_size: int = 11, sigma: float = 1.5, native: bool = True) -> Tensor:
    """Mean SSIM of [H, W, C] / [B, H, W, C] images in [0, 1], as 3DGS's training loss computes it.

    Gaussian window 11x11 with sigma 1.5 (separable), zero padding of window//2 at the border (3DGS),
    C1 = 0.01^2, C2 = 0.03^2, averaged over pixels, channels and batch. `native`: the CPU kernels where they
    apply (False: the PyTorch convolutions everywhere).
    """
    if image.shape != target.shape:
        raise ValueError(f"ssim: image {tuple(image.shape)} and target {tuple(target.shape)} differ in shape")
    image, target = _as_bhwc(image, "ssim"), _as_bhwc(target, "ssim")
    w1 = _gaussian_window_1d(window_size, sigma).to(image)
    if (native and window_size % 2 == 1 and image.device.type == "cpu" and target.device.type == "cpu"
            and image.dtype == target.dtype and image.dtype in (torch.float32, torch.float64)
            and not target.requires_grad and load_extension() is not None):
        return _NativeSSIM.apply(image.contiguous(), target.contiguous(), w1)
    x, y = image.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    channels = x.shape[1]
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
