"""dlib identity similarity: how much a face looks like a person, from dlib's 128-D face descriptors.

    model = identity_model()                          # cached; MetricWeightsError names the install step
    d = model.descriptor(rgb, box)                    # [128] of the face in box (cx, cy, side), uint8 RGB image
    identity_similarity(d, reference)                 # cosine, ~1 for one person

The paper's appendix measures ID preservation as the cosine of ArcFace embeddings; no ArcFace weights can be
had offline, so this is dlib's face-recognition ResNet (dlib_face_recognition_resnet_model_v1, 99.38 % on LFW,
public domain) on a face aligned by dlib's 5-point landmark model (shape_predictor_5_face_landmarks, public
domain), both shipped by the `face-recognition-models` package and run by the `dlib-bin` wheel. It is named
for what it is, "dlib identity similarity": its numbers are not ArcFace's. dlib's 68-point predictor, in the
same package, is licensed for non-commercial use only and is never loaded.

Scale (measured on our videos, docs/cross_reenactment.md): frames of one person score 0.98-0.996 against each
other, different people 0.84-0.87. dlib's own "same person" rule is a Euclidean distance of the (not unit-length)
descriptors below 0.6; it is reported beside the cosine as `id_distance`.

The face box comes from the caller (eval/faces.py: MediaPipe's full-range detector, whose boxes match dlib's
HOG detector's to a few percent in size and centre on our videos); the 5-point model places the landmarks in
it and dlib aligns a 150 px chip (padding 0.25) from them.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from geoavatar.eval.weights import package_file, require_module

DESCRIPTOR_SIZE = 128
DLIB_INSTALL = "install it with `pip install dlib-bin==20.0.1.post1` (`make install` does)"
MODELS_INSTALL = ("install it with `pip install --no-deps face-recognition-models==0.3.0` (a ~100 MB download; "
                  "`make install` does)")
WHAT = "dlib identity similarity"
RESNET_FILE = "models/dlib_face_recognition_resnet_model_v1.dat"
ALIGNER_FILE = "models/shape_predictor_5_face_landmarks.dat"  # never the 68-point model (non-commercial)


class IdentityModel:
    """dlib's 5-point aligner + face-recognition ResNet: descriptor(rgb, box) -> [128]."""

    def __init__(self):
        self._dlib = require_module("dlib", DLIB_INSTALL, WHAT)
        self._aligner = self._dlib.shape_predictor(
            str(package_file("face_recognition_models", ALIGNER_FILE, MODELS_INSTALL, WHAT)))
        self._resnet = self._dlib.face_recognition_model_v1(
            str(package_file("face_recognition_models", RESNET_FILE, MODELS_INSTALL, WHAT)))

    def descriptor(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        """[128] float64 descriptor of the face in the square box (cx, cy, side) of uint8 RGB image [H, W, 3]."""
        image = np.ascontiguousarray(rgb, dtype=np.uint8)
        cx, cy, side = (float(v) for v in box)
        half = side / 2.0
        rect = self._dlib.rectangle(int(round(cx - half)), int(round(cy - half)), int(round(cx + half)),
                                    int(round(cy + half)))
        shape = self._aligner(image, rect)
        return np.asarray(self._resnet.compute_face_descriptor(image, shape), dtype=np.float64)


@lru_cache(maxsize=1)
def identity_model() -> IdentityModel:
    """The shared IdentityModel (the model files are read once per process)."""
    return IdentityModel()


def identity_similarity(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine of descriptors a, b [..., 128] -> [...]."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    norms = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    return (a * b).sum(-1) / np.maximum(norms, 1e-12)


def identity_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """dlib's own measure: the Euclidean distance of descriptors [..., 128] -> [...] (< 0.6: the same person)."""
    return np.linalg.norm(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64), axis=-1)


def mean_descriptor(descriptors: np.ndarray) -> np.ndarray:
    """[128]: the mean of descriptors [N, 128] (a person's reference over many frames)."""
    descriptors = np.asarray(descriptors, dtype=np.float64)
    if descriptors.ndim != 2 or descriptors.shape[1] != DESCRIPTOR_SIZE or len(descriptors) == 0:
        raise ValueError(f"mean_descriptor: expected [N >= 1, {DESCRIPTOR_SIZE}], got {descriptors.shape}")
    return descriptors.mean(axis=0)


__all__ = ["DESCRIPTOR_SIZE", "IdentityModel", "identity_distance", "identity_model", "identity_similarity",
           "mean_descriptor"]
