"""Shared pieces of the commands that use a trained run: render, reenact, orbit, export, view, bench.

    run = open_run(run_dir, device)                 # train/checkpoint.py: LoadedRun; RunError names the folder
    frames = RunFrames(run)                          # train/run_frames.py: per-timestep parameters and the T rule
    params, T = frames.params(timestep)              # HeadParams of a frame and its T (avatar.frame_timestep)
    rgb = render_params(run, params, camera, T)      # avatar.render_avatar on the run's background, clamped
    with Mp4Writer(path, fps=25) as video: video.write(frame_uint8)   # geoavatar.io.video: the one mp4 writer

The posing path (render_params, posed_head_vertices, record_camera, ...) lives in animation/posing.py, with the
sources and sinks the animation commands are built from (reenact, drive, view, export --format web, eval --driver);
this module re-exports it for the commands that pose a frame themselves (render, orbit, export, bench) and for
the tests.

The T rule (the mouth deformer's time input gamma(T)) lives with RunFrames in train/run_frames.py, which
`geoavatar eval` uses too: a training timestep renders with its own T and the run's refined parameters, which
reproduces what training saw; any other timestep (test frames, a driver's frames, edited parameters) renders with
T = 0, the paper's inference setting, and the parameters as tracked (the trainer never refines test rows).

Errors: what the user can cause raises a GeoAvatarError (geoavatar/errors.py): RunError (bad run,
dataset gone or changed), DatasetError, OptionError (a bad option value), DiskFullError. The command
functions let them through and `geoavatar` (cli.py) prints them as one line, `geoavatar <cmd>:
<message>`, with exit status 2. Any other exception, a plain ValueError included, is a bug and keeps
its traceback.
"""

from __future__ import annotations

import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Iterable

import numpy as np
import torch
import tyro
from torch import Tensor

# the posing path and the side-by-side picture moved to the animation layer; re-exported for render, orbit, export,
# bench and the tests, which import them from here
from geoavatar.animation.posing import (browser_pose_code, head_centre, pose_gaussians, posed_head_vertices,
                                        record_camera, render_params, run_background)
from geoavatar.animation.sinks.mp4 import side_by_side
from geoavatar.errors import OptionError
from geoavatar.io.video import check_mp4_options
from geoavatar.runtime import num_threads
from geoavatar.train.checkpoint import LoadedRun

# The RUN folder: the first, positional argument of every command (`geoavatar render RUN`).
RunPath = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]

VIDEO_DIR = "videos"  # RUN/videos/<command>_....mp4 unless --out says otherwise
EXPORT_DIR = "export"


# --- devices ---------------------------------------------------------------------------------------


def synchronize(device: torch.device | str) -> None:
    """Wait for queued kernels on `device` (a no-op on CPU): timings need it on asynchronous devices."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


RENDER_THREADS = 1  # default --threads of the video commands (render, reenact, orbit), as `geoavatar drive`


def serve_until_interrupted(server, serve_forever: bool = True) -> None:
    """Keep a started server (`.stop()`) up until Ctrl-C, then stop it; serve_forever=False stops it at once."""
    try:
        while serve_forever:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()


def check_threads(threads: int) -> int:
    """`threads` when it is a positive int, else OptionError naming --threads."""
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise OptionError(f"--threads must be a positive number of threads, got {threads!r}")
    return threads


def check_resolution(resolution: int | None) -> int | None:
    """`resolution` (None: the run's training resolution) when it is a positive int, else OptionError naming
    --resolution."""
    if resolution is not None and (isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1):
        raise OptionError(f"--resolution must be a positive number of pixels, got {resolution!r}")
    return resolution


@contextmanager
def torch_threads(threads: int):
    """Run a block with `threads` CPU threads for torch and the native rasterizer; the old count after.

    The video commands pose and render one frame at a time: ~70k Gaussians at 256-512 px are small
    tensors, and on a busy 2-core machine 2 OpenMP threads spin-wait for each other at every parallel
    region. reenact at 256 px (load 4-6) took 0.36 CPU s and 0.74 wall s per frame on 2 threads, 0.06 and
    0.08-0.13 on 1 (BENCHMARKS.md, "Video commands"). Ask for more threads on a quiet machine (--threads)."""
    with num_threads(check_threads(threads)):
        yield


# --- per-frame parameters -------------------------------------------------------------------------


def split_timesteps(run: LoadedRun, split: str) -> list[int]:
    """The timesteps of a split of the run (all, train, val, test); OptionError naming --split otherwise."""
    if split == "all":
        return list(run.info.timesteps["all"])
    if split not in run.info.timesteps:
        names = ["all", *(name for name in run.info.timesteps if name != "all")]  # the run's own lists "all" too
        raise OptionError(f"--split must be one of {', '.join(names)}; got {split!r}")
    return list(run.info.timesteps[split])


def clip_timesteps(run: LoadedRun, split: str) -> list[int]:
    """The timesteps of a split, at least one (OptionError naming --split otherwise)."""
    timesteps = split_timesteps(run, split)
    if not timesteps:
        raise OptionError(f"--split {split}: the run has no {split} frames")
    return timesteps


# --- images ------------------------------------------------------------------------------------------


_COLORMAP_CACHE: dict[str, Tensor] = {}


def colormap_lut(name: str = "inferno") -> Tensor:
    """[256, 3] float RGB lookup table of a matplotlib colormap."""
    if name not in _COLORMAP_CACHE:
        with warnings.catch_warnings():  # matplotlib's import warns about its own pyparsing use
            warnings.simplefilter("ignore", DeprecationWarning)
            import matplotlib

        try:
            cmap = matplotlib.colormaps[name]
        except KeyError as err:
            raise OptionError(f"unknown colormap {name!r} (any matplotlib colormap, e.g. inferno, turbo)") from err
        _COLORMAP_CACHE[name] = torch.from_numpy(cmap(np.linspace(0.0, 1.0, 256))[:, :3]).float()
    return _COLORMAP_CACHE[name]


def error_map(pred: Tensor, target: Tensor, error_max: float = 0.25, colormap: str = "inferno") -> Tensor:
    """Per-pixel mean absolute error over the channels, colour-mapped: [H, W, 3] in [0, 1].

    pred, target [H, W, 3]; errors of `error_max` and above get the top colour, so one scale holds for
    every frame of a video."""
    if error_max <= 0:
        raise OptionError(f"--error-max must be positive, got {error_max}")
    error = (pred - target).abs().mean(dim=-1)  # [H, W]
    index = (error / error_max).clamp(0.0, 1.0).mul(255.0).round().long()
    return colormap_lut(colormap).to(pred.device)[index]


def default_output(run: LoadedRun, folder: str, name: str) -> Path:
    return Path(run.info.run_dir) / folder / name


def check_video_options(out: Path | None, fps: float | None = None, crf: int = 18, max_frames: int | None = None,
                        inputs: tuple[Path | None, ...] = ()) -> None:
    """OptionError for an mp4 --out, --fps, --crf or --max-frames that the writer or the source would refuse only
    after the work (a driver tracked, a clip posed), or an --out that would replace one of the `inputs`."""
    check_mp4_options(out, fps, crf)
    inputs = [Path(given).resolve() for given in inputs if given is not None and Path(given).exists()]
    if out is not None and Path(out).resolve() in inputs:
        raise OptionError(f"--out {out} is the input video: give another file name")
    if max_frames is not None and max_frames < 1:
        raise OptionError(f"--max-frames must be positive, got {max_frames}")


def check_replaceable(out: Path, **kept: Path | None) -> None:
    """OptionError when replacing the folder --out would remove one of `kept` (name=folder: a run, a dataset): --out
    is that folder or holds it. --overwrite replaces what a command wrote before, never its inputs."""
    target = Path(out).resolve()
    for name, folder in kept.items():
        if folder is not None and Path(folder).exists() and Path(folder).resolve().is_relative_to(target):
            raise OptionError(f"--out {out} is or holds the {name} ({folder}); replacing it would delete the {name}: "
                              "give another folder")


def progress(iterable: Iterable, total: int | None = None, enabled: bool = True, desc: str | None = None):
    """A tqdm bar over `iterable` (silent when not enabled)."""
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, disable=not enabled, desc=desc, dynamic_ncols=True, unit="frame")


@dataclass
class Timer:
    """Wall seconds of a block, with the device synchronised at both ends."""

    device: torch.device
    seconds: float = 0.0

    def __enter__(self) -> "Timer":
        synchronize(self.device)
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        synchronize(self.device)
        self.seconds = time.perf_counter() - self._start


__all__ = [
    "EXPORT_DIR", "check_replaceable", "check_threads", "check_video_options", "clip_timesteps", "RunPath", "Timer",
    "VIDEO_DIR", "browser_pose_code", "colormap_lut",
    "default_output", "error_map", "head_centre", "pose_gaussians", "posed_head_vertices", "progress", "record_camera",
    "render_params",
    "RENDER_THREADS", "run_background", "side_by_side", "split_timesteps", "synchronize",
    "torch_threads",
]
