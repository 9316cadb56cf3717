"""Copy a generated subject with its exact head parameters in place of the tracker-like ones.

`geoavatar synth` writes tracker-like error into flame_param/ and the truth into flame_param_gt/.
Training and evaluating on the copy this script makes separates what the avatar model can do from
what tracking error costs (issue #13: compare presets on it; issue #12: the ceiling a tracker can reach).

    .venv/bin/python benchmarks/exact_params_dataset.py DATA OUT
    geoavatar ablate --data OUT --presets A B C D E --steps 1500 --resolution 128 --out runs/ablate_exact
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def exact_copy(data: Path, out: Path) -> Path:
    """OUT = DATA with flame_param_gt/ as its flame_param/ (written to a temporary folder, then renamed)."""
    truth = data / "flame_param_gt"
    if not truth.is_dir():
        raise SystemExit(f"{data}: has no flame_param_gt/ (only `geoavatar synth` subjects carry the truth)")
    if out.exists():
        raise SystemExit(f"{out}: exists; choose a new folder")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(data, tmp, ignore=shutil.ignore_patterns("flame_param", "flame_param_gt"))
    shutil.copytree(truth, tmp / "flame_param")
    tmp.rename(out)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="a generated subject (geoavatar synth)")
    parser.add_argument("out", type=Path, help="the new dataset folder")
    args = parser.parse_args(argv)
    print(exact_copy(args.data, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
