"""Where a run's novel-view error lies: its squared error split over pixel classes, per view and segment.

For every frame of the "novel" split (the 160-frame generated subjects of BENCHMARKS.md #18, every 2nd test frame
from the dataset camera and six turned cameras) the pixels are put in one class each, first match wins:
    bg        outside the ground-truth mask dilated by BAND px
    band      within BAND px of the mask's border (the silhouette: hair and ear outlines, the neck edge)
    mouth     the head mesh's mouth and lip faces (eval's mouth region)
    front     faces of the posed head mesh that the dataset camera sees in the same frame (what the front view shows;
              z-buffered at 4x the resolution, so that faces smaller than a pixel count)
    disclosed faces the dataset camera does not see in that frame (sides and back the turn discloses), and mask
              pixels no head face covers (hair volume, glasses)
Per class: its share of the pixels and the PSNR the frame would have if only that class's error were there
(-10 log10(sum of its squared errors / all pixels)); the classes' errors add up to the frame's MSE.
Segments as benchmarks/novel_view_segments.py ("in": head-relative view yaw inside the training sweep).

usage: python benchmarks/novel_view_error_split.py RUN [BAND=2]   (prints a table; writes RUN/eval/novel/error_split.json)
"""

import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from geoavatar.eval.evaluate import mouth_face_mask, mouth_mask, render_run_frames
from geoavatar.render.camera import world_to_camera
from geoavatar.render.mesh import rasterize_mesh, scale_intrinsics
from geoavatar.train.checkpoint import load_run, open_run_dataset

torch.set_num_threads(1)
run_dir = Path(sys.argv[1])
BAND = int(sys.argv[2]) if len(sys.argv) > 2 else 2
YAW = {"front": 0, "yaw+30": 30, "yaw-30": -30, "yaw+60": 60, "yaw-60": -60, "pitch+20": 0, "pitch-20": 0}
CLASSES = ("bg", "band", "mouth", "front", "disclosed")

run = load_run(run_dir)
ds = open_run_dataset(run, "novel")
faces = run.head.faces
mouth_faces = mouth_face_mask(run.head)
front_camera = {f.timestep: i for i, f in enumerate(ds.frames) if f.view == "front"}


def dilate(mask, px):  # [H, W] bool
    return F.max_pool2d(mask[None, None].float(), 2 * px + 1, 1, px)[0, 0] > 0.5


def face_ids(vertices, viewmat, K, w, h):
    return rasterize_mesh(world_to_camera(vertices, viewmat), faces, K, w, h).face_id  # [H, W], -1 = none


records = []
for fr in render_run_frames(run, ds):
    item, frame = fr.item, ds.frames[fr.index]
    h, w = fr.pred.shape[:2]
    gt_mask = item["mask"][..., 0] > 0.5
    outer, inner = dilate(gt_mask, BAND), ~dilate(~gt_mask, BAND)
    front_item = ds[front_camera[item["timestep"]]]
    seen = torch.zeros(faces.shape[0], dtype=torch.bool)
    ids = face_ids(fr.vertices, front_item["viewmat"], scale_intrinsics(front_item["K"], 4), 4 * w, 4 * h)
    seen[ids[ids >= 0].unique()] = True
    ids = face_ids(fr.vertices, item["viewmat"], item["K"], w, h)
    mouth = mouth_mask(fr.vertices, faces, mouth_faces, item["viewmat"], item["K"], w, h)
    visible_front = (ids >= 0) & seen[ids.clamp_min(0)]
    cls = torch.full((h, w), 4, dtype=torch.long)  # disclosed
    cls[visible_front] = 3
    cls[mouth] = 2
    cls[outer & ~inner] = 1
    cls[~outer] = 0
    err = ((fr.pred - fr.target) ** 2).sum(-1) / 3.0  # [H, W] per-pixel MSE over RGB
    rel = YAW[frame.view] - (-15 if item["timestep"] < 140 else 18)
    rec = dict(view=frame.view, timestep=int(item["timestep"]), segment="in" if -30 <= rel <= 22 else "out",
               mse=float(err.mean()))
    for k, name in enumerate(CLASSES):
        sel = cls == k
        rec[name + "_share"] = float(sel.float().mean())
        rec[name + "_sse"] = float(err[sel].sum()) / (h * w)  # its part of the frame's MSE
    records.append(rec)


def db(mse):
    return -10 * math.log10(max(mse, 1e-12))


print(f"{run_dir}: PSNR of the frame mean MSE, and per class: pixel share % / PSNR with only its error (band {BAND} px)")
print(f"{'view':9s} {'seg':>4s} {'n':>3s} {'PSNR':>6s} " + " ".join(f"{c:>15s}" for c in CLASSES))
summary = defaultdict(dict)
for view in YAW:
    for seg in ("all", "in", "out"):
        sel = [r for r in records if r["view"] == view and (seg == "all" or r["segment"] == seg)]
        if not sel or (seg != "all" and len({r["segment"] for r in records if r["view"] == view}) == 1):
            continue
        m = {k: float(np.mean([r[k] for r in sel])) for k in sel[0] if k.endswith(("_share", "_sse")) or k == "mse"}
        summary[view][seg] = dict(frames=len(sel), **m)
        print(f"{view:9s} {seg:>4s} {len(sel):3d} {db(m['mse']):6.2f} "
              + " ".join(f"{100 * m[c + '_share']:6.1f} / {db(m[c + '_sse']):5.2f}" for c in CLASSES))
out = run_dir / "eval" / "novel" / "error_split.json"
out.parent.mkdir(parents=True, exist_ok=True)
out.write_text(json.dumps(dict(band_px=BAND, summary=summary, frames=records), indent=1))
