"""`geoavatar train`: train an avatar on a tracked monocular video (VHAP layout or INSTA)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Literal, Optional

from geoavatar.config import ABLATIONS, DEFAULT_PRESET, PAPER_STEPS, preset as make_preset
from geoavatar.data import DatasetError
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.train.checkpoint import RunError
from geoavatar.train.trainer import RunOptions, TrainingDiverged, train as run_training

PresetName = Literal["A", "B", "C", "D", "E", "F", "G", "H", "I", "E-no-mouth", "E-no-deform"]
assert set(PresetName.__args__) == set(ABLATIONS), "PresetName must list every preset of geoavatar.config"


def train(
    out: Path,
    data: Optional[Path] = None,
    preset: Optional[PresetName] = None,
    steps: Optional[int] = None,
    resolution: Optional[int] = None,
    resume: bool = False,
    seed: int = 0,
    device: str = "auto",
    val_every: Optional[int] = None,
    ckpt_every: Optional[int] = None,
    log_every: Optional[int] = None,
    test_frames: Optional[int] = None,
    flame_dir: Optional[Path] = None,
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    progress: bool = True,
) -> int:
    """Train a GeoAvatar avatar from a tracked video into the folder OUT.

    Writes OUT/config.json, OUT/checkpoints/last.pt (every --ckpt-every steps, on Ctrl-C and at the
    end) and final.pt, OUT/aps.json, OUT/train.log and OUT/val/step_XXXXXX.png (ground truth |
    render). Ctrl-C stops after the current step and saves; `--resume` continues exactly where the
    run stopped. Every step-based milestone (APS at half of the run, densification, opacity resets,
    learning-rate decay) scales with --steps, so short CPU runs keep the paper's proportions.

    Args:
        out: Run folder to create (or to continue with --resume).
        data: Dataset folder (VHAP / GaussianAvatars layout, e.g. from `geoavatar synth`, or INSTA);
            required for a new run, with --resume the run's own unless given (a moved dataset).
        preset: Ablation preset of the paper (Tables 3, 6): A = GaussianAvatars (SH 0) ... E = GeoAvatar
            (default E for a new run; with --resume the run's own).
        steps: Training steps (default: the paper's 200000 for a new run; with --resume the run's own).
        resolution: Downscale images so that the longer side has this many pixels (default: as stored).
        resume: Continue the run in OUT from OUT/checkpoints/last.pt.
        seed: Seed of frame order, initialisation and densification samples.
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        val_every: Save a validation image every this many steps (default: 5 % of the run).
        ckpt_every: Write OUT/checkpoints/last.pt every this many steps (default: 5 % of the run).
        log_every: Write a loss line to OUT/train.log every this many steps (default: 0.5 % of the run).
        test_frames: Hold out the last N frames as the test set (default: the dataset's split files,
            else the INSTA rule: last 350, or the last 25 % of a short video).
        flame_dir: Folder with your FLAME model files (datasets tracked with FLAME only).
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        progress: Show progress bars.
    """
    if steps is not None and steps <= 0:
        raise SystemExit(f"geoavatar train: --steps must be positive, got {steps}")
    for name, value in (("--val-every", val_every), ("--ckpt-every", ckpt_every), ("--log-every", log_every)):
        if value is not None and value <= 0:
            raise SystemExit(f"geoavatar train: {name} must be positive, got {value}")
    if data is None and not resume:
        raise SystemExit("geoavatar train: --data is required for a new run (only --resume finds the run's own)")
    if resume:
        # The run's own configuration governs; explicit --preset/--steps must agree with it.
        config = None
        if preset is not None or steps is not None:
            from geoavatar.train.checkpoint import config_from_json, load_checkpoint, run_checkpoint_path

            try:
                saved = config_from_json(load_checkpoint(run_checkpoint_path(out, "last"))["config"])
            except RunError as err:
                raise SystemExit(f"geoavatar train: {err}") from None
            config = make_preset(preset or DEFAULT_PRESET, steps or saved.steps) if preset else saved.scaled_to(steps)
    else:
        config = make_preset(preset or DEFAULT_PRESET, steps or PAPER_STEPS)
    options = RunOptions(
        data=data, out=out, seed=seed, device=device, backend=backend, resolution=resolution,
        test_frames=test_frames, val_every=val_every, ckpt_every=ckpt_every, log_every=log_every,
        flame_dir=flame_dir, progress=progress, preset=preset or (None if resume else DEFAULT_PRESET),
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("once", ShortVideoWarning)
            result = run_training(options, config, resume=resume)
    except (DatasetError, RunError, TrainingDiverged) as err:
        raise SystemExit(f"geoavatar train: {err}") from None
    except ValueError as err:  # bad option values (device, resolution, configuration)
        raise SystemExit(f"geoavatar train: {err}") from None
    last = result.last
    summary = f"{result.status} at step {result.step}/{result.steps} ({result.steps_per_second:.2f} steps/s)"
    if last is not None:
        summary += f": loss {last.losses['total']:.4f}, PSNR {last.psnr:.2f} dB, {last.num_gaussians} Gaussians"
    print(f"{summary}\nrun: {result.run_dir}")
    return 0 if result.status == "finished" else 130


__all__ = ["train"]
