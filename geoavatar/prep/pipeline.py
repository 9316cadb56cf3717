"""`geoavatar prepare`: video -> dataset, in resumable stages.

    run_prepare(PrepareConfig(video="talk.mp4", out="data/talk"))

Output folder OUT:
    OUT/dataset/          the VHAP / GaussianAvatars layout (LayoutWriter: appears atomically)
    OUT/overlay.mp4       tracked mesh + landmarks over the frames (green: MediaPipe, red: model)
    OUT/report.json       per-frame reprojection error, frames without a face (missing_source_frames: source
                          frame numbers; interpolated_frames: dataset timesteps), focal, fps
    OUT/.prepare/         work files of the stages and their completion markers

Stages (each writes `.prepare/<stage>.json` last, holding its key; a re-run skips a stage whose marker
holds the key it would have now, and redoes it and every stage that depends on it otherwise):
    frames     decode, face detection on whole frames, smoothed square crop, crops as PNG
    landmarks  face mesh on the crops, One-Euro filtering, confidence, missing frames
    masks      selfie segmentation x landmark head region (see geoavatar.prep.masks)
    tracking   the head-model fit (geoavatar.prep.tracking)
    photometric  every frame refined against its crop (geoavatar.prep.photometric); with --no-photometric it only
               records that it was skipped and the dataset is written from the landmark fit
    write      the dataset through LayoutWriter, then the overlay video and the report

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
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from geoavatar.io.atomic import atomic_write_json, atomic_write_npz, atomic_write_png
from geoavatar.prep.errors import PrepareError

STAGES = ("frames", "landmarks", "masks", "tracking", "photometric", "write")
# Part of a stage's key: bumped when the stage's method changes, so a re-run redoes that stage (and the
# ones depending on it) instead of keeping outputs made the old way.
STAGE_VERSIONS = {"frames": 1, "landmarks": 1, "masks": 2, "tracking": 2, "photometric": 2, "write": 4}
# The stages whose outputs a stage reads: a rerun of one redoes these dependants.
DEPENDS_ON: dict[str, tuple[str, ...]] = {
    "frames": (),
    "landmarks": ("frames",),
    "masks": ("frames", "landmarks"),
    "tracking": ("frames", "landmarks"),
    "photometric": ("frames", "landmarks", "masks", "tracking"),
    "write": ("frames", "landmarks", "masks", "tracking", "photometric"),
}
WORK = ".prepare"
# Torch (and native rasterizer) threads of the photometric stage. Its renders are small (128 px, ~10k Gaussians), so
# every parallel region is short: on a 2-core machine shared with other jobs, 2 threads made it 26x slower in wall
# time and 21x in CPU time than 1 thread (BENCHMARKS.md, photometric tracking); 1 thread costs little where it is quiet.
PHOTOMETRIC_THREADS = 1
UNKEYED = "-"  # a PrepareConfig field no stage output depends on (where to write, logging)


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


def stage_frames(config: PrepareConfig, work: Path) -> dict:
    from geoavatar.prep.landmarks import FaceDetector
    from geoavatar.prep.video import crop_square, decode_frames, probe_video, smooth_crop_boxes

    info = probe_video(config.video)
    indices, centres, sizes, scores = [], [], [], []
    with FaceDetector() as detect, _bar(config, config.max_frames or info.num_frames or None, "detect faces") as bar:
        for index, rgb in decode_frames(config.video, config.fps, config.max_frames):
            box = detect(rgb)
            indices.append(index)
            centres.append(box.centre if box else np.zeros(2))
            sizes.append(box.size if box else 0.0)
            scores.append(box.score if box else 0.0)
            bar.update(1)
    found = np.array(scores) > 0
    if len(indices) < config.min_frames:
        raise PrepareError(
            f"video '{config.video}': {len(indices)} frame(s) after --fps/--max-frames, fewer than the "
            f"{config.min_frames} needed (train and test frames)"
        )
    if not found.any():
        raise PrepareError(f"video '{config.video}': no face was found in any of its {len(indices)} frames")
    boxes = smooth_crop_boxes(np.array(centres), np.array(sizes), found, (info.width, info.height),
                              config.crop_scale, config.crop_sigma)
    frames_dir = work / "frames"
    shutil.rmtree(frames_dir, ignore_errors=True)
    frames_dir.mkdir(parents=True)
    by_index = {idx: k for k, idx in enumerate(indices)}
    with _bar(config, len(indices), "crop") as bar:
        for index, rgb in decode_frames(config.video, config.fps, config.max_frames):
            k = by_index[index]
            atomic_write_png(frames_dir / f"{k:05d}.png", crop_square(rgb, boxes[k], config.size), compress_level=1)
            bar.update(1)
    source_fps = info.fps
    fps = min(config.fps, source_fps) if config.fps else source_fps
    atomic_write_npz(work / "frames.npz", source_index=np.array(indices), boxes=boxes, presence=np.array(scores),
                detected=found, frame_size=np.array([info.width, info.height]), fps=np.array(fps))
    return {"frames": len(indices), "no_face_detected": [int(indices[k]) for k in np.flatnonzero(~found)],
            "video": asdict(info)}


def stage_landmarks(config: PrepareConfig, work: Path) -> dict:
    from geoavatar.prep.landmarks import FaceMesh, filter_landmarks, landmark_confidence
    from geoavatar.prep.video import fill_missing

    frames = np.load(work / "frames.npz")
    count = len(frames["source_index"])
    raw = np.zeros((count, 478, 3))
    found = np.zeros(count, bool)
    with FaceMesh() as mesh, _bar(config, count, "landmarks") as bar:
        for k in range(count):
            points = mesh(_read_png(work / "frames" / f"{k:05d}.png"))
            if points is not None:
                raw[k], found[k] = points, True
            bar.update(1)
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


def stage_masks(config: PrepareConfig, work: Path) -> dict:
    from geoavatar.prep.masks import PersonSegmenter, foreground_mask

    marks = np.load(work / "landmarks.npz")
    keep, points = marks["keep"], marks["filtered"]
    masks_dir = work / "masks"
    shutil.rmtree(masks_dir, ignore_errors=True)
    masks_dir.mkdir(parents=True)
    coverage = []
    with PersonSegmenter(config.mask_backend) as segment, _bar(config, len(keep), "masks") as bar:
        for row, k in enumerate(keep):
            rgb = _read_png(work / "frames" / f"{k:05d}.png")
            mask = foreground_mask(segment(rgb), points[row])
            atomic_write_png(masks_dir / f"{k:05d}.png", mask, compress_level=1)
            coverage.append(float(mask.mean() / 255.0))
            bar.update(1)
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


def stage_tracking(config: PrepareConfig, work: Path) -> dict:
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


def stage_photometric(config: PrepareConfig, work: Path) -> dict:
    """Refine every frame's parameters against the crops (masked photometric L1 + the landmark term)."""
    import torch

    from geoavatar.head import HeadModel
    from geoavatar.head.mouth import add_mouth_structure
    from geoavatar.head.params import HeadParams
    from geoavatar.prep.photometric import (LandmarkTargets, PhotometricTargets, crop_boxes, fit_photometric,
                                            residual_report, total_steps, weighted_vertex_ids)
    from geoavatar.prep.tracking import GROUP_OF, GROUP_WEIGHTS
    from geoavatar.render.camera import project
    from geoavatar.runtime import num_threads

    (work / "photometric.npz").unlink(missing_ok=True)
    if not config.photometric:
        return {"skipped": True}
    marks = np.load(work / "landmarks.npz")
    fit = np.load(work / "tracking.npz")
    keep = marks["keep"]
    data, _ = load_tracking_head(config)
    head = HeadModel(add_mouth_structure(data, kind="geoavatar"))
    settings = photometric_config(config)
    params = {k[len("param_"):]: torch.as_tensor(fit[k], dtype=torch.float32) for k in fit.files if k.startswith("param_")}
    if "static_offset" in params:
        params["static_offset"] = params["static_offset"].reshape(1, -1, 3)
    init = HeadParams.from_npz(params)
    images = np.stack([_read_png(work / "frames" / f"{k:05d}.png") for k in keep])
    masks = np.stack([_read_png(work / "masks" / f"{k:05d}.png") for k in keep])
    # No face found (landmarks interpolated): the image is not of the face the parameters say (a hand, a
    # turned-away head, a blank frame), so it gets no image term; its parameters follow the interpolated
    # landmarks (low confidence), the priors and the temporal smoothness with the refined neighbours.
    masks[~marks["found"][keep]] = 0
    viewmat = torch.as_tensor(fit["viewmat"], dtype=torch.float32).expand(len(keep), 4, 4)
    K = torch.as_tensor(fit["K"], dtype=torch.float32)
    boxes = crop_boxes(head, init, viewmat, K, weighted_vertex_ids(head), settings.crop_margin)
    targets = PhotometricTargets.from_arrays(images, masks, viewmat.numpy(), K.numpy(), max(settings.sizes), boxes)
    ids = head.landmark_ids.cpu().numpy()
    points = marks["filtered"]
    landmarks = LandmarkTargets(
        points=torch.as_tensor(points[:, ids, :2], dtype=torch.float32),
        size=torch.as_tensor(np.linalg.norm(points[:, 10, :2] - points[:, 152, :2], axis=-1), dtype=torch.float32).clamp_min(1.0),
        weights=torch.tensor([GROUP_WEIGHTS[GROUP_OF.get(int(i), "face_oval_lower")] for i in ids], dtype=torch.float32),
        confidence=torch.as_tensor(marks["confidence"], dtype=torch.float32).clamp(0.05, 1.0))
    bar = _bar(config, total_steps(settings, len(keep)), "photometric")
    try:
        with torch.enable_grad(), num_threads(PHOTOMETRIC_THREADS):
            result = fit_photometric(head, init, targets, settings, landmarks=landmarks, progress=bar.update)
    finally:
        bar.close()
    with torch.no_grad():
        pixels, _ = project(head.forward_params(result.params, vertex_ids=head.landmark_vertex_ids).landmarks, viewmat, K)
    width = np.maximum(np.linalg.norm(points[:, 234, :2] - points[:, 454, :2], axis=-1), 1e-6)
    errors = np.median((pixels - landmarks.points).norm(dim=-1).numpy(), axis=1) / width
    fitted = {k: v.numpy() for k, v in result.params.to_npz().items() if k != "static_offset"}
    if "param_static_offset" in fit.files:
        fitted["static_offset"] = fit["param_static_offset"]
    atomic_write_npz(work / "photometric.npz", **{f"param_{k}": v for k, v in fitted.items()}, focal=fit["focal"],
                viewmat=fit["viewmat"], K=fit["K"], projected=pixels.numpy(), landmark_ids=ids, errors=errors,
                residual=result.residual, residual_before=result.residual_before)
    for line in result.log:
        config.log(f"prepare: photometric {line}")
    summary = residual_report(result.residual, result.residual_before)
    return {"residual_before": summary["mean_before"], "residual": summary["mean"],
            "median_error": float(np.median(errors)), "log": result.log}


def stage_write(config: PrepareConfig, work: Path) -> dict:
    from geoavatar.data.layout import LayoutWriter
    from geoavatar.data.splits import SplitConfig

    frames = np.load(work / "frames.npz")
    marks = np.load(work / "landmarks.npz")
    fit = np.load(fit_file(config, work))
    keep = marks["keep"]
    count = len(keep)
    test = max(1, math.ceil(config.test_fraction * count)) if config.test_fraction > 0 else 0
    dataset = Path(config.out) / "dataset"
    params = {k[len("param_"):]: fit[k] for k in fit.files if k.startswith("param_")}
    with LayoutWriter(dataset, head_model=config.head, image_size=(config.size, config.size), shape=params["shape"],
                      static_offset=params.get("static_offset"),
                      background=(1.0, 1.0, 1.0), source=str(Path(config.video).name),
                      split=SplitConfig(test_frames=test), overwrite=True) as writer, _bar(config, count, "write") as bar:
        for t, k in enumerate(keep):
            frame = {name: params[name][t] for name in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")}
            writer.add_frame(t, _read_png(work / "frames" / f"{k:05d}.png"), frame, fit["viewmat"], fit["K"][t],
                             mask=_read_png(work / "masks" / f"{k:05d}.png"))
            bar.update(1)
    if config.overlay:
        write_overlay(config, work, Path(config.out) / "overlay.mp4")
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
    if "residual" in fit.files:  # masked L1 of the photometric fit's appearance model, 128 px face crops
        from geoavatar.prep.photometric import residual_report

        report["photometric_residual"] = residual_report(fit["residual"], fit["residual_before"])  # null: no face
    atomic_write_json(Path(config.out) / "report.json", report)
    return {"dataset": str(dataset), "frames": int(count), "test_frames": int(test)}


def overlay_frames(config: PrepareConfig, work: Path, rows=None):
    """Yield (row, overlay picture) for the rows (dataset timesteps) asked for (all by default), each captioned
    with its timestep and the fit shown; a frame where no face was found (interpolated) is flagged."""
    import torch

    from geoavatar.head import HeadModel, npz_frame
    from geoavatar.prep.overlay import overlay_frame

    marks = np.load(work / "landmarks.npz")
    fit = np.load(fit_file(config, work))
    data, _ = load_tracking_head(config)
    head = HeadModel(data)
    keep, found = marks["keep"], marks["found"]
    ids = fit["landmark_ids"]
    shown = "photometric" if config.photometric else "landmark fit"
    params = {k[len("param_"):]: torch.as_tensor(fit[k]) for k in fit.files if k.startswith("param_")}
    viewmat = torch.as_tensor(fit["viewmat"], dtype=torch.float32)
    for row in rows if rows is not None else range(len(keep)):
        frame_params = npz_frame(params, row)
        with torch.no_grad():
            vertices = head.forward_params(frame_params).vertices[0]
        image = _read_png(work / "frames" / f"{keep[row]:05d}.png")
        lost = not found[keep[row]]
        caption = f"{row:05d}  {shown}" + ("  no face: interpolated" if lost else "")
        yield row, overlay_frame(image, vertices, head.faces, viewmat, torch.as_tensor(fit["K"][row], dtype=torch.float32),
                                 marks["filtered"][row, ids, :2], fit["projected"][row], caption=caption, flagged=lost)


def write_overlay(config: PrepareConfig, work: Path, path: Path) -> Path:
    from geoavatar.prep.overlay import write_video

    frames = np.load(work / "frames.npz")
    count = len(np.load(work / "landmarks.npz")["keep"])
    bar = _bar(config, count, "overlay video")

    def pictures():
        for _, picture in overlay_frames(config, work):
            bar.update(1)
            yield picture

    try:
        return write_video(path, pictures(), float(frames["fps"]))
    finally:
        bar.close()


# --- the run ----------------------------------------------------------------------------------------

_RUNNERS = {"frames": stage_frames, "landmarks": stage_landmarks, "masks": stage_masks, "tracking": stage_tracking,
            "photometric": stage_photometric, "write": stage_write}


def run_prepare(config: PrepareConfig) -> Path:
    """Run (or resume) every stage; returns OUT/dataset."""
    video, out = Path(config.video), Path(config.out)
    if config.size < 32:
        raise PrepareError(f"--size must be at least 32 pixels, got {config.size}")
    if not 0.0 <= config.test_fraction < 1.0:
        raise PrepareError(f"--test-fraction must be in [0, 1), got {config.test_fraction}")
    if not video.is_file():
        raise PrepareError(f"video '{video}': file not found")
    created = not out.exists()
    work = out / WORK
    work.mkdir(parents=True, exist_ok=True)
    stages = _Stages(work, _stage_keys(config))
    timings: dict[str, float] = {}
    completed_any = False
    try:
        for stage in STAGES:
            if stages.done(stage):
                config.log(f"prepare: stage '{stage}' is complete, skipped")
                completed_any = True
                continue
            stages.start(stage)
            start, cpu = time.perf_counter(), time.process_time()
            info = _RUNNERS[stage](config, work)
            timings[stage] = time.perf_counter() - start
            stages.finish(stage, {**info, "seconds": timings[stage], "cpu_seconds": time.process_time() - cpu})
            completed_any = True
    except PrepareError:
        if created and not completed_any:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return out / "dataset"


__all__ = ["PrepareConfig", "STAGES", "run_prepare", "load_tracking_head", "overlay_frames", "write_overlay"]
