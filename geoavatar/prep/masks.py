"""Foreground masks of the head and neck: a person mask intersected with a landmark-derived head region.

The paper intersects a matting mask (Background Matting: sharp, but keeps chairs and clothes) with a
face-parsing mask (BiSeNet: only human parts, but over-smoothed). We follow that spirit with what
runs offline:

    mask = person(x) * head_region(x)

- person: MediaPipe selfie segmentation (general model, soft probabilities, sharp at the
  silhouette), the matting-like term; it removes the background;
- head_region: a soft region built from the 478 landmarks, the parsing-like term; it removes the
  clothes and shoulders. With u = the face's up direction (chin 152 -> forehead 10), H = the
  forehead-chin distance and c = the mean of the face-oval points, every face-oval point p is moved
  to c + l * lateral(p - c) + s * up(p - c): above c, l = 1.5 (ears, hair of a turned head) and
  s = 1.9 (hair and the skull; stretched so that the top reaches at least 1.9 x 0.65 face widths,
  because a bowed head foreshortens the forehead), below c, l = 1.3 and s = 1.05 (the jaw line). A neck band joins it: a quadrilateral from the jaw-angle points
  (ids 172 / 397, pulled 15 % towards the mid-line) down to 0.3 H below the chin. The union is
  filled and blurred (sigma = 2 % of H) so its edge is soft; where it is generous (hair, sides) the
  person mask decides the silhouette.

Anything below the neck band (collar, shirt, shoulders) and the background get 0. The rule cannot
tell a turtleneck from a neck; that is the documented limit. An optional better matting backend can
be plugged in through `PersonSegmenter` (only "selfie" ships: Robust Video Matting is GPLv3, see
DESIGN.md).
"""

from __future__ import annotations

import numpy as np

from geoavatar.head import landmarks_mediapipe as mpids
from geoavatar.imaging import to_uint8
from geoavatar.prep.landmarks import _mediapipe
from geoavatar.runtime import quiet_native_logs

HAIR_SCALE = 1.9
HAIR_MIN_REACH = 0.65  # the oval's top above c, before HAIR_SCALE, is at least this many face widths
JAW_SCALE = 1.05
LATERAL_SCALE = 1.3
LATERAL_SCALE_UPPER = 1.5  # above c: room for the ears and the hair of a turned head
NECK_LENGTH = 0.3  # below the chin, in face heights
NECK_INSET = 0.15  # jaw-angle points pulled towards the mid-line
EDGE_SIGMA = 0.02  # blur of the region edge, in face heights
MASK_BACKENDS = ("selfie",)


class PersonSegmenter:
    """Soft person mask [H, W] in [0, 1] of an RGB frame (MediaPipe selfie segmentation, general model)."""

    def __init__(self, backend: str = "selfie"):
        if backend not in MASK_BACKENDS:
            raise ValueError(f"unknown mask backend '{backend}'; available: {', '.join(MASK_BACKENDS)}")
        mp = _mediapipe()
        with quiet_native_logs():
            self._model = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        result = self._model.process(rgb)
        return np.clip(np.asarray(result.segmentation_mask, dtype=np.float32), 0.0, 1.0)

    def close(self) -> None:
        self._model.close()

    def __enter__(self) -> "PersonSegmenter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def head_region_polygons(points: np.ndarray) -> list[np.ndarray]:
    """The head polygon and the neck quadrilateral [N, 2] (pixels) from landmarks [478, >=2]."""
    p = points[:, :2].astype(np.float64)
    up = p[10] - p[152]
    height = float(np.linalg.norm(up))
    up = up / max(height, 1e-9)
    oval = p[list(mpids.FACE_OVAL)]  # [36, 2]
    centre = oval.mean(0)
    d = oval - centre
    along = d @ up  # [36]
    lateral = d - along[:, None] * up
    # A head bowed forward foreshortens the forehead while more of the skull shows: the hair's reach
    # is measured against the face width too (which pitch does not shrink), never below HAIR_MIN_REACH.
    face_width = float(np.linalg.norm(p[234] - p[454]))
    top = max(float(along.max()), 1e-9)
    hair = HAIR_SCALE * max(1.0, HAIR_MIN_REACH * face_width / top)
    upper = along > 0
    head = (centre + np.where(upper, LATERAL_SCALE_UPPER, LATERAL_SCALE)[:, None] * lateral
            + np.where(upper, hair, JAW_SCALE)[:, None] * along[:, None] * up)
    left, right = p[397], p[172]
    mid = 0.5 * (left + right)
    left = left + NECK_INSET * (mid - left)
    right = right + NECK_INSET * (mid - right)
    drop = (float((p[152] - mid) @ -up) + NECK_LENGTH * height) * -up
    neck = np.stack([right, left, left + drop, right + drop])
    return [head, neck]


def head_region(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Soft head-and-neck region [H, W] float32 in [0, 1] from landmarks [478, >=2] (pixels)."""
    import cv2

    canvas = np.zeros((height, width), np.uint8)
    shift = 4  # sub-pixel polygon vertices
    for poly in head_region_polygons(points):
        pts = np.round((poly - 0.5) * (1 << shift)).astype(np.int32)  # pixel centres at +0.5
        cv2.fillPoly(canvas, [pts], 255, lineType=cv2.LINE_AA, shift=shift)
    face_height = float(np.linalg.norm(points[10, :2] - points[152, :2]))
    sigma = max(0.5, EDGE_SIGMA * face_height)
    region = cv2.GaussianBlur(canvas.astype(np.float32) / 255.0, (0, 0), sigma)
    return np.clip(region, 0.0, 1.0)


def foreground_mask(person: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Final mask [H, W] uint8: person mask x head region (soft product, 0..255)."""
    region = head_region(points, person.shape[1], person.shape[0])
    return to_uint8(person * region)


__all__ = ["MASK_BACKENDS", "PersonSegmenter", "head_region_polygons", "head_region", "foreground_mask"]
