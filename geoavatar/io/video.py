"""The one mp4 writer: frames -> H.264 (PyAV, libx264, yuv420p), written atomically, with an optional sound track.

    with Mp4Writer(path, fps=25) as video:
        video.write(frame)                   # uint8 RGB [H, W, 3]
    write_mp4(path, frames, fps=25)          # the same for an iterable of frames
    Mp4Writer(path, fps=25, audio=sound)     # + AAC from a geoavatar.sound.Sound: frame k shows time k / fps of it

With a sound, the sound is muxed beside the frames as they come (interleaved): sample 0 plays with frame 0, and
the sound written never runs past the frames written by more than a frame, so neither drifts from the other.

yuv420p needs even sizes: a frame with an odd height or width gets its last row / column repeated
(nothing is cropped away). Every frame must have the size of the first.
"""

from __future__ import annotations

import contextlib
import os
import sys
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import numpy as np

from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.io.atomic import atomic_file


class EmptyVideoError(GeoAvatarError, ValueError):
    """An mp4 ended before its first frame (a live source stopped at once): no file is written."""


def pad_to_even(frame: np.ndarray) -> np.ndarray:
    """[H, W, 3] -> [H + H % 2, W + W % 2, 3], the edge row / column repeated."""
    pad = ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0))
    return np.pad(frame, pad, mode="edge") if pad[0][1] or pad[1][1] else frame


def check_mp4_options(path: str | os.PathLike | None, fps: float | None = None, crf: int = 18) -> None:
    """OptionError for what Mp4Writer cannot write (None: not given yet); commands call it before their work."""
    if fps is not None and fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    if not 0 <= crf <= 51:
        raise OptionError(f"--crf must be in [0, 51], got {crf}")
    if path is not None and Path(path).suffix.lower() != ".mp4":
        raise OptionError(f"{path}: the video file name must end in .mp4")


class Mp4Writer:
    """Frames -> H.264 mp4 (PyAV, libx264, yuv420p), written atomically (geoavatar.io.atomic_file).

    Leaving the `with` block normally moves the finished file into place; an exception deletes it, so
    `path` is either the old file or the complete new one. A full disk raises DiskFullError.
    """

    def __init__(self, path: str | os.PathLike, fps: float = 25.0, crf: int = 18, preset: str = "medium",
                 audio=None, audio_bitrate: int = 96000):
        check_mp4_options(path, fps, crf)
        self.path = Path(path)
        self.fps, self.crf, self.preset = fps, crf, preset
        self.audio, self.audio_bitrate = audio, audio_bitrate  # a Sound (samples [n] float32, rate) or None
        self._audio_stream = None
        self._audio_written = 0  # samples of `audio` encoded so far
        self.frames = 0
        self._container = self._stream = None
        self._files: contextlib.ExitStack | None = None
        self._size: tuple[int, int] | None = None  # (height, width) of the input frames

    def __enter__(self) -> "Mp4Writer":
        import av

        self._files = contextlib.ExitStack()
        tmp = self._files.enter_context(atomic_file(self.path, suffix=".tmp.mp4"))
        try:
            self._container = av.open(str(tmp), mode="w", format="mp4")
        except BaseException:
            if not self._files.__exit__(*sys.exc_info()):
                raise
        return self

    def write(self, frame: np.ndarray) -> None:
        """Append one uint8 RGB frame [H, W, 3]."""
        import av

        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"Mp4Writer: frames must be uint8 [H, W, 3], got {frame.dtype} {frame.shape}")
        if self._size is None:
            self._size = frame.shape[:2]
            height, width = (s + s % 2 for s in self._size)
            self._stream = self._container.add_stream("libx264", rate=Fraction(self.fps).limit_denominator(1001))
            self._stream.width, self._stream.height = width, height
            self._stream.pix_fmt = "yuv420p"
            self._stream.options = {"crf": str(self.crf), "preset": self.preset}
            if self.audio is not None:
                self._audio_stream = self._container.add_stream("aac", rate=int(self.audio.rate))
                self._audio_stream.layout = "mono"
                self._audio_stream.bit_rate = self.audio_bitrate
        elif frame.shape[:2] != self._size:
            raise ValueError(f"Mp4Writer: frame {self.frames} has size {frame.shape[1]}x{frame.shape[0]}, the first "
                             f"{self._size[1]}x{self._size[0]}; every frame of a video needs one size")
        video_frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(pad_to_even(frame)), format="rgb24")
        for packet in self._stream.encode(video_frame):
            self._container.mux(packet)
        self.frames += 1
        if self._audio_stream is not None:  # the sound up to the end of this frame
            self._write_audio(int(round(self.frames / self.fps * self.audio.rate)))

    def _write_audio(self, until: int) -> None:
        """Encode the sound's samples up to sample `until` (those not encoded yet)."""
        import av

        samples = self.audio.samples
        stop = min(until, len(samples))
        if stop > self._audio_written:
            from geoavatar.sound.track import to_pcm16

            chunk = to_pcm16(samples[self._audio_written:stop])[None]  # [1, n]
            frame = av.AudioFrame.from_ndarray(chunk, format="s16", layout="mono")
            frame.rate, frame.pts = int(self.audio.rate), self._audio_written
            for packet in self._audio_stream.encode(frame):
                self._container.mux(packet)
            self._audio_written = stop

    def __exit__(self, exc_type, exc, tb) -> bool:
        files, self._files = self._files, None
        try:
            try:
                if exc_type is None:
                    if self.frames == 0:  # nothing is written, and nothing that was there is replaced
                        raise EmptyVideoError(f"{self.path}: not written: no frame came to write")
                    for packet in self._stream.encode():  # flush the encoder
                        self._container.mux(packet)
                    if self._audio_stream is not None:  # the sound ends with the last frame: flush its encoder
                        for packet in self._audio_stream.encode(None):
                            self._container.mux(packet)
            finally:
                self._container.close()
        except BaseException:
            if exc_type is None:  # finishing failed: atomic_file removes the file (and names a full disk)
                if not files.__exit__(*sys.exc_info()):
                    raise
                return False
            # the block failed already: its exception is the one to report
        return bool(files.__exit__(exc_type, exc, tb))


def write_mp4(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 25.0, crf: int = 18,
              preset: str = "medium") -> Path:
    """Encode uint8 RGB frames [H, W, 3] as an mp4 at `path` (Mp4Writer); returns the path."""
    with Mp4Writer(path, fps, crf, preset) as video:
        for frame in frames:
            video.write(frame)
    return Path(path)


__all__ = ["EmptyVideoError", "Mp4Writer", "check_mp4_options", "pad_to_even", "write_mp4"]
