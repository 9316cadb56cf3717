"""Test stills of two avatars of one video (before | after): ground truth | avatar A | avatar B | error A | error B,
one row per pair and frame, from `geoavatar eval RUN --save-images` frames.

    .venv/bin/python benchmarks/tracking_stills.py --out docs/images/tracking_test_stills.png \
        --pair R/wojtek_lm R/wojtek_ph --pair R/duda_lm R/duda_ph [--at 0.75 ...]

A RUN is a run folder (its eval/test frames) or one of its eval folders, e.g. R/d3/eval/test@d3_track for the
frames `geoavatar eval R/d3 --data d3_track --save-images` wrote. Each pair gets a row per --at, the test frame at
that fraction of the split (the same frame for both). The panels of an eval frame are ground truth | render | error
map | ...; each panel is kept as written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image


def eval_frames(run: Path) -> list[Path]:
    folder = run if (run / "frames").is_dir() else run / "eval" / "test"
    frames = sorted((folder / "frames").glob("*.png"))
    if not frames:
        raise SystemExit(f"{run}: no eval frames ({folder}/frames/*.png); run `geoavatar eval RUN --save-images` first")
    return frames


def panels(path: Path) -> list[np.ndarray]:
    """The panels of an eval frame (square, side = its height): [gt, render, error, ...]."""
    image = np.asarray(Image.open(path).convert("RGB"))
    side = image.shape[0]
    return [image[:, i:i + side] for i in range(0, image.shape[1] - side + 1, side)]


def pair_row(run_a: Path, run_b: Path, at: float) -> np.ndarray:
    frames_a, frames_b = eval_frames(run_a), eval_frames(run_b)
    if [f.name for f in frames_a] != [f.name for f in frames_b]:
        raise SystemExit(f"{run_a} and {run_b}: their eval frames differ (not the same video's test split?)")
    index = min(len(frames_a) - 1, int(at * len(frames_a)))
    a, b = panels(frames_a[index]), panels(frames_b[index])
    print(f"{frames_a[index].name}: {run_a} | {run_b}")
    # ground truth | A | B | error A | error B
    return np.concatenate([a[0], a[1], b[1], a[2], b[2]], axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair", nargs=2, type=Path, action="append", required=True, metavar=("RUN_A", "RUN_B"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--at", type=float, nargs="+", default=[0.75],
                        help="fractions of the test split where frames are taken (a row each)")
    args = parser.parse_args()
    rows = [pair_row(a, b, at) for a, b in args.pair for at in args.at]
    width = max(row.shape[1] for row in rows)
    rows = [np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)), constant_values=255) for row in rows]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out, optimize=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
