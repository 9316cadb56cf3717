"""Image metrics of the paper's tables: MSE, PSNR, SSIM, LPIPS (+ the masked PSNR of the mouth region).

Images are channel-last in [0, 1], [H, W, 3] (the renderer's layout); each function scores ONE image
pair (the per-frame numbers that the tables average), except `lpips`, which also takes a batch, and
`LpipsTarget`, which scores several renders against one target.

- MSE  mean squared error over pixels and channels (data range 1; Table 1 prints it x 1e3).
- PSNR -10 log10(MSE), data range 1; inf for identical images (`geoavatar.imaging.psnr_from_mse`, which the
  trainer's log uses too).
- SSIM the Gaussian-window SSIM (11 x 11, sigma 1.5, K1 0.01, K2 0.03, data range 1) of 3DGS's
  `ssim`, i.e. `geoavatar.imaging.ssim`: the 3DGS / GaussianAvatars evaluation scores with the
  very function that trains, so we do too (one implementation, no drift). Its border handling is
  3DGS's: zero padding of 5 px, the map averaged over every pixel. scikit-image's
  structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1) reflects the border and averages the map without its 5-px rim; away from the
  border the two maps are identical (tests/test_metrics.py checks both facts).
- LPIPS v0.1 with VGG16 (default, as the 3DGS-family evaluation scripts) or AlexNet; see eval/lpips.py.
"""

from __future__ import annotations

import torch
from torch import Tensor

from geoavatar.eval.lpips import lpips_model
from geoavatar.imaging import psnr_from_mse
from geoavatar.imaging import ssim as _ssim_3dgs


def _check_pair(pred: Tensor, target: Tensor, name: str) -> None:
    if pred.shape != target.shape:
        raise ValueError(f"{name}: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
    if pred.dim() != 3 or pred.shape[-1] != 3:
        raise ValueError(f"{name}: expected images [H, W, 3], got {tuple(pred.shape)}")


def mse(pred: Tensor, target: Tensor) -> float:
    """Mean squared error of one image pair [H, W, 3] (float64 accumulation)."""
    _check_pair(pred, target, "mse")
    return float((pred.double() - target.double()).square().mean())


def psnr(pred: Tensor, target: Tensor) -> float:
    return psnr_from_mse(mse(pred, target))


def ssim(pred: Tensor, target: Tensor) -> float:
    """SSIM of one image pair [H, W, 3] (3DGS's Gaussian-window SSIM, see the module docstring)."""
    _check_pair(pred, target, "ssim")
    with torch.no_grad():
        return float(_ssim_3dgs(pred.float(), target.float()))


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> float:
    """PSNR over the pixels where mask [H, W] (bool) is set, all 3 channels; nan for an empty mask."""
    _check_pair(pred, target, "masked_psnr")
    if mask.shape != pred.shape[:2]:
        raise ValueError(f"masked_psnr: mask {tuple(mask.shape)} does not match the images {tuple(pred.shape[:2])}")
    mask = mask.to(device=pred.device, dtype=torch.bool)
    if not bool(mask.any()):
        return float("nan")
    diff = (pred.double() - target.double())[mask]  # [P, 3]
    return psnr_from_mse(float(diff.square().mean()))


def lpips(pred: Tensor, target: Tensor, net: str = "vgg", unit_inputs: bool = False) -> Tensor:
    """LPIPS distances: pred, target [H, W, 3] or [B, H, W, 3] in [0, 1] -> [B] (B = 1 for one image)."""
    model = lpips_model(net, pred.device, unit_inputs)
    with torch.no_grad():
        return model(pred, target)


class LpipsTarget:
    """One target image [H, W, 3] whose LPIPS taps are computed once, for several renders scored against it: the
    backbone's pass over the target is half of each `lpips` call (eval --speech scores five renders a frame)."""

    def __init__(self, image: Tensor, net: str = "vgg", unit_inputs: bool = False):
        self.shape = tuple(image.shape)
        self.model = lpips_model(net, image.device, unit_inputs)
        with torch.no_grad():
            self.taps = self.model.taps(image, "target")

    def lpips(self, pred: Tensor) -> Tensor:
        """`lpips(pred, target)` -> [B], without the target's pass."""
        if tuple(pred.shape[-3:]) != self.shape[-3:]:
            raise ValueError(f"lpips: pred {tuple(pred.shape)} and target {self.shape} differ in shape")
        with torch.no_grad():
            return self.model.distance(pred, self.taps)


__all__ = ["LpipsTarget", "lpips", "masked_psnr", "mse", "psnr", "psnr_from_mse", "ssim"]
