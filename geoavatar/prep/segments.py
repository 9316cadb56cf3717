"""The photometric fit of a long video in segments, over worker processes: memory and time that scale.

    spans = segments(count, length=300, overlap=8)              # [Segment]: balanced cores, overlapping fits
    jobs = [SegmentJob(rows, core, ...) for span in spans]      # each holds only its own frames' inputs
    fitted = fit_segments(jobs, pool, progress, sample=job)     # SegmentFits: the fits blended, [count] rows

`fit_photometric` holds every frame's crops and renders them every epoch; one call over a 3-minute video
(5,400 frames) would hold gigabytes and use one core. Here the video is cut into segments of at most
`length` frames (balanced: a 400-frame video gives two of 200; the caller may ask for two of a shorter one, so both
cores work), each fitted by `fit_photometric` on its own,
in a worker process, with `overlap` neighbouring frames on each side. The segments share one appearance model
(albedo and lighting), fitted first on a sample of frames spread over the whole video with the poses held
(`shared_appearance`; the segments then skip their own appearance-only epochs), refined by each segment as the
pose moves. Two neighbours' fits of their common frames still differ, most in the head's depth, which the image
pins down least (wojtek.mp4, frames 100-299 in two segments: 10.5 mm apart at the cut with their own
appearances, 6.9 mm with the shared one; the single fit's depth itself drifts ~0.5 mm a frame there), so the
written parameters pass from one fit to the next across the overlap (`blend_weights`) instead of jumping at the
cut. The segments do not depend on the number of workers, so the result does not either. A segment reads its
frames itself (`SegmentJob.load`) and keeps only the resampled crops: memory grows with the segment length and the
number of workers, not with the video.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from geoavatar.workers import WorkerPool, report_progress, split_range, worker_cache


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


def segments(count: int, length: int, overlap: int, min_parts: int = 1) -> list[Segment]:
    """Balanced cores of at most `length` frames covering range(count), at least `min_parts` of them (two keep two
    workers busy on a short video), each fitted with `overlap` more frames on each side where the video has them."""
    if length < 1 or overlap < 0 or min_parts < 1:
        raise ValueError(f"segments: length and min_parts must be >= 1 and overlap >= 0, got {length}, {min_parts}, "
                         f"{overlap}")
    parts = max(-(-count // length), min(min_parts, count))
    return [Segment(a, b, max(0, a - overlap), min(count, b + overlap)) for a, b in split_range(count, parts)]


@dataclass
class SegmentJob:
    """What a worker needs to fit some frames of a video (picklable; per-frame arrays hold those frames only).

    rows [n]: the video rows fitted (a segment with its overlap, or the appearance sample); keep: which of them the
    job writes (a segment's core), positions in `rows`. load(row) -> (image [H, W, 3] uint8, mask [H, W] uint8) for
    a row of the whole video; head_factory() builds the head model (once per worker, under head_key); params: the
    npz layout, per-frame keys [n, ...], shape [S], static_offset [1, V, 3] (optional); viewmat [n, 4, 4], K
    [n, 3, 3] for the stored frames, boxes [n, 3] the crops; landmarks: LandmarkTargets' fields as arrays (points
    [n, L, 2], size [n], weights [L], confidence [n]) or None; appearance: (albedo, light) to start from, or None."""

    rows: np.ndarray
    keep: slice
    head_key: str
    head_factory: Callable
    load: Callable
    settings: object  # PhotometricConfig
    params: dict[str, np.ndarray]
    viewmat: np.ndarray
    K: np.ndarray
    boxes: np.ndarray
    landmarks: dict[str, np.ndarray] | None = None
    appearance: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class SegmentFits:
    """The stitched fit: params (npz layout, per-frame keys [T, ...]), residual / residual_before [T], each
    job's log (the appearance sample's first, when there is one)."""

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
    frames = (job.load(row) for row in job.rows)
    targets = PhotometricTargets.from_frames(frames, len(job.rows), job.viewmat, job.K, max(job.settings.sizes),
                                             job.boxes)
    init = HeadParams.from_npz({k: torch.as_tensor(v, dtype=torch.float32) for k, v in job.params.items()})
    landmarks = None
    if job.landmarks is not None:
        landmarks = LandmarkTargets(**{k: torch.as_tensor(v, dtype=torch.float32) for k, v in job.landmarks.items()})
    with torch.enable_grad():
        result = fit_photometric(head, init, targets, job.settings, landmarks=landmarks, progress=report_progress,
                                 appearance_start=job.appearance)
    return {"params": {k: v.detach().numpy() for k, v in result.params.to_npz().items()},
            "residual": result.residual, "residual_before": result.residual_before, "log": result.log,
            "appearance": (result.albedo, result.light)}


def shared_appearance(sample: SegmentJob, pool: WorkerPool, progress=None) -> tuple[tuple, list[str]]:
    """The appearance (albedo, light) fitted on a sample of a video's frames, with the pose held (a job whose
    settings have no pose epochs), and its log."""
    if any(sample.settings.epochs):
        raise ValueError("shared_appearance: the sample job must have no pose epochs")
    (fitted,) = pool.map(fit_segment, [sample], progress)
    return fitted["appearance"], [f"appearance sample ({len(sample.rows)} frames): {line}" for line in fitted["log"]]


def blend_weights(rows: np.ndarray, keep: slice) -> np.ndarray:
    """[n] a job's share of each row it fitted: 1 inside its core, ramping linearly down across each overlap it
    shares with a neighbour (from the neighbour's core edge minus the overlap to plus it), so that two neighbours'
    shares sum to 1 and the written parameters pass from one fit to the other over 2 x overlap frames."""
    core = rows[keep]
    weights = np.ones(len(rows))
    left, right = core[0] - rows[0], rows[-1] - core[-1]  # the overlaps on each side (0: a video end)
    if left > 0:
        weights = np.minimum(weights, np.clip((rows - (core[0] - left) + 0.5) / (2 * left), 0.0, 1.0))
    if right > 0:
        weights = np.minimum(weights, np.clip((core[-1] + 1 + right - rows - 0.5) / (2 * right), 0.0, 1.0))
    return weights


def fit_segments(jobs: list[SegmentJob], pool: WorkerPool, progress=None,
                 sample: SegmentJob | None = None) -> SegmentFits:
    """Fit every job (in the pool's workers) and blend them by `blend_weights`. With several jobs and a `sample`,
    they all start from the appearance fitted on the sample first. A frame's residual is that of the job whose
    core holds it (its own fit; within `overlap` frames of a cut the written parameters are a blend)."""
    if any(job.settings.fit_shape for job in jobs) and len(jobs) > 1:
        raise ValueError("fit_segments: fit_shape would give each segment its own identity; fit it in one segment")
    logs = []
    if sample is not None and len(jobs) > 1:
        appearance, log = shared_appearance(sample, pool, progress)
        jobs = [replace(job, appearance=appearance) for job in jobs]
        logs.append(log)
    count = max(int(job.rows[job.keep][-1]) for job in jobs) + 1
    sums: dict[str, np.ndarray] = {}
    subject: dict[str, np.ndarray] = {}
    total = np.zeros(count)
    residual, before = np.full(count, np.nan), np.full(count, np.nan)
    for fitted, job in zip(pool.imap(fit_segment, jobs, progress), jobs):
        weights = blend_weights(job.rows, job.keep)  # [n]
        for key, value in fitted["params"].items():
            if key in ("shape", "static_offset"):
                subject[key] = value
                continue
            sums.setdefault(key, np.zeros((count, *value.shape[1:])))
            sums[key][job.rows] += weights.reshape(-1, *[1] * (value.ndim - 1)) * value
        total[job.rows] += weights
        core = job.rows[job.keep]  # the video rows this job owns
        residual[core] = fitted["residual"][job.keep]
        before[core] = fitted["residual_before"][job.keep]
        logs.append(fitted["log"])
    params = {key: (value / total.reshape(-1, *[1] * (value.ndim - 1))).astype(np.float32)
              for key, value in sums.items()}
    return SegmentFits({**params, **subject}, residual, before, logs)


def segment_rows(span: Segment) -> tuple[np.ndarray, slice]:
    """(the rows a segment fits [n], its core as positions in them)."""
    return np.arange(span.fit_start, span.fit_stop), slice(span.start - span.fit_start, span.stop - span.fit_start)


__all__ = ["Segment", "SegmentFits", "SegmentJob", "blend_weights", "fit_segment", "fit_segments", "segment_rows",
           "segments", "shared_appearance"]
