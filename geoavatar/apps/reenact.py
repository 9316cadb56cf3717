"""`geoavatar reenact RUN --driver DATASET | --driver-video VIDEO`: cross-re-enactment, the driver's motion on
the avatar.

The driver is a tracked dataset (`--driver`: any layout `geoavatar train` reads) or a video
(`--driver-video`), which is tracked first by the code of `geoavatar prepare` (geoavatar.prep.pipeline:
crop, landmarks, masks, the landmark fit with the avatar's head model; prepare's photometric stage, on by
default there, only with `--photometric` here: it costs ~0.4 CPU s per frame) at `--driver-size` pixels
(default 256). The driver keeps its own identity; only its motion is transferred, as below. Where the
tracked driver goes:

    RUN/drivers/<video stem>-<8 hex of its absolute path>[-photometric]/    (default)
    --driver-cache DIR                                                       (a folder of your choice)

holding what `geoavatar prepare VIDEO --out DIR` writes (DIR/dataset, DIR/report.json; no overlay).
The next call with the same video reuses it: prepare's stages are keyed by their settings and by the
video file's path, size and time, so nothing is redone unless one of those changed (another
--driver-size, --photometric, or an edited video redoes the stages concerned). With --photometric the
default folder differs, so the landmark-only and the photometric track are both kept. Frames where no
face is found are interpolated (prepare's default) and listed in DIR/report.json. The output video
plays at the driver video's frame rate unless --fps says otherwise.

Parameters of every driver frame (FLAME npz layout; what is taken from whom), by --transfer (driven_params):

    shape, static_offset        the avatar's (its identity, from the run)
    expr, jaw, eyes, neck,      absolute: the driver's values
      rotation                  relative (--relative): the avatar's neutral + the driver's change from its neutral
                                  expr = expr_avatar_neutral + (expr_driver(t) - expr_driver_neutral)
                                  R    = R_driver(t) R_driver_neutral^T R_avatar_neutral   (each joint,
                                         and the global rotation: rotation matrices, not axis-angles)
                                statistics (apps/expression_transfer.py): expr, jaw and eyes standardised by the
                                  driver's statistics and mapped to the avatar's training-set statistics; neck and
                                  rotation as relative
                                subspace: relative, then expr projected onto the expressions the avatar was trained
                                  on and clamped to their range, jaw and eyes clamped to their training range
    translation                 the avatar's neutral translation + the driver's displacement from its
                                neutral frame (tracked translations depend on each video's camera, so
                                only the motion carries over); with --camera driver the driver's own

"Neutral" is a frame of each sequence, `--driver-neutral` / `--avatar-neutral`: `first` (default),
`mean` (the mean over the sequence's frames, the avatar's training frames; the mean of axis-angles
for rotations, fine for the small angles of a talking head), or a timestep number. Relative transfer
is what users of GaussianAvatars / FlashAvatar / NerFace ask for: tracked expression coefficients
carry some of the tracked person's identity (a neutral face is not expr = 0), so transferring the
change from a neutral frame onto the avatar's own neutral frame leaks less of the driver's face shape.

The driver must be tracked with the same head model as the avatar (expression coefficients mean
nothing across models); a model with fewer modes uses the leading ones (zero-padded).

Camera: by default the avatar's own dataset camera (that of its neutral frame, or its first frame
with `mean`), at the run's resolution (or --resolution): the driver's camera may differ (another focal
length, another distance). `--camera driver` renders each frame with the driver's camera instead, for drivers whose
tracker moves the camera rather than the head (INSTA / metrical-tracker data). The mouth deformer
runs with T = 0 (novel animation, as the paper does at inference).

Output: an mp4 with driver | avatar side by side (the driver's frame scaled to the render's height),
or the avatar alone with --no-side-by-side.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal, Optional, Sequence

import torch
from torch import Tensor

from geoavatar.apps.common import (RENDER_THREADS, VIDEO_DIR, RunPath, check_resolution, check_threads, default_output, progress,
                                   record_camera, render_params, run_background, side_by_side, torch_threads)
from geoavatar.apps.expression_transfer import (DEFAULT_TRANSFER, TransferMode, TransferStatistics, resolve_transfer,
                                                statistics_transfer, subspace_projection, transfer_mode,
                                                transfer_statistics)
from geoavatar.data import DataConfig, HeadAvatarDataset, evenly_spaced, open_subject
from geoavatar.data.dataset import item_camera
from geoavatar.data.subject import Subject
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.eval.cross import DrivenPicture
from geoavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from geoavatar.head.params import SUBJECT_KEYS, HeadParams
from geoavatar.imaging import fit_height, to_uint8
from geoavatar.io.video import Mp4Writer
from geoavatar.prep.errors import PrepareError
from geoavatar.render import composite_target
from geoavatar.train.checkpoint import LoadedRun, RunError, open_run
from geoavatar.train.run_frames import RunFrames

ROTATION_KEYS = ("rotation", "neck_pose", "jaw_pose", "eyes_pose")  # axis-angle, 3 numbers per joint
TRANSFERRED_KEYS = ("expr", *ROTATION_KEYS, "translation")


def reference_frame(values: dict[str, Tensor], timesteps: list[int], spec: str, mean_over: list[int] | None = None,
                    what: str = "--driver-neutral") -> dict[str, Tensor]:
    """The neutral frame of a sequence: per-frame keys [1, ...] of row `spec` ('first', 'mean', a timestep).

    values: per-timestep keys [T, ...]; mean_over: the timesteps averaged by 'mean' (default: all)."""
    if spec == "first":
        rows = [0]
    elif spec == "mean":
        wanted = set(mean_over if mean_over else timesteps)
        rows = [i for i, t in enumerate(timesteps) if t in wanted]
    else:
        try:
            timestep = int(spec)
        except ValueError:
            raise OptionError(f"{what} must be 'first', 'mean' or a timestep number, got {spec!r}") from None
        if timestep not in timesteps:
            raise OptionError(f"{what} {timestep}: not a timestep of the sequence ({timesteps[0]}..{timesteps[-1]})")
        rows = [timesteps.index(timestep)]
    index = torch.as_tensor(rows, dtype=torch.long, device=values["expr"].device)
    return {key: values[key].index_select(0, index).mean(dim=0, keepdim=True) for key in TRANSFERRED_KEYS}


def _match_width(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Zero-pad the last dimension of the narrower of a, b (expression coefficients of different lengths)."""
    width = max(a.shape[-1], b.shape[-1])
    pad = lambda x: torch.nn.functional.pad(x, (0, width - x.shape[-1]))  # noqa: E731
    return pad(a), pad(b)


def _compose_relative(driver: Tensor, driver_ref: Tensor, avatar_ref: Tensor) -> Tensor:
    """Axis-angles [T, 3k]: R_driver R_driver_ref^T R_avatar_ref per joint (k joints of 3 numbers)."""
    count = driver.shape[0]
    d = axis_angle_to_matrix(driver.reshape(count, -1, 3))  # [T, k, 3, 3]
    d0 = axis_angle_to_matrix(driver_ref.reshape(1, -1, 3))  # [1, k, 3, 3]
    a0 = axis_angle_to_matrix(avatar_ref.reshape(1, -1, 3))
    return matrix_to_axis_angle(d @ d0.transpose(-1, -2) @ a0).reshape(count, -1)


def driven_params(
    identity: dict[str, Tensor],  # shape [S], static_offset [1, V, 3] (optional): the avatar's
    avatar_ref: dict[str, Tensor],  # the avatar's neutral frame, per-frame keys [1, ...]
    driver: dict[str, Tensor],  # the driver's per-timestep keys [T, ...]
    driver_ref: dict[str, Tensor],  # the driver's neutral frame [1, ...]
    mode: TransferMode | bool = "absolute",  # a bool is the old `relative` flag
    driver_translation: bool = False,  # keep the driver's absolute translation (--camera driver)
    learned: TransferStatistics | None = None,  # for 'statistics' / 'subspace': transfer_statistics(...)
) -> dict[str, Tensor]:
    """Per-frame parameters [T, ...] of the avatar driven by `driver` in transfer `mode` (rules in the module
    docstring and in apps/expression_transfer.py)."""
    mode = transfer_mode(mode)
    if mode in ("statistics", "subspace") and learned is None:
        raise ValueError(f"driven_params: transfer {mode!r} needs the statistics "
                         "(expression_transfer.transfer_statistics)")
    out: dict[str, Tensor] = {}
    driver_expr, ref_expr = _match_width(driver["expr"], driver_ref["expr"])
    if mode == "absolute":
        out["expr"] = driver["expr"].clone()
        for key in ROTATION_KEYS:
            out[key] = driver[key].clone()
    else:
        avatar_expr, delta = _match_width(avatar_ref["expr"], driver_expr - ref_expr)
        out["expr"] = avatar_expr + delta  # [T, E]
        # every joint in one composition (per joint the same arithmetic; one call, not four: drive poses per frame)
        stacked = [torch.cat([values[key] for key in ROTATION_KEYS], -1) for values in (driver, driver_ref, avatar_ref)]
        composed = _compose_relative(*stacked)  # [T, 15]
        widths = [driver[key].shape[-1] for key in ROTATION_KEYS]
        out.update((key, value.contiguous()) for key, value in zip(ROTATION_KEYS, torch.split(composed, widths, dim=-1)))
    if mode == "statistics":
        out.update(statistics_transfer(driver, learned))  # expr, jaw, eyes from the two sequences' statistics
    elif mode == "subspace":
        out.update(subspace_projection(out, learned))  # the relative result kept inside the training expressions
    if driver_translation:
        out["translation"] = driver["translation"].clone()
    else:
        out["translation"] = avatar_ref["translation"] + (driver["translation"] - driver_ref["translation"])
    out.update({key: value for key, value in identity.items() if key in SUBJECT_KEYS})
    return out


def frame_of(params: dict[str, Tensor], row: int) -> HeadParams:
    return HeadParams.from_npz(params).frame(row)


def open_driver(driver: Path, run: LoadedRun) -> Subject:
    try:
        subject = open_subject(driver)
    except GeoAvatarError as err:  # DatasetError, a FLAME file error: name the option
        raise RunError(f"--driver {driver}: {err}") from err
    if subject.head_model != run.info.head_model:
        raise RunError(f"--driver {driver}: tracked with head model '{subject.head_model}', but the avatar uses "
                       f"'{run.info.head_model}'; expression and pose parameters do not carry across head models")
    return subject


def driven_clip(run: LoadedRun, frames: RunFrames, driver_root: Path, mode: TransferMode | bool = "absolute",
                driver_neutral: str = "first", avatar_neutral: str = "first",
                driver_translation: bool = False) -> tuple[Subject, dict[str, Tensor]]:
    """The driver (`--driver`) and the avatar's parameters [T, ...] for each of its timesteps in transfer `mode` (a
    bool is the old `relative` flag); reenact's video, `eval --driver` and `export --format web` pose these."""
    subject = open_driver(driver_root, run)
    return subject, subject_params(run, frames, subject, mode, driver_neutral, avatar_neutral, driver_translation)


def subject_params(run: LoadedRun, frames: RunFrames, subject: Subject, mode: TransferMode | bool = "absolute",
                   driver_neutral: str = "first", avatar_neutral: str = "first",
                   driver_translation: bool = False) -> dict[str, Tensor]:
    """driven_params for every timestep of an opened driver, with the neutral frames of the module docstring and,
    for statistics / subspace transfer, the two sequences' statistics."""
    driver_values = {k: v.to(frames.device) for k, v in subject.params.items()}
    driver_ref = reference_frame(driver_values, list(subject.timesteps), driver_neutral, what="--driver-neutral")
    avatar_ref = reference_frame(frames.values.to_npz(), frames.timesteps, avatar_neutral,
                                 mean_over=run.info.timesteps.get("train"), what="--avatar-neutral")
    learned = transfer_statistics(frames, driver_values) if transfer_mode(mode) in ("statistics", "subspace") else None
    return driven_params(frames.identity(), avatar_ref, driver_values, driver_ref, mode, driver_translation, learned)


DRIVERS_DIR = "drivers"  # RUN/drivers/<video stem>-<hash>/: tracked driver videos, reused by later calls
DRIVER_SIZE = 256  # side of the driver's face crop: enough for the face mesh, cheap to track


def driver_cache_dir(run_dir: Path, video: Path, photometric: bool = False) -> Path:
    """RUN/drivers/<stem>-<8 hex of the video's absolute path>[-photometric]: one folder per video file."""
    digest = hashlib.sha256(str(Path(video).resolve()).encode()).hexdigest()[:8]
    return Path(run_dir) / DRIVERS_DIR / f"{Path(video).stem}-{digest}{'-photometric' if photometric else ''}"


def prepare_driver(video: Path, cache: Path, head_model: str, size: int = DRIVER_SIZE, photometric: bool = False,
                   flame_dir: Path | None = None, progress: bool = True) -> tuple[Path, float]:
    """Track a driver video with `geoavatar prepare`'s pipeline into `cache` (resumed / reused by its stage keys).

    Returns (the dataset folder, the video's frame rate after prepare). PrepareError naming --driver-video on bad
    input (missing file, not a video, no face); as with prepare, a folder in which no stage completed is removed
    (and RUN/drivers when this call made it for nothing)."""
    from geoavatar.prep.pipeline import PrepareConfig, run_prepare

    cache = Path(cache)
    parent_created = not cache.parent.exists()
    config = PrepareConfig(video=Path(video), out=cache, head=head_model, size=size, flame_dir=flame_dir,
                           photometric=photometric, overlay=False, progress=progress,
                           log=lambda message: print(message.replace("prepare:", "reenact: driver", 1)))
    try:
        dataset = run_prepare(config)
    except PrepareError as err:
        if parent_created and cache.parent.is_dir() and not any(cache.parent.iterdir()):
            cache.parent.rmdir()  # RUN/drivers made for nothing
        raise PrepareError(f"--driver-video: {err}") from err
    report = json.loads((cache / "report.json").read_text())
    return dataset, float(report["fps"])


@dataclass
class DrivingOptions:
    """How a driver drives the avatar: the options `reenact` and `eval --driver` share."""

    transfer: TransferMode = DEFAULT_TRANSFER
    driver_neutral: str = "first"
    avatar_neutral: str = "first"
    camera: str = "avatar"  # avatar: the avatar's dataset camera; driver: each driver frame's
    driver_split: str = "all"
    data: Path | None = None  # the avatar's dataset folder, when it moved since training
    backend: str = "auto"
    resolution: int | None = None  # longer side of the renders (None: the run's training resolution)


class DrivenAvatar:
    """An avatar driven by a tracked driver dataset, frame by frame: the one driving path of `reenact` and of
    `eval --driver` (parameters by driven_params, the camera and background below, T = 0)."""

    def __init__(self, run: LoadedRun, driver_root: Path, options: DrivingOptions):
        if options.camera not in ("avatar", "driver"):
            raise OptionError(f"--camera must be avatar or driver, got {options.camera!r}")
        self.run, self.options = run, options
        self.frames = frames = RunFrames(run)
        self.device = frames.device
        self.subject = open_driver(driver_root, run)
        self.row_of = {t: i for i, t in enumerate(self.subject.timesteps)}
        self._params: dict[str, dict[str, Tensor]] = {}
        self.params(options.transfer)  # the neutral frames checked before any work
        self.dataset = HeadAvatarDataset(self.subject, options.driver_split, DataConfig(cache="none"), check_head=False)
        if len(self.dataset) == 0:
            raise OptionError(f"--driver-split {options.driver_split}: the driver has no frames in this split")
        self.resolution = options.resolution or run.info.resolution
        self.fixed_camera = self._avatar_camera(frames) if options.camera == "avatar" else None
        self.background = run_background(run).to(self.device)

    def _avatar_camera(self, frames: RunFrames):
        """The camera of the avatar's neutral frame (its first frame for 'first' and 'mean') at the renders' size."""
        run = self.run
        avatar_root = Path(self.options.data) if self.options.data is not None else run.info.data_root
        if not avatar_root.is_dir():
            raise RunError(f"{run.info.run_dir}: its dataset folder {avatar_root} is not found (the camera comes from "
                           "it); pass --data DIR, or --camera driver")
        neutral = self.options.avatar_neutral
        camera_timestep = frames.timesteps[0] if neutral in ("first", "mean") else int(neutral)
        return record_camera(open_subject(avatar_root), camera_timestep, self.resolution)

    def params(self, mode: TransferMode) -> dict[str, Tensor]:
        """The avatar's per-frame parameters [T, ...] driven in transfer `mode` (computed once per mode)."""
        if mode not in self._params:
            options = self.options
            self._params[mode] = subject_params(self.run, self.frames, self.subject, mode, options.driver_neutral,
                                                options.avatar_neutral, options.camera == "driver")
        return self._params[mode]

    def camera(self, item: dict):
        if self.fixed_camera is not None:
            return self.fixed_camera
        camera = item_camera(item)
        resolution = self.resolution
        if resolution is not None and max(camera.width, camera.height) > resolution:
            camera = camera.resized(resolution)
        return camera

    @torch.no_grad()
    def render(self, item: dict, mode: TransferMode | None = None) -> Tensor:
        """rgb [H, W, 3] in [0, 1]: the avatar driven by the driver's dataset item (default: the options' mode)."""
        params = self.params(mode or self.options.transfer)
        return render_params(self.run, frame_of(params, self.row_of[item["timestep"]]), self.camera(item), None,
                             self.background, self.options.backend)


    def pictures(self, modes: Sequence[str], max_frames: int | None = None) -> Iterator[DrivenPicture]:
        """(driver timestep, driver picture uint8, {mode: render uint8}) of `max_frames` driver frames spread evenly
        (all by default), each rendered in every transfer mode of `modes`: what `eval --driver` scores."""
        for index in evenly_spaced(len(self.dataset), max_frames):
            item = self.dataset[index]
            yield (int(item["timestep"]), to_uint8(driver_picture(item)),
                   {mode: to_uint8(self.render(item, mode)) for mode in modes})


def driver_picture(item: dict) -> Tensor:
    """[H, W, 3] the driver's frame as shown and scored: its photo on its background outside its mask."""
    return composite_target(item["image"], item["mask"], item["background"])


@torch.no_grad()
def reenact_video(
    run: LoadedRun,
    driver_root: Path,
    out: Path,
    options: DrivingOptions,
    max_frames: int | None = None,
    fps: float = 25.0,
    crf: int = 18,
    show_driver: bool = True,
    show_progress: bool = True,
    threads: int = RENDER_THREADS,
) -> int:
    """Write the re-enactment video; returns the number of frames. `threads`: CPU threads of the frame loop."""
    driven = DrivenAvatar(run, driver_root, options)
    with torch_threads(threads), Mp4Writer(out, fps=fps, crf=crf) as video:
        for index in progress(evenly_spaced(len(driven.dataset), max_frames), enabled=show_progress, desc="reenact"):
            item = driven.dataset[index]
            pred = to_uint8(driven.render(item))
            if show_driver:
                pred = side_by_side(fit_height(to_uint8(driver_picture(item)), pred.shape[0]), pred)
            video.write(pred)
    return video.frames


def reenact(
    run: RunPath,
    driver: Optional[Path] = None,
    out: Optional[Path] = None,
    relative: bool = False,
    transfer: Optional[TransferMode] = None,
    driver_neutral: str = "first",
    avatar_neutral: str = "first",
    camera: Literal["avatar", "driver"] = "avatar",
    driver_split: Literal["all", "train", "val", "test"] = "all",
    max_frames: Optional[int] = None,
    side_by_side: bool = True,
    fps: Optional[float] = None,
    crf: int = 18,
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
    driver_video: Optional[Path] = None,
    driver_cache: Optional[Path] = None,
    driver_size: Optional[int] = None,
    photometric: bool = False,
    threads: int = RENDER_THREADS,
    resolution: Optional[int] = None,
) -> int:
    """Cross-re-enactment: drive the avatar with another video's expression, jaw, eyes and head motion.

    The avatar keeps its identity (shape and static offsets); every frame of the driver gives the
    expression, the jaw/neck/eye rotations and the head rotation, transferred as --transfer says; the head's
    translation is the avatar's plus the driver's displacement. The driver is a tracked dataset (--driver) or a video
    (--driver-video), tracked first as `geoavatar prepare` does and cached (RUN/drivers/ by default) for the next call.
    Writes an mp4 of driver | avatar.

    Args:
        run: Run folder written by `geoavatar train` (the avatar).
        driver: Dataset folder of the driving video (any layout `geoavatar train` reads), tracked with the
            same head model as the avatar. Give this or --driver-video.
        out: Video file to write (default RUN/videos/reenact_<driver name>[_<transfer>].mp4, the transfer
            named unless it is the default); atomic.
        relative: The same as --transfer relative (kept from before --transfer existed).
        transfer: How the driver's expression, jaw and eyes become the avatar's: absolute (the driver's values),
            relative (the driver's change from its neutral frame onto the avatar's neutral frame), statistics
            (each coefficient standardised by the driver's statistics, mapped to the avatar's training-set
            statistics) or subspace (relative, then projected onto the expressions the avatar was trained on and
            clamped to their range). Head rotation and neck follow the driver's change from its neutral frame in
            every mode but absolute. Default: relative (docs/cross_reenactment.md).
        driver_neutral: The driver's neutral frame for relative transfer and for the translation: first, mean
            (over all its frames) or a timestep number.
        avatar_neutral: The avatar's neutral frame: first, mean (over its training frames) or a timestep.
        camera: avatar: the avatar's own dataset camera (default); driver: each driver frame's camera
            (for trackers that move the camera, not the head), with the driver's own translation.
        driver_split: Frames of the driver to use: all, train, val or test (INSTA protocol: its last frames).
        max_frames: Use only this many driver frames, spread evenly (default: all).
        side_by_side: Put the driver's frame left of the avatar.
        fps: Frames per second of the video (default: the driver video's rate with --driver-video, else 25).
        crf: H.264 quality (0 lossless ... 51 worst; 18 is visually lossless).
        data: The avatar's dataset folder, when it moved since training (its camera is read from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (FLAME-tracked data only).
        progress: Show progress bars.
        driver_video: A video of the driver (any file `geoavatar prepare` reads), tracked with the avatar's head
            model by prepare's pipeline, then used as --driver. Give this or --driver.
        driver_cache: Folder for the tracked driver video (default RUN/drivers/<video stem>-<hash>/); a later
            call with the same video and settings reuses it.
        driver_size: Side in pixels of the driver's face crop (default 256); --driver-video only.
        photometric: Refine the driver's tracking photometrically, as `prepare` does by default (slower: ~0.4 CPU s
            per frame); --driver-video only.
        threads: CPU threads of the rendering loop (posing and rasterizing). 1 by default, as `geoavatar drive`:
            a frame's tensors are small, and on a busy 2-core machine 2 threads made each frame 5-7x slower
            (OpenMP threads waiting for each other); more may pay on a quiet machine. Tracking a --driver-video
            keeps the process's threads.
        resolution: Longer side of the avatar's renders in pixels (default: the run's training resolution; at most
            the stored size of the camera's images).
    """
    mode = resolve_transfer(transfer, relative)
    check_driver_options(driver, driver_video, driver_cache, driver_size, photometric, "reenact")
    check_threads(threads)  # before a --driver-video is tracked
    check_resolution(resolution)
    loaded = open_run(run, device, flame_dir)
    driver, video_fps, driver_name = track_driver(loaded, driver, driver_video, driver_cache, driver_size, photometric,
                                                  flame_dir, progress)
    name = f"reenact_{driver_name}{'' if mode == DEFAULT_TRANSFER else '_' + mode}.mp4"
    target = out or default_output(loaded, VIDEO_DIR, name)
    options = DrivingOptions(mode, driver_neutral, avatar_neutral, camera, driver_split, data, backend, resolution)
    count = reenact_video(loaded, driver, target, options, max_frames, fps or video_fps or 25.0, crf, side_by_side,
                          progress, threads)
    shown = "driver | avatar" if side_by_side else "avatar"
    print(f"wrote {target} ({count} frames: {shown}, {mode} transfer)")
    return 0


def check_driver_options(driver: Path | None, driver_video: Path | None, driver_cache: Path | None,
                         driver_size: int | None, photometric: bool, command: str) -> None:
    """OptionError unless exactly one of --driver / --driver-video is given, with the options that go with it."""
    if (driver is None) == (driver_video is None):
        raise OptionError(f"{command}: give exactly one of --driver DATASET and --driver-video VIDEO")
    if driver_video is None and (driver_cache is not None or driver_size is not None or photometric):
        raise OptionError("--driver-cache, --driver-size and --photometric go with --driver-video, not --driver")
    if driver_size is not None and driver_size < 32:
        raise OptionError(f"--driver-size must be at least 32 pixels, got {driver_size}")


def dataset_name(root: Path) -> str:
    """A dataset's name: its folder's, or its parent's for prepare's OUT/dataset layout (`.../wojtek/dataset`)."""
    root = Path(root).resolve()
    return root.parent.name if root.name == "dataset" and root.parent.name else root.name


def track_driver(run: LoadedRun, driver: Path | None, driver_video: Path | None, driver_cache: Path | None = None,
                 driver_size: int | None = None, photometric: bool = False, flame_dir: Path | None = None,
                 progress: bool = True) -> tuple[Path, float | None, str]:
    """(the driver's dataset folder, its video's frame rate or None, its name): --driver as given, or --driver-video
    tracked by prepare's pipeline into its cache (reused when nothing changed)."""
    if driver_video is None:
        return Path(driver), None, dataset_name(Path(driver))
    cache = driver_cache or driver_cache_dir(run.info.run_dir, driver_video, photometric)
    dataset, fps = prepare_driver(Path(driver_video), cache, run.info.head_model, driver_size or DRIVER_SIZE,
                                  photometric, flame_dir, progress)
    print(f"driver: {driver_video} tracked in {cache}")
    return dataset, fps, Path(driver_video).stem


__all__ = ["DRIVERS_DIR", "DrivenAvatar", "DrivingOptions", "check_driver_options", "dataset_name", "driven_clip",
           "driven_params", "driver_cache_dir", "driver_picture", "prepare_driver", "reenact", "reenact_video",
           "reference_frame", "subject_params", "track_driver"]
