"""The mesh z-buffer (geoavatar.render.mesh) with its native scan against its PyTorch scan, in one process.

    .venv/bin/python benchmarks/mesh_render_bench.py [--sizes 128 256 512] [--repeats 7] [--threads 1]
    .venv/bin/python benchmarks/mesh_render_bench.py --overlay PREPARED --video VIDEO   # prepare's overlay pictures

For each image side: `rasterize_mesh` and `render_mesh` (ssaa 1) of the OpenHead template, turned 20 degrees and
filling most of the image as prepare's overlay and the generated subjects do, first with the native scan (the CPU
default), then with the PyTorch scan (as on CUDA, or without a compiler). Milliseconds, the best of --repeats after a
warm-up; both scans' fragments are checked equal first. Both sides run in this one process, one after the other, on
one thread by default (prepare's workers and `synth`'s each use one), so a machine's drift between two processes
does not enter the ratio.

--overlay PREPARED (a `geoavatar prepare` output folder, with --video its video) instead times the overlay video's
pictures of 96 frames spread over it, as a worker draws them, with whatever the checkout's z-buffer is: run it from two
trees side by side with benchmarks/pair_together.py to compare.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path


def best_ms(call, repeats: int) -> float:
    call()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return 1e3 * min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--overlay", type=Path, help="a prepared folder: time its overlay pictures instead")
    parser.add_argument("--video", type=Path, help="with --overlay: the video it was prepared from")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    if args.overlay:
        overlay_pictures(args.overlay, args.video)
        return
    from geoavatar.head import load_head_model
    from geoavatar.render import mesh

    native = mesh._native_kernels()
    if native is None:
        raise SystemExit("the native kernels cannot be built here: nothing to compare")
    head = load_head_model("openhead")
    angle = math.radians(20.0)
    turn = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0],
                         [-math.sin(angle), 0.0, math.cos(angle)]])
    vertices = head.v_template.float() @ turn.T  # [V, 3]
    viewmat = torch.eye(4)
    viewmat[2, 3] = 0.6
    camera_vertices = vertices + viewmat[:3, 3]
    print(f"OpenHead template: {vertices.shape[0]} vertices, {head.faces.shape[0]} faces; {args.threads} thread(s); "
          f"load {os.getloadavg()[0]:.2f}")
    print("| side | rasterize_mesh native / PyTorch scan (ms) | ratio "
          "| render_mesh native / PyTorch scan (ms) | ratio |")
    print("|---|---|---|---|---|")
    for size in args.sizes:
        K = torch.tensor([[size * 2.2, 0.0, size / 2], [0.0, size * 2.2, size / 2], [0.0, 0.0, 1.0]])
        timings = {}
        fragments = {}
        for side, kernels in (("native", lambda: native), ("torch", lambda: None)):
            mesh._native_kernels = kernels
            fragments[side] = mesh.rasterize_mesh(camera_vertices, head.faces, K, size, size)
            timings[side] = (
                best_ms(lambda: mesh.rasterize_mesh(camera_vertices, head.faces, K, size, size), args.repeats),
                best_ms(lambda: mesh.render_mesh(vertices, head.faces, viewmat, K, size, size, ssaa=1), args.repeats))
        mesh._native_kernels = lambda: native
        assert all(torch.equal(getattr(fragments["native"], key), getattr(fragments["torch"], key))
                   for key in ("face_id", "depth", "bary")), "the two scans disagree"
        (r_native, m_native), (r_torch, m_torch) = timings["native"], timings["torch"]
        print(f"| {size} | {r_native:.1f} / {r_torch:.1f} | {r_native / r_torch:.2f} | {m_native:.1f} / {m_torch:.1f} "
              f"| {m_native / m_torch:.2f} |")


def overlay_pictures(prepared: Path, video: Path) -> None:
    """Milliseconds per overlay picture of 96 frames spread over a prepared video (after 8 as a warm-up)."""
    import numpy as np

    import geoavatar
    from geoavatar.prep.pipeline import PrepareConfig, overlay_frames

    config = PrepareConfig(video=video, out=prepared)
    work = prepared / ".prepare"
    count = len(np.load(work / "landmarks.npz")["keep"])
    rows = np.linspace(0, count - 1, 96).round().astype(int).tolist()
    sum(1 for _ in overlay_frames(config, work, rows[:8]))
    started = time.perf_counter()
    drawn = sum(1 for _ in overlay_frames(config, work, rows))
    print(f"{1e3 * (time.perf_counter() - started) / drawn:.1f} ms an overlay picture ({drawn} of {prepared}, "
          f"{Path(geoavatar.__file__).parent})")


if __name__ == "__main__":
    main()
