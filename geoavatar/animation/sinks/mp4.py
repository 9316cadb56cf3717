"""An mp4 of the animation: each frame's posed avatar rasterized (avatar.rasterize_gaussians, the one rendering path
of every command: what render_params / render_avatar do) at the frame's camera or the sink's, on the run's
background, with the frame's picture (the driver's frame or face crop) scaled to its height on the left, and written
by io/video.py's Mp4Writer (atomic; with a sound track when `audio` is given).

A skipped frame index (a live source dropped the frame) repeats the last picture, so the video keeps the source's
clock; with a sound, frames dropped before the first one shown repeat that one, so sound and picture start together.
Without a file (`out` None) the frames are still rendered and timed: drive's measurements.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from torch import Tensor

from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.posing import PosedFrame, run_background
from geoavatar.avatar import rasterize_gaussians
from geoavatar.imaging import fit_height, to_uint8
from geoavatar.io.video import Mp4Writer
from geoavatar.render.camera import Camera
from geoavatar.train.checkpoint import LoadedRun


def side_by_side(*images: np.ndarray) -> np.ndarray:
    """uint8 images [H, W_i, 3] of one height, left to right."""
    heights = {image.shape[0] for image in images}
    if len(heights) != 1:
        raise ValueError(f"side_by_side: images of different heights {sorted(heights)}")
    return np.concatenate(images, axis=1)


def mp4_writer(out: Path, fps: float, crf: int = 18, audio=None) -> Mp4Writer:
    """Mp4Writer of `out`, with the sound track `audio` when there is one."""
    return Mp4Writer(out, fps=fps, crf=crf, **({"audio": audio} if audio is not None else {}))


class Mp4Sink:
    """Sink: the frames rendered into the mp4 `out` (module docstring); `check_values`: rasterize's value checks (a
    device sync; drive skips them), `side_by_side`: the frame's picture left of the avatar when it has one."""

    rasterizes = True

    def __init__(self, run: LoadedRun, out: Path | None, fps: float, camera: Camera | None = None,
                 background: Tensor | None = None, backend: str = "auto", crf: int = 18, side_by_side: bool = True,
                 check_values: bool = True, audio=None):
        self.writer = mp4_writer(out, fps, crf, audio) if out is not None else None
        self.camera = camera.to(run.device) if camera is not None else None
        self.background = (run_background(run) if background is None else background).to(run.device)  # [3]
        self.backend, self.show_picture, self.check_values = backend, side_by_side, check_values
        self.last_index, self.last_picture = -1, None

    @property
    def frames(self) -> int:
        """Frames written so far (dropped frames' repeats included)."""
        return self.writer.frames if self.writer is not None else 0

    def __enter__(self) -> "Mp4Sink":
        if self.writer is not None:
            self.writer.__enter__()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        return bool(self.writer.__exit__(exc_type, exc, tb)) if self.writer is not None else False

    def write(self, frame: AnimationFrame, posed: PosedFrame) -> None:
        started = time.perf_counter()
        camera = frame.camera if frame.camera is not None else self.camera
        rgb = rasterize_gaussians(posed.gaussians, camera, self.background, self.backend,
                                  check_values=self.check_values).rgb
        picture = to_uint8(rgb.clamp(0.0, 1.0))  # the read-back synchronises the device
        frame.add_time("render", time.perf_counter() - started)
        if self.writer is None:
            return
        if self.show_picture and frame.picture is not None:
            picture = side_by_side(fit_height(frame.picture, picture.shape[0]), picture)
        if self.last_picture is not None:  # frames a live source dropped: the last picture again (real time)
            repeats, held = frame.index - self.last_index - 1, self.last_picture
        else:  # with a sound, frame k shows time k / fps of it: frames dropped before the first show the first
            repeats, held = (frame.index if self.writer.audio is not None else 0), picture
        for _ in range(repeats):
            self.writer.write(held)
        self.writer.write(picture)
        self.last_index, self.last_picture = frame.index, picture


__all__ = ["Mp4Sink", "mp4_writer", "side_by_side"]
