"""Benchmark of the training step (geoavatar.train.trainer.train_step) on a generated subject.

For each preset (default A and E) a fresh subprocess opens the subject at --resolution, builds the
initial avatar (one Gaussian per head-model face), runs --warmup steps and then times --steps
steps of the preset's schedule scaled to --schedule (so the steps timed are the early ones: before
densification, at the initial Gaussian count). It prints steps per second, seconds per step and the
process's peak RSS (ru_maxrss), a figure of its own since each preset runs in its own process.
Validation images and checkpoints are not part of the step and not timed.

    .venv/bin/python benchmarks/train_bench.py                     # generates a 256 px subject first
    .venv/bin/python benchmarks/train_bench.py --data DIR --presets A E --steps 20 --resolution 256
    .venv/bin/python benchmarks/train_bench.py --backends torch cpu           # before/after the native kernel
    python benchmarks/train_bench.py --device cuda --backends gsplat torch --resolution 512   # on a GPU

On CUDA each timed stretch ends with torch.cuda.synchronize(), and the peak GPU memory is reported too.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path


def child(data: str, preset_name: str, resolution: int, steps: int, warmup: int, schedule: int, seed: int,
          backend: str, device: str) -> dict:
    from geoavatar.runtime import setup_process

    setup_process()
    import torch

    from geoavatar.config import preset
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.train.options import RunOptions
    from geoavatar.train.state import new_state, open_training_data
    from geoavatar.train.trainer import train_step

    warnings.simplefilter("ignore", ShortVideoWarning)
    config = preset(preset_name, steps=schedule)
    options = RunOptions(data=Path(data), out=Path(tempfile.mkdtemp()), seed=seed, device=device, resolution=resolution,
                         backend=backend)
    data_ = open_training_data(options, config)
    state = new_state(data_, config, seed)
    data_.train_set.preload()
    on_cuda = device.startswith("cuda")
    for step in range(1, warmup + 1):
        train_step(data_, state, config, step, seed)
    if on_cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    for step in range(warmup + 1, warmup + steps + 1):
        report = train_step(data_, state, config, step, seed)
    if on_cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    item = data_.train_set[0]
    return {
        "preset": preset_name, "backend": data_.backend, "steps": steps, "seconds": seconds, "steps_per_second": steps / seconds,
        "gaussians": report.num_gaussians, "size": f"{item['width']}x{item['height']}",
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "threads": torch.get_num_threads(), "frames": len(data_.train_set), "device": device,
        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if on_cuda else 0.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="dataset folder (default: generate a subject)")
    parser.add_argument("--presets", nargs="+", default=["A", "E"])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--steps", type=int, default=20, help="timed steps")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--schedule", type=int, default=3000, help="total steps the preset's schedule is scaled to")
    parser.add_argument("--frames", type=int, default=24, help="frames of the generated subject")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--backends", nargs="+", default=["auto"], choices=["auto", "cpu", "torch", "gsplat"],
                        help="rasterizer backends to time side by side (e.g. torch cpu: before/after the native kernel)")
    parser.add_argument("--backend", default="auto", help=argparse.SUPPRESS)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.child:
        result = child(str(args.data), args.child, args.resolution, args.steps, args.warmup, args.schedule, args.seed,
                       args.backend, args.device)
        print("RESULT " + json.dumps(result))
        return

    data = args.data
    if data is None:
        from geoavatar.runtime import setup_process

        setup_process()
        from geoavatar.data.splits import ShortVideoWarning
        from geoavatar.data.synth.generate import SynthConfig, generate_dataset

        warnings.simplefilter("ignore", ShortVideoWarning)
        data = Path(tempfile.mkdtemp(prefix="train-bench-")) / "subject"
        print(f"generating a {args.frames}-frame {args.resolution} px subject in {data} ...", flush=True)
        generate_dataset(data, SynthConfig(subject=0, frames=args.frames, size=args.resolution, seed=0), progress=False)

    rows = []
    for name in args.presets:
        for backend in args.backends:
            command = [sys.executable, __file__, "--child", name, "--data", str(data), "--resolution",
                       str(args.resolution), "--steps", str(args.steps), "--warmup", str(args.warmup), "--schedule",
                       str(args.schedule), "--seed", str(args.seed), "--backend", backend, "--device", args.device]
            out = subprocess.run(command, capture_output=True, text=True, env=os.environ.copy())
            lines = [line for line in out.stdout.splitlines() if line.startswith("RESULT ")]
            if out.returncode != 0 or not lines:
                raise SystemExit(f"preset {name}, backend {backend} failed:\n{out.stderr[-3000:]}")
            rows.append(json.loads(lines[-1][len("RESULT "):]))

    where = args.device if args.device.startswith("cuda") else f"CPU ({rows[0]['threads']} threads)"
    print(f"\ntraining step on {where}, {rows[0]['size']} px, "
          f"{args.steps} timed steps after {args.warmup} warm-up, schedule scaled to {args.schedule} steps")
    print(f"{'preset':<8} {'backend':<8} {'Gaussians':>9} {'steps/s':>8} {'s/step':>7} {'peak RSS MB':>12} {'peak GPU MB':>12}")
    for r in rows:
        print(f"{r['preset']:<8} {r['backend']:<8} {r['gaussians']:>9} {r['steps_per_second']:>8.2f} "
              f"{1 / r['steps_per_second']:>7.3f} {r['peak_rss_mb']:>12.0f} {r['peak_gpu_mb']:>12.0f}")
    for name in args.presets:
        speed = {r["backend"]: r["steps_per_second"] for r in rows if r["preset"] == name}
        if "torch" in speed and "cpu" in speed:
            print(f"preset {name}: the cpu backend takes {speed['cpu'] / speed['torch']:.2f}x the torch backend's steps/s")
        if "torch" in speed and "gsplat" in speed:
            print(f"preset {name}: the gsplat backend takes {speed['gsplat'] / speed['torch']:.2f}x the torch backend's steps/s")


if __name__ == "__main__":
    main()
