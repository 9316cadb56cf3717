"""MediaPipe face detection and face mesh (478 points with irises), temporal filtering, confidence.

mediapipe 0.10.21 is the last release whose wheel ships the legacy `mp.solutions` models, so this
runs offline (see docs/DESIGN.md). Two models are used:
- face detection, full-range model (`model_selection=1`): finds the face in the whole frame, also in
  wide shots (1920x1080 with a small face) where the face mesh's own short-range detector fails;
  its box centres and sizes drive the crop, its score is the per-frame face presence;
- face mesh with `refine_landmarks=True` (478 points) in video mode on the cropped frames.

Landmarks are in crop pixels (x right, y down, pixel centres at +0.5); z is MediaPipe's relative
depth scaled like x (only used weakly, if at all).

Filtering: a One-Euro filter (Casiez et al. 2012, the filter MediaPipe itself uses for landmarks),
run forwards and backwards over the whole video and averaged, so it has no lag; its cut-off adapts to
the speed, which keeps fast mouth motion and removes the still-frame jitter. Confidence per frame
is presence x stability: presence = the detector's score, stability = exp(-r / 0.01) where r is the
mean distance between the raw and the filtered landmarks in units of the face size (jitter of 1 %
of the face size gives 0.37).

MediaPipe's native log lines (geoavatar.runtime says which) stay out of the terminal unless --verbose: a model is
made in quiet_native_logs and returns with its graph started (`_start_synchronously`: its calculators open, load
their models and log on the graph's threads, after the constructor would otherwise have returned), and a face mesh
processes in it until the process's first face (landmark_projection_calculator warns once per process, then).
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from geoavatar.runtime import quiet_native_levels, quiet_native_logs

NUM_POINTS = 478
_face_found = False  # a face mesh of this process found a face: the one warning of the first face is behind us


def _start_synchronously(mp) -> None:
    """Every legacy solution (face detection, face mesh, selfie segmentation) waits in its constructor until its graph
    has started (`wait_until_idle`), so that the lines its calculators log on opening fall inside a constructor's
    quiet_native_logs. Once per process; nothing else changes."""
    from mediapipe.python import solution_base

    init = solution_base.SolutionBase.__init__
    if getattr(init, "_waits_until_started", False):
        return

    @functools.wraps(init)
    def started(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self._graph.wait_until_idle()

    started._waits_until_started = True
    solution_base.SolutionBase.__init__ = started


def _mediapipe():
    quiet_native_levels()  # before the import: glog reads its level when the library loads
    try:
        import mediapipe as mp
    except ImportError as err:  # pragma: no cover - a broken install
        raise RuntimeError(
            "geoavatar prepare needs mediapipe==0.10.21 (installed with --no-deps by `make install`): "
            f"it could not be imported ({err})"
        ) from err
    if not hasattr(mp, "solutions"):
        raise RuntimeError(
            f"mediapipe {getattr(mp, '__version__', '?')} has no legacy `solutions` models; install mediapipe==0.10.21"
        )
    _start_synchronously(mp)
    return mp


@dataclass
class FaceBox:
    centre: np.ndarray  # [2] pixels
    size: float  # pixels (the detector's square box side)
    score: float


class FaceDetector:
    """Full-range MediaPipe face detection on whole frames: the most confident face's box."""

    def __init__(self, min_confidence: float = 0.5):
        mp = _mediapipe()
        with quiet_native_logs():
            self._model = mp.solutions.face_detection.FaceDetection(model_selection=1, min_detection_confidence=min_confidence)

    def __call__(self, rgb: np.ndarray) -> FaceBox | None:
        height, width = rgb.shape[:2]
        result = self._model.process(rgb)
        if not result.detections:
            return None
        best = max(result.detections, key=lambda d: d.score[0])
        box = best.location_data.relative_bounding_box
        w, h = box.width * width, box.height * height
        centre = np.array([(box.xmin + box.width / 2) * width, (box.ymin + box.height / 2) * height])
        return FaceBox(centre=centre, size=float(max(w, h)), score=float(best.score[0]))

    def close(self) -> None:
        self._model.close()

    def __enter__(self) -> "FaceDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FaceMesh:
    """MediaPipe face mesh, 478 landmarks, video mode (tracks from the previous frame)."""

    def __init__(self, static_images: bool = False, min_confidence: float = 0.5):
        mp = _mediapipe()
        with quiet_native_logs():
            self._model = mp.solutions.face_mesh.FaceMesh(
                static_image_mode=static_images, max_num_faces=1, refine_landmarks=True,
                min_detection_confidence=min_confidence, min_tracking_confidence=min_confidence,
            )

    def __call__(self, rgb: np.ndarray) -> np.ndarray | None:
        """[478, 3] (x, y pixels; z relative depth in x's pixel units), or None when no face."""
        global _face_found
        height, width = rgb.shape[:2]
        with contextlib.nullcontext() if _face_found else quiet_native_logs():
            result = self._model.process(rgb)
        if not result.multi_face_landmarks:
            return None
        _face_found = True
        points = np.array([(p.x, p.y, p.z) for p in result.multi_face_landmarks[0].landmark], dtype=np.float64)
        if points.shape[0] != NUM_POINTS:
            return None
        return points * np.array([width, height, width])

    def close(self) -> None:
        self._model.close()

    def __enter__(self) -> "FaceMesh":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def detect_landmarks(frames: Iterable[np.ndarray]) -> Iterator[np.ndarray | None]:
    """Face-mesh landmarks [478, 3] (or None) for each RGB frame, in order."""
    with FaceMesh() as mesh:
        for rgb in frames:
            yield mesh(rgb)


# --- filtering --------------------------------------------------------------------------------------


def face_size(points: np.ndarray) -> np.ndarray:
    """Face size in pixels [...] from landmarks [..., 478, >=2]: forehead (10) to chin (152) distance."""
    return np.linalg.norm(points[..., 10, :2] - points[..., 152, :2], axis=-1)


def one_euro(values: np.ndarray, rate: float, min_cutoff: float, beta: float, d_cutoff: float = 1.0) -> np.ndarray:
    """One-Euro filter along axis 0 of values [T, ...] (each element filtered independently)."""

    def alpha(cutoff):
        tau = 1.0 / (2 * np.pi * cutoff)
        return 1.0 / (1.0 + tau * rate)

    out = np.empty_like(values, dtype=np.float64)
    out[0] = values[0]
    speed = np.zeros_like(values[0], dtype=np.float64)
    a_d = alpha(d_cutoff)
    for t in range(1, len(values)):
        raw_speed = (values[t] - out[t - 1]) * rate
        speed = a_d * raw_speed + (1 - a_d) * speed
        a = alpha(min_cutoff + beta * np.abs(speed))
        out[t] = a * values[t] + (1 - a) * out[t - 1]
    return out


def filter_landmarks(points: np.ndarray, rate: float, min_cutoff: float = 2.0, beta: float = 0.05) -> np.ndarray:
    """Zero-lag One-Euro filtering of landmarks [T, 478, 3] (pixels): forward and backward, averaged.

    Units: the filter works on positions divided by the median face size, so `beta` does not depend
    on the resolution (speed in face sizes per second).
    """
    if len(points) < 3:
        return points.astype(np.float64)
    scale = float(np.median(face_size(points)))
    normalised = points / scale
    forward = one_euro(normalised, rate, min_cutoff, beta)
    backward = one_euro(normalised[::-1], rate, min_cutoff, beta)[::-1]
    return 0.5 * (forward + backward) * scale


def landmark_confidence(raw: np.ndarray, filtered: np.ndarray, presence: np.ndarray) -> np.ndarray:
    """Per-frame confidence [T] in [0, 1] = presence x exp(-(mean raw-filtered distance / face size) / 0.01)."""
    size = np.maximum(face_size(filtered), 1e-6)  # [T]
    jitter = np.linalg.norm(raw[..., :2] - filtered[..., :2], axis=-1).mean(-1) / size  # [T]
    return np.clip(presence, 0.0, 1.0) * np.exp(-jitter / 0.01)


__all__ = ["NUM_POINTS", "FaceBox", "FaceDetector", "FaceMesh", "detect_landmarks", "face_size", "one_euro",
           "filter_landmarks", "landmark_confidence"]
