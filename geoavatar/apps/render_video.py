"""`geoavatar render RUN`: ground truth | render | error map, side by side, as an mp4 (PyAV).

Each frame of the chosen split is rendered as `geoavatar eval` renders it, by its own function
(eval.evaluate.render_run_frames; the T rule of apps/common.py: training frames with their own T and
refined parameters, other frames with T = 0 and the dataset's tracked parameters, a copy's with
`--data COPY`, e.g. the held-out frames `geoavatar track --avatar` fitted), on the run's background colour.
The ground truth is the image composited on the same background with its mask, the training target. The
error map is the per-pixel absolute error averaged over the colour channels, colour-mapped from 0 to
--error-max (one scale for the whole video). `--resolution` renders at another size than training's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import torch

from geoavatar.apps.common import (RENDER_THREADS, VIDEO_DIR, RunPath, check_resolution, default_output, error_map,
                                   progress, side_by_side, torch_threads)
from geoavatar.data import evenly_spaced
from geoavatar.errors import OptionError
from geoavatar.eval.evaluate import render_run_frames
from geoavatar.imaging import to_uint8
from geoavatar.io.video import Mp4Writer
from geoavatar.train.checkpoint import LoadedRun, open_run, open_run_dataset

Split = Literal["test", "val", "train", "all"]


@torch.no_grad()
def render_split_video(
    run: LoadedRun,
    out: Path,
    split: str = "test",
    max_frames: int | None = None,
    fps: float = 25.0,
    crf: int = 18,
    error_max: float = 0.25,
    colormap: str = "inferno",
    backend: str = "auto",
    data: Path | None = None,
    show_progress: bool = True,
    threads: int = RENDER_THREADS,
    resolution: int | None = None,
) -> int:
    """Write the gt | render | error video of a split to `out`; returns the number of frames. `threads`: CPU threads
    of the frame loop (common.torch_threads); `resolution`: longer image side (None: the run's)."""
    dataset = open_run_dataset(run, split, data, resolution=check_resolution(resolution))
    if len(dataset) == 0:
        raise OptionError(f"--split {split}: the run's dataset has no frames in this split")
    indices = progress(evenly_spaced(len(dataset), max_frames), enabled=show_progress, desc=f"render {split}")
    with torch_threads(threads), Mp4Writer(out, fps=fps, crf=crf) as video:
        # eval's own frames, so that a dataset copy's parameters (`track --avatar`'s) show as eval scores them
        for frame in render_run_frames(run, dataset, indices, backend=backend):
            errors = error_map(frame.pred, frame.target, error_max, colormap)
            video.write(side_by_side(to_uint8(frame.target), to_uint8(frame.pred), to_uint8(errors)))
    return video.frames


def render(
    run: RunPath,
    split: Split = "test",
    out: Optional[Path] = None,
    max_frames: Optional[int] = None,
    fps: float = 25.0,
    crf: int = 18,
    error_max: float = 0.25,
    colormap: str = "inferno",
    data: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
    threads: int = RENDER_THREADS,
    resolution: Optional[int] = None,
) -> int:
    """Render a split of the run's dataset into an mp4: ground truth | render | error map.

    Args:
        run: Run folder written by `geoavatar train`.
        split: Frames to render: test (held-out end of the video), val, train or all.
        out: Video file to write (default RUN/videos/render_<split>.mp4); written atomically.
        max_frames: Render only this many frames, spread evenly over the split (default: all).
        fps: Frames per second of the video.
        crf: H.264 quality (0 lossless ... 51 worst; 18 is visually lossless).
        error_max: Absolute error (0..1, mean over RGB) that gets the top colour of the error map.
        colormap: Matplotlib colormap of the error map (inferno, turbo, viridis, ...).
        data: The run's dataset folder, when it moved since training (default: the recorded one), or another copy of
            it, e.g. `geoavatar track --avatar`'s: the frames the run did not train on show its parameters, as
            `eval --data` scores them.
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        progress: Show progress bars.
        threads: CPU threads of the rendering loop. 1 by default, as `geoavatar drive`: a frame's tensors are small,
            and on a busy 2-core machine 2 threads made each frame several times slower (OpenMP threads waiting
            for each other); more may pay on a quiet machine.
        resolution: Longer image side in pixels (default: the run's training resolution; at most the dataset's
            stored size, whose images are never enlarged).
    """
    check_resolution(resolution)
    loaded = open_run(run, device, flame_dir)
    target = out or default_output(loaded, VIDEO_DIR, f"render_{split}.mp4")
    count = render_split_video(loaded, target, split, max_frames, fps, crf, error_max, colormap, backend, data,
                               progress, threads, resolution)
    print(f"wrote {target} ({count} frames: ground truth | render | error)")
    return 0


__all__ = ["render", "render_split_video"]
