"""The live tracker's input: a camera or a video file as upright RGB frames, and the mailboxes between its threads.

    capture = open_video(path)                          # or open_camera(index): a VideoInput; DriveError if unreadable
    mailbox = NewestFrame(lossless=False, depth=2)      # the newest items between two threads, the rest dropped
    start_reader(capture, mailbox, max_frames, stop)    # a thread: (index, available_time, rgb) into the mailbox
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.prep.errors import PrepareError

# Items a stage's mailbox holds (the newest; a new one drops the oldest when full). 2, not 1: with 1 a single slow
# frame (another job taking the core for a moment) dropped the next; on wojtek.mp4 under load 4-6 on 2 cores, 5
# interleaved runs each: median 98.7 % of the frames shown with 2, 94.7 % with 1, median latency 30 vs 34 ms (#28).
MAILBOX_DEPTH = 2


class DriveError(GeoAvatarError):
    """The driving source (camera or video) cannot be opened or read; the message names it."""


@dataclass
class VideoInput:
    """A camera or a video file: where the live tracker's frames come from."""

    name: str  # for messages: "--video FILE" / "--camera N"
    fps: float
    frames: Callable[[], Iterator[np.ndarray]]  # a fresh iterator of upright RGB uint8 frames
    live: bool  # a camera: frames arrive by themselves (no pacing)


def open_video(path: str | Path) -> VideoInput:
    """A video file as a source (PyAV, prep/video.py); DriveError when missing or unreadable."""
    from geoavatar.prep.video import decode_frames, probe_video

    name = f"--video {path}"
    try:
        info = probe_video(path)
    except PrepareError as err:
        raise DriveError(f"{name}: {err}") from err

    def frames() -> Iterator[np.ndarray]:
        try:
            for _index, rgb in decode_frames(path):
                yield rgb
        except PrepareError as err:
            raise DriveError(f"{name}: {err}") from err

    return VideoInput(name, info.fps if info.fps > 0 else 25.0, frames, live=False)


def open_camera(index: int) -> VideoInput:
    """Webcam `index`: PyAV's v4l2 input (/dev/videoN), else OpenCV; DriveError when neither opens it."""
    name = f"--camera {index}"
    if index < 0:
        raise OptionError(f"{name}: the camera number must be >= 0")
    device = f"/dev/video{index}"
    problems = []
    try:
        import av

        container = av.open(device, format="v4l2")
        stream = container.streams.video[0]
        fps = float(stream.average_rate or 30.0)

        def frames() -> Iterator[np.ndarray]:
            try:
                for frame in container.decode(stream):
                    yield frame.to_ndarray(format="rgb24")
            except Exception as err:  # a camera unplugged mid-stream
                raise DriveError(f"{name}: reading {device} failed ({type(err).__name__}: {err})") from err
            finally:
                container.close()

        return VideoInput(name, fps, frames, live=True)
    except Exception as err:  # PyAV raises FileNotFoundError, OSError, av.error.* for a missing device
        problems.append(f"PyAV: {type(err).__name__}: {err}")
    try:
        import cv2

        capture = cv2.VideoCapture(index)
        ok = capture.isOpened() and capture.read()[0]
        if not ok:
            capture.release()
            raise OSError(f"could not open camera {index}")
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 30.0)

        def frames() -> Iterator[np.ndarray]:
            try:
                while True:
                    ok, bgr = capture.read()
                    if not ok:
                        raise DriveError(f"{name}: the camera stopped delivering frames")
                    yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            finally:
                capture.release()

        return VideoInput(name, fps if fps > 0 else 30.0, frames, live=True)
    except Exception as err:
        problems.append(f"OpenCV: {err}")
    raise DriveError(f"{name}: cannot open the camera {device} ({'; '.join(problems)})")


class NewestFrame:
    """A small mailbox between two stages (reader -> fit -> output): it holds at most `depth` items; a new item
    arriving when it is full drops the oldest waiting one (counted), and `get` takes the oldest. depth 1: a new item
    replaces the waiting one.

    With `lossless` the producer waits for the consumer instead (every frame is processed; for measurements)."""

    def __init__(self, lossless: bool = False, depth: int = 1):
        if depth < 1:
            raise ValueError(f"NewestFrame: depth must be >= 1, got {depth}")
        self.lossless, self.depth = lossless, depth
        self._items: deque = deque()
        self._closed = False
        self._error: BaseException | None = None
        self._cond = threading.Condition()
        self.dropped = 0
        self.delivered = 0

    def set_lossless(self, lossless: bool) -> None:
        with self._cond:
            self.lossless = lossless
            self._cond.notify_all()

    def wait_for_room(self) -> None:
        """Lossless: wait until the consumer has taken what waits (where `put` would wait)."""
        with self._cond:
            while self.lossless and self._items and not self._closed:
                self._cond.wait()

    def put(self, item) -> None:
        with self._cond:
            while self.lossless and self._items and not self._closed:
                self._cond.wait()
            if len(self._items) >= self.depth:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self.delivered += 1
            self._cond.notify_all()

    def close(self, error: BaseException | None = None) -> None:
        with self._cond:
            self._closed, self._error = True, error
            self._cond.notify_all()

    def get(self):
        """The oldest waiting item, waiting for one; None when the source ended (its error re-raised)."""
        with self._cond:
            while not self._items and not self._closed:
                self._cond.wait()
            item = self._items.popleft() if self._items else None
            self._cond.notify_all()
            if item is None and self._error is not None:
                raise self._error
            return item


def start_reader(source: VideoInput, mailbox: NewestFrame, max_frames: int | None,
                 stop: threading.Event) -> threading.Thread:
    """A thread putting (index, available_time, rgb) into the mailbox; a file is paced at its frame rate
    from the first frame it puts while the mailbox is not lossless (its clock starts there)."""

    def read() -> None:
        error = None
        try:
            origin = None  # (perf_counter, frame index) where the file's clock started
            for index, rgb in enumerate(source.frames()):
                if stop.is_set() or (max_frames is not None and index >= max_frames):
                    break
                # a frame held back by a lossless mailbox (the identity stage) is available when it goes in, not
                # when it was read: its time is taken after the wait
                mailbox.wait_for_room()
                if not source.live and not mailbox.lossless:
                    if origin is None:
                        origin = (time.perf_counter(), index)
                    wait = origin[0] + (index - origin[1]) / source.fps - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                mailbox.put((index, time.perf_counter(), rgb))
        except BaseException as err:  # handed to the worker, which raises it
            error = err
        finally:
            mailbox.close(error)

    thread = threading.Thread(target=read, name="geoavatar-drive-reader", daemon=True)
    thread.start()
    return thread


__all__ = ["DriveError", "MAILBOX_DEPTH", "NewestFrame", "VideoInput", "open_camera", "open_video", "start_reader"]
