"""Which per-frame parameters cost a run's held-out frames their PSNR: each group of the written parameters swapped
for the same frame's parameters from a second tracking (e.g. `geoavatar track DATA --avatar RUN --out TRACKED`).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/param_swap.py RUN TRACKED [--data DATA] [--every 2]

Every test frame (or every --every-th) is rendered with the run's avatar and the dataset's written parameters, then
with one group replaced by TRACKED's values, then with all of them; the mean PSNR of each row is printed. A group
whose swap gains nothing is not where the written parameters fall short (issue #27: on d3 the rigid pose carries the
whole gap, the expression none). Frames are posed as `geoavatar eval` poses them (RunFrames: the T rule).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from geoavatar.avatar import render_avatar
from geoavatar.data.dataset import item_camera, item_to
from geoavatar.eval import metrics
from geoavatar.head.params import HeadParams
from geoavatar.render import composite_target
from geoavatar.train.checkpoint import open_run, open_run_dataset
from geoavatar.train.run_frames import RunFrames

GROUPS = {
    "translation": ("translation",),
    "rotation + neck": ("rotation", "neck_pose"),
    "jaw": ("jaw_pose",),
    "expression": ("expr",),
    "eyes": ("eyes_pose",),
}
ALL_KEYS = tuple(key for keys in GROUPS.values() for key in keys)


def swap_scores(run_dir: Path, tracked: Path, data: Path | None, every: int) -> dict[str, float]:
    """Mean test PSNR per row: written, each group swapped, all swapped."""
    run = open_run(run_dir, "cpu")
    frames = RunFrames(run)
    written_set = open_run_dataset(run, "test", data)
    tracked_set = open_run_dataset(run, "test", tracked)
    rows = {"written": (), **GROUPS, "all": ALL_KEYS}
    scores: dict[str, list[float]] = {name: [] for name in rows}
    for index in range(0, len(written_set), every):
        item = item_to(written_set[index], frames.device)
        other = item_to(tracked_set[index], frames.device)
        if int(item["timestep"]) != int(other["timestep"]):
            raise SystemExit(f"{tracked}: its test frames are not {data or 'the run dataset'}'s")
        written, timestep = frames.params(item["timestep"], HeadParams.from_npz(item["params"]))
        fitted = HeadParams.from_npz(other["params"])
        target = composite_target(item["image"], item["mask"], item["background"])  # [H, W, 3]
        for name, keys in rows.items():
            params = written.replace(**{key: getattr(fitted, key) for key in keys})
            frame = render_avatar(run.avatar, run.head, params, item_camera(item), timestep, run.deformer,
                                  item["background"])
            scores[name].append(metrics.psnr(frame.result.rgb.clamp(0.0, 1.0), target))  # as eval scores
    return {name: float(np.mean(values)) for name, values in scores.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("tracked", type=Path, help="a copy of the dataset with other parameters for its test frames")
    parser.add_argument("--data", type=Path, default=None, help="the written dataset (default: the run's)")
    parser.add_argument("--every", type=int, default=2, help="every n-th test frame")
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    scores = swap_scores(args.run, args.tracked, args.data, max(1, args.every))
    base = scores["written"]
    for name, value in scores.items():
        print(f"{name:16s} {value:6.2f} dB  ({value - base:+.2f})")


if __name__ == "__main__":
    main()
