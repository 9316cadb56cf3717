"""Log-mel features of speech at 100 frames a second: one implementation for a whole file and for a live stream.

    mel = log_mel(sound)                       # [F, N_MELS]: frame f is centred on sample f * HOP (time f / 100 s)
    stream = LogMelStream(); stream.push(chunk) -> new frames [k, N_MELS]   # the same numbers, chunk by chunk
    mfcc(mel) -> [F, N_MFCC]                   # the DCT of the log-mel frame (cepstrum)

Frame f covers samples [f*HOP - WINDOW/2, f*HOP + WINDOW/2) (zeros before the first sample), Hann-windowed, so a frame
depends only on its own samples: the stream emits frame f as soon as its last sample has arrived, and any chunking
gives the batch function's values exactly. Why our own ~40 lines of numpy and not librosa: this is all we use (a mel
filterbank, a DCT from scipy), it must be chunk-exact for the microphone, and librosa would bring numba, llvmlite and
scikit-learn (~150 MB); torchaudio cannot be installed beside our pinned torch.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from geoavatar.sound.track import RATE, Sound

HOP = RATE // 100  # 160 samples: 10 ms, 100 feature frames a second
WINDOW = 400  # 25 ms
N_FFT = 512
N_MELS = 40
FMIN, FMAX = 60.0, 7600.0
N_MFCC = 13
FLOOR = 1e-10  # power floor: digital silence is log10 = -10, not -inf
FRAME_RATE = RATE / HOP


def _hz_to_mel(hz):
    return 2595.0 * np.log10(1.0 + np.asarray(hz, np.float64) / 700.0)


def _mel_to_hz(mel):
    return 700.0 * (10.0 ** (np.asarray(mel, np.float64) / 2595.0) - 1.0)


@lru_cache(maxsize=4)
def mel_filters(n_mels: int = N_MELS, n_fft: int = N_FFT, rate: int = RATE, fmin: float = FMIN,
                fmax: float = FMAX) -> np.ndarray:
    """[n_mels, n_fft // 2 + 1] triangular filters evenly spaced on the mel scale, each of unit area in Hz (so a band's
    value does not depend on its width)."""
    bins = np.fft.rfftfreq(n_fft, 1.0 / rate)  # [B] Hz
    edges = _mel_to_hz(np.linspace(_hz_to_mel(fmin), _hz_to_mel(fmax), n_mels + 2))  # [M + 2]
    low, centre, high = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    rising = (bins[None] - low) / (centre - low)
    falling = (high - bins[None]) / (high - centre)
    weights = np.maximum(0.0, np.minimum(rising, falling))  # [M, B]
    weights *= (2.0 / (high - low))  # unit area
    return weights.astype(np.float32)


@lru_cache(maxsize=1)
def _window() -> np.ndarray:
    return np.hanning(WINDOW + 2)[1:-1].astype(np.float32)  # a periodic-like Hann with no zero end points


def _frames_power(padded: np.ndarray, first: int, count: int) -> np.ndarray:
    """Power spectra [count, B] of frames first..first+count-1 of a signal padded with WINDOW // 2 zeros in front."""
    starts = (first + np.arange(count)) * HOP  # in the padded signal: frame f starts at f * HOP
    index = starts[:, None] + np.arange(WINDOW)[None]
    frames = padded[index] * _window()[None]  # [count, WINDOW]
    spectrum = np.fft.rfft(frames, n=N_FFT, axis=1)
    return (spectrum.real ** 2 + spectrum.imag ** 2).astype(np.float32)


class PowerStream:
    """Power spectra [k, N_FFT // 2 + 1] of a sound that arrives in chunks: push(samples) returns the frames completed
    by them (frame f as soon as its last sample has arrived); finish() the frames still open at the end."""

    def __init__(self, rate: int = RATE):
        if rate != RATE:
            raise ValueError(f"{type(self).__name__}: sound must be at {RATE} Hz (read_sound resamples), got {rate}")
        self._buffer = np.zeros(WINDOW // 2, np.float32)  # the signal padded in front, from sample `_offset` on
        self._offset = 0  # index in the padded signal of _buffer[0]
        self.frames = 0  # frames emitted so far

    def push(self, samples: np.ndarray) -> np.ndarray:
        """[k, B]: the frames whose last sample has now arrived (k may be 0)."""
        self._buffer = np.concatenate([self._buffer, np.asarray(samples, np.float32).reshape(-1)])
        end = self._offset + len(self._buffer)  # samples of the padded signal available
        complete = (end - WINDOW) // HOP + 1 if end >= WINDOW else 0  # frames f with f * HOP + WINDOW <= end
        count = max(0, complete - self.frames)
        if count == 0:
            return np.zeros((0, N_FFT // 2 + 1), np.float32)
        power = _frames_power(self._buffer[self.frames * HOP - self._offset:], 0, count)
        self.frames += count
        keep_from = self.frames * HOP - self._offset  # the next frame's first sample
        self._buffer = self._buffer[keep_from:]
        self._offset += keep_from
        return power

    def finish(self) -> np.ndarray:
        """The frames still open at the end of the sound (their windows completed with zeros), so that a sound of n
        samples has n // HOP + 1 frames, as `log_mel` gives."""
        total = (self._offset + len(self._buffer) - WINDOW // 2) // HOP + 1
        missing = max(0, total - self.frames)
        return self.push(np.zeros(missing * HOP + WINDOW, np.float32))[:missing]


class LogMelStream(PowerStream):
    """Log-mel frames [k, N_MELS] of a sound that arrives in chunks (PowerStream's frames through the filterbank)."""

    def push(self, samples: np.ndarray) -> np.ndarray:
        return log_mel_of_power(super().push(samples))


def log_mel_of_power(power: np.ndarray) -> np.ndarray:
    """[F, N_MELS] log10 mel power of power spectra [F, B]."""
    return np.log10(np.maximum(np.asarray(power, np.float32) @ mel_filters().T, FLOOR)).astype(np.float32)


def power_frames(sound: Sound | np.ndarray) -> np.ndarray:
    """[F, N_FFT // 2 + 1] power spectra of every frame, F = n // HOP + 1 for n samples (frame f centred on time
    f / FRAME_RATE); what log_mel is made of."""
    samples = sound.samples if isinstance(sound, Sound) else np.asarray(sound, np.float32)
    if isinstance(sound, Sound) and sound.rate != RATE:
        raise ValueError(f"sound features need {RATE} Hz sound, got {sound.rate}")
    stream = PowerStream()
    return np.concatenate([stream.push(samples), stream.finish()])


def log_mel(sound: Sound | np.ndarray) -> np.ndarray:
    """[F, N_MELS] log10 mel power, F = n // HOP + 1 for n samples; frame f is centred on time f / FRAME_RATE."""
    return log_mel_of_power(power_frames(sound))


@lru_cache(maxsize=1)
def _dct_matrix() -> np.ndarray:
    from scipy.fft import dct

    return dct(np.eye(N_MELS), type=2, norm="ortho", axis=0)[:N_MFCC].astype(np.float32)  # [N_MFCC, N_MELS]


def mfcc(mel: np.ndarray) -> np.ndarray:
    """[F, N_MFCC] cepstral coefficients of log-mel frames [F, N_MELS] (orthonormal DCT-II, natural-log scale)."""
    return (np.asarray(mel, np.float32) * np.float32(np.log(10.0))) @ _dct_matrix().T


def frame_energy(mel: np.ndarray) -> np.ndarray:
    """[F] a frame's loudness in log10 units: the log of its summed mel power."""
    return np.log10(np.maximum((10.0 ** np.asarray(mel, np.float64)).sum(axis=1), FLOOR)).astype(np.float32)


__all__ = ["FRAME_RATE", "HOP", "LogMelStream", "N_FFT", "N_MELS", "N_MFCC", "PowerStream", "WINDOW", "frame_energy",
           "log_mel", "log_mel_of_power", "mel_filters", "mfcc", "power_frames"]
