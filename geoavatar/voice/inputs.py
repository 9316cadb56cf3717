"""What the voice model hears: log-mel windows around each video frame, normalised per recording, and the
augmentations that make another voice, a speech synthesiser or a quieter microphone look like the training sound.

    spectra = torch.from_numpy(power_frames(sound))          # [F, B] power spectra at 100 frames a second
    mel = log_mel_torch(spectra, warp=1.0)                   # [F, M] log10 mel power (warp: vocal-tract length)
    stats = speech_stats(mel)                                # per-band mean and one scale over the loud frames
    windows(normalise(mel, stats), centres, past, ahead)     # [N, M, W] the network's inputs

Normalising by the recording's own speech statistics removes its level and most of its microphone: a frame is heard
relative to how this recording sounds when someone speaks. The augmentations (`Augmentation.sample`) act on power
spectra: gain, a warp of the frequency axis (another vocal tract: VTLP, Jaitly & Hinton 2013), a spectral tilt and a
smooth equaliser curve (another microphone), and noise at a random signal-to-noise ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from geoavatar.sound.features import FLOOR, FMAX, FMIN, N_FFT, N_MELS
from geoavatar.sound.track import RATE

LOUD_DB = 35.0  # frames within this many dB of a recording's 95th-percentile loudness count as its speech
CLAMP = 4.0  # normalised features are clamped to +-CLAMP (digital silence would otherwise be an outlier)


def _filters(warp: float, device: torch.device) -> Tensor:
    """[M, B] unit-area mel filters evaluated at warp x each bin's frequency (warp > 1: a shorter vocal tract's
    formants, higher, land where the training voice has them)."""
    bins = torch.fft.rfftfreq(N_FFT, 1.0 / RATE, dtype=torch.float64, device=device) / warp  # [B]
    mel = lambda hz: 2595.0 * torch.log10(1.0 + hz / 700.0)  # noqa: E731
    hz = lambda m: 700.0 * (10.0 ** (m / 2595.0) - 1.0)  # noqa: E731
    edges = hz(torch.linspace(float(mel(torch.tensor(FMIN))), float(mel(torch.tensor(FMAX))), N_MELS + 2,
                              dtype=torch.float64, device=device))
    low, centre, high = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    weights = torch.clamp(torch.minimum((bins[None] - low) / (centre - low), (high - bins[None]) / (high - centre)), 0)
    return (weights * (2.0 / (high - low)) / warp).float()


_FILTER_CACHE: dict[tuple[float, str], Tensor] = {}


def log_mel_torch(power: Tensor, warp: float = 1.0) -> Tensor:
    """[..., M] log10 mel power of power spectra [..., B]; warp 1.0 gives geoavatar.sound.log_mel's values."""
    key = (round(float(warp), 2), str(power.device))  # warps on a 0.01 grid: a few dozen filterbanks at most
    if key not in _FILTER_CACHE:
        _FILTER_CACHE[key] = _filters(key[0], power.device)
    return torch.log10(torch.clamp(power @ _FILTER_CACHE[key].T, min=FLOOR))


@dataclass
class SpeechStats:
    """How a recording sounds when someone speaks: per-band mean [M] and one scale of its loud frames' log-mel."""

    mean: Tensor  # [M]
    scale: Tensor  # []

    def to(self, device) -> "SpeechStats":
        return SpeechStats(self.mean.to(device), self.scale.to(device))


def loud_frames(mel: Tensor) -> Tensor:
    """[F] bool: frames within LOUD_DB of the 95th-percentile loudness (speech, in a recording that has some)."""
    energy = torch.log10(torch.clamp((10.0 ** mel.double()).sum(-1), min=FLOOR))  # [F]
    top = torch.quantile(energy, 0.95)
    return energy >= top - LOUD_DB / 10.0


def speech_stats(mel: Tensor) -> SpeechStats:
    """The statistics of a recording's loud frames (all frames when fewer than 10 are loud)."""
    loud = loud_frames(mel)
    frames = mel[loud] if int(loud.sum()) >= 10 else mel
    mean = frames.mean(0)
    scale = (frames - mean).std().clamp_min(1e-3)
    return SpeechStats(mean, scale)


def speech_level(stats: SpeechStats) -> float:
    """How loud a recording's speech is: its loud frames' log-mel, the bands' mean (log10 power; x10 for dB)."""
    return float(stats.mean.mean())


def normalise(mel: Tensor, stats: SpeechStats) -> Tensor:
    return ((mel - stats.mean) / stats.scale).clamp(-CLAMP, CLAMP)


def windows(features: Tensor, centres: Tensor, past: int, ahead: int) -> Tensor:
    """[N, M, past + 1 + ahead]: the feature frames around each centre (feature frame index [N]); frames outside the
    recording are silence (-CLAMP)."""
    count = features.shape[0]
    offsets = torch.arange(-past, ahead + 1, device=features.device)
    index = centres.long()[:, None] + offsets[None]  # [N, W]
    inside = (index >= 0) & (index < count)
    picked = features[index.clamp(0, count - 1)]  # [N, W, M]
    picked = torch.where(inside[..., None], picked, torch.full_like(picked, -CLAMP))
    return picked.transpose(1, 2).contiguous()


@dataclass
class Augmentation:
    """One recording condition: what another speaker and microphone do to the power spectrum."""

    gain_db: float = 0.0
    warp: float = 1.0
    tilt: float = 0.0  # power x (f / 1 kHz)^tilt
    eq_db: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)  # a smooth curve through these gains across the band
    snr_db: float = math.inf

    @staticmethod
    def sample(rng: np.random.Generator) -> "Augmentation":
        """A random condition: +-15 dB, a vocal tract 0.82-1.22x, tilt +-1, equaliser +-6 dB, SNR 10-50 dB or none."""
        return Augmentation(gain_db=float(rng.uniform(-15, 15)), warp=float(np.exp(rng.uniform(-0.2, 0.2))),
                            tilt=float(rng.uniform(-1.0, 1.0)), eq_db=tuple(float(g) for g in rng.uniform(-6, 6, 5)),
                            snr_db=float(rng.uniform(10, 50)) if rng.random() < 0.7 else math.inf)

    def apply(self, power: Tensor, loud_power: float) -> Tensor:
        """[..., B] augmented power spectra; loud_power: the mean power of the recording's loud frames (noise level
        reference)."""
        bins = torch.fft.rfftfreq(N_FFT, 1.0 / RATE, device=power.device).clamp_min(50.0)  # [B] Hz
        curve = torch.tensor(self.eq_db, dtype=torch.float32, device=power.device)
        where = torch.linspace(0, 1, len(self.eq_db), device=power.device)
        position = torch.log(bins / 50.0) / math.log(RATE / 2 / 50.0)  # [B] 0..1 on a log-frequency axis
        eq = torch.from_numpy(np.interp(position.cpu().numpy(), where.cpu().numpy(), curve.cpu().numpy())).float()
        shaping = 10.0 ** ((self.gain_db + eq.to(power.device)) / 10.0) * (bins / 1000.0) ** self.tilt  # [B]
        out = power * shaping
        if math.isfinite(self.snr_db):
            level = loud_power * 10.0 ** ((self.gain_db - self.snr_db) / 10.0) / power.shape[-1]
            out = out + level * torch.empty_like(out).exponential_()  # white noise: exponential power per bin
        return out


__all__ = ["Augmentation", "CLAMP", "SpeechStats", "log_mel_torch", "loud_frames", "normalise", "speech_level",
           "speech_stats", "windows"]
