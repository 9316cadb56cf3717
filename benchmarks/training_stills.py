"""Training-frame stills of two runs of one dataset (before | after): ground truth | run A | run B | error A | error B,
one row per timestep, each run posed with its own refined parameters and T, as training scores a frame.

    .venv/bin/python benchmarks/training_stills.py R/d3_before R/d3 --timesteps 12 221 233 270 \
        --out docs/images/d3_training_stills.jpg

Prints each timestep's PSNR for both runs. Issue #27: where the head sat off the image's on training frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def error_panel(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8: the error map of eval's and render's stills (apps/common.error_map) of two uint8 images."""
    from geoavatar.apps.common import error_map
    from geoavatar.imaging import to_uint8

    render_rgb, truth_rgb = (torch.from_numpy(image).float() / 255.0 for image in (render, truth))  # [H, W, 3]
    return to_uint8(error_map(render_rgb, truth_rgb))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--timesteps", type=int, nargs="+", required=True, help="training timesteps, a row each")
    parser.add_argument("--out", type=Path, required=True, help="the image (.jpg or .png); scaled to 3/4")
    args = parser.parse_args()

    from web_fixtures import cpu_and_truth, psnr

    from geoavatar.train.checkpoint import open_run

    torch.set_num_threads(1)
    before, after = open_run(args.before, "cpu"), open_run(args.after, "cpu")
    rows = []
    for timestep in args.timesteps:
        if timestep not in before.info.timesteps["train"]:
            raise SystemExit(f"--timesteps: {timestep} is not a training frame of {args.before}")
        render_a, truth = cpu_and_truth(before, timestep)
        render_b, _ = cpu_and_truth(after, timestep)
        print(f"timestep {timestep}: {psnr(render_a, truth):.2f} -> {psnr(render_b, truth):.2f} dB", flush=True)
        rows.append(np.concatenate([truth, render_a, render_b, error_panel(render_a, truth),
                                    error_panel(render_b, truth)], axis=1))
    image = Image.fromarray(np.concatenate(rows, axis=0))
    image.resize((image.width * 3 // 4, image.height * 3 // 4), Image.LANCZOS).save(args.out, quality=88)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
