"""The voice model on a live sound: chunks in, each video frame's face out as soon as its look-ahead has arrived.

    stream = VoiceStream(voice, fps=25)
    for index, face, heard in stream.push(chunk): ...     # frame index, SpokenFace of one frame, seconds of sound heard
    for index, face, heard in stream.finish(samples): ... # the sound ended: the last frames, as a file has them

Frame k (shown at k / fps of the sound) needs the sound up to k / fps + ahead: that is the model's latency floor
(0.1 s by default). The features are the same numbers as a whole file's (sound/features.py is chunk-exact), and so are
the faces when the statistics are fixed and no level is followed (`stats`, or a voice hearing the video's loudness
without a level slope: VoiceModel.hearing); live,
they start from the training sound's statistics and follow the microphone's: every half second, those of its last
ADAPT_SECONDS, once it has held LOUD_SECONDS of loud sound. A voice hearing the video's loudness keeps its statistics
and follows the speech level of those last seconds instead (VoiceModel.level_of; a file's is that of all its sound).
"""

from __future__ import annotations

import numpy as np
import torch

from geoavatar.sound import FRAME_RATE, RATE, video_frames
from geoavatar.sound.features import PowerStream
from geoavatar.voice.inputs import SpeechStats, log_mel_torch, loud_frames, normalise, speech_stats
from geoavatar.voice.model import SpokenFace, VoiceModel

ADAPT_SECONDS = 10.0
LOUD_SECONDS = 2.0
UPDATE_EVERY = 0.5  # seconds of sound between two updates of the statistics


class VoiceStream:
    def __init__(self, voice: VoiceModel, fps: float, stats: SpeechStats | None = None):
        if fps <= 0:
            raise ValueError(f"VoiceStream: fps must be positive, got {fps}")
        self.voice, self.fps = voice, float(fps)
        stats = stats or voice.fixed_stats
        self.fixed = stats is not None
        self.stats = stats or voice.speech
        self.power = PowerStream()
        self.mel = torch.zeros(0, voice.speech.mean.shape[0])  # [F, M] raw log-mel of the recent sound
        self.offset = 0  # feature frame number of self.mel[0]
        self.level = 0.0  # the speech level the face follows (VoiceModel.level_of of the recent sound)
        self.next_frame = 0  # the next video frame to emit
        self._since_update = 0

    @property
    def heard(self) -> float:
        """Seconds of sound whose feature frames are complete."""
        return (self.offset + len(self.mel)) / FRAME_RATE

    def _centre(self, frame: int) -> int:
        return int(round(frame / self.fps * FRAME_RATE))

    def _adapt(self, new_frames: int) -> None:
        self._since_update += new_frames
        if self._since_update < UPDATE_EVERY * FRAME_RATE:
            return
        self._since_update = 0
        recent = self.mel[-int(ADAPT_SECONDS * FRAME_RATE):]
        if int(loud_frames(recent).sum()) < LOUD_SECONDS * FRAME_RATE:
            return
        if not self.fixed:
            self.stats = speech_stats(recent)
        self.level = self.voice.level_of(recent)  # 0 unless the voice hears the video's loudness

    def push(self, samples: np.ndarray) -> list[tuple[int, SpokenFace, float]]:
        """The frames whose sound (with the look-ahead) is now complete: (frame index, its face [1, ...], seconds of
        sound heard when it was made)."""
        power = self.power.push(samples)
        if len(power) == 0:
            return []
        self.mel = torch.cat([self.mel, log_mel_torch(torch.from_numpy(power))])
        self._adapt(len(power))
        ready = []
        while self._centre(self.next_frame) + self.voice.ahead < self.offset + len(self.mel):
            ready.append(self.next_frame)
            self.next_frame += 1
        out = self._faces(ready)
        keep = max(int(ADAPT_SECONDS * FRAME_RATE), self.voice.past + self.voice.ahead + 2)
        if len(self.mel) > 2 * keep:  # drop what no window or statistic needs any more
            drop = len(self.mel) - keep
            self.mel, self.offset = self.mel[drop:], self.offset + drop
        return out

    def finish(self, samples: int) -> list[tuple[int, SpokenFace, float]]:
        """The sound ended after `samples` samples: the frames still owed, up to a file's ceil(seconds x fps), their
        look-ahead past the end heard as a file's is (the windows padded beyond the last feature frame)."""
        power = self.power.finish()
        if len(power):
            self.mel = torch.cat([self.mel, log_mel_torch(torch.from_numpy(power))])
        last = video_frames(samples / RATE, self.fps)
        ready = list(range(self.next_frame, last))
        self.next_frame = max(self.next_frame, last)
        return self._faces(ready)

    def _faces(self, ready: list[int]) -> list[tuple[int, SpokenFace, float]]:
        if not ready:
            return []
        centres = torch.as_tensor([self._centre(k) - self.offset for k in ready])
        face = self.voice.predict_features(normalise(self.mel, self.stats), centres, self.level)
        return [(k, SpokenFace(face.expr[i:i + 1], face.jaw[i:i + 1]), self.heard) for i, k in enumerate(ready)]


__all__ = ["VoiceStream"]
