"""`geoavatar export RUN --out FILE.ply`: the avatar's Gaussians as a standard 3DGS PLY.

What is exported: the *global* Gaussians of one frame, i.e. the avatar posed with that frame's
parameters (the run's refined ones for a training frame), with the mouth deformation and the T rule
of train/run_frames.py (a training frame with its own T, any other frame with T = 0). A splat viewer shows
exactly what `geoavatar render` shows for that frame. Scales are log standard deviations in metres
(local log-scale + log of the face scale k), rotations the global quaternions (face rotation composed
with the local one), colour and opacity are the learned SH-0 coefficient and opacity logit (a run with
model.normal_shading: the SH-0 coefficient of that frame's shaded colour).

`--sequence` exports every frame of a split:
- `--format ply` (default): a folder FRAME_<timestep>.ply, one per frame, built in a temporary folder
  beside OUT and renamed into place when complete;
- `--format npz`: one npz, written atomically, with
    timesteps [T] int64, means [T, N, 3], quats [T, N, 4] (w, x, y, z), log_scales [T, N, 3],
    opacity_logits [N], f_dc [N, 3], binding [N] (face of each Gaussian), faces [F, 3];
  the per-Gaussian colour and opacity do not change over time, so they are stored once (a run with
  model.normal_shading: f_dc [T, N, 3], the colour is shaded per frame).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch

from geoavatar.animation.expression_transfer import TransferMode, resolve_transfer
from geoavatar.animation.posing import pose_gaussians
from geoavatar.apps.common import (EXPORT_DIR, RunPath, check_replaceable, clip_timesteps, default_output, progress,
                                   split_timesteps)
from geoavatar.avatar import GlobalGaussians
from geoavatar.avatar.model import rgb_to_sh_dc
from geoavatar.errors import OptionError
from geoavatar.io.atomic import atomic_folder, atomic_write_npz
from geoavatar.io.ply import GaussianPly, write_gaussian_ply
from geoavatar.train.checkpoint import LoadedRun, open_run
from geoavatar.train.run_frames import RunFrames

FRAME_FILE = "frame_{:05d}.ply"


def to_ply_gaussians(run: LoadedRun, g: GlobalGaussians) -> GaussianPly:
    """Global Gaussians of one posed frame in the PLY parametrisation (numpy float32)."""
    p = run.avatar.params

    def numpy(t: torch.Tensor) -> np.ndarray:
        return t.detach().float().cpu().numpy()

    return GaussianPly(
        means=numpy(g.means),
        f_dc=numpy(rgb_to_sh_dc(g.colors) if run.avatar.normal_shading else p["f_dc"]),  # shaded: this frame's
        opacity_logits=numpy(p["opacities"]),
        log_scales=numpy(torch.log(g.scales.clamp_min(1e-30))),
        quats=numpy(torch.nn.functional.normalize(g.quats, dim=-1)),
    )


@torch.no_grad()
def frame_gaussians(run: LoadedRun, frames: RunFrames, timestep: int) -> GlobalGaussians:
    params, t = frames.params(timestep)
    return pose_gaussians(run, params, t)


def export_frame(run: LoadedRun, out: Path, timestep: int | None = None) -> Path:
    """Write the PLY of one frame (default: the first timestep) to `out`."""
    frames = RunFrames(run)
    return write_gaussian_ply(out, to_ply_gaussians(run, frame_gaussians(run, frames, frames.resolve(timestep))))


def check_folder_target(out: Path, overwrite: bool, run: LoadedRun | None = None) -> Path:
    """--out as a folder to (re)write: OptionError when it exists and --overwrite is not given, or is a file, or when
    replacing it would remove `run`'s folder or its dataset."""
    out = Path(out)
    if run is not None:
        check_replaceable(out, run=run.info.run_dir, dataset=run.info.data_root)
    if out.exists() and not overwrite:
        raise OptionError(f"--out {out} already exists; pass --overwrite to replace it")
    if out.exists() and not out.is_dir():
        raise OptionError(f"--out {out} exists and is not a folder")
    return out


def export_sequence_ply(run: LoadedRun, out: Path, split: str = "all", overwrite: bool = False,
                        show_progress: bool = True) -> Path:
    """One PLY per frame into the folder `out`, which appears complete or not at all."""
    out = check_folder_target(out, overwrite, run)
    frames = RunFrames(run)
    timesteps = clip_timesteps(run, split)  # OptionError for a split with no frames
    with atomic_folder(out) as folder:
        for t in progress(timesteps, enabled=show_progress, desc="export"):
            gaussians = to_ply_gaussians(run, frame_gaussians(run, frames, t))
            write_gaussian_ply(folder / FRAME_FILE.format(t), gaussians)
    return out


def export_sequence_npz(run: LoadedRun, out: Path, split: str = "all", show_progress: bool = True) -> Path:
    """Per-frame Gaussian parameters of a split in one npz (see the module docstring for the keys)."""
    frames = RunFrames(run)
    timesteps = clip_timesteps(run, split)  # OptionError for a split with no frames
    means, quats, log_scales, colours = [], [], [], []
    for t in progress(timesteps, enabled=show_progress, desc="export"):
        g = to_ply_gaussians(run, frame_gaussians(run, frames, t))
        means.append(g.means)
        quats.append(g.quats)
        log_scales.append(g.log_scales)
        colours.append(g.f_dc)
    return atomic_write_npz(
        out,
        timesteps=np.asarray(timesteps, dtype=np.int64),
        means=np.stack(means), quats=np.stack(quats), log_scales=np.stack(log_scales),  # [T, N, ...]
        opacity_logits=g.opacity_logits,  # the same in every frame
        f_dc=np.stack(colours) if run.avatar.normal_shading else g.f_dc,  # [T, N, 3] when shaded per frame
        binding=run.avatar.binding.cpu().numpy(), faces=run.avatar.faces.cpu().numpy(),
    )


def export(
    run: RunPath,
    out: Optional[Path] = None,
    frame: Optional[int] = None,
    sequence: bool = False,
    format: Literal["ply", "npz", "web"] = "ply",
    split: Optional[str] = None,
    driver: Optional[Path] = None,
    driver_video: Optional[Path] = None,
    audio: Optional[Path] = None,
    loudness: Literal["own", "video"] = "own",
    relative: bool = False,
    transfer: Optional[TransferMode] = None,
    fps: Optional[float] = None,
    overwrite: bool = False,
    data: Optional[Path] = None,
    device: str = "cpu",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
) -> int:
    """Export the avatar: a frame's Gaussians as a standard 3DGS PLY, a sequence, or a web player of a clip.

    The Gaussians are posed with the frame's parameters (the run's refined ones for training frames);
    the PLY has x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3 (opacity as logit, scale as log,
    rotation w x y z), binary little-endian. --format web writes a static folder (index.html, its script, the
    avatar and a clip of posed meshes) that plays the animated avatar in any WebGL2 browser from any static
    file server (docs/web_player.md).

    Args:
        run: Run folder written by `geoavatar train`.
        out: File to write (.ply; with --sequence a folder, or an .npz with --format npz; with --format web a
            folder). Default: RUN/export/frame_<K>.ply, RUN/export/sequence_<split>[.npz] or RUN/export/web_<clip>/.
        frame: Timestep (frame index of the video) to pose the avatar with (default: the first one).
        sequence: Export every frame of --split instead of one frame.
        format: With --sequence: ply (a folder of per-frame PLYs) or npz (one file of per-frame arrays); web: the
            browser player of a clip (--split, --driver or --driver-video; no --sequence needed).
        split: The frames: all, train, val or test (default: all with --sequence, test with --format web).
        driver: --format web: play this tracked dataset's motion on the avatar (as `geoavatar reenact --driver`).
        driver_video: --format web: play this video's motion (tracked as `geoavatar reenact --driver-video` does).
        audio: --format web: the avatar says this sound (any sound or video file; the run's voice model, as
            `geoavatar speak --audio`), and the player plays it with its sound in step.
        loudness: With --audio: how the sound is normalised, as `geoavatar speak --loudness`: own (its own speech
            statistics: any voice, any microphone) or video (the training sound's, the mean mouth following the
            sound's level: a recording made as the video was).
        relative: With --driver / --driver-video: the same as --transfer relative.
        transfer: With --driver / --driver-video: how the driver's expression, jaw and eyes become the avatar's,
            as `geoavatar reenact --transfer` (absolute, relative, statistics, subspace; default: reenact's).
        fps: --format web: the clip's frame rate (default: the driver video's, else 25).
        overwrite: Replace an existing --sequence or --format web folder.
        data: The run's dataset folder, when it moved since training (--format web reads its camera there).
        device: cpu, auto (CUDA when available), cuda or cuda:N.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        progress: Show progress bars.
    """
    if format == "web":
        return _export_web(run, out, frame, split, driver, driver_video, audio, loudness, relative, transfer, fps,
                           overwrite, data, device, flame_dir, progress)
    if (driver is not None or driver_video is not None or audio is not None or relative or transfer is not None
            or fps is not None or loudness != "own"):
        raise OptionError("--driver, --driver-video, --audio, --loudness, --relative, --transfer and --fps go with "
                          "--format web")
    if frame is not None and sequence:
        raise OptionError("--frame and --sequence exclude each other (--sequence exports every frame of --split)")
    if not sequence and (split is not None or format == "npz"):  # said, not dropped
        raise OptionError("--split and --format npz go with --sequence (without it, one frame is written as .ply)")
    if out is not None and sequence and format == "npz" and out.is_dir():  # found now, not after every frame
        raise OptionError(f"--out {out} is a folder: --format npz writes one .npz file")
    if out is not None and not sequence and out.suffix.lower() != ".ply":
        raise OptionError(f"--out {out}: a single frame is written as a .ply file")
    if out is not None and sequence and format == "npz" and out.suffix.lower() != ".npz":
        raise OptionError(f"--out {out}: --format npz writes an .npz file")
    split = split or "all"
    loaded = open_run(run, device, flame_dir)
    if not sequence:
        timestep = RunFrames(loaded).resolve(frame)
        target = out or default_output(loaded, EXPORT_DIR, FRAME_FILE.format(timestep))
        export_frame(loaded, target, timestep)
        print(f"wrote {target} ({loaded.avatar.num_gaussians} Gaussians, frame {timestep})")
    elif format == "ply":
        target = out or default_output(loaded, EXPORT_DIR, f"sequence_{split}")
        export_sequence_ply(loaded, target, split, overwrite, progress)
        print(f"wrote {target}/ ({len(split_timesteps(loaded, split))} frames)")
    else:
        target = out or default_output(loaded, EXPORT_DIR, f"sequence_{split}.npz")
        export_sequence_npz(loaded, target, split, progress)
        print(f"wrote {target} ({len(split_timesteps(loaded, split))} frames)")
    return 0


def _export_web(run, out, frame, split, driver, driver_video, audio, loudness, relative, transfer, fps, overwrite, data,
                device, flame_dir, progress) -> int:
    from geoavatar.apps.web_export import export_web, folder_size

    if frame is not None:
        raise OptionError("--frame does not go with --format web (the player plays a whole clip)")
    if sum(x is not None for x in (driver, driver_video, audio)) > 1:
        raise OptionError("give at most one of --driver, --driver-video and --audio")
    if (driver is not None or driver_video is not None or audio is not None) and split is not None:
        raise OptionError("--split chooses the run's own frames; it does not go with --driver / --driver-video / "
                          "--audio")
    if loudness != "own" and audio is None:
        raise OptionError("--loudness goes with --audio")
    if (relative or transfer is not None) and driver is None and driver_video is None:
        raise OptionError("--relative and --transfer go with --driver or --driver-video")
    mode = resolve_transfer(transfer, relative)
    loaded = open_run(run, device, flame_dir)
    named = driver_video or driver or audio
    clip = Path(named).stem if named is not None else (split or "test")
    target = check_folder_target(out or default_output(loaded, EXPORT_DIR, f"web_{clip}"), overwrite, loaded)
    export_web(loaded, target, split or "test", driver, driver_video, mode, fps, data, flame_dir, progress, audio,
               loudness)
    print(f"wrote {target}/ ({folder_size(target) / 1e6:.1f} MB): serve it with any static file server, e.g.\n"
          f"  python3 -m http.server 8000 --bind 127.0.0.1 --directory {target}\n"
          "and open http://127.0.0.1:8000/ in a browser")
    return 0


__all__ = ["check_folder_target", "export", "export_frame", "export_sequence_npz", "export_sequence_ply", "frame_gaussians", "to_ply_gaussians"]
