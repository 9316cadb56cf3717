"""The target a render is compared with: the photo with everything outside its foreground mask
replaced by the background colour (GaussianAvatars' convention; training, eval and the apps share it)."""

from __future__ import annotations

from torch import Tensor


def composite_target(image: Tensor, mask: Tensor, background: Tensor) -> Tensor:
    """image [H,W,3] * mask [H,W,1] + background [3] * (1 - mask): the training target [H, W, 3]."""
    return image * mask + background.view(1, 1, 3) * (1.0 - mask)


__all__ = ["composite_target"]
