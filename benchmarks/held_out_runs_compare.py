"""A long video's held-out fit in runs against the fit of every held-out frame: the same frames, and the means.

    cp -a RUN RUN_ALL && geoavatar train --out RUN_ALL --resume --held-out-frames 0 && geoavatar eval RUN_ALL
    cp -a RUN RUN_RUNS && geoavatar train --out RUN_RUNS --resume && geoavatar eval RUN_RUNS     # the default
    .venv/bin/python benchmarks/held_out_runs_compare.py RUN_ALL RUN_RUNS

Reads both runs' RUN/eval/test/metrics.json and prints, per metric, the runs' mean over the frames they score, the
whole fit's mean over those same frames and over all of its frames, and the fit's and eval's seconds of each
(RUN/held_out.json, metrics.json): whether fitting runs of neighbours loses anything on the frames it scores
(train/held_out_fit.py) and how far its sample lies from the whole split's mean.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

METRICS = ("psnr", "mouth_psnr", "lpips")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("whole", type=Path, help="a run whose held-out fit fitted every held-out frame")
    parser.add_argument("runs", type=Path, help="the same run with the fit in runs (the default on a long video)")
    args = parser.parse_args()
    whole, runs = (json.loads((run / "eval" / "test" / "metrics.json").read_text()) for run in (args.whole, args.runs))
    by_timestep = {frame["timestep"]: frame for frame in whole["frames"]}
    scored = [frame["timestep"] for frame in runs["frames"]]
    missing = [t for t in scored if t not in by_timestep]
    if missing:
        raise SystemExit(f"{args.whole}: its eval did not score timesteps {missing[:5]}...: evaluate it whole")
    print(f"| metric | runs ({len(scored)} frames) | whole fit, same frames | whole fit, all {len(by_timestep)} |")
    print("|---|---|---|---|")
    for key in METRICS:
        ours = np.mean([frame[key] for frame in runs["frames"]])
        same = np.mean([by_timestep[t][key] for t in scored])
        every = np.mean([frame[key] for frame in whole["frames"]])
        print(f"| {key} | {ours:.4f} | {same:.4f} ({ours - same:+.4f}) | {every:.4f} ({ours - every:+.4f}) |")
    for name, run, report in (("whole", args.whole, whole), ("runs", args.runs, runs)):
        fit = json.loads((run / "held_out.json").read_text())
        print(f"{name}: fit {fit['frames']} frames in {fit['seconds']} s; eval {len(report['frames'])} frames in "
              f"{report['seconds']:.0f} s")


if __name__ == "__main__":
    main()
