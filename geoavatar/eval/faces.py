"""What the face metrics read from one image: the face's box, its dlib descriptor, its expression probabilities and
its landmark signals.

    with FaceReader() as reader:
        reading = reader(rgb)            # FaceReading; reading.found is False when no face was detected

One detector for every face metric, so that "no face in this frame" means one thing: MediaPipe's full-range face
detector (prep/landmarks.py, what `prepare` crops with), its most confident face, as a square box (cx, cy, side).
From the box:
- identity: dlib's 5-point alignment + face-recognition ResNet (eval/identity.py), [128];
- expression: the FER2013 mini-Xception's probabilities (eval/expression.py), [7];
- landmarks: MediaPipe's face mesh, static-image mode, on a square crop of LANDMARK_CROP x the box resized to
  LANDMARK_SIZE px, reduced to the signals of eval/landmark_agreement.py, [4] (NaN when the mesh finds no face in
  the crop).
A part can be switched off; its field is then None. The models load when the reader is made, so a missing package
is a MetricWeightsError (one line naming the install step) before any work is done.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoavatar.eval.landmark_agreement import SIGNALS, expression_signals

LANDMARK_CROP = 2.0  # crop side / detector box side for the face mesh (the face with its surroundings)
LANDMARK_SIZE = 256  # crop pixels: the face mesh's own input is 192 px


@dataclass
class FaceReading:
    box: np.ndarray | None = None  # [3] cx, cy, side in pixels; None: no face detected
    score: float | None = None  # the detector's confidence
    descriptor: np.ndarray | None = None  # [128] dlib descriptor
    expression: np.ndarray | None = None  # [7] FER2013 probabilities (eval/expression.EXPRESSIONS)
    signals: np.ndarray | None = None  # [4] SIGNALS, NaN where the face mesh found no face

    @property
    def found(self) -> bool:
        return self.box is not None


class FaceReader:
    """uint8 RGB image [H, W, 3] -> FaceReading (see the module docstring)."""

    def __init__(self, identity: bool = True, expression: bool = True, landmarks: bool = True):
        from geoavatar.eval.expression import expression_model
        from geoavatar.eval.identity import identity_model
        from geoavatar.prep.landmarks import FaceDetector, FaceMesh

        self.identity = identity_model() if identity else None
        self.expression = expression_model() if expression else None
        self._detector = FaceDetector()
        self._mesh = FaceMesh(static_images=True) if landmarks else None

    def __call__(self, rgb: np.ndarray) -> FaceReading:
        from geoavatar.eval.expression import face_crops

        rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
        found = self._detector(rgb)
        if found is None:
            return FaceReading()
        box = np.array([found.centre[0], found.centre[1], found.size], dtype=np.float64)
        reading = FaceReading(box=box, score=found.score)
        if self.identity is not None:
            reading.descriptor = self.identity.descriptor(rgb, box)
        if self.expression is not None:
            reading.expression = self.expression.classify(face_crops(rgb, [box]))[0].numpy().astype(np.float64)
        if self._mesh is not None:
            reading.signals = self._signals(rgb, box)
        return reading

    def _signals(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        from geoavatar.prep.video import crop_square

        crop = crop_square(rgb, np.array([box[0], box[1], box[2] * LANDMARK_CROP]), LANDMARK_SIZE)
        points = self._mesh(np.ascontiguousarray(crop))  # [478, 3] crop pixels, or None
        if points is None:
            return np.full(len(SIGNALS), np.nan)
        return expression_signals(points)

    def close(self) -> None:
        self._detector.close()
        if self._mesh is not None:
            self._mesh.close()

    def __enter__(self) -> "FaceReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["FaceReader", "FaceReading", "LANDMARK_CROP", "LANDMARK_SIZE"]
