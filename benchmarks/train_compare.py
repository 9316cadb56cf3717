"""Test-split PSNR of trained runs, overall and in the mouth region (a quick comparison of presets).

For each RUN folder (written by `geoavatar train`) the avatar is loaded with `load_run`, every test
frame of its dataset is rendered the way a novel animation is (tracked parameters, never refined;
mouth deformer with T = 0, as the paper does at inference) and compared with the ground-truth image
composited on the background with its mask (the training target). Reported per run:

    PSNR          over the whole image
    mouth PSNR    over the pixels inside the convex hull of the projected `lips` region vertices of
                  the posed head (lips plus whatever shows between them: teeth, mouth interior);
                  the same skin vertices exist in every preset's head model, so the region is the
                  same for every run
    SSIM          3DGS's SSIM over the whole image
and, for scale, the PSNR of an empty render (the background colour alone) against the same targets.

    .venv/bin/python benchmarks/train_compare.py RUN_A RUN_E [--split test]

This is a stand-in until the eval layer (geoavatar eval) exists; numbers are on the run's own
training resolution.
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path


def mouth_mask(head, params, viewmat, K, width: int, height: int):
    """[H, W] bool: inside the convex hull of the projected lips-region vertices."""
    import numpy as np
    import torch
    from PIL import Image, ImageDraw
    from scipy.spatial import ConvexHull

    lips = head.regions.get("lips")
    if lips is None or len(lips) < 3:
        raise SystemExit(f"head model '{head.name}' has no 'lips' region")
    with torch.no_grad():
        vertices = head.forward_params(params).vertices[0][torch.as_tensor(np.asarray(lips))]  # [L, 3]
        cam = vertices @ viewmat[:3, :3].T + viewmat[:3, 3]
        pix = (cam @ K.T)[:, :2] / cam[:, 2:3]
    points = pix.cpu().numpy()
    hull = points[ConvexHull(points).vertices]
    canvas = Image.new("L", (width, height), 0)
    ImageDraw.Draw(canvas).polygon([tuple(map(float, p)) for p in hull], fill=1)
    return torch.from_numpy(np.asarray(canvas).astype(bool))


def evaluate(run_dir: Path, split: str) -> dict:
    import torch

    from geoavatar.data import DataConfig, HeadAvatarDataset, open_subject
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.train.checkpoint import load_run
    from geoavatar.train.frame_params import FrameParams
    from geoavatar.train.losses import ssim
    from geoavatar.avatar import render_avatar
    from geoavatar.render import Camera, composite_target

    config, head, avatar, deformer, info = load_run(run_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        subject = open_subject(info.data_root)
        dataset = HeadAvatarDataset(subject, split, DataConfig(resolution=info.resolution,
                                                               test_frames=info.run_options.get("test_frames")))
    if len(dataset) == 0:
        raise SystemExit(f"{info.data_root}: the '{split}' split is empty")
    frames = FrameParams(info.frame_params, refine=False)
    sq_all, n_all, sq_mouth, n_mouth, ssims = 0.0, 0, 0.0, 0, []
    bg_all, bg_mouth = 0.0, 0.0  # the same errors for an empty render (background only), for scale
    with torch.no_grad():
        for index in range(len(dataset)):
            item = dataset[index]
            params = frames(item["row"])
            target = composite_target(item["image"], item["mask"], item["background"])
            timestep = item["timestep"] if split in ("train", "val") else None
            camera = Camera(item["viewmat"], item["K"], item["width"], item["height"])
            result = render_avatar(avatar, head, params, camera, timestep, deformer, item["background"]).result
            rgb = result.rgb.clamp(0, 1)
            err = (rgb - target) ** 2  # [H, W, 3]
            sq_all += float(err.sum())
            n_all += err.numel()
            mask = mouth_mask(head, params, item["viewmat"], item["K"], item["width"], item["height"])
            sq_mouth += float(err[mask].sum())
            bg_err = (item["background"].view(1, 1, 3) - target) ** 2
            bg_all += float(bg_err.sum())
            bg_mouth += float(bg_err[mask].sum())
            n_mouth += int(mask.sum()) * 3
            ssims.append(float(ssim(rgb, target)))

    def psnr(sq: float, n: int) -> float:
        return float("nan") if n == 0 else -10.0 * math.log10(max(sq / n, 1e-12))

    return {"run": str(run_dir), "step": info.step, "frames": len(dataset), "psnr": psnr(sq_all, n_all),
            "mouth_psnr": psnr(sq_mouth, n_mouth), "bg_psnr": psnr(bg_all, n_all),
            "bg_mouth_psnr": psnr(bg_mouth, n_mouth), "mouth_pixels": n_mouth // 3 // len(dataset),
            "ssim": sum(ssims) / len(ssims), "gaussians": avatar.num_gaussians,
            "flexible": [n for n, f in zip(info.aps.get("part_names", []), info.aps.get("flexible", [])) if f]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--split", default="test", choices=["train", "val", "test"])
    args = parser.parse_args()
    from geoavatar.runtime import setup_process

    setup_process()
    rows = [evaluate(run, args.split) for run in args.runs]
    print(f"{'run':<28} {'step':>6} {'frames':>6} {'PSNR':>7} {'mouth PSNR':>10} {'SSIM':>6} {'Gaussians':>9}  flexible parts")
    for r in rows:
        print(f"{Path(r['run']).name:<28} {r['step']:>6} {r['frames']:>6} {r['psnr']:>7.2f} {r['mouth_psnr']:>10.2f} "
              f"{r['ssim']:>6.4f} {r['gaussians']:>9}  {', '.join(r['flexible']) or '-'}")
    print(f"{'(background only)':<28} {'':>6} {'':>6} {rows[0]['bg_psnr']:>7.2f} {rows[0]['bg_mouth_psnr']:>10.2f}")
    print(f"(mouth region: {rows[0]['mouth_pixels']} px per frame on average in the first run)")


if __name__ == "__main__":
    main()
