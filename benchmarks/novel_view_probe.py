"""Two probes of a run's novel-view error (issue #18, sixth round): see-through holes and a misplaced image.

holes  the rendered alpha inside the ground-truth mask eroded by 2 px: mean(1 - alpha) and the share of pixels below
       0.9 and 0.5. Holes inside the head let the training background show through, which a dataset-background run
       can use as a colour (grey-blue on the generated subjects); `--config.background random` takes that away.
shift  the image shift (bicubic, -2..+2 px in steps of 0.25, x and y) that best aligns the render with the ground
       truth, and the PSNR after it: a consistent shift that grows with the turn is colour sitting at the wrong
       depth; none at the front, where the run was trained.
Per view of the novel split, every STEP-th frame.

usage: python benchmarks/novel_view_probe.py RUN [STEP=2]
"""

import math
import sys
from collections import defaultdict

import torch
import torch.nn.functional as F

from geoavatar.eval.evaluate import render_run_frames
from geoavatar.train.checkpoint import load_run, open_run_dataset

torch.set_num_threads(1)
run = load_run(sys.argv[1])
step = int(sys.argv[2]) if len(sys.argv) > 2 else 2
ds = open_run_dataset(run, "novel")
SHIFTS = [0.25 * k for k in range(-8, 9)]


def shifted(image, dx, dy):  # [H, W, 3] sampled at (x + dx, y + dy)
    h, w = image.shape[:2]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    grid = torch.stack([(xs + dx + 0.5) / w * 2 - 1, (ys + dy + 0.5) / h * 2 - 1], -1)[None]
    return F.grid_sample(image.permute(2, 0, 1)[None], grid, mode="bicubic", padding_mode="border",
                         align_corners=False)[0].permute(1, 2, 0)


rows = defaultdict(list)
for fr in render_run_frames(run, ds, list(range(0, len(ds), step))):
    mask = fr.item["mask"][..., 0] > 0.5
    inner = ~(F.max_pool2d((~mask).float()[None, None], 5, 1, 2)[0, 0] > 0.5)  # [H, W] mask eroded by 2 px
    alpha = fr.alpha[..., 0][inner]
    mse = float(((fr.pred - fr.target) ** 2).mean())
    best = min((float(((shifted(fr.pred, dx, dy) - fr.target) ** 2).mean()), dx, dy) for dx in SHIFTS for dy in SHIFTS)
    rows[ds.frames[fr.index].view].append((float((1 - alpha).mean()), float((alpha < 0.9).float().mean()),
                                          float((alpha < 0.5).float().mean()), mse, *best))

print(f"{sys.argv[1]}: holes inside the true mask, and the best image shift (one frame in {step})")
print(f"{'view':9s} {'n':>3s} {'1-alpha %':>9s} {'<0.9 %':>7s} {'<0.5 %':>7s} {'PSNR':>6s} {'shifted':>8s}"
      f" {'dx med':>7s} {'dy med':>7s}")
for view, r in rows.items():
    n = len(r)
    mean = [sum(x[k] for x in r) / n for k in range(5)]
    dx = sorted(x[5] for x in r)[n // 2]
    dy = sorted(x[6] for x in r)[n // 2]
    print(f"{view:9s} {n:3d} {100 * mean[0]:9.2f} {100 * mean[1]:7.2f} {100 * mean[2]:7.2f}"
          f" {-10 * math.log10(mean[3]):6.2f} {-10 * math.log10(mean[4]):8.2f} {dx:+7.2f} {dy:+7.2f}")
