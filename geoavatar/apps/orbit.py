"""`geoavatar orbit RUN [--frame K]`: novel views of one frame, a yaw sweep then a pitch sweep; mp4.

The avatar is posed with frame K's parameters (T rule of apps/common.py). The cameras keep the
dataset camera's focal lengths and its distance to the head centre (apps.common.head_centre: the
bounding-box centre of the posed skin without the neck), are aimed at that centre with the principal
point at the image centre (render.camera.centred_intrinsics: `prepare`'s crops put the dataset's
principal point anywhere, and an aimed camera shows its target there) and turn about it:

    first half of the frames:  yaw(s)   = yaw_max   * sin(2 pi s), s in [0, 1)   about the camera's up axis
    second half:               pitch(s) = pitch_max * sin(2 pi s)                about the camera's right axis

so the video starts and ends at the dataset's own viewpoint (aimed at the head centre, which is in the middle
of every frame) and loops.

Floaters (eval/floaters.py): every frame's share of rendered opacity outside the dilated silhouette of
the posed head mesh is measured; the command prints its mean, its largest value and where, and with
--stills writes a PNG of the sweep's extreme views.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, NamedTuple, Optional

import torch

from geoavatar.apps.common import (RENDER_THREADS, VIDEO_DIR, RunPath, check_resolution, default_output, head_centre,
                                   progress, record_camera, run_background, side_by_side, torch_threads)
from geoavatar.avatar import pose_avatar, rasterize_gaussians
from geoavatar.data import open_subject
from geoavatar.errors import OptionError
from geoavatar.eval.floaters import DEFAULT_DILATE, FloaterConfig, head_silhouette, outside_share
from geoavatar.imaging import to_uint8
from geoavatar.io.atomic import atomic_write_png
from geoavatar.io.video import Mp4Writer
from geoavatar.render.camera import orbit_cameras
from geoavatar.train.checkpoint import RunError, open_run
from geoavatar.train.run_frames import RunFrames


def sweep_angles(frames: int, yaw_max: float, pitch_max: float) -> list[tuple[float, float]]:
    """(yaw, pitch) in degrees per frame: a sinusoidal yaw sweep, then a pitch sweep (none when 0)."""
    if frames < 1:
        raise OptionError(f"--frames must be positive, got {frames}")
    yaw_frames = frames if pitch_max == 0 else (frames + 1) // 2
    angles = [(yaw_max * math.sin(2 * math.pi * i / yaw_frames), 0.0) for i in range(yaw_frames)]
    pitch_frames = frames - yaw_frames
    angles += [(0.0, pitch_max * math.sin(2 * math.pi * i / pitch_frames)) for i in range(pitch_frames)]
    return angles


class OrbitResult(NamedTuple):
    frames: int
    angles: list[tuple[float, float]]  # (yaw, pitch) of each frame, degrees
    outside: list[float]  # share of opacity outside the dilated head silhouette, per frame
    images: list  # uint8 [H, W, 3] numpy per frame, as written to the video


@torch.no_grad()
def orbit_video(
    run,
    out: Path,
    timestep: int | None = None,
    frames: int = 60,
    yaw: float = 60.0,
    pitch: float = 20.0,
    resolution: int | None = None,
    fps: float = 25.0,
    crf: int = 18,
    backend: str = "auto",
    data: Path | None = None,
    show_progress: bool = True,
    stills: Path | None = None,
    threads: int = RENDER_THREADS,
) -> OrbitResult:
    """Write the orbit video of one frame (and with `stills` a PNG of its extreme views). `threads`: CPU threads of
    the frame loop (common.torch_threads)."""
    if not 0 <= yaw < 180 or not 0 <= pitch < 90:
        raise OptionError(f"--yaw must be in [0, 180) and --pitch in [0, 90) degrees, got {yaw}, {pitch}")
    run_frames = RunFrames(run)
    timestep = run_frames.resolve(timestep)
    params, t = run_frames.params(timestep)
    root = Path(data) if data is not None else run.info.data_root
    if not root.is_dir():
        raise RunError(f"{run.info.run_dir}: its dataset folder {root} is not found (the camera comes from it); "
                       "pass --data DIR")
    base = record_camera(open_subject(root), timestep, run.info.resolution)  # as training saw it
    if resolution is not None:
        base = base.resized(resolution)
    centre = head_centre(run, params)  # [3]
    angles = sweep_angles(frames, yaw, pitch)
    cameras = orbit_cameras(base.to(centre.device), centre, angles)
    floaters = FloaterConfig()
    posed = pose_avatar(run.avatar, run.head, params, t, run.deformer)  # one pose, many cameras
    background = run_background(run).to(centre.device)
    outside, images = [], []
    with torch_threads(threads), Mp4Writer(out, fps=fps, crf=crf) as video:
        for camera in progress(cameras, enabled=show_progress, desc="orbit"):
            result = rasterize_gaussians(posed.gaussians, camera, background, backend)
            image = to_uint8(result.rgb.clamp(0.0, 1.0))
            video.write(image)
            images.append(image)
            silhouette = head_silhouette(posed.vertices, run.head.faces, camera,
                                         floaters.dilate_px(camera.width, camera.height))
            outside.append(outside_share(result.alpha, silhouette))
    if stills is not None:
        atomic_write_png(stills, side_by_side(*[images[i] for i in still_indices(angles)]))
    return OrbitResult(video.frames, angles, outside, images)


def still_indices(angles: list[tuple[float, float]]) -> list[int]:
    """Frames of the sweep to show as stills: the front, then the extreme yaws and pitches (each once)."""
    picks = [0]
    for key in (lambda a: a[0], lambda a: -a[0], lambda a: a[1], lambda a: -a[1]):
        best = max(range(len(angles)), key=lambda i: key(angles[i]))
        if key(angles[best]) > 0 and best not in picks:
            picks.append(best)
    return picks


def orbit(
    run: RunPath,
    frame: Optional[int] = None,
    out: Optional[Path] = None,
    frames: int = 60,
    yaw: float = 60.0,
    pitch: float = 20.0,
    resolution: Optional[int] = None,
    fps: float = 25.0,
    crf: int = 18,
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    stills: Optional[Path] = None,
    progress: bool = True,
    threads: int = RENDER_THREADS,
) -> int:
    """Novel views: orbit the camera around the head of one frame (a yaw sweep, then a pitch sweep).

    Args:
        run: Run folder written by `geoavatar train`.
        frame: Timestep (frame index of the video) whose pose and expression are shown (default: the first).
        out: Video file to write (default RUN/videos/orbit_<frame>.mp4); written atomically.
        frames: Number of video frames (half yaw sweep, half pitch sweep).
        yaw: Largest yaw to either side, in degrees.
        pitch: Largest pitch up and down, in degrees (0: yaw sweep only).
        resolution: Longer image side in pixels (default: the run's training resolution).
        fps: Frames per second of the video.
        crf: H.264 quality (0 lossless ... 51 worst; 18 is visually lossless).
        data: The run's dataset folder, when it moved since training (its camera is read from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        stills: Also write this PNG: the front view and the sweep's extreme views side by side.
        progress: Show progress bars.
        threads: CPU threads of the rendering loop. 1 by default, as `geoavatar drive`: a frame's tensors are small,
            and on a busy 2-core machine 2 threads made each frame several times slower (OpenMP threads waiting
            for each other); more may pay on a quiet machine.
    """
    check_resolution(resolution)
    if stills is not None and Path(stills).suffix.lower() != ".png":  # before the sweep, not after it
        raise OptionError(f"--stills {stills}: the stills are written as a .png file")
    loaded = open_run(run, device, flame_dir)
    timestep = RunFrames(loaded).resolve(frame)
    target = out or default_output(loaded, VIDEO_DIR, f"orbit_{timestep:05d}.mp4")
    result = orbit_video(loaded, target, timestep, frames, yaw, pitch, resolution, fps, crf, backend, data, progress,
                         stills, threads)
    print(f"wrote {target} ({result.frames} frames, yaw +-{yaw:g} deg, pitch +-{pitch:g} deg)"
          + (f" and {stills}" if stills is not None else ""))
    worst = max(range(len(result.outside)), key=result.outside.__getitem__)
    print(f"opacity outside the head silhouette (dilated {100 * DEFAULT_DILATE:g} % of the image): mean "
          f"{100 * sum(result.outside) / len(result.outside):.1f} %, largest {100 * result.outside[worst]:.1f} % "
          f"at yaw {result.angles[worst][0]:+.0f}, pitch {result.angles[worst][1]:+.0f} deg")
    return 0


__all__ = ["OrbitResult", "orbit", "orbit_cameras", "orbit_video", "still_indices", "sweep_angles"]
