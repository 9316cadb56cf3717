"""Solid (3D) procedural noise for textures that stick to the skin: band-limited, periodic, fast.

A small random volume is low-pass filtered with a periodic Gaussian (so the noise is smooth and
its spectrum is limited), normalised to zero mean and unit variance, and sampled with trilinear
interpolation at `fract(p * frequency)`: one `grid_sample` call per octave, on any device.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor


def periodic_noise_volume(seed: int, resolution: int = 32, smoothing: float = 1.0) -> Tensor:
    """Unit-variance periodic noise [1, 1, R+1, R+1, R+1] (the last slice repeats the first)."""
    rng = np.random.default_rng([seed, 0xA0153])
    white = rng.standard_normal((resolution,) * 3)
    # Periodic Gaussian low-pass in the Fourier domain.
    freq = np.fft.fftfreq(resolution) * resolution  # cycles per period
    fx, fy, fz = np.meshgrid(freq, freq, freq, indexing="ij")
    sigma_f = resolution / (2.0 * math.pi * max(smoothing, 1e-3))
    gain = np.exp(-0.5 * (fx**2 + fy**2 + fz**2) / sigma_f**2)
    smooth = np.real(np.fft.ifftn(np.fft.fftn(white) * gain))
    smooth = (smooth - smooth.mean()) / (smooth.std() + 1e-12)
    padded = np.pad(smooth, ((0, 1), (0, 1), (0, 1)), mode="wrap")
    return torch.from_numpy(padded.astype(np.float32))[None, None]


class SolidNoise:
    """Samples a periodic noise volume at 3D points; a period of the volume spans 1/frequency metres."""

    def __init__(self, seed: int, resolution: int = 32, smoothing: float = 1.0):
        self.volume = periodic_noise_volume(seed, resolution, smoothing)  # [1, 1, R+1, R+1, R+1]
        self.resolution = resolution

    def __call__(
        self,
        points: Tensor,  # [P, 3] positions (metres)
        cells_per_metre: float | Tensor,  # noise features per metre (scalar or [3] for anisotropy)
        offset: float = 0.0,
    ) -> Tensor:
        """Noise values [P] with zero mean and unit variance (trilinear, periodic)."""
        volume = self.volume.to(device=points.device, dtype=points.dtype)
        scale = torch.as_tensor(cells_per_metre, dtype=points.dtype, device=points.device) / self.resolution
        coords = torch.frac(points * scale + offset)
        coords = torch.where(coords < 0, coords + 1.0, coords) * 2.0 - 1.0  # [P, 3] in [-1, 1]
        grid = coords.view(1, 1, 1, -1, 3)
        return F.grid_sample(volume, grid, mode="bilinear", padding_mode="border", align_corners=True).view(-1)

    def fbm(self, points: Tensor, cells_per_metre: float, octaves: int = 3, gain: float = 0.5) -> Tensor:
        """Fractal sum of `octaves` octaves (frequency x2 each), renormalised to unit variance [P]."""
        total = torch.zeros(points.shape[0], dtype=points.dtype, device=points.device)
        amplitude, norm = 1.0, 0.0
        for k in range(octaves):
            total = total + amplitude * self(points, cells_per_metre * 2.0**k, offset=0.37 * k)
            norm += amplitude**2
            amplitude *= gain
        return total / math.sqrt(norm)


__all__ = ["SolidNoise", "periodic_noise_volume"]
