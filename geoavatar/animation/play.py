"""Run a source into sinks: what every animation command does after its options are checked.

    sinks = [Mp4Sink(run, out, source.fps, camera, audio=source.audio)]
    played = play(run, source, sinks, progress=True, desc="reenact")

Each frame is posed once (PosedFrame: the Gaussians when a sink rasterizes) and handed to every sink in order. The
sinks are entered before the first frame and left after the last one (a file appears complete, or not at all when
anything fails); the source is closed at the end either way.

A live source (`source.live`: drive's tracker, speak's voice) is drive's output stage: its frames come as its threads
deliver them; each shown frame is counted into the source's DriveStats (frames and FPS from the first online frame's
end, its stage times, the latency from the moment the frame was available) and the status line is shown
(stats.LiveStatus). Ctrl-C ends a live source as the end of its input does, so the frames made so far are kept.
"""

from __future__ import annotations

import contextlib
import time
from typing import Sequence

import torch

from geoavatar.animation.frames import AnimationFrame, FrameSink, FrameSource
from geoavatar.animation.posing import PosedFrame
from geoavatar.animation.stats import DriveStats, LiveStatus
from geoavatar.train.checkpoint import LoadedRun


class _LiveCount:
    """drive's accounting of each shown frame (what its output stage counted)."""

    def __init__(self, stats: DriveStats, status: LiveStatus):
        self.stats, self.status = stats, status
        self.started: float | None = None  # perf_counter() at the end of the first online frame

    def __call__(self, frame: AnimationFrame) -> None:
        stats, done = self.stats, time.perf_counter()
        if self.started is None:
            self.started = done  # the first online frame: FPS counts from its end
        else:
            stats.frames += 1
            stats.seconds = done - self.started
        for stage, seconds in frame.timings.items():
            stats.stage_ms[stage].append(1000.0 * seconds)
        stats.latency_ms.append(1000.0 * (done - frame.available))
        if frame.record is not None:
            stats.records.append(frame.record)
        self.status(stats)

    def end(self) -> None:
        """The last status line (after the source closed: its drops are counted by then)."""
        self.status.end(self.stats)


def _frames(source: FrameSource, progress: bool, desc: str | None):
    if source.live:
        return source  # no bar: a live source has no end to count toward; the status line shows its progress
    from tqdm.auto import tqdm

    return tqdm(source, disable=not progress, desc=desc, dynamic_ncols=True, unit="frame")


def _show(run: LoadedRun, frame: AnimationFrame, sinks: Sequence[FrameSink], rasterize: bool) -> None:
    started = time.perf_counter()
    posed = PosedFrame(run, frame, rasterize)
    frame.add_time("pose", time.perf_counter() - started)
    for sink in sinks:
        sink.write(frame, posed)


@torch.no_grad()
def play(run: LoadedRun, source: FrameSource, sinks: Sequence[FrameSink], progress: bool = False,
         desc: str | None = None, status: bool = False) -> int:
    """Every frame of `source` into every sink, until the source ends; returns the number of frames played.
    `progress`: a progress bar (not for a live source); `status`: a live source's status line."""
    rasterize = any(sink.rasterizes for sink in sinks)
    label = getattr(source, "label", "drive")  # the status line's: drive's tracker, speak's voice
    count = _LiveCount(source.stats, LiveStatus(status, label=label)) if source.live else None
    played = 0
    try:
        with contextlib.ExitStack() as entered:
            for sink in sinks:
                entered.enter_context(sink)
            try:
                for frame in _frames(source, progress, desc):
                    _show(run, frame, sinks, rasterize)
                    played += 1
                    if count is not None:
                        count(frame)
            except KeyboardInterrupt:
                if not source.live:
                    raise
                # Ctrl-C ends a live source, while it renders as while it waits: what was made is kept
    finally:
        source.close()
        if count is not None:
            count.end()
    return played


__all__ = ["play"]
