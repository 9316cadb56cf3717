"""Two single-threaded commands started at the same moment, one on each core: their wall times and the ratio.

    .venv/bin/python benchmarks/pair_together.py --rounds 3 \
        --a 'env PYTHONPATH=NEW OMP_NUM_THREADS=1 .venv/bin/python -m geoavatar.cli track DATA --out /tmp/a' \
        --b 'env PYTHONPATH=OLD OMP_NUM_THREADS=1 .venv/bin/python -m geoavatar.cli track DATA --out /tmp/b'

Why: on our shared 2-core machines one command's wall time moves by a third between runs minutes apart (the
same `geoavatar track` took 28-44 s in one session), so A-then-B timings compare two machine states. Two
processes started together on the two cores see the same state; what they share (L3, memory bandwidth) they
share alike. For commands of one thread each (`track` and `prepare --workers 1` run the photometric fit on one
thread). Each round swaps the cores. Prints a Markdown table; the commands' output goes to OUT.a / OUT.b logs.

The commands run with PYTHONSAFEPATH=1: `python -m` and `-c` otherwise put the working folder first on sys.path,
ahead of PYTHONPATH, so from inside a checkout both sides would import that checkout (worker processes too).
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import time
from pathlib import Path


def start(command: str, core: int, log: Path) -> tuple[subprocess.Popen, float]:
    """The command on `core` (its children too), output to `log`; (process, start time)."""
    return subprocess.Popen(shlex.split(command), stdout=log.open("w"), stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONSAFEPATH": "1"},
                            preexec_fn=lambda: os.sched_setaffinity(0, {core})), time.perf_counter()


def run_round(a: str, b: str, swap: bool, out: Path, index: int) -> tuple[float, float]:
    """Both commands at once; their wall seconds (A, B)."""
    cores = (1, 0) if swap else (0, 1)
    running = [start(command, core, out.with_name(f"{out.name}.{index}.{side}.log"))
               for command, core, side in ((a, cores[0], "a"), (b, cores[1], "b"))]
    walls = []
    for process, started in running:
        if process.wait() != 0:
            raise SystemExit(f"pair_together: {process.args[0]} ... exited with {process.returncode}")
        walls.append(time.perf_counter() - started)
    return walls[0], walls[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--a", required=True, help="command A (one string, split as a shell splits words)")
    parser.add_argument("--b", required=True, help="command B")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("/tmp/pair_together"), help="prefix of the logs")
    args = parser.parse_args()
    if len(os.sched_getaffinity(0)) < 2:
        parser.error("needs two cores")
    print("| round | A wall s | B wall s | A / B |\n|---|---|---|---|")
    ratios = []
    for index in range(args.rounds):
        wall_a, wall_b = run_round(args.a, args.b, index % 2 == 1, args.out, index)
        ratios.append(wall_a / wall_b)
        print(f"| {index + 1} | {wall_a:.1f} | {wall_b:.1f} | {ratios[-1]:.3f} |", flush=True)
    print(f"\nA / B: median {sorted(ratios)[len(ratios) // 2]:.3f}, range {min(ratios):.3f}-{max(ratios):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
