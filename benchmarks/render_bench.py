"""Benchmark of geoavatar.render.rasterize on a head-like scene.

Prints, for 256² and 512² images with 10k, 50k and 100k Gaussians: forward seconds, forward+backward
seconds and the peak RSS of the process, for the torch backend's fast renderer ("tiles": tile rows +
hand-written backward), its naive variant ("naive": per-pixel pairs + plain autograd) and the native
CPU backend ("cpu": C++/OpenMP kernels, cpu_backend.py) side by side, the forward+backward speed-up of
"cpu" over "tiles", plus the forward-only frames per second at 512²/50k. --threads takes several
counts (e.g. 1 2) to report the scaling. --simd takes several float32 compositing paths of "cpu"
(GEOAVATAR_CPU_SIMD: auto, avx512, avx2, vector, scalar), e.g. `--simd auto scalar` for the SIMD kernel
against the previous per-pixel one; the path each run took is printed. Each configuration runs in a fresh subprocess so that
its peak RSS is its own. Timings are the best of --repeats runs after one warm-up: wall-clock
seconds, and the CPU seconds of the process (all threads), which a machine shared with other jobs
disturbs less. The load average is printed before and after.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/render_bench.py
    .venv/bin/python benchmarks/render_bench.py --sizes 256 --counts 50000 --methods tiles
    .venv/bin/python benchmarks/render_bench.py --sizes 256 512 --counts 50000 100000 --methods tiles cpu --threads 1 2
    .venv/bin/python benchmarks/render_bench.py --sizes 512 --counts 50000 --methods cpu --threads 1 2 --simd auto scalar
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time


def head_scene(n: int, size: int, seed: int = 0):
    """n Gaussians lying flat on a head-sized ellipsoid (metres) plus a neck, seen from 0.6 m ahead."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    radii = torch.tensor([0.08, 0.11, 0.095])  # half width, half height, half depth of a head
    n_neck = n // 8
    n_head = n - n_neck
    # head: uniform directions on the unit sphere, stretched to the ellipsoid
    d = torch.nn.functional.normalize(torch.randn(n_head, 3, generator=gen), dim=-1)
    head = d * radii
    head_normal = torch.nn.functional.normalize(d / radii, dim=-1)
    # neck: a cylinder below the head
    angle = torch.rand(n_neck, generator=gen) * 2 * math.pi
    neck_y = -0.08 - torch.rand(n_neck, generator=gen) * 0.1
    neck = torch.stack([0.055 * torch.cos(angle), neck_y, 0.055 * torch.sin(angle) - 0.01], -1)
    neck_normal = torch.stack([torch.cos(angle), torch.zeros(n_neck), torch.sin(angle)], -1)
    means = torch.cat([head, neck])
    normals = torch.cat([head_normal, neck_normal])
    # surface-aligned, flat Gaussians: spacing from the surface area per Gaussian
    area = 4 * math.pi * 0.094**2 + 2 * math.pi * 0.055 * 0.1
    spacing = math.sqrt(area / n)
    tangent_scale = spacing * torch.exp(torch.randn(n, 2, generator=gen) * 0.3) * 0.7
    scales = torch.cat([tangent_scale, spacing * 0.1 * torch.ones(n, 1)], -1)
    # rotation taking local z to the normal, with a random twist about it
    from geoavatar.geometry import axis_angle_to_matrix, matrix_to_quaternion

    z = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    axis = torch.linalg.cross(z, normals)
    sin = axis.norm(dim=-1, keepdim=True)
    cos = (z * normals).sum(-1, keepdim=True)
    align = axis_angle_to_matrix(axis / sin.clamp_min(1e-9) * torch.atan2(sin, cos))
    twist = axis_angle_to_matrix(normals * (torch.rand(n, 1, generator=gen) * 2 * math.pi))
    quats = matrix_to_quaternion(twist @ align)
    opacities = torch.sigmoid(torch.randn(n, generator=gen) * 1.5 + 1.0)
    colors = torch.tensor([0.8, 0.6, 0.5]) + 0.15 * torch.rand(n, 3, generator=gen)
    # camera 0.6 m in front of the face (+z out of the face), OpenCV axes: x right, y down, z forward
    viewmat = torch.tensor(
        [[1.0, 0, 0, 0], [0, -1.0, 0, 0.02], [0, 0, -1.0, 0.6], [0, 0, 0, 1.0]]
    )  # rotation diag(1,-1,-1): the camera sits at world z = +0.6 and looks along -z, at the face
    focal = 2.2 * size  # the head fills ~80% of the image height
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    return means, quats, scales, opacities, colors, viewmat, K


def run_one(method: str, size: int, count: int, repeats: int, tile_size: int) -> dict:
    from geoavatar.runtime import setup_process

    setup_process()
    import torch

    from geoavatar.render.cpu_backend import rasterize_cpu, simd_path
    from geoavatar.render.torch_backend import rasterize_torch

    means, quats, scales, opacities, colors, viewmat, K = head_scene(count, size)
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    gen = torch.Generator().manual_seed(1)
    target = torch.rand(1, size, size, 3, generator=gen)
    background = torch.ones(1, 3)

    def render(tensors):
        if method == "cpu":
            return rasterize_cpu(*tensors, viewmat[None], K[None], size, size, background, batched=False)
        return rasterize_torch(*tensors, viewmat[None], K[None], size, size, background, batched=False,
                               method=method, tile_size=tile_size)

    def forward_only():
        with torch.no_grad():
            render(params)

    def forward_backward():
        rgb, alpha, means2d, *_ = render(params)
        loss = (rgb - target).abs().mean() + alpha.mean()
        loss.backward()
        for p in params:
            p.grad = None
        return means2d

    forward_only()
    forward_backward()  # warm-up
    best = {"fwd": math.inf, "fwd_bwd": math.inf, "fwd_cpu": math.inf, "fwd_bwd_cpu": math.inf}
    for _ in range(repeats):
        for name, fn in (("fwd", forward_only), ("fwd_bwd", forward_backward)):
            wall, cpu = time.perf_counter(), time.process_time()
            fn()
            best[name] = min(best[name], time.perf_counter() - wall)
            best[name + "_cpu"] = min(best[name + "_cpu"], time.process_time() - cpu)
    with torch.no_grad():
        rgb, alpha, _, radii, visible, _ = render(params)
    return dict(
        method=method, simd=simd_path() if method == "cpu" else "", size=size, count=count, fwd_s=best["fwd"], fwd_bwd_s=best["fwd_bwd"],
        fwd_cpu_s=best["fwd_cpu"], fwd_bwd_cpu_s=best["fwd_bwd_cpu"],
        peak_rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2,
        visible=int(visible.sum()), coverage=float((alpha > 0.5).float().mean()),
        threads=torch.get_num_threads(), checksum=float(rgb.double().sum()),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 50_000, 100_000])
    parser.add_argument("--methods", nargs="+", default=["tiles", "naive", "cpu"],
                        choices=["tiles", "naive", "cpu"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, nargs="+", default=[2])
    parser.add_argument("--tile-size", type=int, default=4)
    parser.add_argument("--simd", nargs="+", default=["auto"],
                        help="float32 compositing paths of method cpu (auto, avx512, avx2, vector, scalar)")
    parser.add_argument("--one", nargs=3, metavar=("METHOD", "SIZE", "COUNT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        method, size, count = args.one
        print(json.dumps(run_one(method, int(size), int(count), args.repeats, args.tile_size)))
        return

    if "cpu" in args.methods:  # build the native kernel once, before any timing (cached for the children)
        from geoavatar.render.cpu_backend import cpu_backend_available, cpu_backend_error, load_extension

        if not cpu_backend_available():
            print(f"render_bench: method 'cpu' skipped: {cpu_backend_error()}")
            args.methods = [m for m in args.methods if m != "cpu"]
        else:
            paths = load_extension().simd_paths()
            print(f"render_bench: SIMD paths of method cpu on this CPU: {' '.join(paths)} (auto = {paths[0]})")
            unknown = [p for p in args.simd if p != "auto" and p not in paths]
            if unknown:
                parser.error(f"--simd {' '.join(unknown)}: this CPU runs {' '.join(paths)} (or auto)")
    print(f"render_bench: methods {' '.join(args.methods)}, threads {' '.join(map(str, args.threads))}, best of "
          f"{args.repeats}, torch tile size {args.tile_size}, load average {os.getloadavg()[0]:.1f}")
    print(f"{'method':<11} {'thr':>3} {'image':>7} {'gaussians':>9} {'visible':>8} {'fwd s':>8} {'fwd+bwd s':>10} "
          f"{'fwd cpu s':>10} {'f+b cpu s':>10} {'peak RSS GB':>12}")
    results = []
    for size in args.sizes:
        for count in args.counts:
            for threads in args.threads:
                env = dict(os.environ)
                env.update(OMP_NUM_THREADS=str(threads), GEOAVATAR_THREADS=str(threads), MALLOC_MMAP_MAX_="0",
                           MALLOC_TRIM_THRESHOLD_="68719476736")
                runs = [(m, simd) for m in args.methods for simd in (args.simd if m == "cpu" else [""])]
                for method, simd in runs:
                    cmd = [sys.executable, __file__, "--one", method, str(size), str(count), "--repeats",
                           str(args.repeats), "--tile-size", str(args.tile_size)]
                    proc = subprocess.run(cmd, env=dict(env, GEOAVATAR_CPU_SIMD=simd or "auto"), capture_output=True,
                                          text=True)
                    if proc.returncode != 0:
                        print(f"{method:<11} {threads:>3} {size:>4}^2 {count:>9}  failed: "
                              f"{proc.stderr.strip().splitlines()[-1:]}")
                        continue
                    r = json.loads(proc.stdout.strip().splitlines()[-1])
                    r["label"] = f"{method}/{r['simd']}" if r["simd"] else method
                    results.append(r)
                    print(f"{r['label']:<11} {threads:>3} {size:>4}^2 {count:>9} {r['visible']:>8} {r['fwd_s']:>8.3f} "
                          f"{r['fwd_bwd_s']:>10.3f} {r['fwd_cpu_s']:>10.3f} {r['fwd_bwd_cpu_s']:>10.3f} "
                          f"{r['peak_rss_gb']:>12.2f}", flush=True)
    by_key = {(r["label"], r["threads"], r["size"], r["count"]): r for r in results}
    for (label, threads, size, count), r in by_key.items():
        base = by_key.get(("tiles", threads, size, count))
        if r["method"] == "cpu" and base is not None:
            print(f"{label} vs tiles, {threads} thread(s), {size}^2 / {count}: forward+backward "
                  f"{base['fwd_bwd_s'] / r['fwd_bwd_s']:.1f}x (wall), {base['fwd_bwd_cpu_s'] / r['fwd_bwd_cpu_s']:.1f}x "
                  f"(CPU seconds); forward {base['fwd_s'] / r['fwd_s']:.1f}x")
        scalar = by_key.get(("cpu/scalar", threads, size, count))
        if r["method"] == "cpu" and r["simd"] != "scalar" and scalar is not None:
            print(f"{label} vs cpu/scalar (the previous kernel), {threads} thread(s), {size}^2 / {count}: forward "
                  f"{scalar['fwd_s'] / r['fwd_s']:.2f}x (wall), {scalar['fwd_cpu_s'] / r['fwd_cpu_s']:.2f}x (CPU "
                  f"seconds); forward+backward {scalar['fwd_bwd_s'] / r['fwd_bwd_s']:.2f}x")
        one = by_key.get((label, 1, size, count))
        if threads > 1 and one is not None:
            print(f"{label} scaling 1 -> {threads} threads, {size}^2 / {count}: forward+backward "
                  f"{one['fwd_bwd_s'] / r['fwd_bwd_s']:.2f}x, forward {one['fwd_s'] / r['fwd_s']:.2f}x")
    for r in results:
        if r["size"] == 512 and r["count"] == 50_000:
            print(f"forward-only frames per second at 512^2 / 50k ({r['label']}, {r['threads']} threads): "
                  f"{1.0 / r['fwd_s']:.2f}")
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
