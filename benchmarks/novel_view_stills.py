"""Ground truth and several runs side by side at chosen frames of the novel split (BENCHMARKS.md #18, sixth round).

Columns: the ground truth, then each run; rows: (timestep, view) pairs of the novel split. Written 2x upscaled and
quantised to 256 colours.

usage: python benchmarks/novel_view_stills.py OUT.png RUN [RUN ...] [--rows T:VIEW,...]
    (default rows 150:yaw+30,132:yaw-30,150:front,132:yaw+30,150:yaw-60)
"""

import sys

import numpy as np
import torch
from PIL import Image

from geoavatar.eval.evaluate import render_run_frames
from geoavatar.train.checkpoint import load_run, open_run_dataset

torch.set_num_threads(1)
args = sys.argv[1:]
rows_spec = "150:yaw+30,132:yaw-30,150:front,132:yaw+30,150:yaw-60"
if "--rows" in args:
    at = args.index("--rows")
    rows_spec = args[at + 1]
    del args[at:at + 2]
out, run_dirs = args[0], args[1:]
wanted = [(int(t), view) for t, view in (item.split(":") for item in rows_spec.split(","))]
columns = []
for k, run_dir in enumerate(run_dirs):
    run = load_run(run_dir)
    ds = open_run_dataset(run, "novel")
    indices = [next(i for i, f in enumerate(ds.frames) if f.timestep == t and f.view == view) for t, view in wanted]
    frames = list(render_run_frames(run, ds, indices))
    if k == 0:
        columns.append(torch.cat([f.target for f in frames], 0))
    columns.append(torch.cat([f.pred for f in frames], 0))
image = Image.fromarray((torch.cat(columns, 1).numpy() * 255 + 0.5).astype(np.uint8))
image = image.resize((image.width * 2, image.height * 2), Image.LANCZOS)
image.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
print(f"wrote {out}: {len(wanted)} rows, ground truth + {len(run_dirs)} runs")
