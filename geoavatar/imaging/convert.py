"""Float images in [0, 1] to 8 bits, and 8-bit images to a height: the one way every picture, video frame
and dataset image of GeoAvatar is quantised."""

from __future__ import annotations

import numpy as np
from torch import Tensor


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """[..., C] float in [0, 1] -> uint8 numpy, clipped and rounded half up (x * 255 + 0.5, truncated)."""
    if isinstance(image, Tensor):
        image = image.detach().float().cpu().numpy()
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def fit_height(image: np.ndarray, height: int) -> np.ndarray:
    """Resize a uint8 [H, W, 3] image to `height` rows, keeping its aspect ratio (area filter)."""
    if image.shape[0] == height:
        return image
    from PIL import Image

    width = max(1, round(image.shape[1] * height / image.shape[0]))
    return np.asarray(Image.fromarray(image).resize((width, height), Image.Resampling.BOX))


__all__ = ["fit_height", "to_uint8"]
