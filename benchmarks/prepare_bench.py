"""Benchmark `geoavatar prepare` on a whole video, then (optionally) train and evaluate on it.

    .venv/bin/python benchmarks/prepare_bench.py ../shared/data/video/wojtek.mp4 --out runs/prep/wojtek \
        [--no-photometric] [--stills docs/images/prepare_overlay_wojtek.png] [--train-steps 3000 --resolution 256]

Prints (and writes OUT/bench.json): wall and CPU seconds per stage (a stage skipped because it was complete
keeps the figures of the run that made it), the load average before and after, the per-frame median landmark
reprojection error over the face width (median / p90 / max over frames, share of frames below 2 %),
the correlation of the tracked jaw opening with the detected mouth opening (inner-lip gap 13-14 over
the face size; of the fit the dataset is written from), the mean photometric residual before and after
the photometric stage, and with --train-steps the train and eval numbers (PSNR / SSIM / LPIPS on the held-out
last 20 % of the frames). --stills writes three overlay frames side by side (first frame, widest
mouth opening, a late test frame) for the README.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("video", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--no-photometric", dest="photometric", action="store_false",
                        help="skip the photometric stage (prepare --no-photometric)")
    parser.add_argument("--stills", type=Path, default=None)
    parser.add_argument("--train-steps", type=int, default=0)
    parser.add_argument("--resolution", type=int, default=256)
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    from geoavatar.prep.pipeline import STAGES, PrepareConfig, fit_file, overlay_frames, run_prepare

    config = PrepareConfig(video=args.video, out=args.out, size=args.size, max_frames=args.max_frames,
                           photometric=args.photometric)
    load_before = os.getloadavg()
    start, cpu = time.perf_counter(), time.process_time()
    dataset = run_prepare(config)
    result: dict = {"video": str(args.video), "photometric": args.photometric,
                    "prepare_wall_s": time.perf_counter() - start,
                    "prepare_cpu_s_this_process": time.process_time() - cpu,
                    "load_average_1min_before_after": [load_before[0], os.getloadavg()[0]], "stages": {}}
    work = args.out / ".prepare"
    for stage in STAGES:
        marker = json.loads((work / f"{stage}.json").read_text())
        result["stages"][stage] = {"wall_s": round(marker.get("seconds", float("nan")), 1),
                                   "cpu_s": round(marker.get("cpu_seconds", float("nan")), 1)}
    report = json.loads((args.out / "report.json").read_text())
    errors = np.array(report["reprojection_error_over_face_width"]["per_frame"])
    marks = np.load(work / "landmarks.npz")
    fit = np.load(fit_file(config, work))
    points = marks["filtered"]
    mouth = np.linalg.norm(points[:, 13, :2] - points[:, 14, :2], axis=-1) / np.linalg.norm(
        points[:, 10, :2] - points[:, 152, :2], axis=-1)
    jaw = fit["param_jaw_pose"][:, 0]
    result.update({
        "frames": int(len(errors)),
        "missing_source_frames": report["missing_source_frames"],
        "error_median": float(np.median(errors)), "error_p90": float(np.percentile(errors, 90)),
        "error_max": float(errors.max()), "frames_below_2pct": float((errors < 0.02).mean()),
        "jaw_open_rad_range": [float(jaw.min()), float(jaw.max())],
        "corr_jaw_mouth_opening": float(np.corrcoef(jaw, mouth)[0, 1]),
        "focal_px": float(fit["focal"]),
    })
    if "photometric_residual" in report:
        residual = report["photometric_residual"]
        result["photometric_residual_before_after"] = [residual["mean_before"], residual["mean"]]
    if args.stills:
        from PIL import Image

        from geoavatar.prep.overlay import contact_sheet

        rows = [0, int(np.argmax(mouth)), int(0.9 * (len(errors) - 1))]
        pictures = dict(overlay_frames(config, work, rows))
        sheet = contact_sheet([pictures[r] for r in rows],
                              [f"frame {r}  err {errors[r] * 100:.1f}%  jaw {jaw[r]:.2f}" for r in rows])
        args.stills.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(sheet).save(args.stills)
        result["stills"] = str(args.stills)
    if args.train_steps > 0:
        run = args.out / f"train_{args.train_steps}"
        geoavatar = [sys.executable, "-m", "geoavatar.cli"]
        t0, c0 = time.perf_counter(), _children_cpu()
        subprocess.run([*geoavatar, "train", "--data", str(dataset), "--out", str(run), "--steps", str(args.train_steps),
                        "--resolution", str(args.resolution), "--no-progress"], check=True)
        result["train_wall_s"], result["train_cpu_s"] = time.perf_counter() - t0, _children_cpu() - c0
        t0, c0 = time.perf_counter(), _children_cpu()
        subprocess.run([*geoavatar, "eval", str(run), "--no-progress"], check=True)
        result["eval_wall_s"], result["eval_cpu_s"] = time.perf_counter() - t0, _children_cpu() - c0
        metrics = run / "eval" / "test" / "metrics.json"
        if metrics.is_file():
            result["eval"] = json.loads(metrics.read_text()).get("summary")
    (args.out / "bench.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


def _children_cpu() -> float:
    times = os.times()
    return times.children_user + times.children_system


if __name__ == "__main__":
    sys.exit(main())
