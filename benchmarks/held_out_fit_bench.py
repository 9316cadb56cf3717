"""The held-out frames' fit against a trained avatar: time per frame and held-out PSNR, per variant, in one run.

    .venv/bin/python benchmarks/held_out_fit_bench.py RUN --variants 30 10 10:carry 10:carry@128 [--threads 1]

For each variant (Adam steps per frame, `:carry` = start each frame from the previous frame's correction,
train/avatar_tracking.py, `*R` = every rate of AvatarTrackingConfig times R, `@SIZE` = fitted on images of that
longer side instead of the run's) the run's test frames are fitted against its avatar (as `geoavatar track --avatar`
does) and rendered; PSNR as `geoavatar eval` measures it (the render on the dataset's background against the
image composited on it, mean over frames). The row `tracked` renders the dataset's own parameters (no fit).
Prints a Markdown table; writes RUN/held_out_fit_bench.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--variants", nargs="+", default=["30", "10:carry"], help="STEPS[:carry][*RATE][@SIZE]")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-frames", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from geoavatar.avatar import render_avatar
    from geoavatar.data.dataset import DataConfig, HeadAvatarDataset, item_camera, item_to, open_subject
    from geoavatar.eval.metrics import psnr
    from geoavatar.head.params import HeadParams
    from geoavatar.render.composite import composite_target
    from geoavatar.train.avatar_tracking import AvatarTrackingConfig, dataset_frames, track_frames
    from geoavatar.train.checkpoint import open_run

    run = open_run(args.run, "cpu")
    test = HeadAvatarDataset(open_subject(Path(run.info.data_root)), "test",
                             DataConfig(resolution=run.info.resolution, cache="none"))
    indices = list(range(len(test)))
    if args.max_frames:
        indices = indices[:args.max_frames]
    items = [item_to(test[i], "cpu") for i in indices]

    @torch.no_grad()
    def held_out_psnr(params) -> float:
        scores = []
        for i, item in enumerate(items):
            frame = params.frame(i) if params is not None else HeadParams.from_npz(item["params"])
            rgb = render_avatar(run.avatar, run.head, frame, item_camera(item), None, run.deformer,
                                item["background"]).result.rgb.clamp(0, 1)
            scores.append(psnr(rgb, composite_target(item["image"], item["mask"], item["background"])))
        return float(np.mean(scores))

    rows = [{"variant": "tracked", "s_per_frame": 0.0, "psnr": held_out_psnr(None)}]
    for variant in args.variants:
        name, _, size = variant.partition("@")
        name, _, factor = name.partition("*")
        steps, _, carry = name.partition(":")
        config = AvatarTrackingConfig(steps=int(steps), carry=carry == "carry")
        config.rates = {key: rate * float(factor or 1) for key, rate in config.rates.items()}
        fit_on = test if not size else HeadAvatarDataset(test.subject, "test", DataConfig(resolution=int(size),
                                                                                          cache="none"))
        started = time.perf_counter()
        result = track_frames(run.avatar, run.head, run.deformer, dataset_frames(fit_on, indices, "cpu"), config)
        seconds = (time.perf_counter() - started) / len(indices)
        rows.append({"variant": variant, "s_per_frame": seconds, "psnr": held_out_psnr(result.params),
                     "l1": float(np.nanmean(result.loss_after))})
        print(rows[-1], flush=True)
    print(f"\n{len(indices)} held-out frames of {args.run}, {run.info.resolution} px, {args.threads} thread(s)\n")
    print("| variant | s / frame | held-out PSNR |\n|---|---|---|")
    for row in rows:
        print(f"| {row['variant']} | {row['s_per_frame']:.2f} | {row['psnr']:.2f} |")
    (args.run / "held_out_fit_bench.json").write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
