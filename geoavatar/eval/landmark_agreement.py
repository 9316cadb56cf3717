"""Geometric expression agreement: do the render's mouth, eyes and brows move with the driver's? No learned weights
beyond MediaPipe's face mesh (which `prepare` runs anyway).

    s = expression_signals(points)                        # [4] from face-mesh landmarks [478, 3] of one face
    landmark_agreement(driver_signals, render_signals)    # LandmarkAgreement: Pearson r per signal over a clip

Signals of one face (MediaPipe face-mesh indices; 3D distances, so that a turned or tilted head changes them
little), each divided by the distance of the outer eye corners (33, 263) so that they do not depend on the face's
size in the image:

    mouth_open   inner lips, upper 13 to lower 14
    eye_right    the subject's right eye, upper lid 159 to lower lid 145
    eye_left     the subject's left eye, upper lid 386 to lower lid 374
    brow_raise   mean over both sides of brow (105 / 334) to the middle of the eye's corners (33-133 / 362-263)

Agreement over a clip: for each signal the Pearson correlation of the driver's and the render's values over the
frames where both have a face; `agreement` is the mean over the signals whose correlation is defined (a signal
that does not vary in one of the two has none). A correlation asks for the same motion, not the same amplitude:
an avatar that opens its mouth half as wide at the same moments agrees fully, as it should when the driver's
expression is mapped into the range the avatar learned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SIGNALS = ("mouth_open", "eye_right", "eye_left", "brow_raise")
EYE_CORNERS = (33, 263)  # outer corners: the scale
MOUTH = (13, 14)
EYE_RIGHT, EYE_LEFT = (159, 145), (386, 374)
BROWS = ((105, (33, 133)), (334, (362, 263)))  # brow point, eye corners below it
MIN_FRAMES = 3  # a correlation over fewer frames means nothing


def expression_signals(points: np.ndarray) -> np.ndarray:
    """[..., 4] SIGNALS of face-mesh landmarks [..., 478, 3] (any consistent unit: the ratios are unitless)."""
    points = np.asarray(points, dtype=np.float64)

    def distance(a, b):
        return np.linalg.norm(points[..., a, :] - points[..., b, :], axis=-1)

    scale = np.maximum(distance(*EYE_CORNERS), 1e-9)
    brows = [np.linalg.norm(points[..., brow, :] - 0.5 * (points[..., c0, :] + points[..., c1, :]), axis=-1)
             for brow, (c0, c1) in BROWS]
    values = [distance(*MOUTH), distance(*EYE_RIGHT), distance(*EYE_LEFT), 0.5 * (brows[0] + brows[1])]
    return np.stack(values, axis=-1) / scale[..., None]


@dataclass
class LandmarkAgreement:
    agreement: float | None  # mean of the defined correlations
    correlations: dict[str, float | None]  # signal -> Pearson r (None: undefined)
    frames: int  # frames where both faces were found

    def as_dict(self) -> dict:
        return {"agreement": self.agreement, "correlations": self.correlations, "frames": self.frames}


def pearson(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson correlation of a, b [T]; None when either is (numerically) constant or T < MIN_FRAMES."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) < MIN_FRAMES:
        return None
    a, b = a - a.mean(), b - b.mean()
    denominator = np.sqrt((a * a).sum() * (b * b).sum())
    if denominator < 1e-12:
        return None
    return float((a * b).sum() / denominator)


def landmark_agreement(driver: np.ndarray, render: np.ndarray) -> LandmarkAgreement:
    """Agreement of signals driver, render [T, 4] over a clip; rows holding NaN (no face in either) are left out."""
    driver, render = np.asarray(driver, dtype=np.float64), np.asarray(render, dtype=np.float64)
    if driver.shape != render.shape or driver.ndim != 2 or driver.shape[1] != len(SIGNALS):
        raise ValueError(f"landmark_agreement: expected two [T, {len(SIGNALS)}] arrays, got {driver.shape}, "
                         f"{render.shape}")
    both = np.isfinite(driver).all(1) & np.isfinite(render).all(1)  # [T]
    correlations = {name: pearson(driver[both, k], render[both, k]) for k, name in enumerate(SIGNALS)}
    defined = [r for r in correlations.values() if r is not None]
    return LandmarkAgreement(float(np.mean(defined)) if defined else None, correlations, int(both.sum()))


__all__ = ["LandmarkAgreement", "SIGNALS", "expression_signals", "landmark_agreement", "pearson"]
