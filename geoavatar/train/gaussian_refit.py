"""The head parameters of every frame of a dataset, refitted against a quick Gaussian head of the whole video.

    report = refit_dataset(Path("data/talk/dataset"), Path("data/talk/.prepare/gaussian"), GaussianRefitConfig())

`geoavatar prepare` runs this as its last stage. Why: the photometric stage's appearance model (a mesh-bound albedo
in 128 px face crops, prep/photometric.py) cannot see the hair's outline, where a head turned by 1° or sitting 4 mm
too close shows. On d3 (issue #27) the test frames' written rigid pose was off by that much, and it cost them 4.5 dB
of PSNR against an avatar that fitted its own training frames to 29 dB (docs/expressive_video.md). A Gaussian head
has the hair in it.

How: a throwaway GeoAvatar head (preset E, `steps` at `resolution`) is trained on every frame of the dataset, test
frames included, with training's refinement of each frame's parameters (train/frame_params.py). Every tracker fits
every frame; the avatar a user trains afterwards never sees a test frame. Then each frame's parameters are
rewritten in the dataset: a training frame's as that training refined them, a test frame's fitted against the
head (train/avatar_tracking.py, from its refined ones). Training's refinement visits each frame a few times only;
the fit gives the test frames, which the user's training will not refine, the full fit. Identity and static offset
are kept.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from geoavatar.head.params import FRAME_KEYS

HEAD_RUN = "head"  # the throwaway head's run folder under the work folder


@dataclass
class GaussianRefitConfig:
    """The throwaway head's budget and the test frames' fit. Measured on d3 (issue #27): 3000 steps at 256 px, the
    CPU default of `geoavatar train`, and the avatar-tracking fit's 30 steps."""

    steps: int = 3000
    resolution: int = 256  # longer side in pixels (never above the stored size)
    fit_steps: int = 30
    seed: int = 0

    def __post_init__(self):
        if self.steps < 1 or self.resolution < 32 or self.fit_steps < 0:
            raise ValueError(f"gaussian refit: need steps >= 1, resolution >= 32 and fit steps >= 0, got {self.steps}, "
                             f"{self.resolution}, {self.fit_steps}")


def train_head(dataset: Path, image_side: int, run_dir: Path, config: GaussianRefitConfig, device: str,
               progress: bool) -> Path:
    """Train (or resume, or keep a finished) throwaway head on every frame of `dataset`, whose images' longer side is
    `image_side` pixels; returns its run folder."""
    from geoavatar.config import preset
    from geoavatar.train.checkpoint import run_checkpoint_path
    from geoavatar.train.options import RunOptions
    from geoavatar.train.trainer import train

    if run_checkpoint_path(run_dir, "final").is_file():
        return run_dir
    resume = run_checkpoint_path(run_dir, "last").is_file()
    options = RunOptions(out=run_dir, data=dataset, preset="E", resolution=min(config.resolution, image_side),
                         seed=config.seed, device=device, test_frames=0, progress=progress)
    if train(options, None if resume else preset("E", config.steps), resume=resume).status != "finished":
        raise KeyboardInterrupt  # Ctrl-C: saved; a re-run of prepare resumes the head
    return run_dir


def refit_dataset(dataset: Path, work: Path, config: GaussianRefitConfig = GaussianRefitConfig(), device: str = "auto",
                  progress: bool = True, log: Callable[[str], None] = print) -> dict:
    """Rewrite every frame's per-frame parameters of `dataset` (in place) from a head trained in `work`; returns a
    report: frames, test frames fitted, their L1 before and after, how far the test frames' heads moved."""
    from tqdm import tqdm

    from geoavatar.data.dataset import DataConfig, HeadAvatarDataset, open_subject
    from geoavatar.data.layout import rewrite_frame_params
    from geoavatar.train.avatar_tracking import AvatarTrackingConfig, dataset_frames, track_frames
    from geoavatar.train.checkpoint import open_run

    subject = open_subject(dataset)
    image_side = max(subject.info.image_size or (config.resolution, config.resolution))
    run_dir = train_head(Path(dataset), image_side, Path(work) / HEAD_RUN, config, device, progress)
    run = open_run(run_dir, device)
    written = subject.params["translation"].float()  # [T, 3] before the refit
    refined = {key: run.info.frame_params[key].float().clone() for key in FRAME_KEYS}  # [T, ...], rows = timesteps
    test = HeadAvatarDataset(replace(subject, params={**subject.params, **refined}), "test",
                             DataConfig(resolution=run.info.resolution, cache="none"))
    report = {"steps": config.steps, "resolution": run.info.resolution, "frames": subject.num_timesteps,
              "test_frames": len(test)}
    if len(test):
        with tqdm(total=len(test), desc="prepare: gaussian refit", unit="frame", disable=not progress) as bar:
            frames = dataset_frames(test, range(len(test)), run.device)
            fit = AvatarTrackingConfig(steps=config.fit_steps)
            result = track_frames(run.avatar, run.head, run.deformer, frames, fit, progress=bar.update)
        rows = [test.frames[index].row for index in range(len(test))]
        for key in FRAME_KEYS:
            refined[key][rows] = getattr(result.params, key).cpu().float()
        moved = (refined["translation"][rows] - written[rows]).norm(dim=-1) * 1000.0  # [N] mm
        l1 = {"mean_before": float(np.nanmean(result.loss_before)), "mean": float(np.nanmean(result.loss_after))}
        report.update(l1=l1,
                      test_head_moved_mm={"mean": float(moved.mean()), "max": float(moved.max())})
    rewrite_frame_params(dataset, {timestep: {key: refined[key][row].numpy() for key in FRAME_KEYS}
                                   for row, timestep in enumerate(subject.timesteps)})
    shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)  # hundreds of MB; its train.log stays
    log(f"prepare: gaussian refit: {report['frames']} frames rewritten, {report['test_frames']} test frames fitted"
        + (f", L1 {report['l1']['mean_before']:.4f} -> {report['l1']['mean']:.4f}" if len(test) else ""))
    return report


__all__ = ["GaussianRefitConfig", "refit_dataset", "train_head"]
