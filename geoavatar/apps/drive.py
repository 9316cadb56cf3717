"""`geoavatar drive RUN (--camera N | --video FILE)`: drive a trained avatar live from a webcam or a video.

Per frame (a reader thread, a fit thread (landmarks, fit) and the output stage (pose, render), each stage
keeping only the newest MAILBOX_DEPTH (2) items of the one before):

    landmarks   the driver's frame cropped the way `prepare` crops (a square of one side around the
                face, its centre following the face), MediaPipe's face mesh (prep/landmarks.py)
    fit         the driver's pose, jaw, eyes and expression: prep/tracking.py's OnlineFit, two damped
                Gauss-Newton iterations (or L-BFGS, --solver) warm-started from the previous frame, on the
                energy of the batch tracker
    pose        the avatar's parameters from the driver's (apps/reenact.py's driven_params in the --transfer
                mode of apps/expression_transfer.py), avatar.pose_avatar
    render      avatar.rasterize_gaussians with the avatar's dataset camera at --size

The first second of the driver (`--init-seconds`) is the identity stage: its frames are collected,
the crop's side and centres come from the face detector as in `prepare` (prep/video.py's
smooth_crop_boxes), and the batched tracker (prep/tracking.track) fits the driver's identity, smooth
static offset and focal length over them; these stay frozen and the online fit continues from the last
of those frames. The driver's neutral (for relative transfer and for the head's translation) is the mean of
the first second, and so are the driver's statistics (--transfer statistics; their spread is shrunk toward the
avatar's, expression_transfer.PRIOR_FRAMES).

Real time: `--video` plays the file at its own frame rate, as a live source would deliver it: when the
pipeline is busy, at most two frames wait for it (one slow frame, e.g. the machine busy elsewhere, is caught up
on the next, since a frame takes about half of its 40 ms); a frame arriving when two wait drops the older
(counted). Nothing queues beyond that, so a pipeline slower than the source drops frames rather than lagging.
The file's clock starts after the identity stage (a camera's frames are dropped during it).
Latency is measured from the moment a frame is available to the moment its output is done. A status
line shows the FPS, drops and the per-stage times. The written mp4 (`--out`, driver | avatar) runs at
the source's frame rate; a dropped frame repeats the previous output, so the video keeps real time.
`--view` serves the browser player (apps/view.py, geoavatar/web) in live mode: each frame's posed head mesh is
streamed over a websocket and the browser places, shades and draws the splats on its GPU (without --out the render
stage is skipped); the summary adds the stream's latency from frame read to message sent.

The fit runs on the CPU (a few hundred landmarks: a GPU's launch overhead would dominate); posing and
rendering run on --device (auto: CUDA when there).
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Literal, Optional

import numpy as np
import torch
from torch import Tensor

from geoavatar.apps.common import (RunPath, browser_pose_code, posed_head_vertices, record_camera, run_background,
                                   side_by_side)
from geoavatar.apps.expression_transfer import (DEFAULT_TRANSFER, TransferMode, TransferStatistics, avatar_expressions,
                                                expression_statistics, resolve_transfer)
from geoavatar.apps.reenact import TRANSFERRED_KEYS, driven_params, reference_frame
from geoavatar.avatar import pose_avatar, rasterize_gaussians
from geoavatar.data import DatasetError, open_subject
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.head.params import HeadParams
from geoavatar.imaging import fit_height, to_uint8
from geoavatar.io.video import Mp4Writer
from geoavatar.prep.errors import PrepareError
from geoavatar.render.camera import Camera
from geoavatar.train.checkpoint import LoadedRun, RunError, open_run
from geoavatar.train.run_frames import RunFrames

STAGES = ("landmarks", "fit", "pose", "render")
# Items a stage's mailbox holds (the newest; a new one drops the oldest when full). 2, not 1: with 1 a single slow
# frame (another job taking the core for a moment) dropped the next; on wojtek.mp4 under load 4-6 on 2 cores, 5
# interleaved runs each: median 98.7 % of the frames shown with 2, 94.7 % with 1, median latency 30 vs 34 ms (#28).
MAILBOX_DEPTH = 2


class DriveError(GeoAvatarError):
    """The driving source (camera or video) cannot be opened or read; the message names it."""


# --- sources ----------------------------------------------------------------------------------------


@dataclass
class Source:
    name: str  # for messages: "--video FILE" / "--camera N"
    fps: float
    frames: Callable[[], Iterator[np.ndarray]]  # a fresh iterator of upright RGB uint8 frames
    live: bool  # a camera: frames arrive by themselves (no pacing)


def open_video(path: str | Path) -> Source:
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

    return Source(name, info.fps if info.fps > 0 else 25.0, frames, live=False)


def open_camera(index: int) -> Source:
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

        return Source(name, fps, frames, live=True)
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

        return Source(name, fps if fps > 0 else 30.0, frames, live=True)
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


def start_reader(source: Source, mailbox: NewestFrame, max_frames: int | None, stop: threading.Event) -> threading.Thread:
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


# --- the driver: crop, landmarks, identity stage, online fit ----------------------------------------


@dataclass
class DriverFrame:
    crop: np.ndarray  # [S, S, 3] uint8, the face crop the landmarks were found on
    params: HeadParams  # the driver's fitted parameters, per-frame keys [1, ...] (CPU)
    error: float  # median landmark error / face width
    landmarks: np.ndarray  # [478, 3] crop pixels
    found: bool  # False: no face in this frame, the previous fit is held


class DriverTracker:
    """The driver's side of `drive`: frames in, fitted parameters out (see the module docstring).

    push(rgb) returns None while the first `init_frames` are collected, the identity stage's frames
    (a list of DriverFrame) when it finishes, and a DriverFrame for every later frame."""

    def __init__(self, head: str = "openhead", init_frames: int = 25, fps: float = 25.0, crop_size: int = 256,
                 iterations: int | None = None, solver: str = "gauss_newton", flame_dir: Path | None = None,
                 tracking_steps=(100, 300)):
        from geoavatar.prep.landmarks import FaceDetector, FaceMesh
        from geoavatar.prep.pipeline import PrepareConfig, load_tracking_head, tracking_config

        if init_frames < 2:
            raise OptionError(f"--init-seconds gives {init_frames} frame(s); the identity stage needs at least 2")
        self.prepare = PrepareConfig(video=Path("-"), out=Path("-"), head=head, flame_dir=flame_dir,
                                     tracking_steps=tuple(tracking_steps), log=lambda _line: None)
        try:
            self.data, self.model = load_tracking_head(self.prepare)
        except PrepareError as err:
            raise RunError(str(err)) from err
        self.config = tracking_config(self.prepare)
        self.init_frames, self.fps, self.crop_size = init_frames, fps, crop_size
        self.iterations, self.solver = iterations, solver
        self.detector, self.mesh = FaceDetector(), FaceMesh()
        self._buffer: list[np.ndarray] = []
        self._boxes: list = []
        self.online = None  # OnlineFit after the identity stage
        self.box = None  # [3] the current crop (cx, cy, side) in source pixels
        self._offset = np.zeros(2)  # crop centre - landmark centre (source pixels), from the first second
        self.neutral: dict[str, torch.Tensor] | None = None  # the driver's mean over the first second
        self.init_seconds = 0.0
        self._last: DriverFrame | None = None
        self.landmarks_done = 0.0  # perf_counter() when the last online frame's landmarks were found

    def close(self) -> None:
        self.detector.close()
        self.mesh.close()

    def push(self, rgb: np.ndarray):
        if self.online is None:
            self._buffer.append(rgb)
            self._boxes.append(self.detector(rgb))
            if len(self._buffer) < self.init_frames:
                return None
            return self._identity_stage()
        return self._online_frame(rgb)

    def _identity_stage(self) -> list[DriverFrame]:
        from geoavatar.prep.landmarks import filter_landmarks, landmark_confidence
        from geoavatar.prep.tracking import OnlineFit, track_crops
        from geoavatar.prep.video import crop_square, fill_missing, smooth_crop_boxes

        started = time.perf_counter()
        height, width = self._buffer[0].shape[:2]
        found = np.array([b is not None for b in self._boxes])
        if not found.any():
            raise DriveError(f"no face was found in the first {len(self._buffer)} frames of the driver")
        centres = np.array([b.centre if b else np.zeros(2) for b in self._boxes])
        sizes = np.array([b.size if b else 0.0 for b in self._boxes])
        boxes = smooth_crop_boxes(centres, sizes, found, (width, height), self.prepare.crop_scale, self.prepare.crop_sigma)
        crops = [crop_square(rgb, box, self.crop_size) for rgb, box in zip(self._buffer, boxes)]
        raw = np.zeros((len(crops), 478, 3))
        seen = np.zeros(len(crops), bool)
        for k, crop in enumerate(crops):
            points = self.mesh(crop)
            if points is not None:
                raw[k], seen[k] = points, True
        if seen.sum() < 2:
            raise DriveError(f"the face mesh found a face in {seen.sum()} of the first {len(crops)} driver frames; "
                             "the identity stage needs the face in view")
        raw = fill_missing(raw, seen)
        filtered = filter_landmarks(raw, self.fps)
        confidence = landmark_confidence(raw, filtered, np.where(seen, 1.0, 0.0))
        result = track_crops(self.model, self.data, filtered, confidence, boxes, (width, height), self.crop_size,
                             self.config)
        scale = self.crop_size / boxes[0][2]
        self.online = OnlineFit(self.model, result, self.config, self.iterations, solver=self.solver)
        values = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in result.params.items() if k != "static_offset"}
        fitted = HeadParams.from_npz(values)
        npz = fitted.to_npz()
        self.neutral = reference_frame(npz, list(range(fitted.batch)), "mean")
        self.statistics = expression_statistics(npz)  # the driver's, for --transfer statistics / subspace
        # the crop follows the face from here: the detector's centre, estimated from the landmarks
        last = raw[-1][:, :2] / scale + boxes[-1][:2] - boxes[-1][2] / 2
        self._offset = np.mean([boxes[k][:2] - (raw[k][:, :2].mean(0) / scale + boxes[k][:2] - boxes[k][2] / 2)
                                for k in range(len(boxes)) if seen[k]], axis=0)
        self.box = boxes[-1].copy()
        self._target_centre = last.mean(0) + self._offset
        self._frame_size = (width, height)
        frames = [DriverFrame(crops[k], fitted.frame(k), float(result.errors[k]), raw[k], bool(seen[k]))
                  for k in range(len(crops))]
        self._last = frames[-1]
        self._buffer, self._boxes = [], []
        self.init_seconds = time.perf_counter() - started
        return frames

    def _online_frame(self, rgb: np.ndarray) -> DriverFrame:
        from geoavatar.prep.tracking import crop_principal_point
        from geoavatar.prep.video import crop_square

        height, width = rgb.shape[:2]
        side = self.box[2]
        # causal smoothing of the crop centre (prepare smooths over the whole video; live, only the past)
        centre = self.box[:2] + 0.5 * (self._target_centre - self.box[:2])
        centre = np.clip(centre, side / 2, [width - side / 2, height - side / 2])
        self.box = np.array([centre[0], centre[1], side])
        crop = crop_square(rgb, self.box, self.crop_size)
        points = self.mesh(crop)
        if points is None:  # no face: hold the last fit; let the detector find the face again
            box = self.detector(rgb)
            if box is not None:
                self._target_centre = box.centre
            self._last = DriverFrame(crop, self._last.params, float("nan"), self._last.landmarks, False)
            return self._last
        self.landmarks_done = time.perf_counter()
        scale = self.crop_size / side
        self._target_centre = points[:, :2].mean(0) / scale + self.box[:2] - side / 2 + self._offset
        params, error = self.online(points, crop_principal_point(self.box, (width, height), self.crop_size))
        self._last = DriverFrame(crop, params, error, points, True)
        return self._last


# --- the pipeline -----------------------------------------------------------------------------------


@dataclass
class DriveStats:
    frames: int = 0  # frames shown after the first online one (the FPS counts these)
    processed: int = 0  # frames the fit stage took from the source (identity stage included)
    init_frames: int = 0
    dropped: int = 0  # frames the source delivered that were never processed
    delivered: int = 0
    no_face: int = 0
    seconds: float = 0.0  # wall time from the first online frame to the last
    init_seconds: float = 0.0  # the identity stage's fit
    stage_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STAGES})
    latency_ms: list[float] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)  # per processed frame (record=True)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        stages = " ".join(f"{s} {np.mean(v):.1f}" for s, v in self.stage_ms.items() if v)
        latency = f"{np.median(self.latency_ms):.0f} ms" if self.latency_ms else "-"
        return (f"{self.frames} frames, {self.fps:.1f} fps, dropped {self.dropped}/{self.delivered}, latency {latency} "
                f"(median), stages ms: {stages}")


class _Status:
    def __init__(self, enabled: bool, every: float = 1.0):
        self.enabled, self.every, self.last = enabled, every, 0.0
        self.tty = sys.stderr.isatty()

    def __call__(self, stats: DriveStats, force: bool = False) -> None:
        now = time.perf_counter()
        if not self.enabled or (now - self.last < self.every and not force):
            return
        self.last = now
        recent = {s: np.mean(v[-25:]) for s, v in stats.stage_ms.items() if v}
        line = (f"drive: {stats.frames} frames, {stats.fps:5.1f} fps, dropped {stats.dropped}, latency "
                f"{np.mean(stats.latency_ms[-25:]) if stats.latency_ms else 0:5.0f} ms | "
                + " ".join(f"{s} {v:5.1f}" for s, v in recent.items()) + " ms")
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)


@dataclass
class _LiveAvatar:
    """The avatar side of `drive`: what the output stage poses, renders and transfers the driver onto."""

    run: LoadedRun
    camera: Camera  # the avatar's dataset camera at --size, on the run's device
    background: Tensor  # [3]
    reference: dict[str, Tensor]  # the avatar's first frame, per-frame keys [1, ...] (relative transfer)
    learned: tuple  # avatar_expressions: the expressions the avatar was trained on (statistics / subspace transfer)
    identity: dict[str, Tensor]  # the avatar's subject keys

    @property
    def device(self) -> torch.device:
        return self.background.device


def _live_avatar(run: LoadedRun, size: int, data: Path | None) -> _LiveAvatar:
    """The run's camera (from its dataset, or --data when it moved), background and transfer references."""
    frames = RunFrames(run)
    avatar_root = Path(data) if data is not None else run.info.data_root
    try:
        camera = record_camera(open_subject(avatar_root), frames.timesteps[0], None).resized(size).to(frames.device)
    except (DatasetError, OSError) as err:
        raise RunError(f"{run.info.run_dir}: the camera comes from its dataset {avatar_root}, which cannot be read "
                       f"({err}); pass --data DIR") from err
    reference = reference_frame(frames.values.to_npz(), frames.timesteps, "first")
    return _LiveAvatar(run, camera, run_background(run).to(frames.device), reference, avatar_expressions(frames),
                       frames.identity())


def _recorded_params(params: HeadParams) -> dict[str, np.ndarray]:
    """The driver's fitted keys a recorded frame keeps (record=True): expr, jaw_pose, rotation of its one frame."""
    return {key: getattr(params, key)[0].numpy().copy() for key in ("expr", "jaw_pose", "rotation")}


class _OutputStage:
    """The third stage: a fitted driver frame -> the avatar's parameters -> posed, then rendered and written (--out)
    and / or streamed to the browser player (--view); counts what it did into `stats`."""

    def __init__(self, avatar: _LiveAvatar, tracker: DriverTracker, transfer: TransferMode | bool, backend: str,
                 render: bool, viewer, writer: Mp4Writer | None, stats: DriveStats, record: bool,
                 dropped: Callable[[], int]):
        self.avatar, self.tracker, self.transfer, self.backend = avatar, tracker, transfer, backend
        self.render, self.viewer, self.writer, self.stats, self.record = render, viewer, writer, stats, record
        self.dropped = dropped  # frames dropped so far (the viewer's caption)
        self.last_timestep, self.last_picture = -1, None
        self.started: float | None = None  # perf_counter() at the end of the first online frame

    def __call__(self, timestep: int, driver: DriverFrame, timings: dict, available: float) -> None:
        t0 = time.perf_counter()
        params = self._avatar_params(driver)
        run = self.avatar.run
        # the browser places the Gaussians itself: without a render only the head is posed
        posed = pose_avatar(run.avatar, run.head, params, None, run.deformer) if self.render else None
        if self.viewer is not None:
            vertices = posed.vertices if posed is not None else posed_head_vertices(run, params, None)
            self.viewer.show_live(vertices, f"live: frame {timestep}, {self.stats.fps:.1f} fps, "
                                            f"dropped {self.dropped()}", available, browser_pose_code(run, params))
        t1 = time.perf_counter()
        timings["pose"] = t1 - t0
        if self.render:
            rgb = rasterize_gaussians(posed.gaussians, self.avatar.camera, self.avatar.background, self.backend,
                                      check_values=False).rgb
            picture = to_uint8(rgb.clamp(0.0, 1.0))  # the read-back synchronises the device
            timings["render"] = time.perf_counter() - t1
            if self.writer is not None:
                self._write(timestep, side_by_side(fit_height(driver.crop, picture.shape[0]), picture))
        self.last_timestep = timestep
        self._count(timestep, driver, timings, available)

    def _avatar_params(self, driver: DriverFrame) -> HeadParams:
        """The driver's fitted frame transferred onto the avatar (reenact's driven_params, the --transfer mode)."""
        device = self.avatar.device
        driver_now = {k: getattr(driver.params, k).to(device) for k in TRANSFERRED_KEYS}
        driver_ref = {k: v.to(device) for k, v in self.tracker.neutral.items()}
        # the driver's statistics are fitted on CPU, like its neutral: both move to the avatar's device
        learned = TransferStatistics(*self.avatar.learned, self.tracker.statistics.to(device))
        return HeadParams.from_npz(driven_params(self.avatar.identity, self.avatar.reference, driver_now, driver_ref,
                                                 self.transfer, learned=learned))

    def _write(self, timestep: int, picture: np.ndarray) -> None:
        """Write driver | avatar; the frames dropped since the last one repeat it, so the video keeps real time."""
        repeats = timestep - self.last_timestep - 1 if self.last_picture is not None else 0
        for _ in range(repeats):
            self.writer.write(self.last_picture)
        self.writer.write(picture)
        self.last_picture = picture

    def _count(self, timestep: int, driver: DriverFrame, timings: dict, available: float) -> None:
        stats, done = self.stats, time.perf_counter()
        if self.started is None:
            self.started = done  # the first online frame: FPS counts from its end
        else:
            stats.frames += 1
            stats.seconds = done - self.started
        for stage, seconds in timings.items():
            stats.stage_ms[stage].append(1000.0 * seconds)
        stats.latency_ms.append(1000.0 * (done - available))
        if self.record:
            stats.records.append({"index": timestep, "error": driver.error, "found": driver.found,
                                  **_recorded_params(driver.params)})


def _fit_stage(tracker: DriverTracker, source: NewestFrame, fitted: NewestFrame, stats: DriveStats, lossless: bool,
               record: bool) -> threading.Thread:
    """The second stage as a thread: source frames -> tracker.push -> (timestep, DriverFrame, timings, available)
    into `fitted`; the identity stage's frames are counted and recorded, never shown live."""
    identity_timesteps: list[int] = []  # source timesteps of the identity stage's frames

    def identity_done(frames: list[DriverFrame]) -> None:
        stats.init_frames, stats.init_seconds = len(frames), tracker.init_seconds
        source.set_lossless(lossless)  # a file played in real time from here
        if record:
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
        fitted.put((timestep, result, timings, available))

    def fit_frames() -> None:
        error = None
        try:
            while (item := source.get()) is not None:
                fit_one(*item)
        except BaseException as err:  # handed to the output stage, which raises it
            error = err
        finally:
            fitted.close(error)

    return threading.Thread(target=fit_frames, name="geoavatar-drive-fit", daemon=True)


def _check_drive_options(size: int, iterations: int | None, init_seconds: float, threads: int) -> None:
    if size < 16:
        raise OptionError(f"--size must be >= 16, got {size}")
    if iterations is not None and iterations < 1:
        raise OptionError(f"--iterations must be >= 1, got {iterations}")
    if init_seconds <= 0:
        raise OptionError(f"--init-seconds must be positive, got {init_seconds}")
    if threads < 1:
        raise OptionError(f"--threads must be >= 1, got {threads}")


def _show_outputs(fitted: NewestFrame, output: _OutputStage, show: _Status) -> None:
    """The output stage's loop on this thread until the fit stage ends; Ctrl-C ends a live source, what was
    written is kept."""
    while True:
        try:
            item = fitted.get()
        except KeyboardInterrupt:
            item = None
        if item is None:
            return
        output(*item)
        show(output.stats)


@torch.no_grad()
def drive_avatar(
    run: LoadedRun,
    source: Source,
    out: Path | None = None,
    transfer: TransferMode | bool = DEFAULT_TRANSFER,  # a bool is the old `relative` flag
    size: int = 512,
    init_seconds: float = 1.0,
    iterations: int | None = None,
    solver: str = "gauss_newton",
    max_frames: int | None = None,
    lossless: bool = False,
    viewer=None,
    backend: str = "auto",
    data: Path | None = None,
    status: bool = True,
    record: bool = False,
    flame_dir: Path | None = None,
    render: bool | None = None,
    init_steps: tuple[int, int] = (100, 300),
    threads: int = 1,
) -> DriveStats:
    """Run the live pipeline until the source ends; returns the measurements (see the module docstring).

    Three stages, each keeping only the newest MAILBOX_DEPTH items of the one before: the reader thread, the fit
    thread (landmarks + online fit) and the output stage on this thread. The fit of frame t+1 runs while frame t is posed
    and rendered (torch ops and the native rasterizer release the GIL), so the frame rate is bounded by the slower
    stage, not by their sum."""
    _check_drive_options(size, iterations, init_seconds, threads)
    avatar = _live_avatar(run, size, data)
    render = (out is not None or viewer is None) if render is None else render
    init_count = max(2, round(init_seconds * source.fps))
    process_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    tracker = DriverTracker(run.info.head_model, init_count, source.fps, 256, iterations, solver, flame_dir, init_steps)
    stats = DriveStats()
    show = _Status(status)
    # A file waits (nothing dropped) while the identity stage collects and fits its first second, then plays
    # in real time from there; a camera's frames are dropped during it, as at any time the fit stage is busy.
    frames = NewestFrame(lossless or not source.live, MAILBOX_DEPTH)
    fitted = NewestFrame(lossless, MAILBOX_DEPTH)
    stop = threading.Event()
    reader = start_reader(source, frames, max_frames, stop)
    writer = Mp4Writer(out, fps=source.fps) if out is not None else None
    output = _OutputStage(avatar, tracker, transfer, backend, render, viewer, writer, stats, record,
                          dropped=lambda: frames.dropped + fitted.dropped)
    fitter = _fit_stage(tracker, frames, fitted, stats, lossless, record)
    try:
        with writer if writer is not None else contextlib.nullcontext():
            fitter.start()
            _show_outputs(fitted, output, show)
    finally:
        stop.set()
        frames.close()
        reader.join(timeout=5.0)
        if fitter.is_alive():
            fitter.join(timeout=5.0)
        tracker.close()
        torch.set_num_threads(process_threads)
        # a frame is dropped when the fit never took it or when the render stage never took its fit
        stats.dropped, stats.delivered = frames.dropped + fitted.dropped, frames.delivered
        show(stats, force=True)
        if status and sys.stderr.isatty():
            print(file=sys.stderr)
    if stats.init_frames == 0:
        raise DriveError(f"{source.name}: the source ended after {frames.delivered} frame(s), before the identity "
                         f"stage's {init_count} frames (--init-seconds {init_seconds})")
    return stats


def drive(
    run: RunPath,
    camera: Optional[int] = None,
    video: Optional[Path] = None,
    relative: bool = False,
    transfer: Optional[TransferMode] = None,
    out: Optional[Path] = None,
    view: bool = False,
    size: int = 512,
    init_seconds: float = 1.0,
    solver: Literal["gauss_newton", "lbfgs"] = "gauss_newton",
    iterations: Optional[int] = None,
    max_frames: Optional[int] = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    status: bool = True,
    threads: int = 1,
) -> int:
    """Drive a trained avatar live from a webcam or a video: landmarks, online fit, avatar posed and rendered.

    The driver's first second fits its identity (then frozen); every later frame is fitted warm-started
    from the previous one. Frames the pipeline cannot keep up with are dropped (counted), not queued (at most
    two wait).

    Args:
        run: Run folder written by `geoavatar train` (the avatar).
        camera: Webcam number N (/dev/videoN through PyAV's v4l2 input, else OpenCV).
        video: A video file played as a live source at its own frame rate.
        relative: The same as --transfer relative.
        transfer: How the driver's expression, jaw and eyes become the avatar's: absolute, relative (offsets from
            the driver's neutral, its first second, onto the avatar's first frame), statistics (the driver's
            first-second statistics mapped to the avatar's training-set statistics) or subspace (relative, kept
            inside the expressions the avatar was trained on), as `geoavatar reenact --transfer`. Default: relative.
        out: Write driver | avatar to this mp4 (at the source's frame rate; a dropped frame repeats the last output).
        view: Show the avatar live in the browser player on --host/--port (posed meshes streamed to it).
        size: Side of the rendered avatar in pixels (the avatar's dataset camera, scaled).
        init_seconds: Length of the identity stage at the start of the driver.
        solver: Online fit per frame: gauss_newton (damped Gauss-Newton; closer to the offline tracking at
            the same cost) or lbfgs.
        iterations: Iterations of the online fit per frame (default: 2 Gauss-Newton or 8 L-BFGS; its latency
            grows with them).
        max_frames: Stop after this many source frames (default: the whole video, or until Ctrl-C).
        host: Viewer address (--view).
        port: Viewer port (--view).
        data: The avatar's dataset folder, when it moved since training (the camera is read from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N: where the avatar is posed and rendered.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (FLAME avatars only).
        status: Print a status line (FPS, drops, latency per stage) about once a second.
        threads: CPU threads of the pipeline's torch and rasterizer work. 1 by default: its tensors are small,
            and on a busy 2-core machine 2 threads made the fit 10x and posing 3-5x slower (OpenMP waits).
    """
    if (camera is None) == (video is None):
        raise OptionError("give one driving source: --camera N or --video FILE")
    if out is None and not view:
        raise OptionError("nothing to show: pass --out FILE.mp4 and/or --view")
    mode = resolve_transfer(transfer, relative)
    source = open_video(video) if video is not None else open_camera(camera)
    loaded = open_run(run, device, flame_dir)
    viewer = None
    if view:
        from geoavatar.apps.view import start_viewer

        try:
            viewer = start_viewer(loaded, host, port, expr_sliders=0, data=data, live=True)
        except (ImportError, OSError) as err:
            raise GeoAvatarError(f"cannot start the viewer: {err}") from err
        print(f"GeoAvatar live viewer: {viewer.url}", flush=True)
    try:
        stats = drive_avatar(loaded, source, out, mode, size, init_seconds, iterations, solver, max_frames=max_frames,
                             viewer=viewer, backend=backend, data=data, status=status, flame_dir=flame_dir,
                             threads=threads)
    except KeyboardInterrupt:
        return 0
    finally:
        if viewer is not None:
            viewer.stop()
    print(f"drive: {stats.summary()}; identity stage {stats.init_frames} frames in {stats.init_seconds:.1f} s"
          + (f"; wrote {out}" if out is not None else "") + (f"; {viewer.summary()}" if viewer is not None else ""))
    return 0


__all__ = ["DriveError", "DriveStats", "DriverTracker", "NewestFrame", "Source", "drive", "drive_avatar",
           "open_camera", "open_video"]
