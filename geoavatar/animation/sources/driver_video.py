"""A driver video tracked into a driver dataset (`--driver-video` of reenact, export --format web and eval), by the
code of `geoavatar prepare` (geoavatar.prep.pipeline: crop, landmarks, masks, the landmark fit with the avatar's head
model; prepare's photometric stage, on by default there, only with `--photometric` here: it costs ~0.4 CPU s per
frame) at `--driver-size` pixels (default 256). Where the tracked driver goes:

    RUN/drivers/<video stem>-<8 hex of its absolute path>[-photometric]/    (default)
    --driver-cache DIR                                                       (a folder of your choice)

holding what `geoavatar prepare VIDEO --out DIR` writes (DIR/dataset, DIR/report.json; no overlay). The next call
with the same video reuses it: prepare's stages are keyed by their settings and by the video file's path, size and
time, so nothing is redone unless one of those changed (another --driver-size, --photometric, or an edited video
redoes the stages concerned). With --photometric the default folder differs, so the landmark-only and the
photometric track are both kept. Frames where no face is found are interpolated (prepare's default) and listed in
DIR/report.json.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from geoavatar.prep.errors import PrepareError
from geoavatar.train.checkpoint import LoadedRun

DRIVERS_DIR = "drivers"  # RUN/drivers/<video stem>-<hash>/: tracked driver videos, reused by later calls
DRIVER_SIZE = 256  # side of the driver's face crop: enough for the face mesh, cheap to track


def driver_cache_dir(run_dir: Path, video: Path, photometric: bool = False) -> Path:
    """RUN/drivers/<stem>-<8 hex of the video's absolute path>[-photometric]: one folder per video file."""
    digest = hashlib.sha256(str(Path(video).resolve()).encode()).hexdigest()[:8]
    return Path(run_dir) / DRIVERS_DIR / f"{Path(video).stem}-{digest}{'-photometric' if photometric else ''}"


def prepare_driver(video: Path, cache: Path, head_model: str, size: int = DRIVER_SIZE, photometric: bool = False,
                   flame_dir: Path | None = None, progress: bool = True) -> tuple[Path, float]:
    """Track a driver video with `geoavatar prepare`'s pipeline into `cache` (resumed / reused by its stage keys).

    Returns (the dataset folder, the video's frame rate after prepare). PrepareError naming --driver-video on bad
    input (missing file, not a video, no face); as with prepare, a folder in which no stage completed is removed
    (and RUN/drivers when this call made it for nothing)."""
    from geoavatar.prep.pipeline import PrepareConfig, run_prepare

    cache = Path(cache)
    parent_created = not cache.parent.exists()
    config = PrepareConfig(video=Path(video), out=cache, head=head_model, size=size, flame_dir=flame_dir,
                           photometric=photometric, overlay=False, progress=progress,
                           log=lambda message: print(message.replace("prepare:", "reenact: driver", 1)))
    try:
        dataset = run_prepare(config)
    except PrepareError as err:
        if parent_created and cache.parent.is_dir() and not any(cache.parent.iterdir()):
            cache.parent.rmdir()  # RUN/drivers made for nothing
        raise PrepareError(f"--driver-video: {err}") from err
    report = json.loads((cache / "report.json").read_text())
    return dataset, float(report["fps"])


def dataset_name(root: Path) -> str:
    """A dataset's name: its folder's, or its parent's for prepare's OUT/dataset layout (`.../wojtek/dataset`)."""
    root = Path(root).resolve()
    return root.parent.name if root.name == "dataset" and root.parent.name else root.name


def track_driver(run: LoadedRun, driver: Path | None, driver_video: Path | None, driver_cache: Path | None = None,
                 driver_size: int | None = None, photometric: bool = False, flame_dir: Path | None = None,
                 progress: bool = True) -> tuple[Path, float | None, str]:
    """(the driver's dataset folder, its video's frame rate or None, its name): --driver as given, or --driver-video
    tracked by prepare's pipeline into its cache (reused when nothing changed)."""
    if driver_video is None:
        return Path(driver), None, dataset_name(Path(driver))
    cache = driver_cache or driver_cache_dir(run.info.run_dir, driver_video, photometric)
    dataset, fps = prepare_driver(Path(driver_video), cache, run.info.head_model, driver_size or DRIVER_SIZE,
                                  photometric, flame_dir, progress)
    print(f"driver: {driver_video} tracked in {cache}")
    return dataset, fps, Path(driver_video).stem


__all__ = ["DRIVERS_DIR", "DRIVER_SIZE", "dataset_name", "driver_cache_dir", "prepare_driver", "track_driver"]
