"""What flows from a source to its sinks: one AnimationFrame per output frame, and the two interfaces.

    for frame in source:                      # FrameSource: the run's split, a driver dataset, the live tracker
        posed = PosedFrame(run, frame, ...)   # animation/posing.py: the head posed once for every sink
        sink.write(frame, posed)              # FrameSink: an mp4, the web player's clip, the live browser stream

animation/play.py's `play` runs that loop (and, for a live source, drive's measurements).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterator, Protocol

import numpy as np

from geoavatar.head.params import HeadParams
from geoavatar.render.camera import Camera

if TYPE_CHECKING:
    from geoavatar.animation.posing import PosedFrame


@dataclass
class AnimationFrame:
    """One frame of an animation: the avatar's parameters and what the sinks need beside them."""

    index: int  # the frame's number in the output, 0..; a live source skips the numbers of frames it dropped
    params: HeadParams  # the avatar's parameters, per-frame keys [1, ...], on the run's device
    T: int | None = None  # the mouth deformer's time input (RunFrames' T rule); None = T = 0
    camera: Camera | None = None  # None: the sink's fixed camera (reenact --camera driver gives one per frame)
    picture: np.ndarray | None = None  # uint8 [H, W, 3] shown beside the avatar (the driver's frame or face crop)
    timestep: int | None = None  # the frame's number in its source (a dataset's timestep), when it has one
    available: float | None = None  # perf_counter() when a live source had the frame (latency counts from it)
    heard: float | None = None  # speech: Unix time its own instant of sound was captured (the page's latency clock)
    timings: dict[str, float] = field(default_factory=dict)  # live: seconds per stage (stats.STAGES) so far
    record: dict | None = None  # live, record=True: the driver's fit of this frame (DriveStats.records)

    def add_time(self, stage: str, seconds: float) -> None:
        """Count `seconds` into `stage` (the source, play and the sinks each add their part)."""
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds


class FrameSource(Protocol):
    """Yields AnimationFrames over time. A live source runs its own threads, may drop frames (their indices are
    skipped) and counts what it did into `stats` (DriveStats); `audio` is its sound track (None: silent), which the
    front end hands to the sinks."""

    fps: float
    live: bool
    audio: object | None

    def __iter__(self) -> Iterator[AnimationFrame]: ...

    def close(self) -> None: ...


class FrameSink(Protocol):
    """Consumes AnimationFrames inside a `with` block: leaving it normally finishes the output (a file appears
    complete), an exception leaves none. `rasterizes`: it needs the frame's Gaussians, not only the posed head."""

    rasterizes: bool

    def __enter__(self) -> "FrameSink": ...

    def __exit__(self, exc_type, exc, tb) -> bool | None: ...

    def write(self, frame: AnimationFrame, posed: "PosedFrame") -> None: ...


__all__ = ["AnimationFrame", "FrameSink", "FrameSource"]
