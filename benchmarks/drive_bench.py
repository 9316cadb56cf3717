"""Benchmark of `geoavatar drive`: a video drives a trained avatar as a live source.

For each output size: the real-time pipeline (the video played at its frame rate, frames dropped when
the worker falls behind) gives the end-to-end FPS, the drop rate, the latency (frame available ->
output done; median and 95th percentile) and the mean time of each stage (landmarks, fit, pose,
render), after the identity stage (the file's clock starts there), with the mp4 writer on (driver | avatar, as `drive --out` does). With --offline (the
`geoavatar prepare` folder of the driving video), a lossless pass (every frame fitted, nothing
rendered) compares the online fit with the offline landmark tracking of the same frames: median
landmark error per frame (each against its own detections: online vs raw MediaPipe points in its live
crop, offline vs prepare's filtered points), and jaw / expression agreement (jaw opening: correlation
and mean absolute difference; expression: median cosine similarity of the change of the coefficient
vectors from each fit's neutral, the mean of the first second, as --relative transfers it).
The load average is printed before and after; the settings of the avatar's run are printed.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/drive_bench.py --avatar RUN --driver VIDEO \\
        [--offline PREPARED_DIR] [--sizes 256 512] [--seconds 8]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--avatar", type=Path, required=True, help="run folder (geoavatar train)")
    parser.add_argument("--driver", type=Path, required=True, help="driving video")
    parser.add_argument("--offline", type=Path, default=None, help="geoavatar prepare folder of the driving video")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--seconds", type=float, default=8.0, help="seconds of the video played (after the first)")
    parser.add_argument("--solver", choices=["gauss_newton", "lbfgs"], default="gauss_newton")
    parser.add_argument("--iterations", type=int, default=None, help="online fit iterations (default: the solver's)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=1, help="drive's --threads")
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    import torch

    from geoavatar.apps.drive import drive_avatar, open_video
    from geoavatar.train.checkpoint import open_run

    print(f"load average before: {load()}; torch threads {torch.get_num_threads()}, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '-')}")
    run = open_run(args.avatar, args.device)
    config = json.loads((args.avatar / "config.json").read_text())
    source = open_video(args.driver)
    frames = int(round((1.0 + args.seconds) * source.fps))
    print(f"avatar {args.avatar} (preset {config.get('preset', '?')}, checkpoint step {run.info.step} of {config.get('schedule', {}).get('steps', '?')}, "
          f"{run.avatar.num_gaussians} Gaussians, trained at {run.info.resolution} px, device {run.avatar.binding.device}); "
          f"driver {args.driver} at {source.fps:g} fps, {frames} frames; online fit {args.solver} ({args.iterations or 'default'} iterations); "
          f"drive --threads {args.threads}")
    print()
    print("| output | FPS | dropped | latency p50 / p95 (ms) | landmarks | fit | pose | render (ms, mean) | identity stage |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            stats = drive_avatar(run, open_video(args.driver), Path(tmp) / f"drive_{size}.mp4", size=size,
                                 iterations=args.iterations, solver=args.solver, max_frames=frames, status=False, threads=args.threads)
            ms = {s: np.mean(v) if v else float("nan") for s, v in stats.stage_ms.items()}
            lat = np.array(stats.latency_ms)
            print(f"| {size}² | {stats.fps:.1f} | {stats.dropped}/{stats.delivered} | {np.median(lat):.0f} / "
                  f"{np.percentile(lat, 95):.0f} | {ms['landmarks']:.1f} | {ms['fit']:.1f} | {ms['pose']:.1f} | "
                  f"{ms['render']:.1f} | {stats.init_frames} frames, {stats.init_seconds:.1f} s |", flush=True)
    print(f"\nload average after the real-time runs: {load()}")

    if args.offline is None:
        return
    work = args.offline / ".prepare"
    offline_frames = np.load(work / "frames.npz")
    tracked = np.load(work / "tracking.npz")
    row_of = {int(s): r for r, s in enumerate(offline_frames["source_index"])}
    started = time.perf_counter()
    stats = drive_avatar(run, open_video(args.driver), None, size=args.sizes[0], iterations=args.iterations, solver=args.solver,
                         max_frames=frames, lossless=True, record=True, status=False, render=False,
                         threads=args.threads)
    online = [r for r in stats.records if not r.get("init") and r["found"] and r["index"] in row_of]
    rows = [row_of[r["index"]] for r in online]
    jaw_on = np.array([r["jaw_pose"][0] for r in online])
    jaw_off = tracked["param_jaw_pose"][rows, 0]
    expr_on = np.stack([r["expr"] for r in online])
    expr_off = tracked["param_expr"][rows][:, :expr_on.shape[1]]
    # expression as --relative uses it: the change from each fit's neutral (the driver's first second), since each
    # fit's identity differs (first second vs whole video) and expression coefficients absorb some of it
    init_rows = [row_of[r["index"]] for r in stats.records if r.get("init")]
    delta_on = expr_on - np.mean([r["expr"] for r in stats.records if r.get("init")], axis=0)
    delta_off = expr_off - tracked["param_expr"][init_rows][:, :expr_on.shape[1]].mean(0)
    cosine = (delta_on * delta_off).sum(1) / np.maximum(np.linalg.norm(delta_on, axis=1) * np.linalg.norm(delta_off, axis=1), 1e-9)
    err_on = np.array([r["error"] for r in online])
    err_off = tracked["errors"][rows]
    print(f"\naccuracy, every frame fitted (lossless pass, {len(online)} online frames, {time.perf_counter() - started:.0f} s, "
          f"load {load()}):")
    print("| | median landmark error / face width: median frame | worst frame |")
    print("|---|---|---|")
    print(f"| online fit | {100 * np.median(err_on):.2f} % | {100 * err_on.max():.2f} % |")
    print(f"| offline tracking (prepare) | {100 * np.median(err_off):.2f} % | {100 * err_off.max():.2f} % |")
    print(f"\njaw opening online vs offline: correlation {np.corrcoef(jaw_on, jaw_off)[0, 1]:.3f}, mean |difference| "
          f"{np.mean(np.abs(jaw_on - jaw_off)):.4f} rad (offline range {jaw_off.min():.3f}..{jaw_off.max():.3f}); "
          f"expression change from the neutral, cosine similarity: median {np.median(cosine):.3f}, 10th percentile {np.percentile(cosine, 10):.3f}")


if __name__ == "__main__":
    main()
