"""The held-out frames' head parameters fitted against the finished avatar: the last stage of `geoavatar train`.

    report = fit_held_out(run_dir, HeldOutFitConfig())     # writes RUN/held_out.npz and RUN/held_out.json
    rows = read_held_out(run_dir, step)                    # {key: [N, ...]} and timesteps, or None (none / stale)

Why: training refines the parameters of the frames it trains on against the avatar it learns
(train/frame_params.py); the held-out frames keep the tracker's, whose appearance model (prepare's mesh-bound
albedo in face crops) cannot see the hair's outline and does not share the offset the avatar absorbed from its
training frames. On an expressive video that cost the held-out frames 3 dB (docs/expressive_video.md). This
fit gives them what training gives its own frames: parameters in which the avatar explains the image
(train/avatar_tracking.py, each frame alone, the avatar frozen). The avatar never sees a held-out frame's pixels
while it learns; the fit happens after, as `geoavatar track --avatar` does it, and replaces the Gaussian head of
the whole video that `prepare` once trained for the same purpose (a second training of the same frames).

How: the test frames in fixed blocks of BLOCK frames, each block on a worker process (both cores busy, one
torch thread each: geoavatar.workers), each frame from the previous frame's correction when that renders closer
(AvatarTrackingConfig.carry), so fewer steps reach the full fit. The blocks do not depend on the worker count,
so neither does the result. The rows are kept beside the checkpoint, tagged with its step: `load_run` lays them
over the run's parameters while they belong to its checkpoint (an --extend makes them stale until refitted).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from geoavatar.head.params import FRAME_KEYS

HELD_OUT_FILE = "held_out.npz"  # timesteps [N], step, and the per-frame keys [N, ...]
HELD_OUT_REPORT = "held_out.json"
BLOCK = 16  # frames per task: the carry restarts at each block


@dataclass
class HeldOutFitConfig:
    """Adam steps per frame and the carry between neighbouring frames (BENCHMARKS.md, Time to a good avatar)."""

    # 10 / 20 / 30 steps with carry: held-out PSNR duda 34.48 / 34.91 / 35.08 dB, d3 25.42 / 25.60 / 25.66, at
    # 1 / 1.75 / 2.4-2.6 times the fit's time: 20 brings duda within #40's 0.3 dB of prepare's old gaussian stage
    # (34.84)
    steps: int = 20
    carry: bool = True

    def __post_init__(self):
        if self.steps < 1:
            raise ValueError(f"held-out fit: need steps >= 1, got {self.steps}")


def _fit_block(task: tuple) -> dict:
    """A worker's task: fit the test frames `indices` of the run in `run_dir`; rows [n, ...] and L1 [n]."""
    from geoavatar.train.avatar_tracking import AvatarTrackingConfig, dataset_frames, track_frames
    from geoavatar.train.checkpoint import load_run, open_run_dataset
    from geoavatar.workers import report_progress, worker_cache

    run_dir, step, indices, config = task

    def opened():
        run = load_run(run_dir, "cpu")
        return run, open_run_dataset(run, "test")

    run, test = worker_cache(f"held-out:{run_dir}:{step}", opened)
    fit = AvatarTrackingConfig(steps=config["steps"], carry=config["carry"])
    result = track_frames(run.avatar, run.head, run.deformer, dataset_frames(test, indices, run.device), fit,
                          progress=report_progress)
    return {"timesteps": [int(test.timesteps[i]) for i in indices],
            "rows": {key: getattr(result.params, key).cpu().numpy() for key in FRAME_KEYS},
            "before": result.loss_before, "after": result.loss_after}


def fit_held_out(run_dir: Path, config: HeldOutFitConfig = HeldOutFitConfig(), workers: int | None = None,
                 progress: bool = True, log: Callable[[str], None] = print) -> dict | None:
    """Fit the test frames of the finished run in `run_dir` against its avatar; writes RUN/held_out.npz and
    RUN/held_out.json and returns the report (None: the run has no test frames)."""
    from tqdm import tqdm

    from geoavatar.io.atomic import atomic_write_json, atomic_write_npz
    from geoavatar.train.checkpoint import load_run, open_run_dataset
    from geoavatar.workers import WorkerPool, default_workers

    run = load_run(run_dir, "cpu")
    test = open_run_dataset(run, "test")
    if len(test) == 0:
        return None
    blocks = [tuple(range(start, min(start + BLOCK, len(test)))) for start in range(0, len(test), BLOCK)]
    workers = max(1, min(workers or default_workers(), len(blocks)))
    started = time.perf_counter()
    tasks = [(str(run_dir), run.info.step, block, asdict(config)) for block in blocks]
    with tqdm(total=len(test), desc="train: held-out fit", unit="frame", disable=not progress) as bar, \
            WorkerPool(workers) as pool:
        results = pool.map(_fit_block, tasks, progress=bar.update)
    seconds = time.perf_counter() - started
    timesteps = [t for result in results for t in result["timesteps"]]
    rows = {key: np.concatenate([result["rows"][key] for result in results]) for key in FRAME_KEYS}  # [N, ...]
    before = np.concatenate([result["before"] for result in results])  # [N] L1, NaN: empty mask
    after = np.concatenate([result["after"] for result in results])
    atomic_write_npz(Path(run_dir) / HELD_OUT_FILE, timesteps=np.asarray(timesteps, dtype=np.int64),
                     step=np.asarray(run.info.step), **rows)
    report = {"frames": len(timesteps), "checkpoint_step": run.info.step, **asdict(config), "workers": workers,
              "seconds": round(seconds, 1), "l1_before": _nanmean(before), "l1": _nanmean(after)}
    atomic_write_json(Path(run_dir) / HELD_OUT_REPORT, report)
    log(f"held-out fit: {len(timesteps)} test frames fitted against the avatar in {seconds:.0f} s "
        f"({config.steps} steps a frame, {workers} worker(s)); L1 {report['l1_before']:.4f} -> {report['l1']:.4f}")
    return report


def _nanmean(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return round(float(finite.mean()), 5) if finite.size else None


def read_held_out(run_dir: Path, step: int) -> tuple[list[int], dict[str, np.ndarray]] | None:
    """(timesteps [N], per-frame keys [N, ...]) of RUN/held_out.npz when it was fitted against the checkpoint of
    `step`; None when there is none or it is stale (the run trained on since)."""
    path = Path(run_dir) / HELD_OUT_FILE
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as stored:
        if int(stored["step"]) != int(step):
            return None
        return [int(t) for t in stored["timesteps"]], {key: stored[key] for key in FRAME_KEYS}


__all__ = ["BLOCK", "HELD_OUT_FILE", "HELD_OUT_REPORT", "HeldOutFitConfig", "fit_held_out", "read_held_out"]
