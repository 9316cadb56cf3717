"""Training step of two source trees side by side (before/after), at a late-training Gaussian count.

Each measurement is a fresh subprocess whose PYTHONPATH is one tree (e.g. a `git worktree` of the old
commit and this checkout), so both sides run in one script on the same machine state; rounds
alternate A, B, A, B, ... and the table keeps each side's minimum (noise from other processes only
ever adds time). The child code below uses only APIs both trees share (train_step, new_state,
densify.append_gaussians).

The avatar starts from one Gaussian per face and is grown to --gaussians by appending copies of
randomly chosen Gaussians (same face, jittered local mean, smaller scale, random opacity, seeded)
spread like those of trained runs (see grow), as a late-training avatar looks. Timed steps run before
the (scaled) densification start, so the count stays fixed; densification statistics are still
accumulated every step, as in training.

    .venv/bin/python benchmarks/train_step_ab.py --trees /work/wt15_base . --data DIR --gaussians 100000
    .venv/bin/python benchmarks/train_step_ab.py --trees OLD NEW --data DIR --mode losses --steps 30
    .venv/bin/python benchmarks/train_step_ab.py --trees . --data DIR --mode profile

Modes: time (steps/s, wall and CPU seconds per step), losses (every loss term of every step, to check
that two trees train identically), profile (torch.profiler's top ops of a few steps), raster (the
rasterizer alone, fwd + bwd on frame 0's posed Gaussians: the best of --steps calls; "steps/s" = calls/s).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path


def grow(state, target: int, seed: int) -> None:
    """Append Gaussians until there are `target`: jittered copies of random existing ones (same face)."""
    import torch

    from geoavatar.avatar import densify

    avatar = state.avatar
    n = avatar.num_gaussians
    extra = target - n
    if extra <= 0:
        return
    g = torch.Generator().manual_seed(seed + 12345)
    parent = torch.randint(0, n, (extra,), generator=g)
    p = {k: v.detach() for k, v in avatar.params.items()}
    # Spread like the Gaussians of trained runs (1,500-step preset E runs at 50-77k Gaussians: median
    # |local mean| 0.13-0.19 face units, median scale 0.34-0.42 face units, median opacity 0.07).
    new = {
        "means": p["means"][parent] + 0.12 * torch.randn(extra, 3, generator=g),
        "quats": torch.nn.functional.normalize(torch.randn(extra, 4, generator=g), dim=-1),
        "scales": p["scales"][parent] + math.log(0.38) + 0.3 * torch.randn(extra, 3, generator=g),
        "f_dc": p["f_dc"][parent] + 0.5 * torch.randn(extra, 3, generator=g),
        "opacities": math.log(0.07 / 0.93) + 1.5 * torch.randn(extra, generator=g),
    }
    for name in p.keys() - new.keys():  # the optional ones a tree's avatar has (f_normal, f_pose, means_pose): copied
        new[name] = p[name][parent]
    new = {k: v.to(avatar.binding.device) for k, v in new.items()}
    binding = densify.append_gaussians(avatar.params, [state.optimizers["gaussians"]], avatar.binding, new,
                                       avatar.binding[parent.to(avatar.binding.device)], state.stats)
    avatar.binding = binding


def child(args) -> dict:
    from geoavatar.runtime import setup_process

    setup_process()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from geoavatar.config import preset
    from geoavatar.data.splits import ShortVideoWarning
    try:  # the trainer split into modules (#29); older trees hold all of it in trainer.py
        from geoavatar.train.options import RunOptions
        from geoavatar.train.state import new_state, open_training_data
    except ImportError:
        from geoavatar.train.trainer import RunOptions, new_state, open_training_data
    from geoavatar.train.trainer import train_step

    warnings.simplefilter("ignore", ShortVideoWarning)
    config = preset(args.preset, steps=args.schedule)
    options = RunOptions(data=Path(args.data), out=Path(tempfile.mkdtemp()), seed=args.seed, device="cpu",
                         resolution=args.resolution, backend=args.backend)
    data = open_training_data(options, config)
    state = new_state(data, config, args.seed)
    grow(state, args.gaussians, args.seed)
    data.train_set.preload()
    import geoavatar

    out = {"tree": str(Path(geoavatar.__file__).parents[1]), "gaussians": state.avatar.num_gaussians,
           "threads": torch.get_num_threads()}
    step = 0

    def run(count: int, check_values: bool | None = False) -> list:
        nonlocal step
        reports = []
        for _ in range(count):
            step += 1
            reports.append(train_step(data, state, config, step, args.seed, check_values=check_values))
        return reports

    if args.mode == "losses":
        reports = run(args.steps, check_values=None)  # the trainer's default cadence
        out["losses"] = [r.losses for r in reports]
        out["psnr"] = [r.psnr for r in reports]
        out["final_params"] = {k: float(v.detach().double().abs().sum()) for k, v in state.avatar.params.items()}
        return out
    if args.mode == "raster":  # the rasterizer alone (fwd + bwd) on the posed Gaussians of frame 0
        from geoavatar.avatar import pose_avatar
        from geoavatar.render import rasterize
        from geoavatar.data.dataset import item_camera

        item = data.train_set[0]
        camera = item_camera(item)
        with torch.no_grad():
            g = pose_avatar(state.avatar, data.head, state.frames(item["row"]), item["timestep"], state.deformer).gaussians
        leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.colors)]
        target = torch.rand(item["height"], item["width"], 3, generator=torch.Generator().manual_seed(0))

        def once() -> None:
            rgb = rasterize(*leaves, camera.viewmat, camera.K, camera.width, camera.height, item["background"],
                            backend=args.backend, check_values=False).rgb
            (rgb - target).abs().mean().backward()

        for _ in range(args.warmup):
            once()
        wall, cpu = [], []
        for _ in range(args.steps):
            w, c = time.perf_counter(), time.process_time()
            once()
            wall.append(time.perf_counter() - w)
            cpu.append(time.process_time() - c)
        out.update(steps=args.steps, s_per_step=min(wall), cpu_s_per_step=min(cpu), steps_per_second=1 / min(wall),
                   peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        return out
    run(args.warmup)
    if args.mode == "profile":
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            run(args.steps)
        out["table"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows)
        out["table_total"] = prof.key_averages().table(sort_by="cpu_time_total", row_limit=args.rows)
        # the same ops split by their input shapes: which of the many small element-wise calls cost the most
        out["table_shapes"] = prof.key_averages(group_by_input_shape=True).table(
            sort_by="self_cpu_time_total", row_limit=args.rows)
        return out
    wall, cpu = time.perf_counter(), time.process_time()
    run(args.steps)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    out.update(steps=args.steps, s_per_step=wall / args.steps, cpu_s_per_step=cpu / args.steps,
               steps_per_second=args.steps / wall, peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return out


def spawn(tree: Path, args, extra_env: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), **extra_env}
    command = [sys.executable, __file__, "--child", "--data", str(args.data), "--preset", args.preset,
               "--resolution", str(args.resolution), "--gaussians", str(args.gaussians), "--steps", str(args.steps),
               "--warmup", str(args.warmup), "--schedule", str(args.schedule), "--seed", str(args.seed),
               "--threads", str(args.threads), "--mode", args.mode, "--rows", str(args.rows), "--backend", args.backend]
    out = subprocess.run(command, capture_output=True, text=True, env=env, cwd=str(tree))
    lines = [line for line in out.stdout.splitlines() if line.startswith("RESULT ")]
    if out.returncode != 0 or not lines:
        raise SystemExit(f"{tree} failed:\n{out.stderr[-4000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trees", nargs="+", type=Path, default=[Path(".")], help="source trees (PYTHONPATH roots)")
    parser.add_argument("--data", type=Path, help="dataset folder (default: generate a 24-frame subject)")
    parser.add_argument("--preset", default="E")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--gaussians", type=int, default=100_000, help="Gaussians to grow the avatar to")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds (time mode)")
    parser.add_argument("--schedule", type=int, default=3000, help="steps the preset's schedule is scaled to")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--mode", choices=["time", "losses", "profile", "raster"], default="time")
    parser.add_argument("--rows", type=int, default=30)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print("RESULT " + json.dumps(child(args)))
        return

    if args.data is None:
        from geoavatar.runtime import setup_process

        setup_process()
        from geoavatar.data.splits import ShortVideoWarning
        from geoavatar.data.synth.generate import SynthConfig, generate_dataset

        warnings.simplefilter("ignore", ShortVideoWarning)
        args.data = Path(tempfile.mkdtemp(prefix="train-ab-")) / "subject"
        generate_dataset(args.data, SynthConfig(subject=0, frames=24, size=args.resolution, seed=0), progress=False)
    args.data = args.data.resolve()
    env = {"OMP_NUM_THREADS": str(args.threads)} if args.threads else {}
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; preset {args.preset}, {args.resolution} px, "
          f"{args.gaussians} Gaussians, {args.threads} threads, {args.steps} steps after {args.warmup} warm-up")

    if args.mode == "profile":
        for tree in args.trees:
            r = spawn(tree, args, env)
            print(f"\n== {r['tree']} ({r['gaussians']} Gaussians, {args.steps} steps) ==\n{r['table']}\n"
                  f"{r['table_total']}\n{r['table_shapes']}")
        return
    if args.mode == "losses":
        runs = [spawn(tree, args, env) for tree in args.trees]
        ref = runs[0]
        for r in runs:
            print(f"{r['tree']}: final |params| sums {json.dumps({k: round(v, 6) for k, v in r['final_params'].items()})}")
        keys = list(ref["losses"][0])
        print(f"{'step':>4} " + " ".join(f"{k:>12}" for k in keys) + "   max |diff| vs first tree (per term)")
        worst = 0.0
        for i, losses in enumerate(ref["losses"]):
            diffs = [max(abs(r["losses"][i][k] - losses[k]) for r in runs[1:]) if len(runs) > 1 else 0.0 for k in keys]
            worst = max(worst, *[d / max(abs(losses[k]), 1e-12) for d, k in zip(diffs, keys)])
            print(f"{i + 1:>4} " + " ".join(f"{losses[k]:>12.7f}" for k in keys) + "   " +
                  " ".join(f"{d:.1e}" for d in diffs))
        print(f"largest relative difference of any term at any step: {worst:.2e}")
        return

    results: dict[str, list[dict]] = {str(t): [] for t in args.trees}
    for round_ in range(args.rounds):
        for tree in args.trees:
            r = spawn(tree, args, env)
            results[str(tree)].append(r)
            print(f"round {round_ + 1} {tree}: {r['s_per_step']:.3f} s/step wall, {r['cpu_s_per_step']:.3f} CPU s/step "
                  f"(load {os.getloadavg()[0]:.2f})", flush=True)
    print(f"\n{'tree':<40} {'Gaussians':>9} {'steps/s':>8} {'s/step':>7} {'CPU s/step':>10} {'RSS MB':>7}")
    best = {}
    for tree, rows in results.items():
        wall = min(r["s_per_step"] for r in rows)
        cpu = min(r["cpu_s_per_step"] for r in rows)
        best[tree] = (wall, cpu)
        print(f"{tree:<40} {rows[0]['gaussians']:>9} {1 / wall:>8.2f} {wall:>7.3f} {cpu:>10.3f} "
              f"{max(r['peak_rss_mb'] for r in rows):>7.0f}")
    first = str(args.trees[0])
    for tree in list(results)[1:]:
        print(f"{tree} vs {first}: {best[first][0] / best[tree][0]:.2f}x steps/s (wall), "
              f"{best[first][1] / best[tree][1]:.2f}x (CPU time)")
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
