"""The browser player's clip (`export --format web`, `view`): each frame's posed head vertices (the one posing path:
avatar.posed_head with the mouth deformer at the frame's T) and, when the avatar's hair follows the head's turn, its
head pose code, quantised into the player's binaries (web/pack.py); the page turns them into face frames and places,
rotates, scales and shades every splat on the GPU (web/src).

The view the page opens with is the dataset camera's (the camera of `camera_timesteps`' first frame, at the run's
resolution; every frame's viewmat when they differ), and its orbit is limited to the head turns the training frames
covered (head/view_angles.py: where the camera saw the face from, in the head's axes) plus ORBIT_MARGIN degrees,
relative to where the dataset camera sees the clip's head from; the page's "free orbit" lifts the limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.posing import PosedFrame, browser_pose_code, head_centre, record_camera, run_background
from geoavatar.eval.evaluate import trained_view_directions
from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_vertex_ids
from geoavatar.head.view_angles import view_directions, yaw_pitch
from geoavatar.render.camera import Camera
from geoavatar.train.checkpoint import LoadedRun, open_run_dataset
from geoavatar.web.pack import PlayerAssets, player_assets, quantise_clip, write_player_folder

ORBIT_MARGIN = 10.0  # degrees beyond the trained head turns the default orbit allows


@dataclass
class PosedClip:
    """What the player plays: the head posed for each frame, and each frame's head pose code when the avatar's hair
    follows the head's turn (avatar/hair_motion.py)."""

    vertices: Tensor  # [T, V, 3]
    codes: Tensor | None  # [T, 6], or None

    def take(self, rows: list[int]) -> "PosedClip":
        """The clip of these frames, in this order."""
        return PosedClip(self.vertices[rows], None if self.codes is None else self.codes[rows])


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
               source: str, data: Path | None, camera_timesteps: list[int], audio=None) -> PlayerAssets:
    """The player's manifest and binaries of a posed clip (with the sound track `audio` when there is one)."""
    camera, viewmats = clip_cameras(run, data, camera_timesteps)
    orbit = orbit_limits(run, data, clip.vertices, torch.stack(viewmats) if viewmats else camera.viewmat)
    orbit["centre"] = [float(c) for c in head_centre(run, first_params).cpu()]
    sound = {"audio": audio} if audio is not None else {}
    return player_assets(run.avatar, quantise_clip(clip.vertices), fps, camera, orbit, run_background(run).tolist(),
                         timesteps, source, viewmats=viewmats, pose_codes=clip.codes, **sound)


class WebClip:
    """Sink: the frames posed into the player's clip (module docstring). `source` names the clip in the manifest,
    `camera_timesteps` the dataset frames whose cameras the page shows (None: each frame's own timestep); with `out`
    the player folder is written when the play ends (complete or not at all), else `assets()` gives what it holds."""

    rasterizes = False

    def __init__(self, run: LoadedRun, fps: float, source: str, camera_timesteps: list[int] | None = None,
                 data: Path | None = None, out: Path | None = None, audio=None):
        self.run, self.fps, self.source, self.data, self.out, self.audio = run, fps, source, data, out, audio
        self.camera_timesteps = camera_timesteps
        self.timesteps: list[int] = []
        self.first: HeadParams | None = None  # the first frame's parameters: the orbit's centre
        self._vertices: list[Tensor] = []  # [V, 3] per frame
        self._codes: list[Tensor | None] = []  # [6] per frame, or None

    def __enter__(self) -> "WebClip":
        return self

    def write(self, frame: AnimationFrame, posed: PosedFrame) -> None:
        if self.first is None:
            self.first = frame.params
        self._vertices.append(posed.vertices.cpu())
        self._codes.append(browser_pose_code(self.run, frame.params))
        self.timesteps.append(frame.timestep if frame.timestep is not None else frame.index)

    @property
    def clip(self) -> PosedClip:
        codes = None if self._codes[0] is None else torch.stack(self._codes).cpu()
        return PosedClip(torch.stack(self._vertices), codes)

    def assets(self) -> PlayerAssets:
        return web_assets(self.run, self.clip, self.first, self.timesteps, self.fps, self.source, self.data,
                          self.camera_timesteps if self.camera_timesteps is not None else self.timesteps, self.audio)

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None and self.out is not None:
            write_player_folder(self.out, self.assets())
        return False


__all__ = ["ORBIT_MARGIN", "PosedClip", "WebClip", "clip_cameras", "orbit_limits", "web_assets"]
