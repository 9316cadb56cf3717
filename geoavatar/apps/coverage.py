"""`geoavatar coverage DATASET`: the capture check of any dataset (what `prepare` writes for a new video)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import tyro

DatasetPath = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]


def coverage(dataset: DatasetPath, out: Optional[Path] = None, flame_dir: Optional[Path] = None) -> int:
    """Capture check of a dataset: which head turns (yaw, pitch), jaw openings, expressions (smile, brows, blinks)
    and gaze its training and test frames cover, and which test frames leave what training saw.

    Prints one verdict with advice on what to film differently, and writes OUT/coverage.json (the ranges per split,
    the test frames outside training by reason) and OUT/coverage.png. Computed from the tracked parameters alone;
    `geoavatar prepare` runs the same check on every new video (OUT/report.json, OUT/coverage.png).

    Args:
        dataset: A dataset folder (VHAP / GaussianAvatars layout, as `prepare` and `synth` write, or INSTA).
        out: Where to write coverage.json and coverage.png (default: DATASET_coverage beside the dataset).
        flame_dir: Folder with your FLAME files, for a dataset tracked with FLAME.
    """
    from geoavatar.prep.coverage import dataset_capture_check

    dataset = Path(dataset)
    out = Path(out) if out is not None else dataset.parent / f"{dataset.resolve().name}_coverage"
    report = dataset_capture_check(dataset, out, flame_dir)
    print(report["verdict"])
    print(f"picture: {out / 'coverage.png'}\nreport: {out / 'coverage.json'}")
    return 0
