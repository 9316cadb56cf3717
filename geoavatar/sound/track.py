"""A sound track in memory, its one reading path (PyAV: any container or codec FFmpeg decodes) and the wav writer.

    sound = read_sound("talk.mp4")              # mono float32 at 16 kHz; SoundError naming the file when unreadable
    sound.samples, sound.rate, sound.start      # [n] in [-1, 1], 16000, seconds of sample 0 on the file's timeline
    write_wav("audio.wav", sound)               # 16-bit PCM, atomic

Everything that hears sound (prepare, the voice model, speak, the live microphone) reads it here, resampled once to
RATE: the voice model's features are defined at that rate, so a file at 44.1 or 48 kHz, 8-bit or stereo gives the
same features as the same sound at 16 kHz.
"""

from __future__ import annotations

import math
import os
import wave
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoavatar.errors import GeoAvatarError
from geoavatar.io.atomic import atomic_file

RATE = 16000  # samples per second of every sound GeoAvatar works with (speech: 8 kHz of bandwidth is plenty)
GAP_SECONDS = 0.005  # a decoded frame starting this much after the previous one's end follows missing packets


class SoundError(GeoAvatarError, ValueError):
    """A sound file cannot be used (missing, not decodable, no sound track, too short); the message names it."""


@dataclass(frozen=True)
class Sound:
    """Mono sound: samples [n] float32 in [-1, 1] at `rate`; `start` is where sample 0 sits on the timeline of the
    file it came from (seconds; a video's frames are timed on that timeline too)."""

    samples: np.ndarray  # [n] float32
    rate: int = RATE
    start: float = 0.0

    @property
    def seconds(self) -> float:
        return len(self.samples) / self.rate

    def segment(self, start: float, stop: float) -> "Sound":
        """The sound between two times (seconds from sample 0), sample-exact; `start` moves with it."""
        a = max(0, int(round(start * self.rate)))
        b = max(a, min(len(self.samples), int(round(stop * self.rate))))
        return Sound(self.samples[a:b], self.rate, self.start + a / self.rate)

    def padded(self, seconds: float) -> "Sound":
        """The sound with `seconds` of silence appended (a clip's last frame gets sound under it)."""
        extra = max(0, int(round(seconds * self.rate)))
        return Sound(np.concatenate([self.samples, np.zeros(extra, np.float32)]), self.rate, self.start)


def _open(path: Path, what: str):
    import av

    if not path.is_file():
        raise SoundError(f"{what} {path}: file not found")
    try:
        container = av.open(str(path))
    except Exception as err:  # PyAV raises many kinds (InvalidDataError, ValueError, ...)
        raise SoundError(f"{what} {path}: not a readable sound or video file ({type(err).__name__}: {err})") from err
    if not container.streams.audio:
        container.close()
        raise SoundError(f"{what} {path}: the file has no sound track")
    return container


def video_frames(seconds: float, fps: float) -> int:
    """The frames that show a sound of `seconds` at `fps` (frame k at k / fps of it): ceil(seconds x fps), at least
    one, so sound and picture end together and cannot drift over minutes."""
    return max(1, math.ceil(seconds * fps - 1e-9))


def has_sound_track(path: str | os.PathLike) -> bool:
    """Whether the file holds an audio stream (False for a file PyAV cannot open)."""
    try:
        _open(Path(path), "").close()
    except SoundError:
        return False
    return True


def read_sound(path: str | os.PathLike, rate: int = RATE, what: str = "sound") -> Sound:
    """The first audio stream of a file, mixed to mono and resampled to `rate` (PyAV's resampler).

    SoundError naming `what` and the file when it is missing, undecodable, has no sound track or no samples."""
    import av

    path = Path(path)
    container = _open(path, what)
    parts: list[np.ndarray] = []
    start = None
    heard = 0.0  # seconds of sound decoded (the resampler's flush adds its filter's tail beyond them)
    try:
        stream = container.streams.audio[0]
        resampler = av.AudioResampler(format="s16", layout="mono", rate=rate)
        try:
            expected = None  # the time at which the next decoded frame should start
            for frame in container.decode(stream):
                if frame.time is not None:
                    start = float(frame.time) if start is None else start
                    if expected is not None and frame.time - expected > GAP_SECONDS:  # packets missing: silence,
                        gap = _silence_like(frame, frame.time - expected)  # so what follows keeps its own time
                        heard += gap.samples / float(frame.sample_rate)
                        parts.extend(out.to_ndarray().reshape(-1) for out in resampler.resample(gap))
                    expected = float(frame.time) + frame.samples / float(frame.sample_rate)
                heard += frame.samples / float(frame.sample_rate)
                parts.extend(out.to_ndarray().reshape(-1) for out in resampler.resample(frame))
            parts.extend(out.to_ndarray().reshape(-1) for out in resampler.resample(None))
        except Exception as err:
            if not parts:
                raise SoundError(f"{what} {path}: its sound could not be decoded "
                                 f"({type(err).__name__}: {err})") from err
            raise SoundError(f"{what} {path}: decoding its sound failed after {sum(map(len, parts)) / rate:.2f} s "
                             f"({type(err).__name__}: {err})") from err
    finally:
        container.close()
    samples = np.concatenate(parts).astype(np.float32) / 32768.0 if parts else np.zeros(0, np.float32)
    samples = samples[:int(round(heard * rate))]  # as long as the file's sound, whatever the rate
    if len(samples) == 0:
        raise SoundError(f"{what} {path}: the sound track holds no samples")
    return Sound(samples, rate, start or 0.0)


def _silence_like(frame, seconds: float):
    """A silent audio frame of `seconds` in `frame`'s format, layout and rate (to fill a gap in a track)."""
    import av

    silence = av.AudioFrame(format=frame.format.name, layout=frame.layout.name,
                            samples=int(round(seconds * frame.sample_rate)))
    for plane in silence.planes:
        plane.update(bytes(plane.buffer_size))
    silence.sample_rate = frame.sample_rate
    return silence


def resample(sound: Sound, rate: int) -> Sound:
    """The sound at another rate (polyphase filtering, scipy): for a sound made here, not read from a file."""
    from math import gcd

    from scipy.signal import resample_poly

    if rate == sound.rate:
        return sound
    common = gcd(int(rate), int(sound.rate))
    samples = resample_poly(sound.samples, int(rate) // common, int(sound.rate) // common)
    return Sound(np.clip(samples, -1.0, 1.0).astype(np.float32), int(rate), sound.start)


def to_pcm16(samples: np.ndarray) -> np.ndarray:
    """float samples in [-1, 1] -> int16 (clipped, rounded)."""
    return np.clip(np.round(np.asarray(samples, np.float64) * 32767.0), -32768, 32767).astype("<i2")


def write_wav(path: str | os.PathLike, sound: Sound) -> Path:
    """16-bit PCM mono wav, written atomically; returns the path."""
    with atomic_file(path, suffix=".tmp.wav") as tmp, wave.open(str(tmp), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(2)
        out.setframerate(int(sound.rate))
        out.writeframes(to_pcm16(sound.samples).tobytes())
    return Path(path)


__all__ = ["RATE", "Sound", "SoundError", "has_sound_track", "read_sound", "resample", "to_pcm16", "video_frames",
           "write_wav"]
