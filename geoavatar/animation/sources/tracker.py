"""The driver's side of the live tracker: frames in, the driver's fitted parameters out.

    landmarks   the driver's frame cropped the way `prepare` crops (a square of one side around the face, its centre
                following the face), MediaPipe's face mesh (prep/landmarks.py)
    fit         the driver's pose, jaw, eyes and expression: prep/tracking.py's OnlineFit, two damped Gauss-Newton
                iterations (or L-BFGS) warm-started from the previous frame, on the energy of the batch tracker

The first `init_frames` (drive's first second, `--init-seconds`) are the identity stage: their crop's side and centres
come from the face detector as in `prepare` (prep/video.py's smooth_crop_boxes), and the batched tracker
(prep/tracking.track_crops) fits the driver's identity, smooth static offset and focal length over them; these stay
frozen and the online fit continues from the last of those frames. The driver's neutral (for relative transfer and for
the head's translation) is the mean of the first second, and so are the driver's statistics (--transfer statistics).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from geoavatar.animation.expression_transfer import expression_statistics
from geoavatar.animation.sources.capture import DriveError
from geoavatar.animation.transfer import reference_frame
from geoavatar.errors import OptionError
from geoavatar.head.params import HeadParams
from geoavatar.prep.errors import PrepareError
from geoavatar.train.checkpoint import RunError


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


__all__ = ["DriverFrame", "DriverTracker"]
