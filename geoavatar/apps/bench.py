"""`geoavatar bench RUN`: frames per second of the animation path and of rasterization alone.

Stages timed (no gradients, the current device, after --warmup untimed frames):

    head + mouth deformer   posed_head: the head model's LBS with the part-wise mouth offsets (T = 0)
    local -> global         the avatar's face frames and Gaussian placement
    rasterize               rasterize() of one fixed set of global Gaussians
    full animation path     all three for a new frame's parameters each iteration (cycling through the
                            run's frames), which is what a driven avatar costs per frame

The camera is the run's dataset camera of the first frame, scaled so that the longer image side is
--resolution pixels (512 x 512 for a square video); without the dataset, a frontal camera at
--resolution squared aimed at the head. Asynchronous devices are synchronised around every timed
iteration, so the numbers are wall time per frame.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path
from typing import Literal, Optional

import torch

from geoavatar.apps.common import RunPath, head_centre, posed_head_vertices, record_camera, run_background, synchronize
from geoavatar.avatar import rasterize_gaussians
from geoavatar.data import DatasetError, open_subject
from geoavatar.errors import OptionError
from geoavatar.io.atomic import atomic_write_json
from geoavatar.render.camera import Camera, intrinsics_from_fov, look_at
from geoavatar.train.checkpoint import LoadedRun, open_run
from geoavatar.train.run_frames import RunFrames

STAGES = ("head + mouth deformer", "local -> global", "rasterize", "full animation path")


def bench_camera(run: LoadedRun, frames: RunFrames, resolution: int) -> Camera:
    """The dataset camera at `resolution` (longer side), or a frontal square camera when the data is gone."""
    try:
        return record_camera(open_subject(run.info.data_root), frames.timesteps[0], None).resized(resolution)
    except DatasetError:
        params, _ = frames.params(frames.timesteps[0])
        centre = head_centre(run, params).cpu()
        eye = centre + torch.tensor([0.0, 0.0, 1.0])  # 1 m in front (+z is out of the face)
        return Camera(look_at(eye, centre), intrinsics_from_fov(14.0, resolution, resolution, "y"), resolution, resolution)


def _time(fn, iterations: int, warmup: int, device: torch.device, bar=None) -> float:
    """Mean wall seconds of fn(i) over `iterations` calls, after `warmup` untimed ones (`bar`: a tqdm
    advanced once per call, updated outside the timed span)."""
    for i in range(warmup):
        fn(i)
        if bar is not None:
            bar.update(1)
    synchronize(device)
    total = 0.0
    for i in range(iterations):
        synchronize(device)
        start = time.perf_counter()
        fn(warmup + i)
        synchronize(device)
        total += time.perf_counter() - start
        if bar is not None:
            bar.update(1)
    return total / iterations


@torch.no_grad()
def run_bench(run: LoadedRun, resolution: int = 512, iterations: int = 20, warmup: int = 3,
              backend: str = "auto", show_progress: bool = False) -> dict:
    """Seconds per frame of each stage; returns a JSON-able report."""
    if resolution <= 0 or iterations <= 0 or warmup < 0:
        raise OptionError(f"--resolution and --iterations must be positive and --warmup >= 0, got "
                         f"{resolution}, {iterations}, {warmup}")
    device = run.device
    frames = RunFrames(run)
    all_params = [frames.params(t)[0] for t in frames.timesteps]
    camera = bench_camera(run, frames, resolution).to(device)
    background = run_background(run).to(device)
    params_of = lambda i: all_params[i % len(all_params)]  # noqa: E731 - a new frame each iteration

    fixed_vertices = posed_head_vertices(run, all_params[0])
    fixed = run.avatar(fixed_vertices)
    backend_used = rasterize_gaussians(fixed, camera, background, backend).backend

    def full(i: int) -> None:
        rasterize_gaussians(run.avatar(posed_head_vertices(run, params_of(i))), camera, background, backend)

    from tqdm.auto import tqdm

    with tqdm(total=len(STAGES) * (iterations + warmup), disable=not show_progress, desc="bench", unit="frame",
              dynamic_ncols=True) as bar:
        seconds = {
            STAGES[0]: _time(lambda i: posed_head_vertices(run, params_of(i)), iterations, warmup, device, bar),
            STAGES[1]: _time(lambda i: run.avatar(fixed_vertices), iterations, warmup, device, bar),
            STAGES[2]: _time(lambda i: rasterize_gaussians(fixed, camera, background, backend), iterations, warmup,
                             device, bar),
            STAGES[3]: _time(full, iterations, warmup, device, bar),
        }
    return {
        "run": str(run.info.run_dir),
        "device": str(device) if device.type != "cuda" else f"{device} ({torch.cuda.get_device_name(device)})",
        "host": platform.node(),
        "threads": torch.get_num_threads(),
        "backend": backend_used,
        "width": camera.width,
        "height": camera.height,
        "gaussians": run.avatar.num_gaussians,
        "vertices": run.head.num_vertices,
        "mouth_deformer": run.deformer is not None,
        "iterations": iterations,
        "warmup": warmup,
        "stages": {name: {"ms": 1000.0 * s, "fps": 1.0 / s if s > 0 else float("inf")} for name, s in seconds.items()},
    }


def format_report(report: dict) -> str:
    lines = [
        f"device {report['device']}, {report['threads']} threads, backend {report['backend']}, "
        f"{report['width']}x{report['height']}, {report['gaussians']} Gaussians, {report['vertices']} vertices, "
        f"{report['iterations']} iterations after {report['warmup']} warm-up",
        f"{'stage':<24} {'ms/frame':>10} {'FPS':>9}",
    ]
    for name, row in report["stages"].items():
        lines.append(f"{name:<24} {row['ms']:>10.2f} {row['fps']:>9.2f}")
    return "\n".join(lines)


def bench(
    run: RunPath,
    resolution: int = 512,
    iterations: int = 20,
    warmup: int = 3,
    out: Optional[Path] = None,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
) -> int:
    """Measure frames per second of the full animation path and of rasterization alone.

    Times the head model with the mouth deformer, local -> global, rasterize, and all of them for a new
    frame of parameters, at --resolution on the current device, and prints a table.

    Args:
        run: Run folder written by `geoavatar train`.
        resolution: Longer image side in pixels (512: the paper's 512 x 512).
        iterations: Timed frames per stage.
        warmup: Untimed frames before each stage (allocations, kernel caches, gsplat's JIT build).
        out: Also write the report as JSON to this file (atomically).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        progress: Show progress bars.
    """
    loaded = open_run(run, device, flame_dir)
    report = run_bench(loaded, resolution, iterations, warmup, backend, progress)
    if out is not None:
        atomic_write_json(out, report)
    print(format_report(report))
    return 0


__all__ = ["STAGES", "bench", "bench_camera", "format_report", "run_bench"]
