"""Where a sound holds speech: Silero VAD (MIT; its model ships inside the `silero-vad` wheel, nothing downloaded).

    activity = speech_activity(sound)          # SpeechActivity: segments [(start, stop)] in seconds, speech_seconds
    activity.mask(times)                       # [T] bool: which of these times (seconds from sample 0) are speech

prepare's report says how many seconds of a video are speech (a video with none prepares as before, and its avatar
learns no voice); a voice is learned only from training frames that hold some of it (voice/train.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from geoavatar.sound.track import RATE, Sound

MIN_SPEECH_SECONDS = 2.0  # below this a video "has no speech" worth learning a voice from
# below this the voice learned follows the sound loosely: on french.mp4 the held-out lip-opening r was 0.26 / 0.36 /
# 0.59 / 0.72 from 8 / 17 / 26 / 33 s of training speech, still rising (docs/speech.md, "How much talking")
ADVISED_SPEECH_SECONDS = 60.0


@lru_cache(maxsize=1)
def _silero():
    import warnings

    import torch

    threads = torch.get_num_threads()
    try:
        from silero_vad import load_silero_vad  # its import sets torch's thread count to 1: put ours back

        with warnings.catch_warnings():  # its loader's importlib / torch.jit deprecation notices are not ours
            warnings.simplefilter("ignore", DeprecationWarning)
            return load_silero_vad(onnx=False)
    finally:
        torch.set_num_threads(threads)


@dataclass
class SpeechActivity:
    segments: list[tuple[float, float]] = field(default_factory=list)  # seconds from the sound's sample 0

    @property
    def speech_seconds(self) -> float:
        return float(sum(stop - start for start, stop in self.segments))

    @property
    def has_speech(self) -> bool:
        return self.speech_seconds >= MIN_SPEECH_SECONDS

    def mask(self, times: np.ndarray) -> np.ndarray:
        """[T] bool: whether each time (seconds from sample 0) falls in a speech segment."""
        times = np.asarray(times, np.float64)
        inside = np.zeros(times.shape, bool)
        for start, stop in self.segments:
            inside |= (times >= start) & (times < stop)
        return inside

    def to_json(self) -> dict:
        return {"speech_seconds": round(self.speech_seconds, 3),
                "segments": [[round(a, 3), round(b, 3)] for a, b in self.segments]}


def speech_activity(sound: Sound) -> SpeechActivity:
    """The speech segments of a sound at RATE (Silero VAD with its default thresholds, 30 ms of padding)."""
    import torch

    if sound.rate != RATE:
        raise ValueError(f"speech_activity: sound must be at {RATE} Hz, got {sound.rate}")
    if len(sound.samples) < 512:  # shorter than one of the model's windows
        return SpeechActivity([])
    threads = torch.get_num_threads()
    try:
        from silero_vad import get_speech_timestamps  # its first import sets torch's thread count to 1

        with torch.no_grad():
            stamps = get_speech_timestamps(torch.from_numpy(np.ascontiguousarray(sound.samples)), _silero(),
                                           sampling_rate=RATE)
    finally:
        torch.set_num_threads(threads)
    return SpeechActivity([(s["start"] / RATE, s["end"] / RATE) for s in stamps])


__all__ = ["ADVISED_SPEECH_SECONDS", "MIN_SPEECH_SECONDS", "SpeechActivity", "speech_activity"]
