"""`geoavatar export RUN --format web --out DIR`: a static folder that plays the animated avatar in a browser.

Python poses the head, the one posing path of every command (apps/common.py: RunFrames' parameters and T rule,
avatar.posed_head with the mouth deformer), and the clip stores each frame's posed vertices, quantised, with its
head pose code when the avatar's hair follows the head's turn (web/pack.py); the page turns them into face frames
and places, rotates, scales and shades every splat on the GPU (web/src). The clip is

    --split S (default test)          the run's frames of that split, as `geoavatar render` poses them
    --driver DATA / --driver-video F  the driver's motion on the avatar, reenact's rules (--transfer as there);
                                      a video is tracked first as reenact does (RUN/drivers/, reused)

The view the page opens with is the dataset camera's (the camera of the clip's first frame, at the run's
resolution), and its orbit is limited to the head turns the training frames covered (head/view_angles.py:
where the camera saw the face from, in the head's axes) plus ORBIT_MARGIN degrees, relative to where the
dataset camera sees the clip's head from; the page's "free orbit" lifts the limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from geoavatar.apps.common import (browser_pose_code, head_centre, posed_head_vertices, progress, record_camera,
                                   run_background, split_timesteps)
from geoavatar.apps.expression_transfer import DEFAULT_TRANSFER, TransferMode, transfer_mode
from geoavatar.apps.reenact import driven_clip, frame_of, track_driver
from geoavatar.errors import OptionError
from geoavatar.eval.evaluate import trained_view_directions
from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_vertex_ids
from geoavatar.head.view_angles import view_directions, yaw_pitch
from geoavatar.render.camera import Camera
from geoavatar.train.checkpoint import LoadedRun, open_run_dataset
from geoavatar.train.run_frames import RunFrames
from geoavatar.web.pack import PlayerAssets, player_assets, quantise_clip, write_player_folder

ORBIT_MARGIN = 10.0  # degrees beyond the trained head turns the default orbit allows
DEFAULT_FPS = 25.0


def clip_timesteps(run: LoadedRun, split: str) -> list[int]:
    """The timesteps of a split, at least one (OptionError naming --split otherwise)."""
    timesteps = split_timesteps(run, split)
    if not timesteps:
        raise OptionError(f"--split {split}: the run has no {split} frames")
    return timesteps


@dataclass
class PosedClip:
    """What the player plays: the head posed for each frame, and each frame's head pose code when the avatar's hair
    follows the head's turn (avatar/hair_motion.py)."""

    vertices: Tensor  # [T, V, 3]
    codes: Tensor | None  # [T, 6], or None

    def take(self, rows: list[int]) -> "PosedClip":
        """The clip of these frames, in this order."""
        return PosedClip(self.vertices[rows], None if self.codes is None else self.codes[rows])


def _posed_clip(run: LoadedRun, frames: list[tuple[HeadParams, int | None]], show_progress: bool) -> PosedClip:
    """The head posed (the one posing path: apps/common.posed_head_vertices) for each (parameters, T)."""
    vertices = torch.stack([posed_head_vertices(run, params, t)
                            for params, t in progress(frames, enabled=show_progress, desc="pose")]).cpu()
    codes = [browser_pose_code(run, params) for params, _ in frames]
    return PosedClip(vertices, None if codes[0] is None else torch.stack(codes).cpu())


@torch.no_grad()
def split_clip(run: LoadedRun, frames: RunFrames, timesteps: list[int], show_progress: bool) -> PosedClip:
    """Each timestep posed with its parameters and T (RunFrames: the T rule)."""
    return _posed_clip(run, [frames.params(t) for t in timesteps], show_progress)


@torch.no_grad()
def driven_posed_clip(run: LoadedRun, params: dict[str, Tensor], show_progress: bool) -> PosedClip:
    """The head posed by driven parameters [T, ...] (T = 0: a new animation)."""
    count = int(params["expr"].shape[0])
    return _posed_clip(run, [(frame_of(params, row), None) for row in range(count)], show_progress)


def orbit_limits(run: LoadedRun, data: Path | None, vertices: Tensor, viewmats: Tensor,
                 margin: float = ORBIT_MARGIN) -> dict[str, list[float]]:
    """Yaw / pitch ranges (degrees, the page's orbit about the dataset camera) that keep the view within the head
    turns the training frames saw, plus `margin`; each range holds 0 (the dataset view). vertices [T, V, 3],
    viewmats [T, 4, 4] (each frame's camera) or [4, 4] (one for all)."""
    dataset = open_run_dataset(run, "train", data)
    rest, trained = trained_view_directions(run, dataset)  # [S, 3], [N, 3] head axes
    skull = skull_vertex_ids(run.head)
    viewmats = viewmats.cpu().expand(len(vertices), 4, 4)  # [T, 4, 4]
    shown = view_directions(rest, vertices[:, skull].cpu(), viewmats)
    shown_yaw, shown_pitch = (float(a.median()) for a in yaw_pitch(shown))
    if trained.numel() == 0:
        return {"yaw": [-margin, margin], "pitch": [-margin, margin]}
    yaw, pitch = yaw_pitch(trained)  # a positive orbit turn moves the view the same way (view_angles' axes)

    def span(values: Tensor, shown_at: float) -> list[float]:
        low, high = float(values.min()) - shown_at - margin, float(values.max()) - shown_at + margin
        return [round(min(low, 0.0), 2), round(max(high, 0.0), 2)]

    return {"yaw": span(yaw, shown_yaw), "pitch": span(pitch, shown_pitch)}


def clip_cameras(run: LoadedRun, data: Path | None, timesteps: list[int]) -> tuple[Camera, list[Tensor] | None]:
    """The first frame's camera at the run's resolution, and every frame's viewmat when they differ (else None)."""
    subject = open_run_dataset(run, "all", data).subject
    cameras = [record_camera(subject, t, run.info.resolution) for t in timesteps]
    moving = any(not torch.equal(c.viewmat, cameras[0].viewmat) for c in cameras[1:])
    return cameras[0], [c.viewmat for c in cameras] if moving else None


def web_assets(run: LoadedRun, clip: PosedClip, first_params: HeadParams, timesteps: list[int], fps: float,
               source: str, data: Path | None, camera_timesteps: list[int]) -> PlayerAssets:
    """The player's manifest and binaries of a posed clip."""
    camera, viewmats = clip_cameras(run, data, camera_timesteps)
    orbit = orbit_limits(run, data, clip.vertices, torch.stack(viewmats) if viewmats else camera.viewmat)
    orbit["centre"] = [float(c) for c in head_centre(run, first_params).cpu()]
    return player_assets(run.avatar, quantise_clip(clip.vertices), fps, camera, orbit, run_background(run).tolist(),
                         timesteps, source, viewmats=viewmats, pose_codes=clip.codes)


def export_web(run: LoadedRun, out: Path, split: str = "test", driver: Path | None = None,
               driver_video: Path | None = None, transfer: TransferMode | bool = DEFAULT_TRANSFER,
               fps: float | None = None,
               data: Path | None = None, flame_dir: Path | None = None, show_progress: bool = True) -> Path:
    """Write the player folder `out` (complete or not at all); returns it."""
    if fps is not None and fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    frames = RunFrames(run)
    if driver_video is not None:
        driver, video_fps, _ = track_driver(run, None, driver_video, flame_dir=flame_dir, progress=show_progress)
        fps = fps or video_fps
    if driver is not None:
        mode = transfer_mode(transfer)
        subject, params = driven_clip(run, frames, Path(driver), mode)
        timesteps = list(subject.timesteps)
        clip = driven_posed_clip(run, params, show_progress)
        first = frame_of(params, 0)
        source = f"driver {Path(driver_video or driver).name} ({mode} transfer)"
        camera_timesteps = [frames.timesteps[0]]  # reenact's camera: the avatar's (first) neutral frame
    else:
        timesteps = clip_timesteps(run, split)
        clip = split_clip(run, frames, timesteps, show_progress)
        first = frames.params(timesteps[0])[0]
        source = f"split {split}"
        camera_timesteps = timesteps
    assets = web_assets(run, clip, first, timesteps, fps or DEFAULT_FPS, source, data, camera_timesteps)
    return write_player_folder(out, assets)


def folder_size(folder: Path) -> int:
    return sum(f.stat().st_size for f in Path(folder).iterdir() if f.is_file())


__all__ = ["ORBIT_MARGIN", "PosedClip", "clip_timesteps", "driven_posed_clip", "export_web", "folder_size",
           "orbit_limits", "split_clip", "web_assets"]
