"""The photometric fit of a long video in segments, over worker processes: memory and time that scale.

    spans = segments(count, length=300, overlap=8)              # [Segment]: balanced cores, overlapping fits
    jobs = [SegmentJob(...) for span in spans]                  # each holds only its own frames' inputs
    fitted = fit_segments(jobs, pool, progress)                 # SegmentFits: the cores stitched, [count] rows

`fit_photometric` holds every frame's crops and renders them every epoch; one call over a 3-minute video
(5,400 frames) would hold gigabytes and use one core. Here the video is cut into segments of at most
`length` frames (balanced: a 400-frame video gives two of 200), each fitted by `fit_photometric` on its own,
in a worker process, with its own appearance model (albedo and lighting shared by the segment's frames) and
`overlap` neighbouring frames on each side. A segment writes only its core frames, whose temporal terms so
see fitted neighbours on both sides; the overlap frames' own values are dropped. The segments do not depend on
the number of workers, so the result does not either. A segment reads its frames itself (`SegmentJob.load`)
and keeps only the resampled crops: memory grows with the segment length and the number of workers, not with
the video.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from geoavatar.prep.workers import WorkerPool, report_progress, split_range, worker_cache


@dataclass(frozen=True)
class Segment:
    """Frames [start, stop) are this segment's own (its core); it fits [fit_start, fit_stop)."""

    start: int
    stop: int
    fit_start: int
    fit_stop: int

    @property
    def fitted(self) -> int:
        return self.fit_stop - self.fit_start


def segments(count: int, length: int, overlap: int) -> list[Segment]:
    """Balanced cores of at most `length` frames covering range(count), each fitted with `overlap` more frames
    on each side where the video has them."""
    if length < 1 or overlap < 0:
        raise ValueError(f"segments: length must be >= 1 and overlap >= 0, got {length}, {overlap}")
    parts = -(-count // length)
    return [Segment(a, b, max(0, a - overlap), min(count, b + overlap)) for a, b in split_range(count, parts)]


@dataclass
class SegmentJob:
    """What a worker needs to fit one segment (picklable; per-frame arrays hold the segment's fitted frames only).

    load(row) -> (image [H, W, 3] uint8, mask [H, W] uint8) for a row of the whole video; head_factory() builds the
    head model (once per worker, under head_key); params: the npz layout, per-frame keys [n, ...], shape [S],
    static_offset [1, V, 3] (optional); viewmat [n, 4, 4], K [n, 3, 3] for the stored frames, boxes [n, 3] the
    crops; landmarks: LandmarkTargets' fields as arrays (points [n, L, 2], size [n], weights [L], confidence [n])
    or None."""

    segment: Segment
    head_key: str
    head_factory: Callable
    load: Callable
    settings: object  # PhotometricConfig
    params: dict[str, np.ndarray]
    viewmat: np.ndarray
    K: np.ndarray
    boxes: np.ndarray
    landmarks: dict[str, np.ndarray] | None = None


@dataclass
class SegmentFits:
    """The stitched fit: params (npz layout, per-frame keys [T, ...]), residual / residual_before [T], each
    segment's log."""

    params: dict[str, np.ndarray]
    residual: np.ndarray
    residual_before: np.ndarray
    logs: list[list[str]] = field(default_factory=list)


def fit_segment(job: SegmentJob) -> dict:
    """fit_photometric on the job's frames (run in a worker); returns numpy arrays over its fitted frames."""
    import torch

    from geoavatar.head.params import HeadParams
    from geoavatar.prep.photometric import LandmarkTargets, PhotometricTargets, fit_photometric

    head = worker_cache(job.head_key, job.head_factory)
    span = job.segment
    frames = (job.load(row) for row in range(span.fit_start, span.fit_stop))
    targets = PhotometricTargets.from_frames(frames, span.fitted, job.viewmat, job.K, max(job.settings.sizes),
                                             job.boxes)
    init = HeadParams.from_npz({k: torch.as_tensor(v, dtype=torch.float32) for k, v in job.params.items()})
    landmarks = None
    if job.landmarks is not None:
        landmarks = LandmarkTargets(**{k: torch.as_tensor(v, dtype=torch.float32) for k, v in job.landmarks.items()})
    with torch.enable_grad():
        result = fit_photometric(head, init, targets, job.settings, landmarks=landmarks, progress=report_progress)
    return {"params": {k: v.detach().numpy() for k, v in result.params.to_npz().items()},
            "residual": result.residual, "residual_before": result.residual_before, "log": result.log}


def fit_segments(jobs: list[SegmentJob], pool: WorkerPool, progress=None) -> SegmentFits:
    """Fit every segment (in the pool's workers) and keep each one's core frames."""
    if any(job.settings.fit_shape for job in jobs) and len(jobs) > 1:
        raise ValueError("fit_segments: fit_shape would give each segment its own identity; fit it in one segment")
    count = jobs[-1].segment.stop
    params: dict[str, np.ndarray] = {}
    residual, before = np.full(count, np.nan), np.full(count, np.nan)
    logs = []
    for fitted, job in zip(pool.imap(fit_segment, jobs, progress), jobs):
        span = job.segment
        core = slice(span.start - span.fit_start, span.stop - span.fit_start)  # rows of the fitted frames
        for key, value in fitted["params"].items():
            if key in ("shape", "static_offset"):
                params[key] = value
                continue
            if key not in params:
                params[key] = np.zeros((count, *value.shape[1:]), value.dtype)
            params[key][span.start:span.stop] = value[core]
        residual[span.start:span.stop] = fitted["residual"][core]
        before[span.start:span.stop] = fitted["residual_before"][core]
        logs.append(fitted["log"])
    return SegmentFits(params, residual, before, logs)


def fitted_frames(jobs: list[SegmentJob]) -> int:
    """Frames fitted over all segments (cores and overlaps): what the progress total counts per epoch."""
    return sum(job.segment.fitted for job in jobs)


__all__ = ["Segment", "SegmentFits", "SegmentJob", "fit_segment", "fit_segments", "fitted_frames", "segments"]
