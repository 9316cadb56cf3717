"""Speed and accuracy of drive's online fit (prep/tracking.py OnlineFit) on a prepared video's landmarks.

Replays what `geoavatar drive` does after its landmark stage, without video decoding or MediaPipe:
the identity stage (`track_crops` on the first --init-frames frames), then `OnlineFit` on every later
frame's raw landmarks, warm-started frame to frame. Compares each solver's per-frame time (process CPU
time and wall time, one torch thread) and its result with the offline tracking of the whole video
(`prepare`'s tracking.npz): median landmark error / face width, jaw opening (correlation, mean
|difference|), expression change from the neutral (cosine similarity with the offline change).

    .venv/bin/python benchmarks/online_fit_bench.py data/talk   # a `geoavatar prepare` folder
    .venv/bin/python benchmarks/online_fit_bench.py data/talk --solvers lbfgs gauss_newton --iterations 8 3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("prepared", type=Path, help="a `geoavatar prepare` output folder (reads .prepare/*.npz)")
    parser.add_argument("--solvers", nargs="+", default=["lbfgs", "gauss_newton"])
    parser.add_argument("--iterations", nargs="+", type=int, default=None,
                        help="iterations per solver (default: each solver's default)")
    parser.add_argument("--init-frames", type=int, default=25)
    parser.add_argument("--frames", type=int, default=None, help="online frames to fit (default: all)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    import numpy as np
    import torch

    from geoavatar.prep.pipeline import PrepareConfig, load_tracking_head, tracking_config
    from geoavatar.prep.tracking import ONLINE_SOLVERS, OnlineFit, crop_principal_point, track_crops

    torch.set_num_threads(args.threads)
    work = args.prepared / ".prepare"
    with np.load(work / "landmarks.npz") as z:
        raw, filtered, confidence = z["raw"], z["filtered"], z["confidence"]
    with np.load(work / "frames.npz") as z:
        boxes, frame_size = z["boxes"], tuple(int(v) for v in z["frame_size"])
    with np.load(work / "tracking.npz") as z:
        offline = {k[len("param_"):]: z[k] for k in z.files if k.startswith("param_")}
    crop_size = int(json.loads((args.prepared / "report.json").read_text())["size"])  # the crops the landmarks are in
    prepare = PrepareConfig(video=Path("-"), out=Path("-"), log=lambda _line: None)
    data, model = load_tracking_head(prepare)
    config = tracking_config(prepare)
    n0 = args.init_frames
    init = track_crops(model, data, filtered[:n0], confidence[:n0], boxes[:n0], frame_size, crop_size, config)
    end = len(raw) if args.frames is None else min(len(raw), n0 + args.frames)
    iterations = args.iterations or [None] * len(args.solvers)
    if len(iterations) != len(args.solvers):
        parser.error("--iterations needs one value per solver")

    neutral_offline = offline["expr"][:n0].mean(0)
    print(f"{args.prepared}: identity from {n0} frames, {end - n0} online frames, crop {crop_size} px, "
          f"{args.threads} thread(s)")
    print("| solver | iterations | ms/frame CPU (median) | ms/frame wall (median / p95) | landmark error median / worst (%) "
          "| jaw corr. / mean abs diff (rad) | expression change cosine (median) |")
    print("|---|---|---|---|---|---|---|")
    for solver, iters in zip(args.solvers, iterations):
        if solver not in ONLINE_SOLVERS:
            parser.error(f"unknown solver {solver!r}; one of {', '.join(ONLINE_SOLVERS)}")
        kwargs = {} if iters is None else {"iterations": iters}
        online = OnlineFit(model, init, config, solver=solver, **kwargs)
        cpu, wall, errors, jaw, expr = [], [], [], [], []
        for t in range(n0, end):
            principal = crop_principal_point(boxes[t], frame_size, crop_size)
            c0, w0 = time.process_time(), time.perf_counter()
            params, error = online(raw[t], principal)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            errors.append(error)
            jaw.append(float(params.jaw_pose[0, 0]))
            expr.append(params.expr[0].numpy())
        neutral_online = init.params["expr"].mean(0)  # [E] the driver's first second, as drive --relative takes it
        change_on = np.asarray(expr) - neutral_online
        change_off = offline["expr"][n0:end] - neutral_offline
        cos = (change_on * change_off).sum(-1) / (np.linalg.norm(change_on, axis=-1) * np.linalg.norm(change_off, axis=-1) + 1e-12)
        jaw_off = offline["jaw_pose"][n0:end, 0]
        corr = float(np.corrcoef(jaw, jaw_off)[0, 1])
        print(f"| {solver} | {online.iterations} | {1e3 * np.median(cpu):.1f} | {1e3 * np.median(wall):.1f} / "
              f"{1e3 * np.percentile(wall, 95):.1f} | {100 * np.median(errors):.2f} / {100 * np.max(errors):.2f} | "
              f"{corr:.2f} / {np.mean(np.abs(np.asarray(jaw) - jaw_off)):.3f} | {np.median(cos):.2f} |", flush=True)


if __name__ == "__main__":
    main()
