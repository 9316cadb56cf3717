"""`geoavatar track DATASET --out DIR`: photometric tracking of an existing dataset (geoavatar.prep.photometric).

Reads a monocular VHAP / GaussianAvatars dataset (geoavatar.data), fits every frame (train and test
alike: the split is never read) starting from its parameters, and writes a copy of the dataset whose
flame_param/ holds the fitted parameters; images, masks, cameras and every other file are copied
unchanged. DIR/track.json holds the per-frame photometric residual before and after and the fit's log.
`geoavatar prepare` runs the same fit (prep.photometric.fit_photometric) as its photometric stage.

With `--avatar RUN` the appearance model is a trained avatar instead (train/avatar_tracking.py): every
frame's parameters are fitted so that the avatar explains its image. On the run's own dataset the frames
it trained on keep the run's refined parameters (training already fitted them against the avatar) unless
`--refit-trained`; the others, the held-out frames, are fitted. On any other dataset of the same person
(a new clip, prepared with `prepare`) every frame is fitted. The fit is train's held-out fit (train/held_out_fit.py):
its steps, each frame from the previous frame's correction when that renders closer, in its blocks of neighbouring
frames, one worker process per core (one thread each) on a CPU.
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro

from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.head.params import FRAME_KEYS, HeadParams
from geoavatar.prep.photometric import PhotometricConfig
from geoavatar.train.avatar_tracking import AvatarTrackingConfig
from geoavatar.train.held_out_fit import HeldOutFitConfig
from geoavatar.train.run_frames import TRACKED_COPY_REPORT

_DEFAULTS = PhotometricConfig()  # the command's defaults are the fit's own (and prepare's photometric stage's)
_AVATAR_DEFAULTS = HeldOutFitConfig()  # train's last stage: its steps, each frame from its neighbour's correction

DatasetPath = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATASET")]
REPORT_FILE = TRACKED_COPY_REPORT  # track.json: it also tells eval that a folder is a copy


class TrackError(GeoAvatarError):
    """A dataset `geoavatar track` cannot fit (multi-view, unreadable) or an output it will not replace."""


@dataclass
class TrackInputs:
    params: HeadParams  # [T] the dataset's parameters, rows = subject.timesteps
    images: np.ndarray  # [T, H, W, 3] uint8 at the working size
    masks: np.ndarray  # [T, H, W] uint8
    viewmat: np.ndarray  # [T, 4, 4]
    K: np.ndarray  # [T, 3, 3] for the working size


def load_inputs(subject) -> TrackInputs:
    """Frames of a monocular `Subject` (full size), with their cameras and parameters."""
    from geoavatar.data.dataset import decode_frame

    cameras = {frame.camera for frame in subject.frames}
    if len(cameras) > 1 or len(subject.frames) != subject.num_timesteps:
        raise TrackError(f"{subject.root}: {len(cameras)} cameras; geoavatar track fits monocular datasets only")
    frames = sorted(subject.frames, key=lambda f: f.row)
    images, masks, viewmats, Ks = [], [], [], []
    for frame in frames:
        pixels = decode_frame(frame, (frame.width, frame.height))  # [H, W, 4]
        images.append(pixels[..., :3])
        masks.append(pixels[..., 3])
        viewmats.append(frame.viewmat)
        Ks.append(frame.K)
    params = {k: v.float() for k, v in subject.params.items()}
    return TrackInputs(HeadParams.from_npz(params), np.stack(images), np.stack(masks), np.stack(viewmats), np.stack(Ks))


def tracking_head(subject, flame_dir: Path | None = None):
    """The head model of the dataset (with the GeoAvatar mouth structure, so an open mouth shows its inside)."""
    from geoavatar.data.dataset import check_head_model
    from geoavatar.head import load_head_model

    options = {"flame_dir": flame_dir} if subject.head_model == "flame" and flame_dir is not None else {}
    check_head_model(subject, **options)
    return load_head_model(subject.head_model, mouth="geoavatar", **options)


def track_subject(subject, config=None, flame_dir: Path | None = None, progress: bool = True, log=print):
    """Fit every frame of `subject`; returns the PhotometricResult (params rows = subject.timesteps)."""
    from tqdm import tqdm

    from geoavatar.prep.photometric import (PhotometricTargets, crop_boxes, fit_photometric, total_steps,
                                            weighted_vertex_ids)

    config = config or PhotometricConfig()
    head = tracking_head(subject, flame_dir)
    inputs = load_inputs(subject)
    boxes = crop_boxes(head, inputs.params, torch.as_tensor(inputs.viewmat, dtype=torch.float32),
                       torch.as_tensor(inputs.K, dtype=torch.float32), weighted_vertex_ids(head), config.crop_margin)
    targets = PhotometricTargets.from_arrays(inputs.images, inputs.masks, inputs.viewmat, inputs.K, max(config.sizes), boxes)
    with torch.enable_grad(), tqdm(total=total_steps(config, targets.frames), desc="track", unit="frame",
                                   disable=not progress) as bar:
        result = fit_photometric(head, inputs.params, targets, config, progress=bar.update)
    for line in result.log:
        log(f"track: {line}")
    return result


def track_with_avatar(subject, run_dir: Path, steps: int, refit_trained: bool, device: str = "auto",
                      flame_dir: Path | None = None, progress: bool = True, log=print,
                      workers: int | None = None) -> tuple[HeadParams, dict]:
    """The dataset's parameters [T] with its frames fitted against the run's avatar, and a report (which rows
    came from the run, which were fitted, their L1 before and after). The frames to fit go in the held-out fit's
    blocks (train/held_out_fit.py: the same rows as `train`'s fit on its own held-out frames), on `workers`
    processes on a CPU (default: every core), in this process on a GPU."""
    from tqdm import tqdm

    from geoavatar.prep.photometric import residual_report
    from geoavatar.train.checkpoint import open_clip_dataset, open_run
    from geoavatar.train.held_out_fit import FitTask, fit_plan, fit_tasks
    from geoavatar.workers import default_workers

    run = open_run(run_dir, device, flame_dir=flame_dir)
    if subject.head_model != run.info.head_model:
        raise TrackError(f"{subject.root}: tracked with head model '{subject.head_model}', the run {run_dir} with "
                         f"'{run.info.head_model}'")
    if len({frame.camera for frame in subject.frames}) > 1:
        raise TrackError(f"{subject.root}: several cameras; geoavatar track fits monocular datasets only")
    try:  # --steps checked here, before the workers load anything
        AvatarTrackingConfig(steps=steps, carry=_AVATAR_DEFAULTS.carry)
    except ValueError as err:
        raise OptionError(f"--steps: {err}") from None
    trained = _trained_timesteps(subject, run, refit_trained)
    rows = _start_rows(subject, run, trained)  # key -> [T, ...]
    dataset = open_clip_dataset(run, subject.root, flame_dir)
    to_fit = [index for index in range(len(dataset)) if dataset.timesteps[index] not in trained]
    nothing = np.zeros(0)
    report = {"avatar": str(Path(run_dir).resolve()), "steps": steps, "from_run": sorted(trained),
              "fitted": [int(dataset.timesteps[index]) for index in to_fit], "l1": residual_report(nothing, nothing)}
    if to_fit:
        on_cpu = run.device.type == "cpu"
        tasks = [FitTask(str(run_dir), run.info.step, tuple(to_fit[i] for i in block), steps,
                         _AVATAR_DEFAULTS.carry, str(subject.root), str(run.device),
                         str(flame_dir) if flame_dir is not None else None)
                 for block in fit_plan(len(to_fit), None)[0]]
        with tqdm(total=len(to_fit), desc="track (avatar)", unit="frame", disable=not progress) as bar:
            fitted, before, after = fit_tasks(tasks, (workers or default_workers()) if on_cpu else 1, bar.update)
        for i, index in enumerate(to_fit):
            for key in FRAME_KEYS:
                rows[key][dataset.frames[index].row] = torch.from_numpy(fitted[key][i])
        report["l1"] = residual_report(after, before)  # null: an empty mask, not fitted
    l1 = report["l1"]  # means NaN when no frame had pixels to compare
    log(f"track: {len(to_fit)} frame(s) fitted against the avatar ({len(trained)} kept the run's refined parameters); "
        f"L1 {l1['mean_before']:.4f} -> {l1['mean']:.4f}")
    return HeadParams.from_npz({**subject.params, **rows}).map(lambda x: x.float()), report


def _trained_timesteps(subject, run, refit_trained: bool) -> set[int]:
    """The run's training timesteps when `subject` is the run's own dataset (and not --refit-trained), else none."""
    from geoavatar.train.checkpoint import RunError

    if refit_trained or Path(subject.root).resolve() != Path(run.info.data_root).resolve():
        return set()
    if list(subject.timesteps) != run.info.timesteps["all"]:
        raise RunError(f"{subject.root}: its timesteps differ from those the run {run.info.run_dir} trained on; the "
                       "dataset changed since training")
    return {int(t) for t in run.info.timesteps.get("train", [])}


def _start_rows(subject, run, trained: set[int]) -> dict:
    """Per-frame keys [T, ...]: the run's refined rows for `trained` timesteps, the dataset's for the others."""
    rows = {key: subject.params[key].float().clone() for key in FRAME_KEYS}
    for row, timestep in enumerate(subject.timesteps):
        if timestep in trained:  # the run's rows follow the same timesteps (_trained_timesteps checked)
            for key in FRAME_KEYS:
                rows[key][row] = run.info.frame_params[key][row].float()
    return rows


def write_tracked_copy(subject, params: HeadParams, out: Path, report: dict) -> Path:
    """Copy the dataset folder to `out` (atomically) with flame_param/ rewritten from `params` [T]
    (every other key of each npz kept; shape in each npz and in canonical_flame_param.npz from `params`)."""
    from geoavatar.data.layout import CANONICAL_FILE, rewrite_frame_params, rewrite_npz_rows
    from geoavatar.io.atomic import atomic_folder

    fitted = {k: v.detach().cpu().numpy() for k, v in params.to_npz().items() if k in FRAME_KEYS or k == "shape"}
    with atomic_folder(out) as folder:
        shutil.copytree(subject.root, folder, dirs_exist_ok=True)
        rewrite_frame_params(folder, {timestep: {key: values[row] if key != "shape" else values
                                                 for key, values in fitted.items()}
                                      for row, timestep in enumerate(subject.timesteps)}, optional=("shape",))
        if (folder / CANONICAL_FILE).is_file():
            rewrite_npz_rows(folder / CANONICAL_FILE, {"shape": fitted["shape"]}, optional=("shape",))
        (folder / REPORT_FILE).write_text(json.dumps(report, indent=2) + "\n")
    return out


def track(
    dataset: DatasetPath,
    out: Path,
    sizes: tuple[int, ...] = _DEFAULTS.sizes,
    epochs: tuple[int, ...] = _DEFAULTS.epochs,
    chunk: int = _DEFAULTS.chunk,
    per_face: int = _DEFAULTS.per_face,
    fit_shape: bool = False,
    avatar: Path | None = None,
    steps: int = _AVATAR_DEFAULTS.steps,
    refit_trained: bool = False,
    device: str = "auto",
    overwrite: bool = False,
    flame_dir: Path | None = None,
    threads: int = 1,
    workers: int | None = None,
    progress: bool = True,
) -> int:
    """Photometric tracking of an existing monocular dataset: fit every frame's rotation, translation, neck,
    jaw, eyes and expression to its images (masked L1 of a mesh-bound Gaussian appearance model on the
    native CPU rasterizer, coarse to fine), starting from its parameters; write a copy with them.

    Args:
        dataset: A VHAP / GaussianAvatars dataset (one camera).
        out: Output folder: a copy of DATASET whose flame_param/ holds the fitted parameters, plus track.json.
        sizes: Pyramid levels, image side in pixels.
        epochs: Passes over all frames at each level.
        chunk: Frames per optimiser step.
        per_face: Gaussians per rendered face: 1 (the centroid) or 4 (the centroid and the corner
            sub-triangles' centroids; 1.8-2.5x the cost, no more accurate at 128 px).
        fit_shape: Refine the identity shape too.
        avatar: A trained run (RUN folder) of this person: fit every per-frame parameter against its avatar instead
            of the mesh-bound albedo, each frame from the previous frame's correction (as train's held-out fit); the
            options above do not apply. On the run's own dataset, the frames it trained on keep its refined parameters.
        steps: With --avatar: Adam steps per frame.
        refit_trained: With --avatar on the run's own dataset: fit its training frames too.
        device: With --avatar: where the avatar renders (auto: CUDA when available).
        overwrite: Replace an existing OUT.
        flame_dir: FLAME files for a FLAME dataset.
        threads: Torch threads (1 is fastest on a busy 2-core machine: the fit runs many small operations and
            renders; 2 threads made it 26x slower there, BENCHMARKS.md).
        workers: With --avatar on a CPU: worker processes, one thread each (default: every core, at most 8).
        progress: Show a progress bar.
    """
    import time

    from geoavatar.apps.common import check_replaceable, check_threads, torch_threads
    from geoavatar.data.dataset import open_subject
    from geoavatar.prep.photometric import residual_report

    check_replaceable(out, dataset=dataset, run=avatar)  # DATASET is copied, never changed or replaced
    if Path(out).exists() and not overwrite:
        raise TrackError(f"{out} exists; pass --overwrite to replace it")
    if avatar is not None and fit_shape:
        raise OptionError("--fit-shape: the identity is the avatar's with --avatar; leave one of them out")
    if avatar is None and refit_trained:
        raise OptionError("--refit-trained applies to --avatar only")
    try:
        config = PhotometricConfig(sizes=tuple(sizes), epochs=tuple(epochs), chunk=chunk, per_face=per_face,
                                   fit_shape=fit_shape)
    except ValueError as err:
        raise OptionError(str(err)) from None
    check_threads(threads)
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise OptionError(f"--workers must be at least 1, got {workers}")
    if avatar is None and workers is not None:
        raise OptionError("--workers applies to --avatar only (the photometric fit runs in this process)")
    subject = open_subject(dataset)
    started = time.perf_counter()
    with torch_threads(threads):
        if avatar is None:
            result = track_subject(subject, config, flame_dir, progress)
            fitted = result.params
        else:
            fitted, avatar_report = track_with_avatar(subject, Path(avatar), steps, refit_trained, device, flame_dir,
                                                      progress, workers=workers)
    seconds = time.perf_counter() - started
    report = {"source": str(Path(dataset).resolve()), "frames": subject.num_timesteps, "seconds": round(seconds, 2)}
    if avatar is None:
        report.update({
            "config": {k: v for k, v in asdict(config).items() if k != "tracking"},
            "photometric_residual": residual_report(result.residual, result.residual_before),  # null: an empty mask
            "log": result.log,
        })
        summary = report["photometric_residual"]
        before, after = summary["mean_before"], summary["mean"]
    else:
        report["avatar_tracking"] = avatar_report
        before, after = avatar_report["l1"]["mean_before"], avatar_report["l1"]["mean"]
    write_tracked_copy(subject, fitted, Path(out), report)
    print(f"tracked {subject.num_timesteps} frames in {seconds:.1f} s; residual {before:.4f} -> {after:.4f}; "
          f"dataset: {out}", file=sys.stderr if not progress else sys.stdout)
    return 0


__all__ = ["REPORT_FILE", "TrackError", "TrackInputs", "load_inputs", "track", "track_subject", "track_with_avatar",
           "tracking_head", "write_tracked_copy"]
