"""How much work one frame of a trained avatar gives the CPU rasterizer, and what it costs per unit of work.

    .venv/bin/python benchmarks/raster_work.py RUN [--resolution 256] [--threads 2] [--calls 20]

Poses the run's first frame, projects its Gaussians with the dataset camera at --resolution (the training size) and
counts what the compositing kernels visit: the Gaussians on screen, the area of their boxes (the kernel's box: the
ellipse where alpha >= 1/255, csrc/rasterize_cpu.cpp gather_splats) against the image's, and the 4 x 4 pixel blocks
those boxes touch (an upper bound: a block whose pixels are all saturated is skipped). Then it times rasterize()
forward and forward + backward (an L1 loss against a fixed random image), best of --calls, and prints the
nanoseconds per block. Read with BENCHMARKS.md, "Time to a good avatar": the step's rasterizer cost is this work.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch


def box_work(means2d, conics, radii, opacities, width: int, height: int) -> dict:
    """Gaussians on screen, their boxes' area over the image's and the 4 x 4 blocks they touch (float64 maths)."""
    a, b, c = (conics[:, k].double() for k in range(3))
    det = a * c - b * b
    cut = torch.log(255.0 * opacities.double())  # sigma where alpha = 1/255
    on = (radii[:, 0] > 0) & (cut > 0) & (det > 0)
    half_x = torch.minimum(torch.sqrt((2 * cut.clamp_min(0) * c / det).clamp_min(0)), radii[:, 0].double())
    half_y = torch.minimum(torch.sqrt((2 * cut.clamp_min(0) * a / det).clamp_min(0)), radii[:, 1].double())
    mx, my = means2d[:, 0].double(), means2d[:, 1].double()
    x0, x1 = (mx - half_x - 0.5).ceil().clamp(0, width - 1), (mx + half_x - 0.5).floor().clamp(0, width - 1)
    y0, y1 = (my - half_y - 0.5).ceil().clamp(0, height - 1), (my + half_y - 0.5).floor().clamp(0, height - 1)
    on &= (x1 >= x0) & (y1 >= y0)
    area = ((x1 - x0 + 1) * (y1 - y0 + 1))[on]
    blocks = (((x1 // 4) - (x0 // 4) + 1) * ((y1 // 4) - (y0 // 4) + 1))[on]
    opacity = opacities.double()[on]
    shares = {f"{lo:g}-{hi:g}": float(area[(opacity >= lo) & (opacity < hi)].sum() / area.sum())
              for lo, hi in OPACITY_CLASSES}
    return {"on_screen": int(on.sum()), "box_area_over_image": float(area.sum()) / (width * height),
            "median_box_px": float(area.median()), "blocks": int(blocks.sum()), "area_share_by_opacity": shares}


OPACITY_CLASSES = ((0.0, 0.05), (0.05, 0.2), (0.2, 0.5), (0.5, 1.01))


def best_of(fn, calls: int) -> float:
    for _ in range(3):
        fn()
    best = float("inf")
    for _ in range(calls):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--calls", type=int, default=20)
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    torch.set_num_threads(args.threads)
    from geoavatar.apps.bench import bench_camera
    from geoavatar.apps.common import posed_head_vertices, run_background
    from geoavatar.render import rasterize
    from geoavatar.render.cpu_backend import project_gaussians_cpu
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames

    run = open_run(args.run, device="cpu")
    frames = RunFrames(run)
    camera = bench_camera(run, frames, args.resolution)
    with torch.no_grad():
        g = run.avatar(posed_head_vertices(run, frames.params(frames.timesteps[0])[0]))
        leaves = [t.detach().clone() for t in (g.means, g.quats, g.scales, g.opacities.reshape(-1), g.colors)]
        p = project_gaussians_cpu(*leaves[:4], camera.viewmat, camera.K, camera.width, camera.height)
    work = box_work(p.means2d, p.conics, p.radii, leaves[3], camera.width, camera.height)
    background = run_background(run)
    target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(0))
    grads = [t.clone().requires_grad_() for t in leaves]

    def forward():
        with torch.no_grad():
            return rasterize(*leaves, camera.viewmat, camera.K, camera.width, camera.height, background,
                             check_values=False)

    def forward_backward() -> None:
        rgb = rasterize(*grads, camera.viewmat, camera.K, camera.width, camera.height, background,
                        check_values=False).rgb
        (rgb - target).abs().mean().backward()

    fwd, both = best_of(forward, args.calls), best_of(forward_backward, args.calls)
    print(f"{args.run}: {len(leaves[0])} Gaussians, {work['on_screen']} on screen at {camera.width} x {camera.height}; "
          f"their boxes cover {work['box_area_over_image']:.1f} x the image "
          f"(median box {work['median_box_px']:.0f} px), {work['blocks']} blocks of 4 x 4 px")
    covered = float((forward().alpha > 0.5).float().mean())
    print(f"the avatar covers {100 * covered:.0f} % of the image (alpha > 0.5): each covered pixel lies in "
          f"~{work['box_area_over_image'] / covered:.0f} boxes; the boxes' area by opacity "
          + ", ".join(f"{k}: {100 * v:.0f} %" for k, v in work["area_share_by_opacity"].items()))
    print(f"{args.threads} thread(s): forward {fwd * 1e3:.1f} ms, forward + backward {both * 1e3:.1f} ms; "
          f"{fwd / work['blocks'] * 1e9 * args.threads:.0f} / {both / work['blocks'] * 1e9 * args.threads:.0f} "
          f"core-ns a block")


if __name__ == "__main__":
    main()
