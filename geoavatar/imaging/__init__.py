"""Image helpers every layer may use (below head, render and the rest, beside io/ and geometry):
float images to 8 bits and back to a height (convert.py), and the image-similarity scores the training
loss and the evaluation share (quality.py: SSIM as 3DGS computes it, PSNR from an MSE)."""

from geoavatar.imaging.convert import fit_height, to_uint8
from geoavatar.imaging.quality import psnr_from_mse, ssim

__all__ = ["fit_height", "psnr_from_mse", "ssim", "to_uint8"]
