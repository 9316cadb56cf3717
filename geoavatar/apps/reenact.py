"""`geoavatar reenact RUN --driver DATASET | --driver-video VIDEO`: cross-re-enactment, the driver's motion on
the avatar, as an mp4 of driver | avatar.

The front end of the animation layer's driver source and mp4 sink:

    driver, fps, name = track_driver(run, driver, driver_video, ...)      # sources/driver_video.py: a video tracked
    driven = DrivenAvatar(run, driver, DrivingOptions(...), fps)           # sources/driver.py: the transferred motion
    play(run, driven, [Mp4Sink(run, out, fps, driven.fixed_camera)])       # sinks/mp4.py: rendered, written

The driver is a tracked dataset (`--driver`: any layout `geoavatar train` reads) or a video (`--driver-video`), tracked
first by the code of `geoavatar prepare` into RUN/drivers/<video stem>-<hash>/ (or --driver-cache DIR) and reused by
the next call (animation/sources/driver_video.py). The driver keeps its own identity; only its motion is transferred,
by --transfer (animation/transfer.py: absolute, relative, statistics, subspace). "Neutral" is a frame of each
sequence, `--driver-neutral` / `--avatar-neutral`: `first` (default), `mean` or a timestep number. Relative transfer is
what users of GaussianAvatars / FlashAvatar / NerFace ask for: tracked expression coefficients carry some of the
tracked person's identity (a neutral face is not expr = 0), so transferring the change from a neutral frame onto the
avatar's own neutral frame leaks less of the driver's face shape.

Camera: by default the avatar's own dataset camera (that of its neutral frame, or its first frame with `mean`), at the
run's resolution (or --resolution): the driver's camera may differ (another focal length, another distance).
`--camera driver` renders each frame with the driver's camera instead, for drivers whose tracker moves the camera
rather than the head (INSTA / metrical-tracker data). The mouth deformer runs with T = 0 (novel animation, as the paper
does at inference). The output video plays at the driver video's frame rate unless --fps says otherwise.

Output: an mp4 with driver | avatar side by side (the driver's frame scaled to the render's height), or the avatar
alone with --no-side-by-side.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import torch

from geoavatar.animation.expression_transfer import DEFAULT_TRANSFER, TransferMode, resolve_transfer
from geoavatar.animation.play import play
from geoavatar.animation.sinks.mp4 import Mp4Sink
# DrivenAvatar, DrivingOptions and driver_picture are also imported from here by benchmarks/cross_reenactment.py
from geoavatar.animation.sources.driver import DrivenAvatar, DrivingOptions, driver_picture  # noqa: F401
from geoavatar.animation.sources.driver_video import track_driver
from geoavatar.apps.common import (RENDER_THREADS, VIDEO_DIR, RunPath, check_resolution, check_threads,
                                   check_video_options, default_output, torch_threads)
from geoavatar.errors import OptionError
from geoavatar.train.checkpoint import LoadedRun, open_run


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
    driven = DrivenAvatar(run, driver_root, options, fps, max_frames, pictures=show_driver)
    video = Mp4Sink(run, out, fps, driven.fixed_camera, driven.background, options.backend, crf, show_driver,
                    audio=driven.audio)
    with torch_threads(threads):
        play(run, driven, [video], progress=show_progress, desc="reenact")
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
    check_video_options(out, fps, crf, max_frames, (driver_video,))
    loaded = open_run(run, device, flame_dir)
    driver, video_fps, driver_name = track_driver(loaded, driver, driver_video, driver_cache, driver_size, photometric,
                                                  flame_dir, progress)
    name = f"reenact_{driver_name}{'' if mode == DEFAULT_TRANSFER else '_' + mode}.mp4"
    target = out or default_output(loaded, VIDEO_DIR, name)
    options = DrivingOptions(mode, driver_neutral, avatar_neutral, camera, driver_split, data, backend, resolution)
    fps = fps if fps is not None else (video_fps or 25.0)
    count = reenact_video(loaded, driver, target, options, max_frames, fps, crf, side_by_side, progress, threads)
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


__all__ = ["check_driver_options", "reenact", "reenact_video"]
