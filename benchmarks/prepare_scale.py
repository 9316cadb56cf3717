"""How `geoavatar prepare` scales with the length of a video: wall time, CPU time and peak memory at N frames.

    .venv/bin/python benchmarks/prepare_scale.py ../shared/data/video/duda.mp4 --frames 300 1000 5400 \
        --out /tmp/prepare_scale [--geoavatar /path/to/other/checkout/.venv/bin/geoavatar] [-- --no-photometric]

The test video is looped to each length (played forwards, then backwards, and so on: no jump cut for the
crop smoothing and the face tracker to stumble on) at its own resolution (duda.mp4: 1920x1080, 25 fps, so
5,400 frames is the paper's 3-minute video) and written once to OUT/looped_N.mp4. Then `geoavatar prepare`
runs on it as a separate process (arguments after `--` are passed on) while this script samples, once
a second, the memory of that process and all its descendants (the worker processes) from /proc. Set
GEOAVATAR_EXT_CACHE to a folder of this checkout's own: where worktrees share one build cache, a run may rebuild the
native rasterizer (a compiler of 1.5 GB that the sampled memory then includes).

Prints and writes OUT/scale.json and OUT/scale.md: per length the wall time, the CPU time of the process tree
(user + system, from the kernel's accounting of waited-for children), the peak memory of the tree (sampled:
summed PSS, what the tree uses, shared library pages split among the processes; summed RSS, which counts them in
every process), the largest single process's peak RSS (sampled), the sampler's own CPU seconds, the load average
before and after,
and each stage's wall / CPU seconds from prepare's stage markers. `--geoavatar` runs another checkout's
prepare (e.g. main's, for a before / after table on the same machine); its own --workers etc. are its own.
Time on a quiet machine only: other jobs sharing the cores make every figure meaningless.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

STAGES = ("frames", "landmarks", "masks", "tracking", "photometric", "write")


def loop_video(source: Path, frames: int, out: Path) -> Path:
    """OUT: `frames` frames of `source` played forwards, backwards, forwards ... (written once, then reused)."""
    from geoavatar.io.video import Mp4Writer
    from geoavatar.prep.video import decode_frames, probe_video

    if out.is_file():
        return out
    info = probe_video(source)
    originals = [rgb for _, rgb in decode_frames(source)]  # a test video: a few hundred frames fit in memory
    cycle = originals + originals[-2:0:-1]  # forwards, then backwards without repeating the ends
    with Mp4Writer(out, fps=info.fps, crf=18, preset="veryfast") as video:
        for k in range(frames):
            video.write(cycle[k % len(cycle)])
    return out


def _children(pid: int) -> list[int]:
    """Every descendant of `pid` (from /proc/*/stat's parent ids)."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    parents[int(entry)] = int(stat.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found, frontier = [], [pid]
    while frontier:
        parent = frontier.pop()
        kids = [child for child, ppid in parents.items() if ppid == parent]
        found += kids
        frontier += kids
    return found


def _memory_bytes(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of a process in bytes: PSS shares each shared page (libtorch, MediaPipe's libraries: the same
    pages in every worker) among the processes mapping it, so summed over a tree it is the memory the tree uses;
    summed RSS counts those pages once per process. (0, 0) for a process gone."""
    values = {"Rss:": 0, "Pss:": 0}
    try:
        with open(f"/proc/{pid}/smaps_rollup") as rollup:
            for line in rollup:
                key, _, rest = line.partition(" ")
                if key in values:
                    values[key] = int(rest.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return values["Rss:"], values["Pss:"]


class TreeMemory(threading.Thread):
    """Samples the summed RSS and PSS of a process and its descendants until stopped: `.peak` (rss, pss) in bytes,
    `.largest` the largest single process's RSS seen, `.cpu_s` this sampler's own CPU seconds. Once a second: reading
    smaps_rollup walks each process's page tables in the kernel, and at five times a second the sampler took about a
    third of a core from the run it measured."""

    def __init__(self, pid: int, every: float = 1.0):
        super().__init__(daemon=True)
        self.pid, self.every, self.peak, self.largest, self.cpu_s = pid, every, (0, 0), 0, 0.0
        self._done = threading.Event()

    def run(self) -> None:
        start = time.thread_time()
        while not self._done.is_set():
            samples = [_memory_bytes(p) for p in [self.pid, *_children(self.pid)]]
            rss, pss = sum(s[0] for s in samples), sum(s[1] for s in samples)
            self.peak = (max(self.peak[0], rss), max(self.peak[1], pss))
            self.largest = max([self.largest, *(s[0] for s in samples)])
            self.cpu_s = time.thread_time() - start
            self._done.wait(self.every)

    def stop(self) -> tuple[int, int]:
        self._done.set()
        self.join()
        return self.peak


def run_prepare(geoavatar: str, video: Path, out: Path, extra: list[str]) -> dict:
    """One `geoavatar prepare` process on `video`: wall, CPU of the tree, peak memory, per-stage markers."""
    before_cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    command = [geoavatar, "prepare", str(video), "--out", str(out), "--no-progress", *extra]
    with open(out.parent / f"{out.name}.log", "w") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        memory = TreeMemory(process.pid)
        memory.start()
        code = process.wait()
    peak_rss, peak_pss = memory.stop()
    wall = time.perf_counter() - start
    after_cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    if code != 0:
        raise SystemExit(f"prepare failed ({code}); see {out.parent / f'{out.name}.log'}")
    stages = {}
    for stage in STAGES:
        marker = out / ".prepare" / f"{stage}.json"
        if marker.is_file():
            info = json.loads(marker.read_text())
            stages[stage] = {"wall_s": round(info.get("seconds", float("nan")), 1),
                             "cpu_s": round(info.get("cpu_seconds", float("nan")), 1)}
    cpu = (after_cpu.ru_utime - before_cpu.ru_utime) + (after_cpu.ru_stime - before_cpu.ru_stime)
    return {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "peak_pss_tree_gb": round(peak_pss / 1e9, 3),
            "peak_rss_tree_gb": round(peak_rss / 1e9, 3),
            "peak_rss_largest_process_gb": round(memory.largest / 1e9, 3), "sampler_cpu_s": round(memory.cpu_s, 1),
            "load_1min_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)], "stages": stages}


def table(results: dict) -> str:
    lines = ["| frames | wall | CPU (tree) | peak PSS, tree | peak RSS, tree | largest process (RSS) "
             "| load before, after |",
             "|---|---|---|---|---|---|---|"]
    for frames, r in results.items():
        load = r["load_1min_before_after"]
        lines.append(f"| {frames} | {r['wall_s'] / 60:.1f} min | {r['cpu_s'] / 60:.1f} min "
                     f"| {r['peak_pss_tree_gb']:.2f} GB | {r['peak_rss_tree_gb']:.2f} GB "
                     f"| {r['peak_rss_largest_process_gb']:.2f} GB | {load[0]} -> {load[1]} |")
    lines += ["", "| frames | " + " | ".join(STAGES) + " |", "|---" * (len(STAGES) + 1) + "|"]
    for frames, r in results.items():
        cells = [f"{r['stages'][s]['wall_s']:.0f} / {r['stages'][s]['cpu_s']:.0f}" if s in r["stages"] else "-"
                 for s in STAGES]
        lines.append(f"| {frames} (wall / CPU s) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("video", type=Path)
    parser.add_argument("--frames", type=int, nargs="+", default=[300, 1000, 5400])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--geoavatar", default=str(Path(sys.executable).with_name("geoavatar")),
                        help="the geoavatar executable to time (default: this environment's)")
    parser.add_argument("extra", nargs="*", help="after --: more options for prepare")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    machine = {"cpu": platform.processor() or platform.machine(), "cores": len(os.sched_getaffinity(0)),
               "python": platform.python_version(), "geoavatar": args.geoavatar, "prepare_options": args.extra}
    for frames in args.frames:
        video = loop_video(args.video, frames, args.out / f"looped_{frames}.mp4")
        print(f"prepare on {frames} frames ...", flush=True)
        results[frames] = run_prepare(args.geoavatar, video, args.out / f"prepare_{frames}", args.extra)
        print(json.dumps(results[frames]), flush=True)
        (args.out / "scale.json").write_text(json.dumps({"machine": machine, "results": results}, indent=2) + "\n")
    (args.out / "scale.md").write_text(table(results))
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
