"""Time (or profile) one segment of `prepare`'s photometric fit in this process, on one thread.

    .venv/bin/python benchmarks/photometric_segment_bench.py OUT/.prepare --video VIDEO --frames 64 --epochs 8 8 \
        [--no-supersample] [--freeze-gc] [--profile]

OUT/.prepare is a finished `prepare`'s work folder (its frames, landmarks and tracking stages are read; nothing is
written). The first `--frames` rows of the first segment are fitted with one appearance-only epoch and `--epochs` at
64 and 128 px, after a short warm-up fit (the native loops' first use), and the line printed is the wall time and the
milliseconds per frame and epoch. `--profile` prints cProfile's heaviest functions instead of a bare timing (its
overhead inflates the figure). Compare settings as pairs started together on the two cores
(`benchmarks/pair_together.py`): this machine's speed drifts between runs minutes apart.
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import pstats
import time
from dataclasses import replace
from pathlib import Path

import torch


def segment_job(work: Path, video: Path, frames: int, epochs: tuple[int, int], supersample: bool):
    """The first segment's job of the work folder, cut to its first `frames` rows, with this schedule."""
    from geoavatar.prep import pipeline

    config = pipeline.PrepareConfig(video=video, out=work.parent)
    marks, fit, head, init = pipeline.photometric_inputs(config, work)
    jobs, _ = pipeline._segment_jobs(config, work, head, init, fit, marks)
    job = jobs[0]
    n = min(frames, len(job.rows))
    per_frame = lambda value: value[:n] if value.ndim and value.shape[0] == len(job.rows) else value  # noqa: E731
    return replace(job, rows=job.rows[:n], keep=slice(0, n), viewmat=job.viewmat[:n], K=job.K[:n], boxes=job.boxes[:n],
                   params={k: per_frame(v) if k != "shape" else v for k, v in job.params.items()},
                   landmarks={k: v if k == "weights" else v[:n] for k, v in job.landmarks.items()},
                   settings=replace(job.settings, epochs=epochs, appearance_epochs=1, supersample=supersample))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("work", type=Path, help="a finished prepare's OUT/.prepare")
    parser.add_argument("--video", type=Path, required=True, help="the video that prepare ran on")
    parser.add_argument("--frames", type=int, default=64)
    parser.add_argument("--epochs", type=int, nargs=2, default=(8, 8), help="at 64 px, at 128 px")
    parser.add_argument("--no-supersample", action="store_true", help="the coarse level rendered at its own size")
    parser.add_argument("--freeze-gc", action="store_true", help="gc.freeze() and a raised threshold before the fit")
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()

    from geoavatar.prep.segments import fit_segment

    torch.set_num_threads(1)  # as prepare's workers run the fit
    job = segment_job(args.work, args.video, args.frames, tuple(args.epochs), not args.no_supersample)
    fit_segment(replace(job, settings=replace(job.settings, epochs=(1, 1))))  # warm-up: first use of the loops
    if args.freeze_gc:
        gc.collect()
        gc.freeze()
        gc.set_threshold(100_000, 50, 100)
    profile = cProfile.Profile() if args.profile else None
    start = time.perf_counter()
    if profile:
        profile.enable()
    fit_segment(job)
    if profile:
        profile.disable()
    wall = time.perf_counter() - start
    if profile:
        pstats.Stats(profile).sort_stats("tottime").print_stats(30)
    frame_epochs = len(job.rows) * (sum(args.epochs) + 1)
    print(f"{wall:.2f} s, {wall / frame_epochs * 1e3:.2f} ms per frame and epoch ({len(job.rows)} frames, epochs "
          f"{tuple(args.epochs)} + 1 appearance-only)")


if __name__ == "__main__":
    main()
