"""Orbit stills of several runs of one video side by side, and the floater share per view (BENCHMARKS.md #18, third
round): one `geoavatar orbit` sweep per run (apps/orbit.py's orbit_video, 24 frames: the sweep then passes exactly
through yaw 0, +-30, +-60 and pitch +-20), the views picked from it, a grid PNG (rows: runs, columns: views, each
still cropped to the middle `--crop` of the frame, where orbit puts the head) and a Markdown table of the share of
rendered opacity outside the dilated head-mesh silhouette (eval/floaters.py) per view.

usage: OMP_NUM_THREADS=1 python benchmarks/orbit_compare.py --frame 226 --out grid.png before=RUN_A after=RUN_B
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from geoavatar.apps.orbit import orbit_video
from geoavatar.train.checkpoint import open_run

VIEWS = [("yaw -60", -60.0, 0.0), ("yaw -30", -30.0, 0.0), ("front", 0.0, 0.0), ("yaw +30", 30.0, 0.0),
         ("yaw +60", 60.0, 0.0), ("pitch +20", 0.0, 20.0), ("pitch -20", 0.0, -20.0)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="NAME=RUN_DIR, one row each")
    parser.add_argument("--frame", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--crop", type=float, default=0.78, help="side of the middle square kept, of the frame's")
    parser.add_argument("--tile", type=int, default=144, help="pixels per still in the grid")
    args = parser.parse_args()
    rows, shares = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for item in args.runs:
            name, _, path = item.partition("=")
            result = orbit_video(open_run(path, "cpu"), Path(tmp) / f"{name}.mp4", args.frame, frames=24, yaw=60.0,
                                 pitch=20.0, show_progress=False)
            picks = [min(range(len(result.angles)), key=lambda i: abs(result.angles[i][0] - yaw)
                         + abs(result.angles[i][1] - pitch)) for _, yaw, pitch in VIEWS]
            shares[name] = [result.outside[i] for i in picks]
            tiles = []
            for i in picks:
                image = result.images[i]
                h, w = image.shape[:2]
                side = int(round(args.crop * min(h, w)))
                top, left = (h - side) // 2, (w - side) // 2
                tile = Image.fromarray(image[top:top + side, left:left + side])
                tiles.append(np.asarray(tile.resize((args.tile, args.tile), Image.Resampling.LANCZOS)))
            rows.append((name, np.concatenate(tiles, axis=1)))
    label_w, head_h = 56, 14
    sheet = Image.new("RGB", (label_w + rows[0][1].shape[1], head_h + len(rows) * args.tile), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, (view, _, _) in enumerate(VIEWS):
        draw.text((label_w + k * args.tile + 4, 1), view, fill=(0, 0, 0))
    for r, (name, strip) in enumerate(rows):
        sheet.paste(Image.fromarray(strip), (label_w, head_h + r * args.tile))
        draw.text((4, head_h + r * args.tile + args.tile // 2 - 6), name, fill=(0, 0, 0))
    sheet.save(args.out, optimize=True)
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KB)")
    print("| run | " + " | ".join(v for v, _, _ in VIEWS) + " | mean |")
    print("|---|" + "---:|" * (len(VIEWS) + 1))
    for name, values in shares.items():
        print(f"| {name} | " + " | ".join(f"{100 * v:.2f}" for v in values) + f" | {100 * np.mean(values):.2f} |")


if __name__ == "__main__":
    main()
