"""`geoavatar drive RUN (--camera N | --video FILE)`: drive a trained avatar live from a webcam or a video.

The front end of the animation layer's live tracker (animation/sources/live.py: a reader thread, the fit thread with
the identity stage over the first second, then the online fit; its module docstring says how a file keeps real time
and what is dropped) and its sinks, run by animation/play.py as drive's output stage:

    landmarks   the driver's frame cropped the way `prepare` crops, MediaPipe's face mesh (sources/tracker.py)
    fit         the driver's pose, jaw, eyes and expression: prep/tracking.py's OnlineFit, two damped Gauss-Newton
                iterations (or L-BFGS, --solver) warm-started from the previous frame
    pose        the avatar's parameters from the driver's (animation/transfer.py's driven_params in the --transfer
                mode), avatar.pose_avatar
    render      avatar.rasterize_gaussians with the avatar's dataset camera at --size (sinks/mp4.py)

Latency is measured from the moment a frame is available to the moment its output is done. A status line shows the
FPS, drops and the per-stage times. The written mp4 (`--out`, driver | avatar) runs at the source's frame rate; a
dropped frame repeats the previous output, so the video keeps real time. `--view` serves the browser player
(animation/sinks/browser.py, geoavatar/web) in live mode: each frame's posed head mesh is streamed over a websocket and
the browser places, shades and draws the splats on its GPU (without --out the render stage is skipped); the summary
adds the stream's latency from frame read to message sent.

The fit runs on the CPU (a few hundred landmarks: a GPU's launch overhead would dominate); posing and
rendering run on --device (auto: CUDA when there).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import torch

from geoavatar.animation.expression_transfer import DEFAULT_TRANSFER, TransferMode, resolve_transfer
from geoavatar.animation.play import play
from geoavatar.animation.sinks.browser import LiveStream
from geoavatar.animation.sinks.mp4 import Mp4Sink
# open_video is also imported from here by benchmarks/drive_bench.py and web_player_bench.py
from geoavatar.animation.sources.capture import VideoInput, open_camera, open_video
from geoavatar.animation.sources.live import LiveDriver
from geoavatar.animation.stats import DriveStats
from geoavatar.apps.common import RunPath, check_video_options, record_camera
from geoavatar.data import DatasetError, open_subject
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.io.video import EmptyVideoError
from geoavatar.render.camera import Camera
from geoavatar.runtime import show_native_logs
from geoavatar.train.checkpoint import LoadedRun, RunError, open_run


def _check_drive_options(size: int, iterations: int | None, init_seconds: float, threads: int) -> None:
    if size < 16:
        raise OptionError(f"--size must be >= 16, got {size}")
    if iterations is not None and iterations < 1:
        raise OptionError(f"--iterations must be >= 1, got {iterations}")
    if init_seconds <= 0:
        raise OptionError(f"--init-seconds must be positive, got {init_seconds}")
    if threads < 1:
        raise OptionError(f"--threads must be >= 1, got {threads}")


def _avatar_camera(run: LoadedRun, size: int, data: Path | None) -> Camera:
    """The avatar's dataset camera (from its dataset, or --data when it moved) at --size."""
    avatar_root = Path(data) if data is not None else run.info.data_root
    first = run.info.timesteps["all"][0]  # the avatar's first frame (RunFrames' timesteps[0])
    try:
        return record_camera(open_subject(avatar_root), first, None).resized(size).to(run.device)
    except (DatasetError, OSError) as err:
        raise RunError(f"{run.info.run_dir}: the camera comes from its dataset {avatar_root}, which cannot be read "
                       f"({err}); pass --data DIR") from err


@torch.no_grad()
def drive_avatar(
    run: LoadedRun,
    source: VideoInput,
    out: Path | None = None,
    transfer: TransferMode | bool = DEFAULT_TRANSFER,  # a bool is the old `relative` flag
    size: int = 512,
    init_seconds: float = 1.0,
    iterations: int | None = None,
    solver: str = "gauss_newton",
    max_frames: int | None = None,
    lossless: bool = False,
    viewer=None,
    backend: str = "auto",
    data: Path | None = None,
    status: bool = True,
    record: bool = False,
    flame_dir: Path | None = None,
    render: bool | None = None,
    init_steps: tuple[int, int] = (100, 300),
    threads: int = 1,
) -> DriveStats:
    """Run the live pipeline until the source ends; returns the measurements (see the module docstring).

    `viewer`: a LiveViewer in live mode (--view); `render`: rasterize each frame (default: when writing `out` or
    without a viewer; rendered without `out`, the frames are timed and dropped); `lossless`: every frame processed,
    nothing dropped; `record`: each frame's fit kept in the stats' records."""
    _check_drive_options(size, iterations, init_seconds, threads)
    camera = _avatar_camera(run, size, data)
    render = (out is not None or viewer is None) if render is None else render
    sinks = [Mp4Sink(run, out, source.fps, camera, backend=backend, check_values=False)] if render else []
    live = LiveDriver(run, source, transfer, init_seconds, iterations, solver, max_frames, lossless, record, flame_dir,
                      init_steps, threads)
    if viewer is not None:  # the browser first: its mesh goes out before the render
        sinks.insert(0, LiveStream(viewer, run, live))
    try:
        play(run, live, sinks, status=status)
    except EmptyVideoError:  # no frame came: say why (the source ended within the identity stage) when that is it
        live.check_identity_stage()
        raise
    live.check_identity_stage()
    return live.stats


def drive(
    run: RunPath,
    camera: Optional[int] = None,
    video: Optional[Path] = None,
    relative: bool = False,
    transfer: Optional[TransferMode] = None,
    out: Optional[Path] = None,
    view: bool = False,
    size: int = 512,
    init_seconds: float = 1.0,
    solver: Literal["gauss_newton", "lbfgs"] = "gauss_newton",
    iterations: Optional[int] = None,
    max_frames: Optional[int] = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    status: bool = True,
    threads: int = 1,
    verbose: bool = False,
) -> int:
    """Drive a trained avatar live from a webcam or a video: landmarks, online fit, avatar posed and rendered.

    The driver's first second fits its identity (then frozen); every later frame is fitted warm-started
    from the previous one. Frames the pipeline cannot keep up with are dropped (counted), not queued (at most
    two wait).

    Args:
        run: Run folder written by `geoavatar train` (the avatar).
        camera: Webcam number N (/dev/videoN through PyAV's v4l2 input, else OpenCV).
        video: A video file played as a live source at its own frame rate.
        relative: The same as --transfer relative.
        transfer: How the driver's expression, jaw and eyes become the avatar's: absolute, relative (offsets from
            the driver's neutral, its first second, onto the avatar's first frame), statistics (the driver's
            first-second statistics mapped to the avatar's training-set statistics) or subspace (relative, kept
            inside the expressions the avatar was trained on), as `geoavatar reenact --transfer`. Default: relative.
        out: Write driver | avatar to this mp4 (at the source's frame rate; a dropped frame repeats the last output).
        view: Show the avatar live in the browser player on --host/--port (posed meshes streamed to it).
        size: Side of the rendered avatar in pixels (the avatar's dataset camera, scaled).
        init_seconds: Length of the identity stage at the start of the driver.
        solver: Online fit per frame: gauss_newton (damped Gauss-Newton; closer to the offline tracking at
            the same cost) or lbfgs.
        iterations: Iterations of the online fit per frame (default: 2 Gauss-Newton or 8 L-BFGS; its latency
            grows with them).
        max_frames: Stop after this many source frames (default: the whole video, or until Ctrl-C).
        host: Viewer address (--view).
        port: Viewer port (--view).
        data: The avatar's dataset folder, when it moved since training (the camera is read from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N: where the avatar is posed and rendered.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (FLAME avatars only).
        status: Print a status line (FPS, drops, latency per stage) about once a second.
        threads: CPU threads of the pipeline's torch and rasterizer work. 1 by default: its tensors are small,
            and on a busy 2-core machine 2 threads made the fit 10x and posing 3-5x slower (OpenMP waits).
        verbose: Also show the log lines of the libraries underneath (MediaPipe, TensorFlow Lite), which are
            kept out of the terminal otherwise.
    """
    if (camera is None) == (video is None):
        raise OptionError("give one driving source: --camera N or --video FILE")
    if out is None and not view:
        raise OptionError("nothing to show: pass --out FILE.mp4 and/or --view")
    check_video_options(out, max_frames=max_frames, inputs=(video,))
    mode = resolve_transfer(transfer, relative)
    source = open_video(video) if video is not None else open_camera(camera)
    loaded = open_run(run, device, flame_dir)
    viewer = None
    if view:
        from geoavatar.apps.view import start_viewer

        try:
            viewer = start_viewer(loaded, host, port, expr_sliders=0, data=data, live=True)
        except (ImportError, OSError) as err:
            raise GeoAvatarError(f"cannot start the viewer: {err}") from err
        print(f"GeoAvatar live viewer: {viewer.url}", flush=True)
    try:
        with show_native_logs(verbose):
            stats = drive_avatar(loaded, source, out, mode, size, init_seconds, iterations, solver,
                                 max_frames=max_frames, viewer=viewer, backend=backend, data=data, status=status,
                                 flame_dir=flame_dir, threads=threads)
    except KeyboardInterrupt:
        return 0
    finally:
        if viewer is not None:
            viewer.stop()
    print(f"drive: {stats.summary()}; identity stage {stats.init_frames} frames in {stats.init_seconds:.1f} s"
          + (f"; wrote {out}" if out is not None else "") + (f"; {viewer.summary()}" if viewer is not None else ""))
    return 0


__all__ = ["drive", "drive_avatar"]
