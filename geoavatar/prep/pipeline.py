"""`geoavatar prepare`: video -> dataset, in resumable stages.

    run_prepare(PrepareConfig(video="talk.mp4", out="data/talk"))

Output folder OUT:
    OUT/dataset/          the VHAP / GaussianAvatars layout (LayoutWriter: appears atomically)
    OUT/overlay.mp4       tracked mesh + landmarks over the frames (green: MediaPipe, red: model)
    OUT/report.json       per-frame reprojection error, frames without a face (missing_source_frames: source
                          frame numbers; interpolated_frames: dataset timesteps), focal, fps; "capture": the
                          capture check (geoavatar.prep.coverage: head turns, jaw, expressions, gaze per split,
                          test frames outside training, the verdict)
    OUT/coverage.png      the capture check's picture
    OUT/.prepare/         work files of the stages and their completion markers

Stages (each writes `.prepare/<stage>.json` last, holding its key; a re-run skips a stage whose marker
holds the key it would have now, and redoes it and every stage that depends on it otherwise):
    frames     decode, face detection on whole frames, smoothed square crop, crops as PNG
    landmarks  face mesh on the crops, One-Euro filtering, confidence, missing frames
    masks      selfie segmentation x landmark head region (see geoavatar.prep.masks)
    tracking   the head-model fit (geoavatar.prep.tracking)
    photometric  every frame refined against its crop (geoavatar.prep.photometric); with --no-photometric it only
               records that it was skipped and the dataset is written from the landmark fit
    write      the dataset through LayoutWriter, then the overlay video, the capture check and the report
    sound      the video's sound track resampled once into the dataset, each frame timed on it, and where the speech is
               (geoavatar.data.sound); a video without sound, or without speech, prepares as before and says so

Every stage splits its frames into tasks for a WorkerPool (geoavatar.workers: spawned processes, one torch
thread each, `workers` of them, by default one per core): decoding + face detection and the crops one range of the
video per worker, the landmarks, masks and overlay pictures in fixed blocks, the photometric fit in segments
(geoavatar.prep.segments); the tracking stage is one batched fit (its data term in chunks). The tasks do not depend
on the worker count, so neither does the dataset. No stage holds every frame's pixels: a long video costs time and
disk, not memory. A marker's cpu_seconds counts this process and its workers. (Spawned workers import the caller's
main module: a script that calls run_prepare with more than one worker needs the `if __name__ == "__main__":` guard.)

A stage's key is the sha256 of the canonical JSON of {its version, its config, its upstream stages'
keys}. Its config is derived from PrepareConfig: every field names the stage that reads it
(`_stage_field`; the class will not import with a field that does not), and the tracking stage adds
every field of the TrackingConfig it runs with, so a new option or a changed default can never reuse
results made without it. Upstream (DEPENDS_ON): landmarks <- frames; masks, tracking <- frames,
landmarks; write <- all four. Changing --mask-backend redoes masks and write, not the tracking.

Bad input raises PrepareError with a message naming the file or option; OUT/dataset is only ever
created complete. A run that fails before any stage completes removes an OUT it created itself.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, fields, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from geoavatar.io.atomic import atomic_write_json, atomic_write_npz, atomic_write_png
from geoavatar.prep.errors import PrepareError
from geoavatar.workers import WorkerPool, default_workers, report_progress, split_range, worker_cache

STAGES = ("frames", "landmarks", "masks", "tracking", "photometric", "write", "sound")
# Part of a stage's key: bumped when the stage's method changes, so a re-run redoes that stage (and the
# ones depending on it) instead of keeping outputs made the old way.
STAGE_VERSIONS = {"frames": 1, "landmarks": 1, "masks": 2, "tracking": 2, "photometric": 3, "write": 5, "sound": 1}
# The stages whose outputs a stage reads: a rerun of one redoes these dependants.
DEPENDS_ON: dict[str, tuple[str, ...]] = {
    "frames": (),
    "landmarks": ("frames",),
    "masks": ("frames", "landmarks"),
    "tracking": ("frames", "landmarks"),
    "photometric": ("frames", "landmarks", "masks", "tracking"),
    "write": ("frames", "landmarks", "masks", "tracking", "photometric"),
    "sound": ("frames", "landmarks", "write"),  # the write stage replaces the dataset folder, sound files included
}
WORK = ".prepare"
# Torch (and native rasterizer) threads of the photometric stage. Its renders are small (128 px, ~10k Gaussians), so
# every parallel region is short: on a 2-core machine shared with other jobs, 2 threads made it 26x slower in wall
# time and 21x in CPU time than 1 thread (BENCHMARKS.md, photometric tracking); 1 thread costs little where it is quiet.
PHOTOMETRIC_THREADS = 1
UNKEYED = "-"  # a PrepareConfig field no stage output depends on (where to write, logging)
# Frames per task of the landmark and mask stages (fixed, so that a dataset does not depend on the worker count). The
# face mesh tracks from frame to frame: a landmark block starts LANDMARK_WARMUP frames early and drops them.
LANDMARK_BLOCK = 600
LANDMARK_WARMUP = 16
MASK_BLOCK = 256
# The photometric stage fits segments of at most this many frames, each with this many more on either side, in the
# workers (geoavatar.prep.segments); both are part of the stage's key.
PHOTOMETRIC_SEGMENT = 300
PHOTOMETRIC_OVERLAP = 8
# A video of at least twice this many frames is fitted in two segments or more, so both cores work on it (one segment
# of 252 frames kept one core idle for most of duda.mp4's prepare; #40).
PHOTOMETRIC_MIN_SEGMENT = 100
# Frames, spread over the whole video, of the one appearance (albedo, lighting) that several segments start from: fitted
# first, on one core while the other waits, so it is kept short (#40).
PHOTOMETRIC_SAMPLE = 100
OVERLAY_BLOCK = 32  # overlay pictures per worker task


def _stage_field(stage: str, *default: Any, **kwargs) -> Any:
    """A PrepareConfig field read by `stage` (a name of STAGES, or UNKEYED): it goes into that stage's key.
    Without a default the field is required."""
    if stage != UNKEYED and stage not in STAGES:
        raise ValueError(f"unknown prepare stage '{stage}'")
    if default:
        kwargs["default"] = default[0]
    return field(metadata={"stage": stage}, **kwargs)


@dataclass
class PrepareConfig:
    video: Path = _stage_field("frames")  # keyed by its resolved path, size and mtime
    out: Path = _stage_field(UNKEYED)
    head: Literal["openhead", "flame"] = _stage_field("tracking", "openhead")
    size: int = _stage_field("frames", 512)  # side of the square crop written to the dataset
    fps: float | None = _stage_field("frames", None)  # subsample to this rate (None: every frame)
    max_frames: int | None = _stage_field("frames", None)
    missing: Literal["interpolate", "drop"] = _stage_field("landmarks", "interpolate")
    min_frames: int = _stage_field("landmarks", 5)
    crop_scale: float = _stage_field("frames", 2.6)  # crop side / face-detector box side
    crop_sigma: float = _stage_field("frames", 12.0)  # temporal smoothing of the crop centre, frames
    test_fraction: float = _stage_field("write", 0.2)  # the last 20 % of the frames are the test split
    flame_dir: Path | None = _stage_field("tracking", None)
    # MediaPipe embedding for FLAME (default: FLAME_DIR/mediapipe_landmark_embedding.npz)
    flame_landmarks: Path | None = _stage_field("tracking", None)
    tracking_steps: tuple[int, int] = _stage_field("tracking", (100, 300))  # rigid, full
    # fit a smooth static offset of the mesh (geoavatar.head.smooth_offset)
    static_offset: bool = _stage_field("tracking", True)
    # photometric tracking of every frame after the landmark fit (geoavatar.prep.photometric)
    photometric: bool = _stage_field("photometric", True)  # False (--no-photometric): the landmark fit is written
    photometric_epochs: tuple[int, int] = _stage_field("photometric", (16, 12))  # at 64 px, at 128 px (PhotometricConfig's)
    overlay: bool = _stage_field("write", True)
    mask_backend: str = _stage_field("masks", "selfie")
    # worker processes (None: the cores this process may use, at most 8); the dataset does not depend on it
    workers: int | None = _stage_field(UNKEYED, None)
    progress: bool = _stage_field(UNKEYED, True)
    log: Callable[[str], None] = _stage_field(UNKEYED, print, repr=False)


_unassigned = [f.name for f in fields(PrepareConfig) if f.metadata.get("stage") is None]
if _unassigned:  # a field outside every stage key would silently reuse stale stage results
    raise TypeError(f"PrepareConfig fields without a stage (use _stage_field): {_unassigned}")


# --- small helpers ----------------------------------------------------------------------------------


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image).copy()


def _bar(config: PrepareConfig, total: int | None, desc: str, unit: str = "frame"):
    from tqdm import tqdm

    return tqdm(total=total, desc=f"prepare: {desc}", unit=unit, disable=not config.progress, leave=True)


class _Stages:
    """Completion markers `.prepare/<stage>.json` holding the key of each stage."""

    def __init__(self, work: Path, keys: dict[str, str]):
        self.work, self.keys = work, keys
        self.rerun: set[str] = set()  # stages redone by this run: their dependants are redone too

    def done(self, stage: str) -> bool:
        marker = self.work / f"{stage}.json"
        ok = marker.is_file() and not self.rerun.intersection(DEPENDS_ON[stage])
        if ok:
            try:
                ok = json.loads(marker.read_text()).get("key") == self.keys[stage]
            except (OSError, json.JSONDecodeError):
                ok = False
        if not ok:
            self.rerun.add(stage)
        return ok

    def start(self, stage: str) -> None:
        (self.work / f"{stage}.json").unlink(missing_ok=True)

    def finish(self, stage: str, info: dict) -> None:
        atomic_write_json(self.work / f"{stage}.json", {"key": self.keys[stage], **info})


def tracking_config(config: PrepareConfig):
    """The TrackingConfig the tracking stage runs with (all of its fields are part of the stage's key)."""
    from geoavatar.prep.tracking import TrackingConfig

    return TrackingConfig(rigid_steps=config.tracking_steps[0], full_steps=config.tracking_steps[1],
                          fit_static_offset=config.static_offset)


def photometric_config(config: PrepareConfig):
    """The PhotometricConfig the photometric stage runs with (all of its fields are part of the stage's key)."""
    from geoavatar.prep.photometric import PhotometricConfig

    return PhotometricConfig(sizes=(64, 128), epochs=tuple(config.photometric_epochs), tracking=tracking_config(config))


def fit_file(config: PrepareConfig, work: Path) -> Path:
    """The head-model fit the dataset is written from: photometric.npz (same keys as tracking.npz) unless
    --no-photometric."""
    return work / ("photometric.npz" if config.photometric else "tracking.npz")


def _canonical(value: Any) -> Any:
    """JSON-able form of a config value: paths as strings, tuples as lists, dataclasses as dicts."""
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if hasattr(value, "__dataclass_fields__"):
        return _canonical(asdict(value))
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"prepare stage key: cannot put {type(value).__name__} {value!r} into a key")


def stage_configs(config: PrepareConfig) -> dict[str, dict[str, Any]]:
    """Each stage's config: the PrepareConfig fields it reads (by their `_stage_field` stage), plus the
    video file's identity (frames), the full TrackingConfig (tracking) and PhotometricConfig (photometric;
    with --no-photometric only that flag)."""
    out: dict[str, dict[str, Any]] = {stage: {} for stage in STAGES}
    for f in fields(PrepareConfig):
        stage = f.metadata["stage"]
        if stage != UNKEYED:
            out[stage][f.name] = _canonical(getattr(config, f.name))
    video = Path(config.video).resolve()
    stat = video.stat()
    out["frames"]["video"] = {"path": str(video), "bytes": stat.st_size, "mtime": int(stat.st_mtime)}
    out["tracking"]["tracking_config"] = _canonical(tracking_config(config))
    if config.photometric:
        out["photometric"]["photometric_config"] = _canonical(photometric_config(config))
        out["photometric"]["segments"] = {"length": PHOTOMETRIC_SEGMENT, "overlap": PHOTOMETRIC_OVERLAP,
                                          "min_length": PHOTOMETRIC_MIN_SEGMENT, "sample": PHOTOMETRIC_SAMPLE}
    else:  # skipped: its settings are not read, so changing them must not redo the dataset written without them
        out["photometric"] = {"photometric": False}
    return out


def _stage_keys(config: PrepareConfig) -> dict[str, str]:
    """sha256 of {stage, version, config, upstream keys} in canonical JSON, per stage (STAGES order)."""
    configs, keys = stage_configs(config), {}
    for stage in STAGES:
        record = {"stage": stage, "version": STAGE_VERSIONS[stage], "config": configs[stage],
                  "upstream": {up: keys[up] for up in DEPENDS_ON[stage]}}
        text = json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False)
        keys[stage] = hashlib.sha256(text.encode()).hexdigest()
    return keys


# --- stages -----------------------------------------------------------------------------------------


def _expected_frames(config: PrepareConfig, info) -> int:
    """The frames the frames stage will keep, from the container's count (0: unknown)."""
    count = info.num_frames
    if count and config.fps:
        count = math.ceil(count * min(1.0, config.fps / info.fps))
    if count and config.max_frames:
        count = min(count, config.max_frames)
    return int(count)


def _video_ranges(config: PrepareConfig, info, workers: int) -> list[tuple[int, int | None]]:
    """One (start, stop) range of kept frames per worker; the last one is open (the count may be an estimate)."""
    expected = _expected_frames(config, info)
    if not expected:
        return [(0, None)]
    ranges: list[tuple[int, int | None]] = list(split_range(expected, workers))
    ranges[-1] = (ranges[-1][0], None)
    return ranges


def _detect_task(task) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Face detection on whole frames of a range: (source indices [n], centres [n, 2], sizes [n], scores [n])."""
    from geoavatar.prep.landmarks import FaceDetector
    from geoavatar.prep.video import decode_frames

    video, fps, max_frames, start, stop = task
    detect = worker_cache("face_detector", FaceDetector)  # stateless: one per process
    indices, centres, sizes, scores = [], [], [], []
    for index, rgb in decode_frames(video, fps, max_frames, start, stop):
        box = detect(rgb)
        indices.append(index)
        centres.append(box.centre if box else np.zeros(2))
        sizes.append(box.size if box else 0.0)
        scores.append(box.score if box else 0.0)
        report_progress(1)
    return np.array(indices, np.int64), np.array(centres).reshape(-1, 2), np.array(sizes), np.array(scores)


def _crop_task(task) -> int:
    """Crop the frames of a range to frames/KKKKK.png (K: kept-frame number); returns how many."""
    from geoavatar.prep.video import crop_square, decode_frames

    video, fps, max_frames, start, boxes, size, frames_dir = task
    count = 0
    for k, (_, rgb) in enumerate(decode_frames(video, fps, max_frames, start, start + len(boxes)), start):
        atomic_write_png(frames_dir / f"{k:05d}.png", crop_square(rgb, boxes[k - start], size), compress_level=1)
        count += 1
        report_progress(1)
    return count


def stage_frames(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    from geoavatar.prep.video import probe_video, smooth_crop_boxes

    info = probe_video(config.video)
    ranges = _video_ranges(config, info, pool.workers)
    tasks = [(config.video, config.fps, config.max_frames, a, b) for a, b in ranges]
    with _bar(config, _expected_frames(config, info) or None, "detect faces") as bar:
        parts = pool.map(_detect_task, tasks, progress=bar.update)
    indices, centres, sizes, scores = (np.concatenate(column) for column in zip(*parts))
    found = scores > 0
    if len(indices) < config.min_frames:
        raise PrepareError(
            f"video '{config.video}': {len(indices)} frame(s) after --fps/--max-frames, fewer than the "
            f"{config.min_frames} needed (train and test frames)"
        )
    if not found.any():
        raise PrepareError(f"video '{config.video}': no face was found in any of its {len(indices)} frames")
    boxes = smooth_crop_boxes(centres, sizes, found, (info.width, info.height), config.crop_scale, config.crop_sigma)
    frames_dir = work / "frames"
    shutil.rmtree(frames_dir, ignore_errors=True)
    frames_dir.mkdir(parents=True)
    tasks = [(config.video, config.fps, config.max_frames, a, boxes[a:b], config.size, frames_dir)
             for a, b in split_range(len(indices), pool.workers)]
    with _bar(config, len(indices), "crop") as bar:
        cropped = sum(pool.map(_crop_task, tasks, progress=bar.update))
    if cropped != len(indices):  # the second decoding pass must meet the same frames
        raise PrepareError(f"video '{config.video}': {cropped} frames decoded on the second pass, "
                           f"{len(indices)} on the first")
    source_fps = info.fps
    fps = min(config.fps, source_fps) if config.fps else source_fps
    atomic_write_npz(work / "frames.npz", source_index=indices, boxes=boxes, presence=scores,
                     detected=found, frame_size=np.array([info.width, info.height]), fps=np.array(fps))
    return {"frames": len(indices), "no_face_detected": [int(indices[k]) for k in np.flatnonzero(~found)],
            "video": asdict(info)}


def _landmark_task(task) -> tuple[np.ndarray, np.ndarray]:
    """Face mesh (video mode) on the crops of a block: raw points [n, 478, 3] and found [n]. The tracker starts
    LANDMARK_WARMUP frames early, so that the block's first frames are tracked, not detected afresh."""
    from geoavatar.prep.landmarks import FaceMesh

    frames_dir, start, stop = task
    raw = np.zeros((stop - start, 478, 3))
    found = np.zeros(stop - start, bool)
    with FaceMesh() as mesh:
        for k in range(max(0, start - LANDMARK_WARMUP), stop):
            points = mesh(_read_png(frames_dir / f"{k:05d}.png"))
            if k >= start:
                if points is not None:
                    raw[k - start], found[k - start] = points, True
                report_progress(1)
    return raw, found


def stage_landmarks(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    from geoavatar.prep.landmarks import filter_landmarks, landmark_confidence
    from geoavatar.prep.video import fill_missing

    frames = np.load(work / "frames.npz")
    count = len(frames["source_index"])
    blocks = split_range(count, math.ceil(count / LANDMARK_BLOCK))
    with _bar(config, count, "landmarks") as bar:
        parts = pool.map(_landmark_task, [(work / "frames", a, b) for a, b in blocks], progress=bar.update)
    raw, found = (np.concatenate(column) for column in zip(*parts))
    source = frames["source_index"]
    missing = [int(source[k]) for k in np.flatnonzero(~found)]
    if not found.any():
        raise PrepareError(f"video '{config.video}': the face mesh found no face in any of the {count} cropped frames")
    if missing:
        config.log(f"prepare: no face in {len(missing)} frame(s) (source frame numbers): {missing[:50]}"
                   + (" ..." if len(missing) > 50 else "") + f"; --missing {config.missing}")
    if config.missing == "drop":
        keep = np.flatnonzero(found)
    else:
        keep = np.arange(count)
        raw = fill_missing(raw, found)
    if len(keep) < config.min_frames:
        raise PrepareError(
            f"video '{config.video}': only {len(keep)} frame(s) with a face, fewer than the {config.min_frames} needed"
        )
    filtered = filter_landmarks(raw[keep], float(frames["fps"]))
    presence = np.where(found, np.clip(frames["presence"], 0.5, 1.0), 0.0)[keep]  # interpolated frames: 0 presence
    confidence = landmark_confidence(raw[keep], filtered, presence)
    atomic_write_npz(work / "landmarks.npz", raw=raw[keep], filtered=filtered, confidence=confidence, keep=keep,
                found=found)
    return {"frames": int(len(keep)), "missing_source_frames": missing, "mode": config.missing}


def _mask_task(task) -> list[float]:
    """Masks of a block of frames (rows of landmarks.npz's keep); returns each mask's coverage."""
    from geoavatar.prep.masks import PersonSegmenter, foreground_mask

    work, backend, keep, points = task
    segment = worker_cache(f"segmenter:{backend}", lambda: PersonSegmenter(backend))  # stateless: one per process
    coverage = []
    for k, landmarks in zip(keep, points):
        mask = foreground_mask(segment(_read_png(work / "frames" / f"{k:05d}.png")), landmarks)
        atomic_write_png(work / "masks" / f"{k:05d}.png", mask, compress_level=1)
        coverage.append(float(mask.mean() / 255.0))
        report_progress(1)
    return coverage


def stage_masks(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    marks = np.load(work / "landmarks.npz")
    keep, points = marks["keep"], marks["filtered"]
    masks_dir = work / "masks"
    shutil.rmtree(masks_dir, ignore_errors=True)
    masks_dir.mkdir(parents=True)
    blocks = split_range(len(keep), math.ceil(len(keep) / MASK_BLOCK))
    tasks = [(work, config.mask_backend, keep[a:b], points[a:b]) for a, b in blocks]
    with _bar(config, len(keep), "masks") as bar:
        coverage = [value for part in pool.map(_mask_task, tasks, progress=bar.update) for value in part]
    return {"frames": int(len(keep)), "mean_coverage": float(np.mean(coverage))}


def load_tracking_head(config: PrepareConfig):
    """(full HeadModelData for rendering, landmark-only HeadModel for fitting) of --head."""
    from geoavatar.head import load_head_data
    from geoavatar.prep.tracking import landmark_head, load_landmark_embedding

    if config.head == "openhead":
        data = load_head_data("openhead")
    elif config.head == "flame":
        from geoavatar.head.flame import FlameFileNotFoundError, resolve_flame_dir

        try:
            data = load_head_data("flame", flame_dir=config.flame_dir)
        except FlameFileNotFoundError as err:
            raise PrepareError(str(err)) from err
        path = config.flame_landmarks or resolve_flame_dir(config.flame_dir) / "mediapipe_landmark_embedding.npz"
        try:
            ids, faces, bary = load_landmark_embedding(path)
        except FileNotFoundError:
            raise PrepareError(
                f"--head flame needs FLAME's MediaPipe landmark embedding '{path}' (the "
                "mediapipe_landmark_embedding.npz that metrical-tracker and VHAP use; keys landmark_indices, "
                "lmk_face_idx, lmk_b_coords): put it in the FLAME folder or pass --flame-landmarks FILE"
            ) from None
        except ValueError as err:
            raise PrepareError(str(err)) from err
        if faces.max() >= len(data.faces):
            raise PrepareError(f"'{path}': face ids up to {faces.max()} but FLAME has {len(data.faces)} faces")
        data = data.copy_with(landmark_ids=ids, landmark_faces=faces, landmark_bary=bary)
    else:
        raise PrepareError(f"--head must be openhead or flame, got '{config.head}'")
    return data, landmark_head(data)


def stage_tracking(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    from geoavatar.prep.tracking import track_crops

    frames = np.load(work / "frames.npz")
    marks = np.load(work / "landmarks.npz")
    keep = marks["keep"]
    data, model = load_tracking_head(config)
    frame_size = tuple(int(v) for v in frames["frame_size"])
    bar = _bar(config, sum(config.tracking_steps), "tracking", unit="step")
    try:
        result = track_crops(model, data, marks["filtered"], marks["confidence"], frames["boxes"][keep], frame_size,
                             config.size, tracking_config(config), progress=lambda n, _stage: bar.update(n))
    finally:
        bar.close()
    atomic_write_npz(work / "tracking.npz", **{f"param_{k}": v for k, v in result.params.items()}, focal=result.focal,
                viewmat=result.viewmat, K=result.K, projected=result.projected, landmark_ids=result.landmark_ids,
                errors=result.errors)
    for line in result.log:
        config.log(f"prepare: tracking {line}")
    return {"focal": result.focal, "median_error": float(np.median(result.errors)), "log": result.log}


def _photometric_head(config: PrepareConfig):
    """The head model the photometric stage renders: --head with the GeoAvatar mouth structure."""
    from geoavatar.head import HeadModel
    from geoavatar.head.mouth import add_mouth_structure

    data, _ = load_tracking_head(config)
    return HeadModel(add_mouth_structure(data, kind="geoavatar"))


def _load_crop(work: Path, keep: np.ndarray, found: np.ndarray, row: int) -> tuple[np.ndarray, np.ndarray]:
    """(crop [H, W, 3], mask [H, W]) of dataset row `row`. No face found (landmarks interpolated): the image is
    not of the face the parameters say (a hand, a turned-away head), so its mask is empty: no image term."""
    k = keep[row]
    image, mask = _read_png(work / "frames" / f"{k:05d}.png"), _read_png(work / "masks" / f"{k:05d}.png")
    return image, mask if found[k] else np.zeros_like(mask)


def _worker_config(config: PrepareConfig) -> PrepareConfig:
    """The config as a worker gets it: picklable (the log callback may be a lambda; workers do not log)."""
    return replace(config, log=print, progress=False)


def _segment_jobs(config: PrepareConfig, work: Path, head, init, fit, marks) -> tuple[list, object]:
    """The photometric stage's SegmentJobs (one per segment: its rows of the landmark fit, cameras, crops and
    landmarks) and the appearance sample's (frames spread over the whole video, no pose epochs)."""
    import torch

    from geoavatar.data.splits import evenly_spaced
    from geoavatar.head.params import SUBJECT_KEYS
    from geoavatar.prep.photometric import crop_boxes, weighted_vertex_ids
    from geoavatar.prep.segments import SegmentJob, segment_rows, segments
    from geoavatar.prep.tracking import GROUP_OF, GROUP_WEIGHTS

    settings = photometric_config(config)
    keep = marks["keep"]
    T = len(keep)
    viewmat = np.repeat(fit["viewmat"][None], T, 0)  # [T, 4, 4]: one camera
    boxes = crop_boxes(head, init, torch.as_tensor(viewmat, dtype=torch.float32),
                       torch.as_tensor(fit["K"], dtype=torch.float32), weighted_vertex_ids(head), settings.crop_margin)
    ids = head.landmark_ids.cpu().numpy()
    points = marks["filtered"]
    size = np.maximum(np.linalg.norm(points[:, 10, :2] - points[:, 152, :2], axis=-1), 1.0)
    landmarks = {"points": points[:, ids, :2], "size": size, "confidence": np.clip(marks["confidence"], 0.05, 1.0)}
    weights = np.array([GROUP_WEIGHTS[GROUP_OF.get(int(i), "face_oval_lower")] for i in ids])
    params = {k: v.numpy() for k, v in init.to_npz().items()}
    workers = _worker_config(config)
    head_key = f"photometric-head:{config.head}:{config.flame_dir}:{config.flame_landmarks}"

    def job(rows: np.ndarray, core: slice, settings) -> SegmentJob:
        return SegmentJob(
            rows=rows, keep=core, head_key=head_key,
            head_factory=partial(_photometric_head, workers), load=partial(_load_crop, work, keep, marks["found"]),
            settings=settings, params={k: v if k in SUBJECT_KEYS else v[rows] for k, v in params.items()},
            viewmat=viewmat[rows], K=fit["K"][rows], boxes=boxes[rows],
            landmarks={**{k: v[rows] for k, v in landmarks.items()}, "weights": weights})

    spans = segments(T, PHOTOMETRIC_SEGMENT, PHOTOMETRIC_OVERLAP, 2 if T >= 2 * PHOTOMETRIC_MIN_SEGMENT else 1)
    jobs = [job(*segment_rows(span), settings) for span in spans]
    sample = job(np.array(evenly_spaced(T, PHOTOMETRIC_SAMPLE)), slice(0, 0),
                 replace(settings, epochs=(0,) * len(settings.epochs)))
    return jobs, sample


def photometric_inputs(config: PrepareConfig, work: Path) -> tuple[dict, dict, Any, Any]:
    """What the photometric stage starts from: the landmark stage's arrays, the tracking stage's fit, the head model
    it renders and the fit's parameters as HeadParams (marks, fit, head, init)."""
    import torch

    from geoavatar.head.params import HeadParams

    marks = dict(np.load(work / "landmarks.npz"))
    fit = dict(np.load(work / "tracking.npz"))
    params = {k[len("param_"):]: torch.as_tensor(fit[k], dtype=torch.float32) for k in fit if k.startswith("param_")}
    if "static_offset" in params:
        params["static_offset"] = params["static_offset"].reshape(1, -1, 3)
    return marks, fit, _photometric_head(config), HeadParams.from_npz(params)


def stage_photometric(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    """Refine every frame's parameters against the crops (masked photometric L1 + the landmark term), segment by
    segment over the workers (geoavatar.prep.segments)."""
    import torch

    from geoavatar.head.params import HeadParams
    from geoavatar.prep.photometric import residual_report, total_steps
    from geoavatar.prep.segments import fit_segments
    from geoavatar.render.camera import project

    (work / "photometric.npz").unlink(missing_ok=True)
    if not config.photometric:
        return {"skipped": True}
    marks, fit, head, init = photometric_inputs(config, work)
    jobs, sample = _segment_jobs(config, work, head, init, fit, marks)
    shared = len(jobs) > 1  # several segments start from one appearance, fitted on the sample first
    steps = sum(total_steps(job.settings, len(job.rows), appearance_start=shared) for job in jobs)
    bar = _bar(config, steps + (total_steps(sample.settings, len(sample.rows)) if shared else 0), "photometric")
    try:
        result = fit_segments(jobs, pool, progress=bar.update, sample=sample)
    finally:
        bar.close()
    fitted = {k: v for k, v in result.params.items() if k != "static_offset"}
    if "param_static_offset" in fit:
        fitted["static_offset"] = fit["param_static_offset"]
    values = {k: torch.as_tensor(v) for k, v in fitted.items() if k != "static_offset"}
    ids, points = head.landmark_ids.cpu().numpy(), marks["filtered"]
    with torch.no_grad():
        refined = HeadParams.from_npz({**values, "static_offset": init.static_offset})
        pixels, _ = project(head.forward_params(refined, vertex_ids=head.landmark_vertex_ids).landmarks,
                            torch.as_tensor(fit["viewmat"], dtype=torch.float32),
                            torch.as_tensor(fit["K"], dtype=torch.float32))
    width = np.maximum(np.linalg.norm(points[:, 234, :2] - points[:, 454, :2], axis=-1), 1e-6)
    detected = torch.as_tensor(points[:, ids, :2], dtype=torch.float32)
    errors = np.median((pixels - detected).norm(dim=-1).numpy(), axis=1) / width
    atomic_write_npz(work / "photometric.npz", **{f"param_{k}": v for k, v in fitted.items()}, focal=fit["focal"],
                     viewmat=fit["viewmat"], K=fit["K"], projected=pixels.numpy(), landmark_ids=ids, errors=errors,
                     residual=result.residual, residual_before=result.residual_before)
    summary = residual_report(result.residual, result.residual_before)
    log = [f"{len(jobs)} segment(s) of at most {PHOTOMETRIC_SEGMENT} frames (+{PHOTOMETRIC_OVERLAP} overlap)"
           + (f", one appearance fitted on {len(sample.rows)} frames first" if shared else "")]
    log += result.logs[0] if shared else []
    cores = [job.rows[job.keep] for job in jobs]
    log += [f"segment {i} (frames {core[0]}-{core[-1]}): {line}"
            for i, (core, lines) in enumerate(zip(cores, result.logs[shared:])) for line in lines]
    config.log(f"prepare: photometric {log[0]}; residual (masked L1): {summary['mean_before']:.4f} -> "
               f"{summary['mean']:.4f}")
    return {"residual_before": summary["mean_before"], "residual": summary["mean"],
            "median_error": float(np.median(errors)), "log": log}


def _fit_params(fit: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The head-model parameters of a fit file (its param_<key> arrays, [T, ...] or [S], by key)."""
    return {k[len("param_"):]: fit[k] for k in fit if k.startswith("param_")}


def _written_frame(params: dict[str, np.ndarray], t: int) -> dict[str, np.ndarray]:
    """Dataset timestep t's per-frame parameters as the write stage writes them."""
    from geoavatar.head.params import FRAME_KEYS

    return {key: params[key][t] for key in FRAME_KEYS}


def stage_write(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    from geoavatar.data.layout import LayoutWriter
    from geoavatar.data.splits import SplitConfig

    frames = dict(np.load(work / "frames.npz"))  # every array read once (an npz re-reads an array at each access)
    marks = dict(np.load(work / "landmarks.npz"))
    fit = dict(np.load(fit_file(config, work)))
    keep = marks["keep"]
    count = len(keep)
    test = max(1, math.ceil(config.test_fraction * count)) if config.test_fraction > 0 else 0
    dataset = Path(config.out) / "dataset"
    params = _fit_params(fit)
    with LayoutWriter(dataset, head_model=config.head, image_size=(config.size, config.size), shape=params["shape"],
                      static_offset=params.get("static_offset"),
                      background=(1.0, 1.0, 1.0), source=str(Path(config.video).name),
                      split=SplitConfig(test_frames=test), overwrite=True) as writer, _bar(config, count, "write") as bar:
        for t, k in enumerate(keep):  # the crops and masks are PNGs already: linked into the dataset, not re-encoded
            writer.add_frame(t, work / "frames" / f"{k:05d}.png", _written_frame(params, t), fit["viewmat"],
                             fit["K"][t], mask=work / "masks" / f"{k:05d}.png")
            bar.update(1)
    if config.overlay:
        write_overlay(config, work, Path(config.out) / "overlay.mp4", pool)
    errors = fit["errors"]
    source = frames["source_index"][keep]
    report = {
        "video": str(config.video), "frames": int(count), "source_frames": [int(s) for s in source],
        "missing_source_frames": json.loads((work / "landmarks.json").read_text()).get("missing_source_frames", []),
        # dataset timesteps whose landmarks were interpolated (no face found; --missing interpolate)
        "interpolated_frames": [int(t) for t in np.flatnonzero(~marks["found"][keep])],
        "test_frames": int(test), "fps": float(frames["fps"]), "focal_px": float(fit["focal"]), "size": config.size,
        "reprojection_error_over_face_width": {
            "median": float(np.median(errors)), "p90": float(np.percentile(errors, 90)), "max": float(errors.max()),
            "frames_below_2pct": float((errors < 0.02).mean()), "per_frame": [round(float(e), 5) for e in errors],
        },
        "jaw_open_rad": {"min": float(params["jaw_pose"][:, 0].min()), "max": float(params["jaw_pose"][:, 0].max())},
    }
    if "residual" in fit:  # masked L1 of the photometric fit's appearance model, 128 px face crops
        from geoavatar.prep.photometric import residual_report

        report["photometric_residual"] = residual_report(fit["residual"], fit["residual_before"])  # null: no face
    report["capture"] = write_capture_check(config, params, fit["viewmat"], count - test, count, marks["raw"])
    atomic_write_json(Path(config.out) / "report.json", report)
    return {"dataset": str(dataset), "frames": int(count), "test_frames": int(test)}


def stage_sound(config: PrepareConfig, work: Path, pool: WorkerPool) -> dict:
    """The video's sound into the dataset (audio.wav, audio.json: each timestep's time on it, the speech segments)
    and report.json's "sound"; one line for the user either way."""
    from geoavatar.data.sound import remove_dataset_sound, write_dataset_sound
    from geoavatar.sound.activity import ADVISED_SPEECH_SECONDS, speech_activity

    dataset = Path(config.out) / "dataset"
    remove_dataset_sound(dataset)
    sound, times, silent = _sound_under_frames(config, work)
    if sound is None:
        info = {"track": False}
    else:
        activity = speech_activity(sound)
        write_dataset_sound(dataset, sound, {t: float(s) for t, s in enumerate(times)}, activity,
                            source=Path(config.video).name)
        info = {"track": True, "seconds": round(sound.seconds, 3), "speech_seconds": round(activity.speech_seconds, 3),
                "has_speech": activity.has_speech, "rate": sound.rate, "frames_without_sound": silent}
        if silent:
            config.log(f"prepare: {silent} of the {len(times)} frames lie before or after the sound track (the voice "
                       "learns from the others)")
        if activity.has_speech:
            advice = ("" if activity.speech_seconds >= ADVISED_SPEECH_SECONDS else
                      "; a minute or more of talking makes the mouth follow the sound closer")
            config.log(f"prepare: sound track: {activity.speech_seconds:.1f} s of speech in {sound.seconds:.1f} s "
                       f"(its avatar learns the voice{advice})")
        else:
            config.log(f"prepare: the sound track holds {activity.speech_seconds:.1f} s of speech (an avatar learns "
                       "to speak only from a video with speech)")
    report_path = Path(config.out) / "report.json"
    atomic_write_json(report_path, {**json.loads(report_path.read_text()), "sound": info})
    return info


def _sound_under_frames(config: PrepareConfig, work: Path):
    """(the video's sound under the frames kept, each timestep's time on it [T], how many of them lie outside it),
    or (None, None, 0) after one line for the user when there is no sound to keep."""
    from geoavatar.prep.video import frame_times
    from geoavatar.sound import SoundError, has_sound_track, read_sound

    if not has_sound_track(config.video):
        config.log("prepare: the video has no sound track (an avatar learns to speak only from a video with speech)")
        return None, None, 0
    try:
        sound = read_sound(config.video, what="video")
    except SoundError as err:  # a track with no samples, or one that does not decode: the frames still stand
        config.log(f"prepare: the sound track cannot be used ({err}); the dataset has no sound")
        return None, None, 0
    frames = np.load(work / "frames.npz")
    source = frames["source_index"][np.load(work / "landmarks.npz")["keep"]]  # [T] source frame of each timestep
    times = frame_times(config.video)
    times = times[np.minimum(source, len(times) - 1)] - sound.start  # [T] seconds on the sound
    silent = int(np.sum((times < 0) | (times >= sound.seconds)))  # frames shown before or after the sound
    if silent == len(times):
        config.log("prepare: the sound track lies before or after all the frames kept; the dataset has no sound")
        return None, None, 0
    # the sound under the frames kept (--max-frames, a video cut short): up to the last one's end
    return sound.segment(0.0, float(times[-1]) + 1.0 / float(frames["fps"])), times, silent


def write_capture_check(config: PrepareConfig, params: dict[str, np.ndarray], viewmat: np.ndarray, train: int,
                        count: int, landmarks: np.ndarray) -> dict:
    """The capture check (geoavatar.prep.coverage) of the written fit: OUT/coverage.png; returns its report.
    params: the fit's npz arrays (per-frame keys [T, ...]); the first `train` rows are the training frames;
    landmarks [T, 478, 3] the face mesh's unfiltered points (its blinks: the filter and the fit may smooth a short
    one away)."""
    import torch

    from geoavatar.head import HeadModel
    from geoavatar.head.params import HeadParams
    from geoavatar.prep.coverage import capture_check, eye_openness

    data, _ = load_tracking_head(config)
    values = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in params.items()}
    if "static_offset" in values:
        values["static_offset"] = values["static_offset"].reshape(1, -1, 3)
    splits = {"train": np.arange(train), "test": np.arange(train, count)}
    return capture_check(HeadModel(data), HeadParams.from_npz(values), viewmat, splits, np.arange(count),
                         Path(config.out) / "coverage.png", detected_eyes=eye_openness(landmarks))


@dataclass
class _OverlayBlock:
    """What a worker needs to draw the overlay of some dataset rows (picklable; arrays hold those rows only)."""

    config: PrepareConfig  # picklable (_worker_config): names the head model
    rows: np.ndarray  # [n] dataset rows
    frame_paths: list[Path]
    params: dict[str, np.ndarray]  # the npz layout, per-frame keys [n, ...]
    viewmat: np.ndarray  # [4, 4]
    K: np.ndarray  # [n, 3, 3]
    detected: np.ndarray  # [n, L, 2] MediaPipe's filtered landmarks (the model's embedded ones)
    projected: np.ndarray  # [n, L, 2] the fit's
    lost: np.ndarray  # [n] bool: no face found, landmarks interpolated


def _overlay_blocks(config: PrepareConfig, work: Path, rows) -> list[_OverlayBlock]:
    """The rows asked for, OVERLAY_BLOCK at a time, with their inputs (each npz read once)."""
    marks = dict(np.load(work / "landmarks.npz"))
    fit = dict(np.load(fit_file(config, work)))
    keep, found, ids = marks["keep"], marks["found"], fit["landmark_ids"]
    rows = np.arange(len(keep)) if rows is None else np.asarray(rows, np.int64)
    params = {k[len("param_"):]: fit[k] for k in fit if k.startswith("param_")}
    blocks = []
    for a, b in split_range(len(rows), math.ceil(len(rows) / OVERLAY_BLOCK)):
        chosen = rows[a:b]
        blocks.append(_OverlayBlock(
            config=_worker_config(config), rows=chosen,
            frame_paths=[work / "frames" / f"{keep[r]:05d}.png" for r in chosen],
            params={k: v if k in ("shape", "static_offset") else v[chosen] for k, v in params.items()},
            viewmat=fit["viewmat"], K=fit["K"][chosen], detected=marks["filtered"][chosen][:, ids, :2],
            projected=fit["projected"][chosen], lost=~found[keep[chosen]]))
    return blocks


def _overlay_task(block: _OverlayBlock) -> list[np.ndarray]:
    """The overlay pictures of a block's rows (in a worker; the head model is built once per process)."""
    import torch

    from geoavatar.head import HeadModel, npz_frame
    from geoavatar.prep.overlay import overlay_frame

    config = block.config
    head = worker_cache(f"overlay-head:{config.head}:{config.flame_dir}:{config.flame_landmarks}",
                        lambda: HeadModel(load_tracking_head(config)[0]))
    shown = "photometric" if config.photometric else "landmark fit"
    params = {k: torch.as_tensor(v) for k, v in block.params.items()}
    viewmat = torch.as_tensor(block.viewmat, dtype=torch.float32)
    pictures = []
    for i, row in enumerate(block.rows):
        with torch.no_grad():
            vertices = head.forward_params(npz_frame(params, i)).vertices[0]
        caption = f"{row:05d}  {shown}" + ("  no face: interpolated" if block.lost[i] else "")
        pictures.append(overlay_frame(_read_png(block.frame_paths[i]), vertices, head.faces, viewmat,
                                      torch.as_tensor(block.K[i], dtype=torch.float32), block.detected[i],
                                      block.projected[i], caption=caption, flagged=bool(block.lost[i])))
        report_progress(1)
    return pictures


def overlay_frames(config: PrepareConfig, work: Path, rows=None):
    """Yield (row, overlay picture) for the rows (dataset timesteps) asked for (all by default), each captioned
    with its timestep and the fit shown; a frame where no face was found (interpolated) is flagged."""
    for block in _overlay_blocks(config, work, rows):
        yield from zip(block.rows.tolist(), _overlay_task(block))


def write_overlay(config: PrepareConfig, work: Path, path: Path, pool: WorkerPool) -> Path:
    """OUT/overlay.mp4: the pictures drawn in the workers, a few blocks ahead, encoded here in order."""
    from geoavatar.prep.overlay import write_video

    frames = np.load(work / "frames.npz")
    blocks = _overlay_blocks(config, work, None)
    bar = _bar(config, sum(len(block.rows) for block in blocks), "overlay video")
    try:
        pictures = (picture for done in pool.imap(_overlay_task, blocks, bar.update, window=2 * pool.workers)
                    for picture in done)
        return write_video(path, pictures, float(frames["fps"]))
    finally:
        bar.close()


# --- the run ----------------------------------------------------------------------------------------

_RUNNERS = {"frames": stage_frames, "landmarks": stage_landmarks, "masks": stage_masks, "tracking": stage_tracking,
            "photometric": stage_photometric, "write": stage_write, "sound": stage_sound}


def run_prepare(config: PrepareConfig) -> Path:
    """Run (or resume) every stage; returns OUT/dataset."""
    video, out = Path(config.video), Path(config.out)
    if config.size < 32:
        raise PrepareError(f"--size must be at least 32 pixels, got {config.size}")
    if not 0.0 <= config.test_fraction < 1.0:
        raise PrepareError(f"--test-fraction must be in [0, 1), got {config.test_fraction}")
    if not video.is_file():
        raise PrepareError(f"video '{video}': file not found")
    if config.workers is not None and config.workers < 1:
        raise PrepareError(f"--workers must be at least 1, got {config.workers}")
    created = not out.exists()
    work = out / WORK
    try:
        work.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # --out is a file, or lies under one, or in a folder that cannot be written
        raise PrepareError(f"{out}: cannot make the output folder ({err.strerror}: {err.filename})") from err
    stages = _Stages(work, _stage_keys(config))
    timings: dict[str, float] = {}
    completed_any = False
    try:
        with WorkerPool(config.workers or default_workers()) as pool:
            for stage in STAGES:
                if stages.done(stage):
                    config.log(f"prepare: stage '{stage}' is complete, skipped")
                    completed_any = True
                    continue
                stages.start(stage)
                start, cpu = time.perf_counter(), time.process_time() + pool.cpu_seconds()
                info = _RUNNERS[stage](config, work, pool)
                timings[stage] = time.perf_counter() - start
                cpu = time.process_time() + pool.cpu_seconds() - cpu  # this process and its workers
                stages.finish(stage, {**info, "seconds": timings[stage], "cpu_seconds": cpu})
                completed_any = True
    except PrepareError:
        if created and not completed_any:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return out / "dataset"


__all__ = ["PrepareConfig", "STAGES", "run_prepare", "load_tracking_head", "photometric_inputs", "overlay_frames",
           "write_overlay"]
