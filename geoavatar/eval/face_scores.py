"""The face metrics of a clip: identity, expression and landmark agreement of renders against source frames.

    scorer = FaceScorer(reference_images)           # reads the avatar's own frames: its identity reference
    source = scorer.read(driver_or_gt_rgb)          # FaceReading of a source frame (read once, reused per render)
    frame = scorer.score(render_rgb, source)        # FaceScores of one render
    summary = face_summary(frames)                  # mean / std / count, faces found, landmark agreement

The same scores serve self re-enactment (`geoavatar eval RUN`: the source is the ground-truth frame) and cross
re-enactment (`geoavatar eval RUN --driver ...`: the source is the driver's frame), so the two read on one scale:

- id_similarity: dlib identity similarity (eval/identity.py) of the render against the mean descriptor of the
  avatar's own training frames (the reference); source_id_similarity is the source frame's against the same
  reference: near 1 for the avatar's own test frames, a stranger's level for another person's face, so a driver's
  value is what a render that copied the driver's face would score;
- id_distance: dlib's Euclidean descriptor distance to the reference (< 0.6: dlib's "same person");
- expression_similarity: cosine of the FER2013 classifier's probabilities (eval/expression.py) on the render and on
  the source frame, as the paper's appendix scores expression;
- landmark agreement (clip-level): Pearson correlation of mouth opening, eye openings and brow height between
  source and render over the frames where both show a face (eval/landmark_agreement.py).

A render without a detected face gets no identity or expression score; such frames are counted in the summary
(`faces.render_missing`), never dropped silently, and every mean says how many frames it covers (`count`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Sequence

import numpy as np

from geoavatar.eval.expression import EXPRESSIONS, expression_similarity
from geoavatar.eval.faces import FaceReader, FaceReading
from geoavatar.eval.identity import identity_distance, identity_similarity, mean_descriptor
from geoavatar.eval.landmark_agreement import SIGNALS, landmark_agreement

REFERENCE_FRAMES = 24  # training frames read for the avatar's identity reference, spread evenly
SCORE_NAMES = ("id_similarity", "id_distance", "source_id_similarity", "expression_similarity")


@dataclass
class FaceScores:
    """Face metrics of one render against its source frame (None where a face is missing)."""

    face_found: bool
    source_face_found: bool
    id_similarity: float | None = None
    id_distance: float | None = None
    source_id_similarity: float | None = None
    expression_similarity: float | None = None
    expression: str | None = None  # the render's most likely FER2013 class
    source_expression: str | None = None
    signals: list[float] | None = None  # the render's landmark signals (SIGNALS order; None: no face mesh)
    source_signals: list[float] | None = None


@dataclass
class IdentityReference:
    descriptor: np.ndarray | None  # [128] mean over the frames with a face; None when none had one
    frames: int  # frames read
    found: int  # frames with a face


def _signals_list(reading: FaceReading) -> list[float] | None:
    if reading.signals is None or not np.isfinite(reading.signals).all():
        return None
    return [round(float(v), 5) for v in reading.signals]


class FaceScorer:
    """Reads faces with one FaceReader and scores renders against source frames and an identity reference."""

    def __init__(self, reference_images: Iterable[np.ndarray]):
        self.reader = FaceReader()
        descriptors, frames = [], 0
        for image in reference_images:
            frames += 1
            reading = self.reader(image)
            if reading.found:
                descriptors.append(reading.descriptor)
        self.reference = IdentityReference(mean_descriptor(np.stack(descriptors)) if descriptors else None, frames,
                                           len(descriptors))

    def read(self, rgb: np.ndarray) -> FaceReading:
        return self.reader(rgb)

    def _identity(self, reading: FaceReading) -> tuple[float | None, float | None]:
        if not reading.found or self.reference.descriptor is None:
            return None, None
        return (float(identity_similarity(reading.descriptor, self.reference.descriptor)),
                float(identity_distance(reading.descriptor, self.reference.descriptor)))

    def score(self, render_rgb: np.ndarray, source: FaceReading) -> FaceScores:
        render = self.reader(render_rgb)
        scores = FaceScores(face_found=render.found, source_face_found=source.found)
        scores.id_similarity, scores.id_distance = self._identity(render)
        scores.source_id_similarity = self._identity(source)[0]
        if render.found:
            scores.expression = EXPRESSIONS[int(np.argmax(render.expression))]
            scores.signals = _signals_list(render)
        if source.found:
            scores.source_expression = EXPRESSIONS[int(np.argmax(source.expression))]
            scores.source_signals = _signals_list(source)
        if render.found and source.found:
            import torch

            scores.expression_similarity = float(expression_similarity(torch.from_numpy(render.expression),
                                                                       torch.from_numpy(source.expression)))
        return scores

    def close(self) -> None:
        self.reader.close()

    def __enter__(self) -> "FaceScorer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _stats(values: Sequence[float | None]) -> dict[str, float | int | None]:
    kept = np.array([v for v in values if v is not None], dtype=np.float64)
    kept = kept[np.isfinite(kept)]
    return {"mean": float(kept.mean()) if kept.size else None, "std": float(kept.std()) if kept.size else None,
            "count": int(kept.size)}


def _signal_rows(rows: Sequence[list[float] | None]) -> np.ndarray:
    """[T, 4] with NaN rows where a frame has no signals."""
    return np.array([row if row is not None else [np.nan] * len(SIGNALS) for row in rows], dtype=np.float64)


def face_summary(frames: Sequence[FaceScores]) -> dict:
    """mean / std / count of SCORE_NAMES, the clip's landmark agreement and how many frames showed a face."""
    summary: dict = {name: _stats([getattr(f, name) for f in frames]) for name in SCORE_NAMES}
    agreement = landmark_agreement(_signal_rows([f.source_signals for f in frames]),
                                   _signal_rows([f.signals for f in frames]))
    summary["landmark_agreement"] = agreement.as_dict()
    found = sum(f.face_found for f in frames)
    summary["faces"] = {"frames": len(frames), "render_found": found, "render_missing": len(frames) - found,
                        "source_found": sum(f.source_face_found for f in frames)}
    return summary


def scores_dict(scores: FaceScores) -> dict:
    """A FaceScores as a JSON-safe dict (numbers rounded to 6 decimals)."""
    return {k: round(v, 6) if isinstance(v, float) else v for k, v in asdict(scores).items()}


__all__ = ["FaceScorer", "FaceScores", "IdentityReference", "REFERENCE_FRAMES", "SCORE_NAMES", "face_summary",
           "scores_dict"]
