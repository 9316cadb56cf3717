"""Where a run's error lies: PSNR and share of the squared error per image region, train and test frames.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/region_errors.py runs/d3 [--data DATASET] [--frames 40] [--json out.json]

Regions of each frame (from the posed head mesh, z-buffered with the mouth structure, and the dataset's mask):
- face:   pixels whose visible mesh face is on the face skin, nose, eyes, lips, forehead or the mouth structure;
- head:   the rest of the mask (hair, ears, neck, clothing the mask keeps);
- edge:   a band of `--edge` of the image side around the mask's border (loose strands, matting);
- back:   the rest of the background.
Training frames use the run's refined parameters, test frames the dataset's (or --data's) tracking, as eval does.
Issue #27's diagnosis: an error that lives in the face is the head model's or the tracker's; one in the hair and at
the mask's edge is what a rigged avatar cannot follow.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from geoavatar.data import evenly_spaced
from geoavatar.eval.evaluate import render_run_frames
from geoavatar.head.regions import face_parts
from geoavatar.render.camera import world_to_camera
from geoavatar.render.mesh import dilate_mask, dilation_pixels, rasterize_mesh
from geoavatar.train.checkpoint import open_run, open_run_dataset

FACE_PARTS = ("eyeballs", "lips", "nose", "eye_region", "forehead", "face")
REGIONS = ("face", "head", "edge", "back")


def face_selection(head) -> torch.Tensor:
    """[F] bool: faces of the skin parts the head model fits, plus the mouth structure."""
    parts = face_parts(head.data)
    wanted = [parts.part_names.index(name) for name in FACE_PARTS]
    chosen = np.isin(parts.part_of_face, wanted) | (parts.part_of_face < 0)
    return torch.from_numpy(chosen)


def frame_regions(frame, head, selected: torch.Tensor, edge_px: int) -> dict[str, torch.Tensor]:
    item = frame.item
    frags = rasterize_mesh(world_to_camera(frame.vertices, item["viewmat"]), head.faces, item["K"], item["width"],
                           item["height"])
    face = (frags.face_id >= 0) & selected.to(frags.face_id.device)[frags.face_id.clamp_min(0)]  # [H, W]
    inside = item["mask"][..., 0] > 0.5  # [H, W]
    band = dilate_mask(inside, edge_px) & dilate_mask(~inside, edge_px)
    face = face & inside & ~band
    return {"face": face, "head": inside & ~face & ~band, "edge": band, "back": ~inside & ~band}


def measure(run_dir: Path, data: Path | None, split: str, frames: int, edge: float) -> dict:
    run = open_run(run_dir, "cpu")
    dataset = open_run_dataset(run, split, data)
    selected = face_selection(run.head)
    sums = {r: [0.0, 0] for r in REGIONS}
    per_frame = []
    for frame in render_run_frames(run, dataset, evenly_spaced(len(dataset), frames)):
        sq = ((frame.pred.double() - frame.target.double()) ** 2).sum(-1)  # [H, W]
        px = dilation_pixels(edge, frame.item["width"], frame.item["height"])
        record = {"timestep": int(frame.item["timestep"])}
        for name, mask in frame_regions(frame, run.head, selected, px).items():
            sums[name][0] += float(sq[mask].sum())
            sums[name][1] += int(mask.sum())
            n = int(mask.sum())
            record[name] = float(10 * np.log10(3 * n / max(float(sq[mask].sum()), 1e-12))) if n else None
        total = float(sq.sum())
        record["all"] = float(10 * np.log10(3 * sq.numel() / max(total, 1e-12)))
        per_frame.append(record)
    total_sq = sum(s for s, _ in sums.values())
    summary = {name: {"psnr": 10 * np.log10(3 * n / max(s, 1e-12)) if n else None,
                      "error_share": s / total_sq if total_sq else None, "pixel_share": n / max(1, sum(
                          c for _, c in sums.values()))} for name, (s, n) in sums.items()}
    summary["all"] = {"psnr": float(np.mean([r["all"] for r in per_frame]))}
    return {"split": split, "frames": len(per_frame), "summary": summary, "per_frame": per_frame}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", type=Path, default=None, help="dataset whose test frames to use (tracked otherwise)")
    parser.add_argument("--frames", type=int, default=40, help="frames per split, evenly spaced")
    parser.add_argument("--edge", type=float, default=0.01, help="half-width of the mask-edge band, of the image side")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    out = {}
    for split in ("train", "test"):
        result = measure(args.run, args.data, split, args.frames, args.edge)
        out[split] = result
        cells = "  ".join(f"{name} {v['psnr']:.2f} dB ({100 * v['error_share']:.0f} % of error, "
                          f"{100 * v['pixel_share']:.0f} % px)" for name, v in result["summary"].items() if name != "all")
        print(f"{args.run} {split:5s} all {result['summary']['all']['psnr']:.2f} dB  {cells}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
