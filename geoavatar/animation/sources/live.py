"""The live tracker as a source (`geoavatar drive`): a camera or a video file, tracked frame by frame, drives the
avatar.

Three stages, each keeping only the newest MAILBOX_DEPTH (2) items of the one before: the reader thread (capture.py),
the fit thread (tracker.py's DriverTracker: landmarks, then the online fit; the identity stage over the first second)
and the consumer, play's output stage, on the caller's thread: there each fitted frame's parameters become the
avatar's (transfer.driven_params in the --transfer mode, against the driver's first second) and go to the sinks. The
fit of frame t+1 runs while frame t is posed and rendered (torch ops and the native rasterizer release the GIL), so
the frame rate is bounded by the slower stage, not by their sum.

Real time: a video file plays at its own frame rate, as a live source would deliver it: when the pipeline is busy, at
most two frames wait for it (one slow frame, e.g. the machine busy elsewhere, is caught up on the next, since a frame
takes about half of its 40 ms); a frame arriving when two wait drops the older (counted). Nothing queues beyond that,
so a pipeline slower than the source drops frames rather than lagging; a dropped frame's index is skipped. The file
waits (nothing dropped) while the identity stage collects and fits its first second; its clock starts after it (a
camera's frames are dropped during it, as at any time the fit stage is busy). `lossless`: every frame is processed
(for measurements). Latency counts from the moment a frame is available (AnimationFrame.available).

The fit runs on the CPU (a few hundred landmarks: a GPU's launch overhead would dominate); the transfer runs on the
run's device.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from geoavatar.animation.expression_transfer import (DEFAULT_TRANSFER, TransferMode, TransferStatistics,
                                                     avatar_expressions)
from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.sources.capture import MAILBOX_DEPTH, DriveError, NewestFrame, VideoInput, start_reader
from geoavatar.animation.sources.tracker import DriverFrame, DriverTracker
from geoavatar.animation.stats import DriveStats
from geoavatar.animation.transfer import TRANSFERRED_KEYS, driven_params, reference_frame
from geoavatar.head.params import HeadParams
from geoavatar.train.checkpoint import LoadedRun
from geoavatar.train.run_frames import RunFrames

CROP_SIZE = 256  # side of the driver's face crop (as prepare's default)


class LiveTransfer:
    """The avatar's side of the live transfer: its identity, its first frame (the relative transfer's neutral) and
    the expressions it was trained on (statistics / subspace transfer), on the run's device."""

    def __init__(self, run: LoadedRun, mode: TransferMode | bool):
        frames = RunFrames(run)
        self.device, self.mode = frames.device, mode
        self.reference = reference_frame(frames.values.to_npz(), frames.timesteps, "first")  # per-frame keys [1, ...]
        self.learned = avatar_expressions(frames)
        self.identity = frames.identity()

    def __call__(self, driver: HeadParams, tracker: DriverTracker) -> HeadParams:
        """The driver's fitted frame transferred onto the avatar (driven_params in the --transfer mode)."""
        device = self.device
        driver_now = {k: getattr(driver, k).to(device) for k in TRANSFERRED_KEYS}
        driver_ref = {k: v.to(device) for k, v in tracker.neutral.items()}
        # the driver's statistics are fitted on CPU, like its neutral: both move to the avatar's device
        learned = TransferStatistics(*self.learned, tracker.statistics.to(device))
        return HeadParams.from_npz(driven_params(self.identity, self.reference, driver_now, driver_ref, self.mode,
                                                 learned=learned))


def _recorded_params(params: HeadParams) -> dict[str, np.ndarray]:
    """The driver's fitted keys a recorded frame keeps (record=True): expr, jaw_pose, rotation of its one frame."""
    return {key: getattr(params, key)[0].numpy().copy() for key in ("expr", "jaw_pose", "rotation")}


class LiveDriver:
    """Source: a camera or a video tracked live (module docstring). `stats` counts what the fit stage took, fitted and
    dropped (play adds what was shown); `record`: each frame's fit kept in stats.records; `threads`: the process's
    torch threads while it runs (1: its tensors are small, and on a busy 2-core machine 2 threads made the fit 10x
    and posing 3-5x slower), restored by close()."""

    live = True
    audio = None

    def __init__(self, run: LoadedRun, capture: VideoInput, transfer: TransferMode | bool = DEFAULT_TRANSFER,
                 init_seconds: float = 1.0, iterations: int | None = None, solver: str = "gauss_newton",
                 max_frames: int | None = None, lossless: bool = False, record: bool = False,
                 flame_dir: Path | None = None, init_steps: tuple[int, int] = (100, 300), threads: int = 1):
        self.capture, self.fps, self.max_frames = capture, capture.fps, max_frames
        self.lossless, self.record, self.init_seconds = lossless, record, init_seconds
        self.transfer = LiveTransfer(run, transfer)
        self.init_count = max(2, round(init_seconds * capture.fps))
        # the pipeline's torch threads from here (the tracker included) until close(): its tensors are small
        self._process_threads = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            self.tracker = DriverTracker(run.info.head_model, self.init_count, capture.fps, CROP_SIZE, iterations,
                                         solver, flame_dir, init_steps)
        except BaseException:
            torch.set_num_threads(self._process_threads)
            raise
        self.stats = DriveStats()
        # A file waits (nothing dropped) while the identity stage collects and fits its first second, then plays
        # in real time from there; a camera's frames are dropped during it, as at any time the fit stage is busy.
        self._frames = NewestFrame(lossless or not capture.live, MAILBOX_DEPTH)
        self._fitted = NewestFrame(lossless, MAILBOX_DEPTH)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def dropped(self) -> int:
        """Frames dropped so far: the fit never took them, or the output stage never took their fit."""
        return self._frames.dropped + self._fitted.dropped

    def __iter__(self) -> Iterator[AnimationFrame]:
        self._threads = [start_reader(self.capture, self._frames, self.max_frames, self._stop), self._fit_stage()]
        self._threads[1].start()
        while True:
            try:
                item = self._fitted.get()
            except KeyboardInterrupt:  # Ctrl-C ends a live source; what was written is kept
                return
            if item is None:
                return
            yield self._frame(*item)

    def _frame(self, timestep: int, driver: DriverFrame, timings: dict, available: float) -> AnimationFrame:
        started = time.perf_counter()
        params = self.transfer(driver.params, self.tracker)
        frame = AnimationFrame(timestep, params, picture=driver.crop, available=available, timings=timings)
        frame.add_time("pose", time.perf_counter() - started)  # the transfer counts as posing, as drive always showed
        if self.record:
            frame.record = {"index": timestep, "error": driver.error, "found": driver.found,
                            **_recorded_params(driver.params)}
        return frame

    def _fit_stage(self) -> threading.Thread:
        """The second stage as a thread: source frames -> tracker.push -> (timestep, DriverFrame, timings, available)
        into the fitted mailbox; the identity stage's frames are counted and recorded, never shown live."""
        identity_timesteps: list[int] = []  # source timesteps of the identity stage's frames
        tracker, stats = self.tracker, self.stats

        def identity_done(frames: list[DriverFrame]) -> None:
            stats.init_frames, stats.init_seconds = len(frames), tracker.init_seconds
            self._frames.set_lossless(self.lossless)  # a file played in real time from here
            if self.record:
                stats.records.extend({"index": identity_timesteps[k], "init": True, "error": frame.error,
                                      **_recorded_params(frame.params)} for k, frame in enumerate(frames))

        def fit_one(timestep: int, available: float, rgb: np.ndarray) -> None:
            stats.processed += 1
            if tracker.online is None:
                identity_timesteps.append(timestep)
            t0 = time.perf_counter()
            result = tracker.push(rgb)
            if result is None:
                return
            if isinstance(result, list):
                identity_done(result)
                return
            now = time.perf_counter()
            timings = ({"landmarks": tracker.landmarks_done - t0, "fit": now - tracker.landmarks_done}
                       if result.found else {"landmarks": now - t0})
            stats.no_face += 0 if result.found else 1
            self._fitted.put((timestep, result, timings, available))

        def fit_frames() -> None:
            error = None
            try:
                while (item := self._frames.get()) is not None:
                    fit_one(*item)
            except DriveError as err:  # the driver's own trouble (no face in it): named by the source
                error = DriveError(f"{self.capture.name}: {err}")
            except BaseException as err:  # handed to the output stage, which raises it
                error = err
            finally:
                self._fitted.close(error)

        return threading.Thread(target=fit_frames, name="geoavatar-drive-fit", daemon=True)

    def close(self) -> None:
        """Stop the threads and the tracker, restore the process's torch threads; the drops are counted into
        `stats`."""
        self._stop.set()
        self._frames.close()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(timeout=5.0)
        self.tracker.close()
        torch.set_num_threads(self._process_threads)
        # a frame is dropped when the fit never took it or when the render stage never took its fit
        self.stats.dropped, self.stats.delivered = self.dropped, self._frames.delivered

    def check_identity_stage(self) -> None:
        """DriveError when the source ended before the identity stage had its frames."""
        if self.stats.init_frames == 0:
            raise DriveError(f"{self.capture.name}: the source ended after {self._frames.delivered} frame(s), before "
                             f"the identity stage's {self.init_count} frames (--init-seconds {self.init_seconds})")


__all__ = ["LiveDriver", "LiveTransfer"]
