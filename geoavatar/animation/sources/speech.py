"""Speech drives the avatar: a sound file, a text spoken by a speech synthesiser, or a live microphone, through the
run's voice model (geoavatar/voice), as a source.

    source = SpeechFrames(run, voice, sound, fps=25, playback=sound48k)   # a file: every frame at once
    source = LiveSpeech(run, voice, RealTimeSound(sound), fps=25)         # live: a file played in real time, or
    source = LiveSpeech(run, voice, MicrophoneSound(), fps=25)            #   the browser's microphone (speak --view)

Frame k is shown at k / fps of the sound: its expression and jaw are the voice model's for the sound around that
instant; its head pose, gaze, blinks and brows are the person's own idle motion from their training frames
(voice/idle.py), so the head is alive while it speaks; T = 0 (a new animation). A file gives ceil(seconds x fps)
frames, one per 1/fps of sound, so sound and picture cannot drift over minutes.

Live, the sound arrives in chunks (20 ms) on a thread of its own; each frame is made as soon as its sound and the
model's look-ahead have arrived and goes through a mailbox of the newest MAILBOX_DEPTH frames to play's output stage
(a pipeline slower than the sound drops frames rather than lagging). A frame's `available` is the moment its own
instant of sound was captured (perf_counter), so drive's latency figure is sound-to-picture: the look-ahead, the
chunking, the model, the posing and the streaming; `heard` is the same moment in Unix seconds for the browser,
which measures it up to the drawn picture.
"""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.posing import record_camera
from geoavatar.animation.sources.capture import MAILBOX_DEPTH, NewestFrame
from geoavatar.animation.stats import DriveStats
from geoavatar.data import DatasetError, open_subject
from geoavatar.errors import GeoAvatarError
from geoavatar.head.params import HeadParams
from geoavatar.render.camera import Camera
from geoavatar.sound import RATE, Sound, video_frames
from geoavatar.train.checkpoint import LoadedRun, RunError
from geoavatar.train.run_frames import RunFrames
from geoavatar.voice import VoiceModel, speaking_params
from geoavatar.voice.stream import VoiceStream

CHUNK_SECONDS = 0.02  # a live sound's chunks (the browser's AudioWorklet sends 20 ms)
SPEECH_STAGES = ("voice", "pose", "render")


def avatar_camera(run: LoadedRun, data: Path | None = None, resolution: int | None = None) -> Camera:
    """The avatar's dataset camera of its first frame, at the run's resolution (what reenact and drive show)."""
    root = Path(data) if data is not None else run.info.data_root
    try:
        subject = open_subject(root)
    except (DatasetError, OSError) as err:
        raise RunError(f"{run.info.run_dir}: the camera comes from its dataset {root}, which cannot be read ({err}); "
                       "pass --data DIR") from err
    return record_camera(subject, RunFrames(run).timesteps[0], resolution or run.info.resolution)


class SpeechFrames:
    """Source: a whole sound through the voice model (module docstring); `playback` is the sound the sinks carry
    (the same sound at a better rate, say; default `sound`)."""

    live = False

    def __init__(self, run: LoadedRun, voice: VoiceModel, sound: Sound, fps: float = 25.0,
                 playback: Sound | None = None, seed: int = 0):
        if fps <= 0:
            raise ValueError(f"SpeechFrames: fps must be positive, got {fps}")
        self.run, self.voice, self.sound, self.fps = run, voice, sound, float(fps)
        self.audio = playback if playback is not None else sound
        count = video_frames(sound.seconds, self.fps)
        face = voice.predict(sound, np.arange(count) / self.fps)
        idle = voice.idle.player(self.fps, seed).take(count)
        frames = RunFrames(run)
        self.params = speaking_params(face, idle, frames.identity(), frames.device)  # npz layout [N, ...]
        self.count = count

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[AnimationFrame]:
        every = HeadParams.from_npz(self.params)
        for index in range(self.count):
            yield AnimationFrame(index, every.frame(index), None)

    def close(self) -> None:
        pass


# --- live sound --------------------------------------------------------------------------------------


class RealTimeSound:
    """A sound played as a live source: CHUNK_SECONDS chunks delivered at the sound's own pace (a microphone's), each
    with the perf_counter() time its last sample was 'captured'."""

    live = True

    def __init__(self, sound: Sound, name: str = "--audio"):
        if sound.rate != RATE:
            raise ValueError(f"RealTimeSound: the sound must be at {RATE} Hz, got {sound.rate}")
        self.sound, self.name = sound, name

    def chunks(self, stop: threading.Event) -> Iterator[tuple[np.ndarray, float]]:
        size = int(CHUNK_SECONDS * RATE)
        origin = time.perf_counter()
        for start in range(0, len(self.sound.samples), size):
            chunk = self.sound.samples[start:start + size]
            captured = origin + (start + len(chunk)) / RATE  # when its last sample would have been spoken
            wait = captured - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            if stop.is_set():
                return
            yield chunk, captured


class MicrophoneError(GeoAvatarError):
    """The browser page could not open its microphone; the message is the page's."""


class MicrophoneSound:
    """The browser's microphone (web/live.py's on_audio): chunks of 16 kHz sound with the page's capture times, queued
    here for the source's thread; `error` ends it with the page's one-line message."""

    live = True
    name = "--microphone"

    def __init__(self):
        self._queue: queue.Queue = queue.Queue()
        self.chunks_received = 0

    def on_audio(self, samples: np.ndarray, capture_time: float, sequence: int) -> None:
        """LiveServer's callback: Unix capture time of the chunk's last sample, converted to perf_counter."""
        self.chunks_received += 1
        self._queue.put((np.asarray(samples, np.float32), time.perf_counter() - (time.time() - capture_time)))

    def on_error(self, message: str) -> None:
        self._queue.put(MicrophoneError(f"--microphone: {message}"))

    def chunks(self, stop: threading.Event) -> Iterator[tuple[np.ndarray, float]]:
        while not stop.is_set():
            try:
                item = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise item
            yield item


class LiveSpeech:
    """Source: live sound through the voice model, frame by frame (module docstring). `stats` counts the frames made
    and dropped; `max_seconds` ends it after that much sound (None: when the sound ends, or Ctrl-C)."""

    live = True
    audio = None
    label = "speak"  # the status line's

    def __init__(self, run: LoadedRun, voice: VoiceModel, sound_input, fps: float = 25.0, seed: int = 0,
                 max_seconds: float | None = None):
        self.run, self.voice, self.input, self.fps = run, voice, sound_input, float(fps)
        self.stream = VoiceStream(voice, self.fps)
        self.idle = voice.idle.player(self.fps, seed)
        frames = RunFrames(run)
        self.identity, self.device = frames.identity(), frames.device
        self.max_seconds = max_seconds
        self.stats = DriveStats(stage_ms={stage: [] for stage in SPEECH_STAGES})
        self._frames = NewestFrame(False, MAILBOX_DEPTH)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._samples = 0  # samples heard so far

    @property
    def dropped(self) -> int:
        return self._frames.dropped

    def _frames_of(self, chunk: np.ndarray, captured: float) -> None:
        """Push a chunk; each frame it completes goes into the mailbox, timed from its own instant of sound."""
        started = time.perf_counter()
        ready = self.stream.push(chunk)
        self._samples += len(chunk)
        self._deliver(ready, captured, started)

    def _deliver(self, ready: list, captured: float, started: float) -> None:
        end = self._samples / RATE  # the sound's end so far on its own clock, captured at `captured`
        for index, face, _ in ready:
            idle = {k: v[None] for k, v in self.idle.next().items()}
            params = HeadParams.from_npz(speaking_params(face, idle, self.identity, self.device))
            instant = captured - (end - index / self.fps)  # perf_counter() when frame k's own sound was spoken
            frame = AnimationFrame(index, params, None, available=instant,
                                   heard=time.time() - (time.perf_counter() - instant))
            frame.add_time("voice", (time.perf_counter() - started) / len(ready))
            self.stats.delivered += 1
            self._frames.put(frame)

    def _listen(self) -> None:
        error = None
        try:
            for chunk, captured in self.input.chunks(self._stop):
                self._frames_of(chunk, captured)
                if self.max_seconds is not None and self.stream.heard >= self.max_seconds:
                    break
            else:
                if not self._stop.is_set():  # the sound ended by itself: its last frames, as a file gives them,
                    self._frames.set_lossless(True)  # each one shown (no sound is left to keep pace with)
                    now = time.perf_counter()
                    self._deliver(self.stream.finish(self._samples), now, now)
        except BaseException as err:  # handed to the output stage, which raises it
            error = err
        finally:
            self._frames.close(error)

    def __iter__(self) -> Iterator[AnimationFrame]:
        self._thread = threading.Thread(target=self._listen, name="geoavatar-speech", daemon=True)
        self._thread.start()
        while True:
            try:
                frame = self._frames.get()
            except KeyboardInterrupt:
                return
            if frame is None:
                return
            yield frame

    def close(self) -> None:
        self._stop.set()
        self._frames.close()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.stats.dropped = self.dropped


__all__ = ["CHUNK_SECONDS", "LiveSpeech", "MicrophoneError", "MicrophoneSound", "RealTimeSound", "SpeechFrames",
           "avatar_camera"]
