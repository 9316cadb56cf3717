"""How a training run is executed (RunOptions: folders, seed, device, intervals), as opposed to what it learns
(config.TrainConfig). `geoavatar train` parses RunOptions' fields as its options; the comments are their help."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from geoavatar.config import PresetName

# The intervals' defaults, as fractions of the run's steps.
VAL_EVERY_FRACTION = 0.05
CKPT_EVERY_FRACTION = 0.05
LOG_EVERY_FRACTION = 0.005


@dataclass
class RunOptions:
    """How a run is executed (not what is learned: that is TrainConfig). `geoavatar train` parses these
    fields as its options (--out, --data, --preset, ...); the comments are their help."""

    # Run folder to create (or to continue with --resume / --extend).
    out: Path
    # Dataset folder (VHAP / GaussianAvatars layout, e.g. from `geoavatar synth`, or INSTA); required for
    # a new run, with --resume the run's own unless given (a moved dataset).
    data: Path | None = None
    # Ablation preset of the paper (Tables 3, 6): A = GaussianAvatars (SH 0) ... E = GeoAvatar; its values
    # are the defaults of the --config.* options (default E for a new run; with --resume the run's own).
    preset: PresetName | None = None
    # Downscale images so that the longer side has this many pixels (default: as stored).
    resolution: int | None = None
    # Seed of frame order, initialisation and densification samples.
    seed: int = 0
    # auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
    device: str = "auto"
    # Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu,
    # torch or gsplat.
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto"
    # Save a validation image every this many steps (default: 5 % of the run).
    val_every: int | None = None
    # Write OUT/checkpoints/last.pt every this many steps (default: 5 % of the run).
    ckpt_every: int | None = None
    # Write a loss line to OUT/train.log every this many steps (default: 0.5 % of the run).
    log_every: int | None = None
    # Hold out the last N frames as the test set (default: the dataset's split files, else the INSTA rule:
    # last 350, or the last 25 % of a short video).
    test_frames: int | None = None
    # Folder with your FLAME model files (datasets tracked with FLAME only).
    flame_dir: Path | None = None
    # Show progress bars.
    progress: bool = True

    def to_json(self) -> dict:
        out = asdict(self)
        for key in ("data", "out", "flame_dir"):
            out[key] = None if out[key] is None else str(out[key])
        return out

    def intervals(self, steps: int) -> "Intervals":
        """The validation, checkpoint and log intervals of a run of `steps` steps (defaults: fractions of it)."""
        return Intervals(val=self.val_every or default_interval(steps, VAL_EVERY_FRACTION),
                         ckpt=self.ckpt_every or default_interval(steps, CKPT_EVERY_FRACTION),
                         log=self.log_every or default_interval(steps, LOG_EVERY_FRACTION))


@dataclass(frozen=True)
class Intervals:
    """Steps between validation images, checkpoints and log lines."""

    val: int
    ckpt: int
    log: int


def default_interval(steps: int, fraction: float) -> int:
    return max(1, int(round(steps * fraction)))


__all__ = ["Intervals", "RunOptions", "default_interval"]
