"""The held-out frames' head parameters fitted against the finished avatar: the last stage of `geoavatar train`.

    report = fit_held_out(run_dir, HeldOutFitConfig())     # writes RUN/held_out.npz and RUN/held_out.json
    stored = read_held_out(run_dir, step)                  # HeldOutRows(timesteps, rows, scored); None: none / stale

Why: training refines the parameters of the frames it trains on against the avatar it learns
(train/frame_params.py); the held-out frames keep the tracker's, whose appearance model (prepare's mesh-bound
albedo in face crops) cannot see the hair's outline and does not share the offset the avatar absorbed from its
training frames. On an expressive video that cost the held-out frames 3 dB (docs/expressive_video.md). This
fit gives them what training gives its own frames: parameters in which the avatar explains the image
(train/avatar_tracking.py, each frame alone, the avatar frozen). The avatar never sees a held-out frame's pixels
while it learns; the fit happens after, as `geoavatar track --avatar` does it, and replaces the Gaussian head of
the whole video that `prepare` once trained for the same purpose (a second training of the same frames).

How: the test frames in an even number of contiguous blocks of at most BLOCK frames (two for a 12-s video), each
block on a worker process (both cores busy to the end, one torch thread each: geoavatar.workers), each frame from
the previous frame's correction when that renders closer (AvatarTrackingConfig.carry), so fewer steps reach the
full fit. The blocks do not depend on the worker count, so neither does the result. A long video (more than
MAX_FRAMES test frames) is fitted on runs of RUN_LENGTH neighbours spread evenly over its test split, so the fit's
time is bounded whatever the video's length: a frame's fit needs its neighbours' correction (the carry builds it up
over a few frames), so the first WARM_UP frames of each run only hand their correction on and are not scored. The
frames between the runs get the tracker's rows plus the correction interpolated from their fitted neighbours, so a
render of the whole split stays smooth; `geoavatar eval` scores the scored ones (eval/evaluate.py). The rows are
kept beside the checkpoint, tagged with its step: `load_run` lays them over the run's parameters while they belong
to its checkpoint (an --extend makes them stale until refitted).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from geoavatar.head.params import FRAME_KEYS
from geoavatar.workers import split_range

HELD_OUT_FILE = "held_out.npz"  # timesteps [N], scored [N] (bool), step, and the per-frame keys [N, ...]
HELD_OUT_REPORT = "held_out.json"
BLOCK = 36  # frames per task at most, in an even number of tasks: the carry restarts at each block
MAX_FRAMES = 144  # test frames fitted at most: beyond, 24 runs of RUN_LENGTH, 96 of them scored
RUN_LENGTH = 6  # a long video's runs of neighbouring frames...
WARM_UP = 2  # ...whose first frames only hand their correction on (not scored)
RUNS_PER_BLOCK = 4  # runs per worker task at most (fewer when that leaves a worker idle): the carry goes on across
                    # the gaps between them


@dataclass
class HeldOutFitConfig:
    """Adam steps per frame and the carry between neighbouring frames (BENCHMARKS.md, Time to a good avatar)."""

    # 10 / 20 / 30 steps with carry: held-out PSNR duda 34.48 / 34.91 / 35.08 dB, d3 25.42 / 25.60 / 25.66, at
    # 1 / 1.75 / 2.4-2.6 times the fit's time: 20 brings duda within #40's 0.3 dB of prepare's old gaussian stage
    # (34.84)
    steps: int = 20
    carry: bool = True
    # Test frames fitted at most (None: all), beyond which the fit takes runs spread evenly (module docstring). A
    # 12-s video's ~70 are all fitted; all of a 50-s video's 302 took 9 minutes, a 3-minute video's ~1,080 would take
    # over half an hour (BENCHMARKS.md, Time to a good avatar).
    max_frames: int | None = MAX_FRAMES

    def __post_init__(self):
        if self.steps < 1:
            raise ValueError(f"held-out fit: need steps >= 1, got {self.steps}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"held-out fit: need max_frames >= 1 (or None: all), got {self.max_frames}")


@dataclass(frozen=True)
class FitTask:
    """One worker task: fit frames `indices` of a dataset against the run's avatar, the carry running through them."""

    run_dir: str
    step: int  # the checkpoint's (a worker's cache key)
    indices: tuple[int, ...]  # into the run's test split, or into the "all" split of `data`
    steps: int
    carry: bool
    data: str | None = None  # another dataset of the run's person (track --avatar); None: the run's own test split
    device: str = "cpu"
    flame_dir: str | None = None


def _fit_block(task: FitTask) -> dict:
    """A worker's task: rows [n, ...] of its frames and their L1 [n] before and after."""
    from geoavatar.train.avatar_tracking import AvatarTrackingConfig, dataset_frames, track_frames
    from geoavatar.train.checkpoint import load_run, open_clip_dataset, open_run_dataset
    from geoavatar.workers import report_progress, worker_cache

    def opened():
        run = load_run(task.run_dir, task.device, flame_dir=task.flame_dir)
        dataset = open_run_dataset(run, "test") if task.data is None else open_clip_dataset(run, task.data,
                                                                                             task.flame_dir)
        return run, dataset

    run, dataset = worker_cache(f"avatar-fit:{task.run_dir}:{task.step}:{task.data}:{task.device}", opened)
    fit = AvatarTrackingConfig(steps=task.steps, carry=task.carry)
    result = track_frames(run.avatar, run.head, run.deformer, dataset_frames(dataset, task.indices, run.device), fit,
                          progress=report_progress)
    return {"rows": {key: getattr(result.params, key).cpu().numpy() for key in FRAME_KEYS},
            "before": result.loss_before, "after": result.loss_after}


def fit_tasks(tasks: list[FitTask], workers: int, progress: Callable[[int], None] | None = None
              ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The tasks on `workers` processes (one torch thread each; inline with one): the fitted rows [n, ...] of all
    their frames in task order, and the L1 [n] before and after (NaN: an empty mask, not fitted)."""
    from geoavatar.workers import WorkerPool

    with WorkerPool(max(1, min(workers, len(tasks)))) as pool:
        results = pool.map(_fit_block, tasks, progress=progress)
    rows = {key: np.concatenate([result["rows"][key] for result in results]) for key in FRAME_KEYS}
    return (rows, np.concatenate([result["before"] for result in results]),
            np.concatenate([result["after"] for result in results]))


def fit_held_out(run_dir: Path, config: HeldOutFitConfig = HeldOutFitConfig(), workers: int | None = None,
                 progress: bool = True, log: Callable[[str], None] = print) -> dict | None:
    """Fit the test frames of the finished run in `run_dir` against its avatar; writes RUN/held_out.npz and
    RUN/held_out.json and returns the report (None: the run has no test frames)."""
    from tqdm import tqdm

    from geoavatar.io.atomic import atomic_write_json, atomic_write_npz
    from geoavatar.train.checkpoint import load_run, open_run_dataset
    from geoavatar.workers import default_workers

    run = load_run(run_dir, "cpu")
    test = open_run_dataset(run, "test")
    if len(test) == 0:
        return None
    blocks, scored = fit_plan(len(test), config.max_frames)  # indices into the test split, in time order
    picked = [index for block in blocks for index in block]
    workers = max(1, min(workers or default_workers(), len(blocks)))
    started = time.perf_counter()
    tasks = [FitTask(str(run_dir), run.info.step, block, config.steps, config.carry) for block in blocks]
    with tqdm(total=len(picked), desc="train: held-out fit", unit="frame", disable=not progress) as bar:
        fitted, before, after = fit_tasks(tasks, workers, bar.update)  # [n, ...], [n], [n]
    seconds = time.perf_counter() - started
    timesteps = [int(frame.timestep) for frame in test.frames]  # [N] the whole test split
    rows_of_split = [frame.row for frame in test.frames]
    tracked = {key: test.subject.params[key][rows_of_split].numpy() for key in FRAME_KEYS}  # [N, ...] the tracker's
    rows = fill_between(timesteps, tracked, picked, fitted)
    atomic_write_npz(Path(run_dir) / HELD_OUT_FILE, timesteps=np.asarray(timesteps, dtype=np.int64),
                     scored=np.isin(np.arange(len(timesteps)), scored), step=np.asarray(run.info.step), **rows)
    report = {"frames": len(picked), "scored_frames": len(scored), "test_frames": len(timesteps),
              "checkpoint_step": run.info.step, **asdict(config), "workers": workers, "seconds": round(seconds, 1),
              "l1_before": _nanmean(before), "l1": _nanmean(after)}
    atomic_write_json(Path(run_dir) / HELD_OUT_REPORT, report)
    some = (f"{len(picked)} of the {len(timesteps)} test frames ({len(scored)} scored)" if len(picked) < len(timesteps)
            else f"{len(picked)} test frames")
    log(f"held-out fit: {some} fitted against the avatar in {seconds:.0f} s "
        f"({config.steps} steps a frame, {workers} worker(s)); L1 {report['l1_before']:.4f} -> {report['l1']:.4f}")
    return report


def fit_plan(count: int, limit: int | None) -> tuple[list[tuple[int, ...]], list[int]]:
    """(blocks: tuples of indices into a test split of `count` frames, one worker task each, the carry running
    through it; scored: the indices eval scores). Up to `limit` frames (None: no limit) every frame, in an even
    number of blocks of at most BLOCK; beyond, runs of RUN_LENGTH neighbours spread evenly, RUNS_PER_BLOCK to a
    block, without their first WARM_UP frames in the scores. Fitted alone from a predecessor two to three frames
    away, the frames of french.mp4 scored 0.22 dB under the full fit's; in runs of four a run's n-th frame scored
    -0.38 / -0.21 / -0.12 / +0.04 dB against it (BENCHMARKS.md, Time to a good avatar)."""
    if limit is None or count <= max(limit, RUN_LENGTH):
        tasks = 2 * math.ceil(count / (2 * BLOCK))  # even: two workers end together (blocks of 16 left one idle)
        return [tuple(range(a, b)) for a, b in split_range(count, tasks)], list(range(count))
    starts = np.round(np.linspace(0, count - RUN_LENGTH, max(1, limit // RUN_LENGTH))).astype(int)
    runs = [tuple(range(int(start), int(start) + RUN_LENGTH)) for start in starts]
    per_block = max(1, min(RUNS_PER_BLOCK, len(runs) // 2))  # two tasks at least: both cores busy
    blocks = [sum(runs[i:i + per_block], ()) for i in range(0, len(runs), per_block)]
    return blocks, [index for run in runs for index in run[WARM_UP:]]


def fill_between(timesteps: list[int], tracked: dict[str, np.ndarray], picked: list[int],
                 fitted: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows [N, ...] of every test frame: the fitted rows at `picked` (indices into `timesteps`, rising), elsewhere
    the tracker's row plus the fit's correction (fitted - tracked) interpolated linearly in time between the
    nearest fitted frames (held beyond the ends). A frame's correction is not smooth in time (docs/REJECTED.md,
    #40 ninth round), so these rows render a smooth video of the split but are not scored."""
    times = np.asarray(timesteps, dtype=np.float64)
    rows = {}
    for key, values in tracked.items():
        flat = values.reshape(len(times), -1).astype(np.float64)  # [N, D]
        correction = fitted[key].reshape(len(picked), -1) - flat[picked]  # [n, D]
        filled = np.stack([np.interp(times, times[picked], correction[:, d]) for d in range(flat.shape[1])], 1)
        filled = flat + filled
        filled[picked] = fitted[key].reshape(len(picked), -1)
        rows[key] = filled.reshape(values.shape).astype(fitted[key].dtype)
    return rows


def is_fitted(run_dir: Path, config: HeldOutFitConfig) -> bool:
    """Whether RUN/held_out.npz belongs to the run's last checkpoint and RUN/held_out.json says it was fitted with
    `config` (the same frames, steps and carry give the same rows, whatever the worker count)."""
    import json

    from geoavatar.train.checkpoint import run_checkpoint_path, saved_step

    try:
        report = json.loads((Path(run_dir) / HELD_OUT_REPORT).read_text())
    except (OSError, ValueError):
        return False
    step = saved_step(run_checkpoint_path(run_dir, "last"))
    settings = asdict(config)
    same = isinstance(report, dict) and all(report.get(key, "missing") == value for key, value in settings.items())
    return same and step is not None and read_held_out(run_dir, step) is not None


def _nanmean(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return round(float(finite.mean()), 5) if finite.size else None


class HeldOutRows(NamedTuple):
    timesteps: list[int]  # [N] the test frames the file holds rows for
    rows: dict[str, np.ndarray]  # per-frame keys [N, ...]
    scored: list[int]  # the timesteps among them that eval scores (fitted, not warm-ups; the others: fill_between)


def read_held_out(run_dir: Path, step: int) -> HeldOutRows | None:
    """RUN/held_out.npz when it was fitted against the checkpoint of `step`; None when there is none or it is stale
    (the run trained on since)."""
    path = Path(run_dir) / HELD_OUT_FILE
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as stored:
        if int(stored["step"]) != int(step):
            return None
        timesteps = [int(t) for t in stored["timesteps"]]
        scored = stored["scored"] if "scored" in stored.files else np.ones(len(timesteps), bool)  # before the cap
        return HeldOutRows(timesteps, {key: stored[key] for key in FRAME_KEYS},
                           [t for t, was in zip(timesteps, scored) if was])


__all__ = ["BLOCK", "HELD_OUT_FILE", "HELD_OUT_REPORT", "MAX_FRAMES", "RUN_LENGTH", "WARM_UP", "FitTask",
           "HeldOutFitConfig", "HeldOutRows", "fill_between", "fit_held_out", "fit_plan", "fit_tasks",
           "is_fitted", "read_held_out"]
